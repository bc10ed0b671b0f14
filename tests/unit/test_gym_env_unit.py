"""The labelling envs without a simulated episode: the perception cache's spec and detector identity,
the object slots (association, actions, the assignment-based cost, withdrawing, evidence), the policy
table, and the evidence policy on a hand-built perception (gymnasium's checks, reproducibility, the
baselines and vector envs on short drives: ``tests/e2e/test_gym_env.py``).

DOPE is replaced by a noisy ground-truth double (tests/labelling_double.py) so that these tests do
not depend on trained weights.
"""
import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import testbed.envs  # noqa: F401  (registers the ids)
from helpers.gym_env import SCENE, cost_of_score, env_kwargs, run_policy
from stack.object_store import Observation, label_of
from testbed.envs import perception_cache as pc
from testbed.envs.slots import _robust_mean, slot_features


# --- the cache -----------------------------------------------------------------------------------------

def test_spec_validates_its_fields():
    with pytest.raises(ValueError, match="input"):
        pc.make_spec(SCENE, 0, 1.0, None, "thermal", (6,), "x")
    with pytest.raises(ValueError, match="stages"):
        pc.make_spec(SCENE, 0, 1.0, None, "rgb", (7,), "x")
    with pytest.raises(ValueError, match="detector_id"):
        pc.make_spec(SCENE, 0, 1.0, None, "rgb", (6,), "")


def test_uncached_episode_without_a_detector_says_which_file(tmp_path):
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(tmp_path, detector_factory=None, build=False))
    with pytest.raises(pc.PerceptionCacheError, match="not cached"):
        env.reset(options={"episode": 0})


# --- baselines ---------------------------------------------------------------------------------------

def test_env_robust_mean_is_the_object_store_policy():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 5, 8, 31):
        P = rng.normal(0, 0.02, (n, 3)) + [1.0, 2.0, 0.5]
        P[: n // 4] += rng.normal(0, 0.8, (n // 4, 3))  # outliers
        beliefs = rng.uniform(5, 20, n)
        obs = [Observation(float(t), "Mustard", p, np.array([0, 0, 0, 1.0]), b, True, 1.0)
               for t, (p, b) in enumerate(zip(P, beliefs))]
        ref = label_of(obs, "robust-mean")
        xyz, belief = _robust_mean(P, beliefs)
        assert np.allclose(xyz, ref.xyz) and belief == pytest.approx(ref.score)


# --- evaluate-policy -------------------------------------------------------------------------------

def test_evaluate_policy_rejects_an_unknown_policy(tmp_path, capsys):
    from testbed.cli import main

    assert main(["evaluate-policy", "newest", "--episodes", "1", "--out", str(tmp_path)]) == 2
    assert "dopeslam evaluate-policy: unknown policy 'newest'" in capsys.readouterr().err


# --- slots: association, actions, cost (no simulation) -------------------------------------------------

def frame_dets(rows):
    """rows: (cls, xyz, belief, fpr) -> the detection dict SlotMap reads."""
    from testbed.envs.slots import with_lists

    d = {"cls": np.array([r[0] for r in rows], dtype=np.int16).reshape(-1),
         "xyz": np.array([r[1] for r in rows], dtype=float).reshape(-1, 3),
         "belief": np.array([r[2] for r in rows], dtype=float), "fpr": np.array([r[3] for r in rows], dtype=bool),
         "range": np.ones(len(rows))}
    d["err"] = np.zeros(len(rows))
    return with_lists(d)


def test_slots_associate_replace_fuse_and_score():
    from testbed.envs.slots import FUSE, IGNORE, REPLACE, SlotMap

    truth_cls, truth_xyz = np.array([0, 1]), np.array([[1.0, 0.0, 0.5], [2.0, 1.0, 0.5]])
    sm = SlotMap(3, 6, truth_cls, truth_xyz, gate_m=0.5)
    assert sm.cost == pytest.approx(2 * 0.5)  # both missing
    # frame 1: class 0 near its truth, class 1 far off (a false label if taken), and a duplicate of class 0
    sm.observe(frame_dets([(0, (1.1, 0.0, 0.5), 9.0, True), (1, (2.0, 1.6, 0.5), 9.0, True),
                           (0, (1.05, 0.0, 0.5), 20.0, False)]), 0, 3, 6)
    assert sm.cur.tolist()[:2] == [0, 1] and sm.duplicates == 1  # the FPR-passing, more certain one kept
    r = sm.act(np.array([REPLACE, REPLACE, IGNORE]))
    # object 0: 0.1 m; object 1: 0.6 m, a false label (+0.5)
    assert sm.cost == pytest.approx(0.1 + 0.6 + 0.5) and r == pytest.approx(1.0 - sm.cost)
    # frame 2: class 0 again within the gate -> the same slot; fused with the first
    sm.observe(frame_dets([(0, (0.9, 0.0, 0.5), 9.0, True)]), 0, 1, 6)
    assert sm.cur.tolist() == [0, -1, -1]
    sm.act(np.array([FUSE, IGNORE, IGNORE]))
    assert np.allclose(sm.label[0], [1.0, 0.0, 0.5])
    # a class-1 detection far from slot 1's anchor opens slot 2; replacing there adds a phantom label
    sm.observe(frame_dets([(1, (2.05, 1.0, 0.5), 9.0, True)]), 0, 1, 6)
    assert sm.cur.tolist() == [-1, -1, 0]
    sm.act(np.array([IGNORE, IGNORE, REPLACE]))
    # object 1 now takes the nearer label (slot 2, 0.05 m); slot 1's label is matched to nothing
    assert sm.cost == pytest.approx(0.0 + 0.05 + 0.25)


def test_slots_recycle_unlabelled_candidates_when_full():
    from testbed.envs.slots import IGNORE, REPLACE, SlotMap

    sm = SlotMap(2, 6, np.array([0]), np.array([[1.0, 0.0, 0.5]]))
    sm.observe(frame_dets([(0, (1.0, 0.0, 0.5), 9.0, True), (1, (3.0, 0.0, 0.5), 50.0, False)]), 0, 2, 6)
    sm.act(np.array([REPLACE, IGNORE]))  # slot 0 labelled, slot 1 a candidate left unlabelled
    sm.observe(frame_dets([(2, (0.0, 2.0, 0.5), 9.0, True)]), 0, 1, 6)
    assert sm.recycled == 1 and sm.cls.tolist() == [0, 2] and sm.cur.tolist() == [-1, 0]
    obs = sm.slots_obs()
    assert obs[1, 2 + 2] == 1.0 and obs[1, 2 + 1] == 0.0  # the slot now describes the new class
    sm.act(np.array([IGNORE, REPLACE]))
    sm.observe(frame_dets([(3, (5.0, 2.0, 0.5), 9.0, True)]), 0, 1, 6)
    assert sm.dropped == 1  # every slot holds a label: nothing to recycle


def test_real_detector_identity_changes_with_weights_thresholds_and_colour_model(tmp_path, monkeypatch):
    """The FPR verdicts are cached, so every file they depend on is part of the cache key."""
    from stack import dope_fpr
    from testbed.envs.perception_cache import dope_detector_id

    w = tmp_path / "dope_rgb.pt"
    w.write_bytes(b"weights-a")
    colour = tmp_path / "colour.json"
    colour.write_text("{}")
    monkeypatch.setattr(dope_fpr, "default_colour_model_path", lambda: colour)
    a = dope_detector_id("rgb", w)
    (tmp_path / "fpr_thresholds_rgb.json").write_text("{}")
    b = dope_detector_id("rgb", w)
    colour.write_text('{"x": 1}')
    c = dope_detector_id("rgb", w)
    w.write_bytes(b"weights-b")
    d = dope_detector_id("rgb", w)
    assert len({a, b, c, d}) == 4
    assert "rule" in a and "colour" in a

    class Fp32:
        precision = "fp32"

    class Bf16:
        precision = "bf16"

    e, f = dope_detector_id("rgb", w, Fp32()), dope_detector_id("rgb", w, Bf16())
    assert e == d and f == d + ":bf16"  # bf16 maps are another cache; fp32 (the default) keeps its identity

    class Int8:
        precision = "int8"
        int8_calibration = tmp_path / "w_int8.json"

    g = dope_detector_id("rgb", w, Int8())
    Int8.int8_calibration.write_text("{}")
    h = dope_detector_id("rgb", w, Int8())
    Int8.int8_calibration.write_text('{"x": 1}')
    assert g == d + ":int8none" and len({g, h, dope_detector_id("rgb", w, Int8())}) == 3  # the scales count


def test_policy_table_warns_when_object_slots_run_out():
    """A map with more candidate objects than slots drops detections: the table says so."""
    from testbed.commands.policy import summarise, table_markdown

    def run(dropped):
        return {"policy": "robust-mean", "scenario": "sc", "seed": 0, "objects": 6, "mean_error_m": 0.02,
                "labels_in_map": 9, "false_labels": 3, "misplaced": 0, "phantom": 3, "missing": 0,
                "map_precision": 6 / 9, "map_recall": 1.0, "candidates": 2, "return": 0.0,
                "dropped_detections": dropped}

    ok = table_markdown(summarise(["robust-mean"], ["sc"], [0], [run(0)]))
    full = table_markdown(summarise(["robust-mean"], ["sc"], [0], [run(37)]))
    assert "no free object slot" not in ok
    assert "| robust-mean | - | 2.0 ± 0.0 | 9.0 ± 0.0 | 3.00 ± 0.00 (0.0 + 3.0) | 0.00 ± 0.00 | 0.67 ± 0.00 | 1.00 ± 0.00 |" in ok
    assert "up to 37 detections per episode found no free object slot" in full


# --- the assignment-based cost, withdrawing, evidence (no simulation) ----------------------------------

def slot_map_with_labels(truth_cls, truth_xyz, labels, **kw):
    """A SlotMap whose slots hold ``labels`` ((cls, xyz) each, one slot per label, REPLACE)."""
    from testbed.envs.slots import IGNORE, REPLACE, SlotMap

    sm = SlotMap(len(labels), 6, np.array(truth_cls), np.array(truth_xyz, dtype=float), gate_m=0.05, **kw)
    for j, (c, xyz) in enumerate(labels):
        sm.observe(frame_dets([(c, xyz, 9.0, True)]), 0, 1, 6)
        assert sm.cur[j] == 0
        sm.act(np.array([REPLACE if k == j else IGNORE for k in range(len(labels))]))
    return sm


def score_of(sm, truth_cls, truth_xyz):
    from types import SimpleNamespace

    from testbed.envs.labelling import final_score

    objects = [SimpleNamespace(name=f"o{k}", cls=f"c{c}", T_world_obj=np.block([[np.eye(3), np.array(p)[:, None]],
                                                                                  [np.zeros((1, 3)), np.ones((1, 1))]]))
               for k, (c, p) in enumerate(zip(truth_cls, truth_xyz))]
    return final_score(sm, objects, np.eye(4), [f"c{i}" for i in range(6)])


@pytest.mark.parametrize("case", ["two labels of one object", "a label between two objects", "a phantom far away",
                                  "a misplaced label", "a wrong class on an object"])
def test_cost_is_the_one_to_one_assignment_of_score_map(case):
    truth_cls, truth_xyz = [0, 1, 1], [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [3.0, 0.0, 0.5]]
    labels, expect = {
        # the nearer one is correct, the other a phantom (object 0 is the only one of its class)
        "two labels of one object": ([(0, (0.05, 0.0, 0.5)), (0, (-0.1, 0.0, 0.5)), (1, (3.0, 0.0, 0.5))],
                                     dict(correct=2, misplaced=0, phantom=1, missing=1)),
        # a label halfway between two objects of its class takes one of them (misplaced), never both
        "a label between two objects": ([(0, (0.0, 0.0, 0.5)), (1, (2.0, 0.0, 0.5))],
                                        dict(correct=1, misplaced=1, phantom=0, missing=2)),
        "a phantom far away": ([(0, (0.0, 0.0, 0.5)), (1, (1.0, 0.0, 0.5)), (1, (3.0, 0.0, 0.5)), (2, (9.0, 9.0, 0.5))],
                               dict(correct=3, misplaced=0, phantom=1, missing=0)),
        "a misplaced label": ([(1, (3.6, 0.0, 0.5))], dict(correct=0, misplaced=1, phantom=0, missing=3)),
        # a class the scene does not hold, on a real object
        "a wrong class on an object": ([(1, (3.0, 0.0, 0.5)), (2, (3.0, 0.0, 0.5))],
                                       dict(correct=1, misplaced=0, phantom=1, missing=2)),
    }[case]
    sm = slot_map_with_labels(truth_cls, truth_xyz, labels)
    score = score_of(sm, truth_cls, truth_xyz)
    s = score["summary"]
    got = dict(correct=s["correct_labels"], misplaced=s["misplaced"], phantom=s["phantom"], missing=s["missing"])
    assert got == expect
    assert sm.cost == pytest.approx(cost_of_score(score))
    # recomputed from scratch (every slot changed) it is the same
    assert sm._cost(range(len(labels))) == pytest.approx(sm.cost)


def test_cost_assignment_prefers_more_matches_within_the_threshold():
    """Greedy per object, object 0 would take the label 0.1 m off and leave object 1 only the far one;
    the assignment matches both within 0.25 m."""
    truth_cls, truth_xyz = [0, 0], [[0.0, 0.0, 0.5], [0.3, 0.0, 0.5]]
    sm = slot_map_with_labels(truth_cls, truth_xyz, [(0, (0.1, 0.0, 0.5)), (0, (-0.2, 0.0, 0.5))])
    s = score_of(sm, truth_cls, truth_xyz)["summary"]
    assert s["correct_labels"] == 2 and s["false_labels"] == 0
    assert sm.cost == pytest.approx(0.2 + 0.2)


def test_withdraw_takes_a_label_off_the_map_and_keeps_its_evidence():
    from testbed.envs.slots import FUSE, IGNORE, WITHDRAW, SlotMap

    sm = SlotMap(2, 6, np.array([0]), np.array([[1.0, 0.0, 0.5]]))
    sm.observe(frame_dets([(0, (1.1, 0.0, 0.5), 9.0, True), (1, (4.0, 0.0, 0.5), 9.0, True)]), 0, 2, 6)
    sm.act(np.array([FUSE, FUSE]))
    assert sm.cost == pytest.approx(0.1 + 0.25)  # slot 1 is a phantom
    # withdraw the phantom on a frame without a detection of it
    sm.observe(frame_dets([]), 0, 0, 6)
    r = sm.act(np.array([IGNORE, WITHDRAW]))
    assert r == pytest.approx(0.25) and sm.cost == pytest.approx(0.1)
    assert sm.has.tolist() == [True, False] and sm.withdrawn == 1
    obs = sm.slots_obs()
    assert obs[1, sm._lab0] == 0.0 and obs[1, 1] == 1.0  # no label, still a slot in use (a candidate)
    # withdrawn, it gathers FPR-passing detections (not rejected ones) without publishing ...
    sm.observe(frame_dets([(0, (0.9, 0.0, 0.5), 9.0, True)]), 0, 1, 6)
    assert sm.act(np.array([WITHDRAW, IGNORE])) == pytest.approx(-0.5 + 0.1)  # object 0 now missing
    sm.observe(frame_dets([(0, (1.05, 0.0, 0.5), 9.0, False)]), 0, 1, 6)
    sm.act(np.array([WITHDRAW, IGNORE]))
    assert sm.ev_n[0] == 2 and not sm.has[0]
    # ... and a FUSE publishes it again with all of its evidence (1.1, 0.9, then 1.0)
    sm.observe(frame_dets([(0, (1.0, 0.0, 0.5), 9.0, True)]), 0, 1, 6)
    sm.act(np.array([FUSE, IGNORE]))
    assert sm.has[0] and sm.ev_n[0] == 3 and np.allclose(sm.label[0], [1.0, 0.0, 0.5])
    assert sm.cost == pytest.approx(0.0)
    s = score_of(sm, [0], [[1.0, 0.0, 0.5]])["summary"]
    assert s["labels_in_map"] == 1 and s["candidates"] == 1 and s["map_precision"] == 1.0


def evidence_dets(rows):
    """rows: (cls, xyz, fpr, stamp, cam, half) -> the detection dict SlotMap reads."""
    from testbed.envs.slots import with_lists

    d = {"cls": np.array([r[0] for r in rows], dtype=np.int16), "xyz": np.array([r[1] for r in rows], float).reshape(-1, 3),
         "belief": np.full(len(rows), 9.0), "fpr": np.array([r[2] for r in rows], bool), "range": np.ones(len(rows)),
         "stamp": np.array([r[3] for r in rows], float), "cam": np.array([r[4] for r in rows], float).reshape(-1, 3),
         "half": np.array([r[5] for r in rows], float), "err": np.zeros(len(rows))}
    return with_lists(d)


def test_evidence_columns_follow_the_stack_definitions():
    from stack.evidence import EvidenceConfig, view_angle_deg
    from testbed.envs.slots import SlotMap

    floor = (np.array([0.0, 0.0, 1.0]), 0.1)  # the floor is 0.1 m below the map's origin
    sm = SlotMap(3, 6, np.array([0]), np.array([[2.0, 0.0, 0.4]]), floor=floor)
    c = {n: k for k, n in enumerate(slot_features(6))}
    cams, xyz = [], []
    for t in range(6):
        cam = (0.0, 0.2 * t, 0.3)
        p = (2.0 + 0.01 * t, 0.0, 0.4)
        fpr = t != 3
        # class 3 right beside the object in frames 0 and 1: the class vote
        rows = [(0, p, fpr, 10.0 + 0.5 * t, cam, 0.05)] + ([(3, (2.05, 0.0, 0.4), True, 10.0 + 0.5 * t, cam, 0.05)]
                                                          if t < 2 else [])
        sm.observe(evidence_dets(rows), 0, len(rows), 6)
        xyz.append(p)
        if fpr:
            cams.append(cam)
    o = sm.slots_obs()
    anchor = np.mean(xyz, axis=0)
    assert o[0, c["ev_fpr_detections"]] == 5  # frame 3's detection failed FPR
    assert o[0, c["ev_span_s"]] == pytest.approx(2.5)
    assert o[0, c["ev_view_angle_deg"]] == pytest.approx(view_angle_deg(anchor, [np.array(q) for q in cams]), abs=1e-4)
    assert o[0, c["ev_anchor_height_m"]] == pytest.approx(anchor[2] + 0.1, abs=1e-6)
    assert o[0, c["ev_floor_clearance_m"]] == pytest.approx(anchor[2] + 0.1 - 0.05, abs=1e-6)
    assert EvidenceConfig().vote_radius_m > 0.05  # the two slots are one place
    assert o[0, c["ev_vote_share"]] == pytest.approx(5 / 7) and o[1, c["ev_vote_share"]] == pytest.approx(2 / 7)
    assert o[0, c["ev_vote_lead"]] == pytest.approx(5 / 7) and o[1, c["ev_vote_lead"]] == pytest.approx(2 / 7)
    assert np.isfinite(o).all()
    # without a floor plane the floor columns are 0 (bounded, never NaN)
    bare = SlotMap(1, 6, np.array([0]), np.array([[2.0, 0.0, 0.4]]))
    bare.observe(evidence_dets([(0, (2.0, 0.0, 0.4), True, 0.0, (0, 0, 0.3), 0.05)]), 0, 1, 6)
    ob = bare.slots_obs()
    assert ob[0, c["ev_anchor_height_m"]] == 0.0 and ob[0, c["ev_floor_clearance_m"]] == 0.0
    assert ob[0, c["ev_view_angle_deg"]] == 0.0 and ob[0, c["ev_vote_share"]] == 1.0 and ob[0, c["ev_vote_lead"]] == 1.0


# --- a hand-built perception: the evidence policy against robust-mean ----------------------------------

def hand_built_perception(frames, objects, floor=(np.array([0.0, 0.0, 1.0]), 0.0)):
    """A cached episode without the simulator: ``frames`` is a list of (stamp, camera xyz in map,
    [(class index, xyz in map, fpr), ...]); map = world; ``objects``: (name, class, xyz)."""
    from testbed.envs.labelling import catalog_classes

    classes = catalog_classes()
    T = []
    cols = {k: [] for k in pc.DET_FIELDS}
    det_frame, det_stage = [], []
    for f, (t, cam, dets) in enumerate(frames):
        Tb = np.eye(4)
        Tb[:3, 3] = cam
        T.append(Tb)
        for c, p, fpr in dets:
            det_frame.append(f)
            det_stage.append(6)
            for k, v in (("cls", c), ("xyz", p), ("quat", (0, 0, 0, 1.0)), ("belief", 9.0), ("fpr", fpr),
                         ("range", float(np.linalg.norm(np.subtract(p, cam)))), ("kp", np.zeros((9, 2))), ("cam", cam)):
                cols[k].append(np.asarray(v, dtype=pc.DET_FIELDS[k][0]))
    arrays = {"frame_stamp": np.array([f[0] for f in frames], float), "frame_T_map_base": np.array(T),
              "frame_T_world_base": np.array(T), "frame_detect_s": np.zeros(len(frames)),
              "det_frame": np.array(det_frame, np.int32), "det_stage": np.array(det_stage, np.int8),
              **{f"det_{k}": np.array(v, dtype=pc.DET_FIELDS[k][0]).reshape(-1, *pc.DET_FIELDS[k][1])
                 for k, v in cols.items()},
              "traj_stamp": np.array([f[0] for f in frames], float), "traj_T_map_base": np.array(T),
              "map_xy": np.zeros((0, 2), np.float32), "T_world_map": np.eye(4), "T_base_cam": np.eye(4),
              "floor_plane": pc.floor_array(floor)}
    duration = frames[-1][0] - frames[0][0]
    spec = pc.make_spec(SCENE, 0, duration, None, "rgb", (6,), "hand-built")
    objs = [{"name": n, "cls": classes[c], "T_world_obj": np.block([[np.eye(3), np.array(p, float)[:, None]],
                                                                   [np.zeros((1, 3)), np.ones((1, 1))]]).tolist(),
             "dims": [0.1, 0.1, 0.1]} for n, c, p in objects]
    meta = {"classes": classes, "objects": objs, "stage_seconds": None, "detect_seconds_per_frame": 0.0}
    return pc.Perception(spec, meta, arrays)


def test_evidence_policy_beats_robust_mean_on_map_precision(tmp_path):
    from testbed.envs.labelling import DopeSlamLabellingEnv, Replay

    rng = np.random.default_rng(0)
    a, b = (2.0, 0.0, 0.3), (2.0, 1.5, 0.3)  # two real objects (classes 0 and 1)
    frames = []
    for f in range(40):
        t, cam = 0.2 * f, (0.1 * f, -1.0, 0.3)  # the robot drives past: the viewpoint changes
        dets = [(0, tuple(np.add(a, rng.normal(0, 0.01, 3))), True), (1, tuple(np.add(b, rng.normal(0, 0.01, 3))), True)]
        if f in (5, 6):
            dets.append((2, (0.5, 2.5, 0.3), True))  # seen twice: too little evidence
        if f < 8:
            dets.append((3, (2.05, 1.5, 0.3), True))  # a wrong class on object b, outvoted there
        if 10 <= f < 20:
            dets.append((4, (3.5, -0.5, -0.4), True))  # would reach below the floor
        frames.append((t, cam, dets))
    for f in range(40, 52):  # the robot stands still: a reflection seen from one viewpoint only
        frames.append((0.2 * f, (4.0, -1.0, 0.3), [(5, (5.0, 1.0, 0.3), True)]))
    perception = hand_built_perception(frames, [("a", 0, a), ("b", 1, b)])
    env = DopeSlamLabellingEnv(scenario=SCENE, seeds=[0], detector_id="hand-built", build=False,
                               cache_dir=str(tmp_path), renderer="tiny")
    env._replays[0] = Replay(perception, env.classes, 6)
    scores = {n: run_policy(env, n, 0) for n in ("robust-mean", "evidence")}
    rm, ev = scores["robust-mean"]["summary"], scores["evidence"]["summary"]
    assert rm["labels_in_map"] == 6 and rm["correct_labels"] == 2 and rm["phantom"] == 4
    assert ev["labels_in_map"] == 2 and ev["correct_labels"] == 2 and ev["map_precision"] == 1.0
    assert ev["map_precision"] > rm["map_precision"] and ev["map_recall"] == rm["map_recall"]
    assert ev["candidates"] == 4
    # the labels it publishes rest on all their FPR-passing detections, as the stack's robust mean
    assert ev["mean_error_m"] == pytest.approx(rm["mean_error_m"])
    for name, r in scores.items():
        assert r["summary"]["final_cost"] == pytest.approx(cost_of_score(r)), name
    check_env(env)  # the hand-built episode's observations are bounded and finite
