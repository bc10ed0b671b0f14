"""How often a map object's place was in view (stack.evidence.count_views), kept across a loop closure's
re-fusion and a save (carry_views, the ``views`` column)."""
import numpy as np

from stack.evidence import carry_views, count_views
from stack.messages import CameraInfo
from stack.object_store import ObjectStore, Observation

DIMS = {"Mustard": (0.16, 0.05, 0.065), "Yogurt": (0.054, 0.068, 0.068)}
INFO = CameraInfo(640, 480, np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1.0]]))
T_CAM = np.eye(4)  # the camera's optical frame is the map's: looking along +z


def obs(cls, xyz, t, rng=1.0, fpr=True):
    return Observation(t, cls, np.asarray(xyz, dtype=float), np.array([0, 0, 0, 1.0]), 10.0, fpr, rng,
                       np.zeros(3))


def store_with(*observations):
    store = ObjectStore(DIMS)
    for o in observations:
        store.add(o)
    return store


def depth(z):
    return np.full((480, 640), z, dtype=np.float32)


def test_an_object_in_view_with_its_place_visible_gets_a_view():
    store = store_with(obs("Mustard", (0.0, 0.0, 1.0), 0.0, rng=1.5))
    (obj,) = list(store)
    assert count_views(store, T_CAM, INFO, depth(1.0)) == 1 and obj.views == 1  # something there: present
    count_views(store, T_CAM, INFO, depth(3.0))  # seen through: its place is empty, a view all the same
    assert obj.views == 2
    count_views(store, T_CAM, INFO, depth(0.5))  # something in front of it: no view either way
    count_views(store, T_CAM, INFO, None)  # no depth image: only a sighting would count
    assert obj.views == 2
    count_views(store, T_CAM, INFO, None, seen=[obj.id])
    assert obj.views == 3


def test_out_of_the_image_or_beyond_its_detected_range_is_no_view():
    store = store_with(obs("Mustard", (0.0, 0.0, 1.0), 0.0, rng=1.0), obs("Yogurt", (3.0, 0.0, 1.0), 0.0, rng=1.0))
    mustard, yogurt = list(store)
    count_views(store, T_CAM, INFO, depth(1.0))
    assert (mustard.views, yogurt.views) == (1, 0)  # the Yogurt projects far outside the image
    far = np.eye(4)
    far[2, 3] = -1.5  # camera 1.5 m further back: the Mustard at 2.5 m, seen at most 1.0 m away
    count_views(store, far, INFO, depth(2.5))
    assert mustard.views == 1


def test_views_follow_the_observations_into_a_new_store_and_a_save(tmp_path):
    old = store_with(obs("Mustard", (0.0, 0.0, 1.0), 0.0), obs("Mustard", (0.0, 0.0, 1.0), 0.1),
                     obs("Yogurt", (0.5, 0.0, 1.0), 0.1))
    mustard, yogurt = list(old)
    mustard.views, yogurt.views = 7, 3
    new = store_with(*[o for obj in old for o in obj.history])  # placed again (a loop closure)
    carry_views(old, new)
    assert sorted(o.views for o in new) == [3, 7]
    old.save(tmp_path / "s.xlsx")
    old.save(tmp_path / "s.json")
    for name in ("s.xlsx", "s.json"):
        assert sorted(o.views for o in ObjectStore.load(tmp_path / name)) == [3, 7]


def judged(n_obs, views, config, span=0.1):
    """One object with ``n_obs`` FPR-passing observations over ``span`` s from a moving camera, whose
    place ``views`` images showed."""
    from stack.evidence import EvidenceConfig  # noqa: F401 (the config type the callers pass)

    cams = [(x, -1.0, 0.3) for x in np.linspace(-0.5, 0.5, n_obs)]
    store = ObjectStore(DIMS, evidence=config)
    for k in range(n_obs):
        o = obs("Mustard", (0.0, 0.0, 0.3), k * span / max(1, n_obs - 1))
        o.cam_xyz = np.asarray(cams[k], dtype=float)
        store.add(o)
    (obj,) = list(store)
    obj.views = views
    store.publish()
    return obj


def test_an_object_detected_in_few_of_the_images_that_showed_it_stays_a_candidate():
    from stack.evidence import EvidenceConfig

    cfg = EvidenceConfig(min_detection_rate=0.25, rate_min_views=10, min_span_s=0.0)
    assert judged(6, 12, cfg).status == "label"  # half of its views
    weak = judged(6, 40, cfg)
    assert weak.status == "candidate" and "6 of 40 images" in weak.reason
    assert judged(6, 9, cfg.model_copy(update={"rate_min_views": 30})).status == "label"  # too few views to judge


def test_an_object_detected_whenever_in_view_needs_fewer_observations():
    from stack.evidence import EvidenceConfig

    cfg = EvidenceConfig(min_observations=5, min_span_s=1.0, quick_observations=3, quick_detection_rate=0.6)
    assert judged(3, 4, cfg).status == "label"  # a quick pass: 3 of 4 images, 0.1 s
    slow = judged(3, 8, cfg)  # 3 of 8: not enough for the quick path
    assert slow.status == "candidate" and "3 observations" in slow.reason
    assert judged(2, 2, cfg).status == "candidate"  # fewer than the quick path's count
    assert judged(3, 4, cfg.model_copy(update={"quick_observations": 0})).status == "candidate"  # off
    assert judged(3, 0, cfg).status == "candidate"  # views not counted: the ordinary rules
