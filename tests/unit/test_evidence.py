"""Which map objects the store publishes as labels, and which it keeps as candidates (stack.evidence)."""
import numpy as np
import pytest

from stack.evidence import CANDIDATE, LABEL, EvidenceConfig, lowest_corner_height, view_angle_deg
from stack.object_store import ObjectStore, Observation

DIMS = {"Mustard": (0.160050, 0.048574, 0.065133), "Yogurt": (0.053677, 0.067962, 0.067915),
        "OrangeJuice": (0.192483, 0.072781, 0.071583)}
FLOOR = (np.array([0.0, 0.0, 1.0]), 0.0)  # z up, the floor at z = 0


def stream(cls, xyz, n=10, t0=0.0, dt=0.2, cams=None, fpr=True):
    """n observations of one object at xyz, taken from camera positions ``cams`` (cycled) or from
    positions driving past it along x (a view angle of tens of degrees)."""
    cams = cams or [(x, -1.0, 0.3) for x in np.linspace(-0.5, 0.5, n)]
    return [Observation(t0 + k * dt, cls, np.asarray(xyz, dtype=float), np.array([0, 0, 0, 1.0]), 10.0, fpr,
                        1.0, np.asarray(cams[k % len(cams)], dtype=float)) for k in range(n)]


def published(observations, config=EvidenceConfig(), floor=FLOOR):
    store = ObjectStore(DIMS, evidence=config)
    for o in sorted(observations, key=lambda o: o.stamp):
        store.add(o)
    store.floor = floor
    store.publish()
    return store


def test_an_object_seen_consistently_from_a_moving_camera_is_a_label():
    store = published(stream("Mustard", (0.0, 0.0, 0.3)))
    (obj,) = list(store)
    assert obj.status == LABEL and obj.reason == "" and store.labels() == [obj]


def test_too_few_observations_keep_an_object_a_candidate():
    store = published(stream("Mustard", (0.0, 0.0, 0.3), n=2))
    (obj,) = list(store)
    assert obj.status == CANDIDATE and "observations" in obj.reason and store.labels() == []


def test_rejected_detections_are_no_evidence():
    obs = stream("Mustard", (0.0, 0.0, 0.3), n=3) + stream("Mustard", (0.0, 0.0, 0.3), n=20, t0=5.0, fpr=False)
    assert published(obs).labels() == []


def test_an_object_seen_from_one_viewpoint_only_stays_a_candidate():
    store = published(stream("Mustard", (2.0, 0.0, 0.3), n=30, cams=[(0.0, 0.0, 0.3)]))
    assert store.labels() == [] and "viewpoint" in store.candidates()[0].reason


def test_an_object_below_the_floor_is_impossible():
    below = published(stream("Yogurt", (0.0, 0.0, -0.07)))
    assert below.labels() == [] and "below the floor" in below.candidates()[0].reason
    on_floor = published(stream("Yogurt", (0.0, 0.0, 0.034)))  # resting on it: its centre half its height up
    assert len(on_floor.labels()) == 1
    assert len(published(stream("Yogurt", (0.0, 0.0, -0.07)), floor=None).labels()) == 1  # no floor known


def test_detections_of_different_classes_at_one_place_vote_for_one_object():
    """The depth network's typical error: a wrong class on a right object. The better supported class
    keeps the label; the other becomes a candidate that names the winner."""
    right = stream("OrangeJuice", (1.0, 0.0, 0.4), n=30)
    wrong = stream("Mustard", (1.03, 0.02, 0.41), n=12, t0=0.1)
    store = published(right + wrong)
    assert [o.cls for o in store.labels()] == ["OrangeJuice"]
    (loser,) = store.candidates()
    assert loser.cls == "Mustard" and "outvoted" in loser.reason and "OrangeJuice" in loser.reason


def test_objects_of_different_classes_side_by_side_are_both_labels():
    store = published(stream("OrangeJuice", (1.0, 0.0, 0.4), n=30) + stream("Mustard", (1.0, 0.3, 0.4), n=12))
    assert sorted(o.cls for o in store.labels()) == ["Mustard", "OrangeJuice"]


def test_a_hand_edited_object_keeps_the_status_a_person_gave_it():
    store = published(stream("Mustard", (0.0, 0.0, 0.3), n=2))
    (obj,) = list(store)
    obj.edited, obj.status = True, LABEL
    store.publish()
    assert store.labels() == [obj]


def test_no_evidence_rule_publishes_everything():
    assert len(published(stream("Mustard", (0.0, 0.0, -0.3), n=1), config=None).labels()) == 1


def test_status_and_reason_survive_a_save_and_load(tmp_path):
    store = published(stream("Mustard", (0.0, 0.0, 0.3)) + stream("Yogurt", (3.0, 0.0, -0.2), t0=0.05))
    for name in ("labels.xlsx", "labels.json"):
        store.save(tmp_path / name)
        back = ObjectStore.load(tmp_path / name, dims=DIMS)
        assert [(o.cls, o.status, o.reason) for o in back] == [(o.cls, o.status, o.reason) for o in store]
        back.publish()  # .json holds the history, .xlsx does not: either way the verdicts stand
        assert [o.status for o in back] == [o.status for o in store]


def test_view_angle_and_lowest_corner_geometry():
    assert view_angle_deg((0, 0, 0), [(1, 0, 0), (0, 1, 0)]) == pytest.approx(90.0)
    assert view_angle_deg((0, 0, 0), [(1, 0, 0)]) == 0.0
    # a 0.1 m cube standing on the floor, turned 45 deg about z: its lowest corner is on the floor
    q = np.array([0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
    assert lowest_corner_height((0, 0, 0.05), q, (0.1, 0.1, 0.1), FLOOR) == pytest.approx(0.0, abs=1e-12)
