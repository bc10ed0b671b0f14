"""Place recognition and loop closure: the cost of each step, per call and per simulated second.

Inputs are real: ``--seconds`` of the office_loop scenario (camera at the key-frame rate, 1 Hz, LiDAR
through KISS-ICP odometry) give key-frame images and key-frame scans. Steps timed:

* describe: blur + Shi-Tomasi + SIFT of one 640x480 key frame (resized to the configured width);
* quantise + add: the key frame into the vocabulary tree and the database;
* query: TF-IDF retrieval against a database of N key frames (N = 100, 500, 2000: the images are
  repeated with other noise to fill it);
* verify: geometric verification of one candidate (point-to-plane ICP, restarts, checks);
* pose graph: one iSAM2 update with a loop edge at K key frames, and the final batch optimisation.

Key frames come at 1 Hz (one image in ten at 10 Hz); the loop closer verifies at most ``top_k`` (3)
candidates per key frame, so the budget per simulated second is describe + add + query + 3 x verify +
update. The run's real-time factor is kept if that stays well under the sensors' own cost.

    python benchmarks/bench_place_recognition.py [--seconds 12] [--repeats 5] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def collect(seconds: float):
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from stack.lidar_slam import LidarOdometry
    from stack.messages import CameraFrame, LidarScan

    sc = load_scenario("office_loop")
    sc.sensors.camera_rate = 1.0
    images, scans, poses = [], [], []
    want = False
    with Episode(sc, duration=seconds) as ep:
        odom = LidarOdometry(ep.T_base_velodyne)
        for msg in ep.frames():
            if isinstance(msg, LidarScan):
                T = odom.process(msg)
                if T is not None and want:
                    scans.append(odom.last_points_base.copy())
                    poses.append(T)
                    want = False
            elif isinstance(msg, CameraFrame):
                images.append(msg.rgb)
                want = True
    return images, scans, poses


def timed(fn, repeats: int):
    out = None
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        t.append(time.perf_counter() - t0)
    return float(np.median(t)) * 1000, out


def main(argv=None) -> int:
    from stack.loops.closure import KeyFrame, LoopClosureConfig, LoopCloser, _voxel_down, surface_normals, verify
    from stack.loops.place_recognition import PlaceDatabase, describe
    from stack.transforms import inv
    from testbed.vocabulary import default_vocabulary

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.1f}")
    tree = default_vocabulary()
    images, scans, poses = collect(a.seconds)
    cfg = LoopClosureConfig()
    rows = []

    img = images[len(images) // 2]
    ms, feats = timed(lambda: describe(img, tree.feature_config), a.repeats)
    rows.append(("describe (640x480 -> %d px wide)" % tree.feature_config.max_width_px, ms, 1.0))
    all_feats = [describe(im, tree.feature_config) for im in images]
    all_feats = [f for f in all_feats if f is not None]
    db = PlaceDatabase(tree)
    ms, _ = timed(lambda: db.add(feats.descriptors), a.repeats)
    rows.append(("quantise + add to database", ms, 1.0))
    rng = np.random.default_rng(0)
    for n in (100, 500, 2000):
        db = PlaceDatabase(tree)
        for i in range(n):
            f = all_feats[i % len(all_feats)].descriptors
            db.add(f + rng.normal(0, 0.02, f.shape).astype(np.float32))
        ms, _ = timed(lambda: db.query(feats.descriptors, k=cfg.top_k), a.repeats)
        rows.append((f"query, database of {n} key frames", ms, 1.0 if n == 500 else 0.0))

    # verification: the first and the last key frame scans (a real, short revisit is not in 12 s; the
    # cost is the same), from the odometry's relative pose
    i, j = 0, min(3, len(scans) - 1)
    pi = _voxel_down(scans[i], cfg.keyframe_voxel_m)
    pj = _voxel_down(scans[j], cfg.keyframe_voxel_m)
    ni, nj = surface_normals(pi), surface_normals(pj)
    ms_n, _ = timed(lambda: surface_normals(pj), a.repeats)
    rows.append(("normals of a key-frame scan (once per key frame)", ms_n, 1.0))
    T_init = inv(poses[i]) @ poses[j]
    ms, v = timed(lambda: verify(pj, pi, T_init, 10.0, cfg, nj, ni), a.repeats)
    rows.append((f"verify one candidate ({v.reason})", ms, float(cfg.top_k)))

    # pose graph: iSAM2 with K key frames, then one more key frame that closes a loop to the first
    for K in (100, 500):
        lc = LoopCloser(None, LoopClosureConfig(scan_keyframe_every=1, proximity="never"))
        step = np.eye(4)
        step[0, 3] = 1.0
        T = np.eye(4)
        for k in range(K):
            lc.add_scan(float(k), T, pi[:10])
            T = T @ step
        kf = KeyFrame(K, float(K), T, pi[:10].astype(np.float32), float(K), False)
        lc.key_frames.append(kf)
        lc.T_opt.append(T)
        edge = (0, K, inv(lc.key_frames[0].T_odom) @ T @ step, np.array([0.05] * 3 + [0.01] * 3))
        lc._loop_edges.append(edge)
        t0 = time.perf_counter()
        lc._update_graph(kf, [edge])
        rows.append((f"iSAM2 update closing a loop, {K} key frames", (time.perf_counter() - t0) * 1000, 0.0))
        t0 = time.perf_counter()
        lc.finalise()
        rows.append((f"final batch optimisation, {K} key frames", (time.perf_counter() - t0) * 1000, 0.0))

    per_s = sum(ms * n for _, ms, n in rows)
    print(f"\n{'step':<52} {'ms/call':>9} {'calls/sim s':>12}")
    for name, ms, n in rows:
        print(f"{name:<52} {ms:9.1f} {n:12.1f}")
    print(f"{'worst-case budget per simulated second':<52} {per_s:9.1f}")
    print(f"load average {os.getloadavg()[0]:.1f}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"rows": [{"step": r[0], "ms": r[1], "calls_per_sim_s": r[2]} for r in rows],
                       "ms_per_sim_s": per_s}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
