"""Long runs keep memory bounded: an object's observation history is thinned past its limit (with the
same counts and labels close to the whole history's), and trajectories are kept compactly."""
import math
import tracemalloc

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stack.evidence import EvidenceConfig, assess, evidence_of
from stack.object_store import (HISTORY_LIMIT, ObjectStore, Observation, label_of, thin_history,
                                weighted_median)
from stack.pose_track import PoseTrack
from stack.transforms import interpolate_trajectory

DIMS = {"Yogurt": [0.054, 0.068, 0.068], "Mustard": [0.16, 0.049, 0.065]}
TRUE_XYZ = np.array([1.0, 2.0, 0.1])


def stream(n: int, seed: int = 0, cls: str = "Yogurt", xyz=TRUE_XYZ, reject_every: int = 7):
    """A robot passing an object, then staring at it: 1 cm noise, every ``reject_every``-th rejected by FPR."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        cam = np.array([0.0, min(i, 600) * 0.005, 0.5])  # it drives 3 m, then stands still
        out.append(Observation(0.1 * i, cls, np.asarray(xyz) + rng.normal(0, 0.01, 3),
                               Rotation.from_euler("z", rng.normal(0, 0.02)).as_quat(), float(rng.uniform(0.5, 3.0)),
                               i % reject_every != 3, float(np.linalg.norm(np.asarray(xyz) - cam)), cam))
    return out


def test_weighted_median_is_the_median_of_the_repeated_values():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 4, 7, 10):
        v, w = rng.normal(size=n), rng.integers(1, 5, n)
        assert weighted_median(v, np.ones(n, dtype=int)) == np.median(v)
        assert weighted_median(v, w) == np.median(np.repeat(v, w))


def test_below_the_limit_the_store_is_what_it_always_was():
    obs = stream(1500)
    a, b = ObjectStore(DIMS), ObjectStore(DIMS, history_limit=10**9)
    for o in obs:
        a.add(o)
        b.add(o)
    (oa,), (ob,) = list(a), list(b)
    assert len(oa.history) == 1500 and all(h.weight == 1 for h in oa.history)
    assert np.array_equal(oa.xyz, ob.xyz) and np.array_equal(oa.quat_xyzw, ob.quat_xyzw) and oa.score == ob.score
    assert "weight" not in oa.history[0].to_dict()  # saved files are unchanged too


def test_a_long_stream_keeps_the_history_bounded_with_the_same_counts_and_a_close_label():
    limit = 1024
    obs = stream(4000)
    bounded = ObjectStore(DIMS, history_limit=limit)
    longest = 0
    for o in obs:
        bounded.add(o)
        longest = max(longest, len(next(iter(bounded)).history))
    obj = next(iter(bounded))
    assert longest <= limit and len(obj.history) < limit
    assert sum(h.weight for h in obj.history) == obj.observations == 4000
    # the evidence counts exactly what the whole history holds; span and viewpoints are kept
    whole = ObjectStore(DIMS, history_limit=10**9)
    whole.objects[1] = type(obj)(1, obj.cls, obj.xyz, obj.quat_xyzw, obj.size, 0.0, 0.0, history=list(obs))
    config = EvidenceConfig()
    ev_b, ev_w = evidence_of(obj, config, None), evidence_of(whole.objects[1], config, None)
    assert ev_b.observations == ev_w.observations and ev_b.span_s == ev_w.span_s
    assert ev_b.view_angle_deg == pytest.approx(ev_w.view_angle_deg, abs=0.5)
    assert assess([obj], config, None)[1][0] == "label"
    # the label: the weighted mean of an even sample of about limit / 4 past detections, so within
    # ~2 sigma / sqrt(limit) per axis (0.6 mm here for 1 cm noise) of the whole history's robust mean
    full = label_of(obs, "robust-mean")
    assert np.linalg.norm(obj.xyz - full.xyz) < 0.003
    assert np.degrees((Rotation.from_quat(obj.quat_xyzw).inv() * Rotation.from_quat(full.quat_xyzw)).magnitude()) < 0.2
    assert np.linalg.norm(obj.xyz - TRUE_XYZ) < 0.003
    # the single-detection policies give exactly what they give on the whole history
    for policy in ("last", "last-fpr", "best-score", "closest-fpr"):
        got, want = label_of(obj.history, policy), label_of(obs, policy)
        assert np.array_equal(got.xyz, want.xyz) and np.array_equal(got.quat_xyzw, want.quat_xyzw), policy


def test_thinning_keeps_the_newest_and_the_pinned_observations():
    obs = stream(1000)
    passing = [o for o in obs if o.fpr_pass]
    best = min(passing, key=lambda o: o.belief_sum)
    closest = min(passing, key=lambda o: o.range_m)
    thinned = thin_history(obs, keep_newest=200, keep_older=100)
    assert thinned[-200:] == obs[-200:]
    assert len(thinned) <= 200 + 100 + 4
    ids = {id(o) for o in thinned}
    for o in (obs[0], passing[0], best, closest):
        assert id(o) in ids
    assert sum(o.weight for o in thinned if o.fpr_pass) == len(passing)
    assert sum(o.weight for o in thinned if not o.fpr_pass) == len(obs) - len(passing)
    assert [o.stamp for o in thinned] == sorted(o.stamp for o in thinned)
    # the kept past is an even sample: its weights are (nearly) all the same
    w = np.array([o.weight for o in thinned[:-200] if id(o) not in {id(obs[0]), id(best), id(closest)}])
    assert np.median(w) == w.max() or (w.max() - np.median(w)) <= np.median(w)


def test_a_store_watching_objects_for_hours_stays_within_its_memory():
    limit = 128
    store = ObjectStore(DIMS, history_limit=limit)
    for o in stream(600):
        store.add(o)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for o in stream(1500, seed=1):
        store.add(o)
    ours = [tracemalloc.Filter(True, "*object_store.py"), tracemalloc.Filter(True, "*test_long_runs.py")]
    after = tracemalloc.take_snapshot().filter_traces(ours)
    grown = sum(s.size_diff for s in after.compare_to(before.filter_traces(ours), "filename"))
    tracemalloc.stop()
    assert grown < 100 * 1024  # what the store holds; an unbounded history would grow by 1500 x ~600 bytes
    assert len(next(iter(store)).history) <= limit


def test_a_thinned_history_round_trips_through_json_with_its_weights(tmp_path):
    store = ObjectStore(DIMS, history_limit=64)
    for o in stream(300):
        store.add(o)
    path = tmp_path / "labels.json"
    store.save(path)
    again = ObjectStore.load(path, DIMS)
    a, b = next(iter(store)), next(iter(again))
    assert [h.weight for h in a.history] == [h.weight for h in b.history]
    assert max(h.weight for h in b.history) > 1
    assert evidence_of(a, EvidenceConfig(), None) == evidence_of(b, EvidenceConfig(), None)


def test_the_default_limit_is_above_what_a_scenario_collects():
    # the longest scenario shipped (242 s) at the default camera rate (10 Hz), seen in every image
    assert HISTORY_LIMIT >= 242 * 10


def test_a_pose_track_is_the_list_it_replaces():
    rng = np.random.default_rng(0)
    track = PoseTrack(capacity=2)
    stamps, poses = [], []
    for k in range(1000):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        track.append(0.1 * k, T)
        stamps.append(0.1 * k)
        poses.append(T)
    s, P = track.arrays()
    assert np.array_equal(s, np.array(stamps)) and np.array_equal(P, np.array(poses))
    assert len(track) == 1000 and not track.stamps.flags.writeable
    for t in rng.uniform(-1, 101, 50):
        assert np.array_equal(interpolate_trajectory(track.stamps, track.poses, t),
                              interpolate_trajectory(np.array(stamps), np.array(poses), t))
    assert math.isclose(track.stamps[-1], 99.9)
