"""``dopeslam navigate OBJECT [SCENARIO] --out DIR --seed N``: the second seed's navigation (its
section 4.4) in the simulator.

1. The map: the scenario's scripted drive (its own seed, lit) is the mapping run; its camera stream
   (cached) goes through ``stack.topo_map.TopoMapper`` (ORPE poses, vocabulary-tree words,
   colour-verified HOG attributes). The map is cached by scenario and settings.
2. The navigation run: a fresh episode of the same scenario whose start pose is perturbed by the
   seed (up to +-0.15 m, +-8 deg) and whose sensor noise is the seed's. The robot software sees the
   camera and its wheel odometry only:
   - localise by retrieval (vocabulary tree -> candidate nodes) verified by the pose against the
     node's points (ORPE in RANSAC); between visual fixes the pose is carried by wheel odometry;
     while a recent fix exists, the nodes nearest the predicted pose are the candidates;
   - plan over the topological graph (Dijkstra) from the node it is at to the node holding OBJECT
     (the node where OBJECT's box is largest);
   - follow the path's nodes (base positions in the plane of the first node's base) with a
     heading controller, stopping at the target node.
3. Scored with ground truth: ``final_distance_m`` (robot base to the target node's true base
   position, in the plane), ``distance_to_object_m`` (to the object, in the plane),
   ``path_length_m`` (driven).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np

from stack.mono_pose import MonoConfig, detect_features
from stack.topo_map import MapperConfig, TopoMap, TopoMapper, localise
from stack.transforms import inv, yaw_of
from testbed.seed2.stream import CameraStream, cache_root, camera_stream

log = logging.getLogger(__name__)
SUCCESS_M = 0.5


def _weights_tag() -> str:
    from stack.hog_detector import DEFAULT_COLOUR, DEFAULT_WEIGHTS

    h = hashlib.sha1()
    for p in (DEFAULT_WEIGHTS, DEFAULT_COLOUR):
        if p.exists():
            h.update(p.read_bytes())
    return h.hexdigest()[:8]


def load_detector():
    from stack.hog_detector import DEFAULT_WEIGHTS, HogDetector

    if not DEFAULT_WEIGHTS.exists():
        log.warning("%s missing: the map gets no object attributes (train with python -m testbed.seed2.detector train)",
                    DEFAULT_WEIGHTS)
        return None
    return HogDetector.load()


def load_tree():
    from testbed.vocabulary import default_vocabulary

    return default_vocabulary()


def build_map(stream: CameraStream, tree=None, detector=None, cfg: MapperConfig | None = None,
              mono_cfg: MonoConfig | None = None, progress_every: float = 30.0) -> TopoMap:
    """Run the mapper over a cached stream (images with their wheel odometry)."""
    mapper = TopoMapper(stream.info.K, (stream.info.width, stream.info.height), stream.T_base_camera, tree, detector,
                        cfg, mono_cfg, meta={"scenario": stream.scenario, "seed": stream.seed, "light": stream.light})
    last = time.perf_counter()
    for i in range(len(stream)):
        mapper.add(i, float(stream.stamps[i]), stream.rgb[i], stream.T_odom_base[i])
        if time.perf_counter() - last > progress_every:
            last = time.perf_counter()
            log.info("mapping %s: frame %d / %d, %d nodes", stream.scenario, i + 1, len(stream), len(mapper.topo))
    return mapper.finish()


def scenario_map(scenario=None, light: float | None = None, cache: bool = True) -> tuple[TopoMap, CameraStream]:
    """The scenario's map from its own scripted drive (cached)."""
    stream = camera_stream(scenario, light=light)
    cfg = MapperConfig()
    # the attribute score threshold is applied when the map is used, so it is not part of the key
    key_cfg = {k: v for k, v in cfg.__dict__.items() if k != "attribute_min_score"}
    key = hashlib.sha1(f"{stream.scenario}/{stream.seed}/{stream.light}/{key_cfg}/{MonoConfig()}/{_weights_tag()}".encode()).hexdigest()[:10]
    d = cache_root() / "maps" / f"{stream.scenario}_{key}"
    if cache and (d / "topo_map.json").exists():
        try:
            topo = TopoMap.load(d)
            topo.meta["attribute_min_score"] = cfg.attribute_min_score
            return topo, stream
        except ValueError as exc:
            log.warning("rebuilding the map: %s", exc)
    log.info("building the topological map of %s", stream.scenario)
    topo = build_map(stream, load_tree(), load_detector(), cfg)
    if cache:
        topo.save(d)
    return topo, stream


def node_truth(topo: TopoMap, stream: CameraStream) -> dict[int, np.ndarray]:
    return {n.id: stream.T_world_camera[n.frame] for n in topo.nodes}


def resolve_object(name: str, objects) -> tuple[str, object]:
    """OBJECT may be an object's name or its class; returns (class, the object)."""
    for o in objects:
        if o.name == name:
            return o.cls, o
    for o in objects:
        if o.cls == name:
            return o.cls, o
    raise SystemExit(f"OBJECT: expected one of the scenario's objects {[o.name for o in objects]}, got {name!r}")


class PoseTracker:
    """The robot's pose in the map: visual fixes, wheel odometry in between."""

    def __init__(self, T_base_camera: np.ndarray):
        self.T_base_camera = T_base_camera
        self.T_map_base_fix: np.ndarray | None = None
        self.T_odom_fix: np.ndarray | None = None
        self.fix_time = -np.inf
        self.segment = -1
        self.fixes = 0

    def predict(self, T_odom_base: np.ndarray) -> np.ndarray | None:
        if self.T_map_base_fix is None:
            return None
        return self.T_map_base_fix @ inv(self.T_odom_fix) @ T_odom_base

    def correct(self, T_map_camera: np.ndarray, T_odom_base: np.ndarray, t: float, segment: int = 0) -> bool:
        """Take a visual fix unless it disagrees with a recent fix of the same map segment (segments
        are joined only by a bridge, so a fix from another segment restarts the track)."""
        T_map_base = T_map_camera @ inv(self.T_base_camera)
        pred = self.predict(T_odom_base)
        if pred is not None and t - self.fix_time < 5.0 and segment == self.segment:
            d = np.linalg.norm(pred[:3, 3] - T_map_base[:3, 3])
            R = pred[:3, :3].T @ T_map_base[:3, :3]
            ang = math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
            if d > 0.6 or ang > 25:  # an outlying fix: keep the odometry
                return False
        self.T_map_base_fix = T_map_base
        self.T_odom_fix = T_odom_base.copy()
        self.fix_time = t
        self.segment = segment
        self.fixes += 1
        return True


def _plane(T_nav_map: np.ndarray, T_map_base: np.ndarray) -> tuple[float, float, float]:
    T = T_nav_map @ T_map_base
    return float(T[0, 3]), float(T[1, 3]), yaw_of(T)


def navigate(object_name: str, scenario=None, out_dir="out/navigate", seed: int = 0, max_seconds: float = 90.0,
             localise_every: int = 3, speed: float = 0.25, topo: TopoMap | None = None,
             stream: CameraStream | None = None, tree=None, target_node: int | None = None) -> dict:
    import pybullet as p

    from sim.camera import render_rgbd
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from testbed.simulate import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    if topo is None or stream is None:
        topo, stream = scenario_map(scenario)
    tree = tree or load_tree()
    cls, obj = resolve_object(object_name, stream.objects)
    k_obj = [o.name for o in stream.objects].index(obj.name)
    target = topo.target_node(cls) if target_node is None else target_node
    report = {"object": object_name, "class": cls, "scenario": stream.scenario, "seed": seed,
              "map": {"nodes": len(topo), "edges": len(topo.edges), "segments": topo.meta.get("segments")},
              "target_node": target}
    if target is None:
        report.update({"reached": False, "success": False, "reason": f"no node of the map holds {cls}",
                       "final_distance_m": None, "distance_to_object_m": None, "path_length_m": 0.0})
        write_json(out / "navigate.json", report)
        return report
    T_base_cam = topo.T_base_camera
    node_base = {n.id: n.T_map_camera @ inv(T_base_cam) for n in topo.nodes}
    T_nav_map = inv(node_base[0])  # the plane of the first node's base_link
    true_node_base = {n.id: stream.T_world_camera[n.frame] @ inv(stream.T_base_camera) for n in topo.nodes}

    sc = load_scenario(scenario if scenario is not None else stream.scenario)
    rng = np.random.default_rng(seed)
    x, y, yaw = sc.robot.start
    sc.robot.start = [x + float(rng.uniform(-0.15, 0.15)), y + float(rng.uniform(-0.15, 0.15)),
                      yaw + float(rng.uniform(-8, 8))]
    sc.sensors.camera_width, sc.sensors.camera_height = topo.width, topo.height
    sc.sensors.lidar = False
    mono_cfg = MonoConfig()
    tracker = PoseTracker(T_base_cam)
    path: list[int] | None = None
    wp = 0
    trace = []
    fix_log = []
    loc_seconds = 0.0
    loc_calls = 0
    done = False
    with Episode(sc, seed=seed, light=None) as ep:
        dt = ep.dt
        cam_every = max(1, int(round(1.0 / (sc.sensors.camera_rate * dt))))
        steps = int(max_seconds / dt)
        v = w = 0.0
        frame_no = 0
        for k in range(steps):
            t = k * dt
            T_world_base = ep.robot.T_world_base()
            if k > 0:
                ep.robot.update_odometry(dt)
            T_odom = ep.robot.T_odom_base.copy()
            trace.append(T_world_base[:3, 3].copy())
            if k % cam_every == 0:
                if frame_no % localise_every == 0:
                    T_world_cam = T_world_base @ ep.T_base_camera
                    rgb, _, _ = render_rgbd(ep.client, T_world_cam, ep.camera_info, ep.light, ep.rng_camera,
                                            sc.sensors.noise, ep.renderer)
                    t0 = time.perf_counter()
                    pred = tracker.predict(T_odom)
                    cands = None
                    if pred is not None and t - tracker.fix_time < 3.0:
                        d = [np.linalg.norm(node_base[n.id][:3, 3] - pred[:3, 3]) for n in topo.nodes]
                        cands = [int(i) for i in np.argsort(d)[:2]]
                    feats = detect_features(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), mono_cfg)
                    fix = localise(topo, rgb, tree, k=3, rng=rng, cfg=mono_cfg, feats=feats, candidates=cands)
                    if fix is None and cands is not None:  # the prediction's nodes failed: ask retrieval
                        fix = localise(topo, rgb, tree, k=3, rng=rng, cfg=mono_cfg, feats=feats)
                    loc_seconds += time.perf_counter() - t0
                    loc_calls += 1
                    if fix is not None and fix.inliers >= 20:
                        accepted = tracker.correct(fix.T_map_camera, T_odom, t, topo.nodes[fix.node].segment)
                        est = fix.T_map_camera @ inv(T_base_cam)
                        fix_log.append({"t": t, "node": fix.node, "inliers": fix.inliers, "accepted": accepted,
                                        "error_m": float(np.linalg.norm(
                                            (true_node_base[0] @ inv(node_base[0]) @ est)[:2, 3] - T_world_base[:2, 3]))})
                        if path is None and accepted:
                            path = topo.shortest_path(fix.node, target)
                            wp = 0
                            report["start_node"] = fix.node
                            report["path"] = path
                frame_no += 1
            # control
            pose = tracker.predict(T_odom)
            if path is None or pose is None:
                v, w = 0.0, 0.3 if t > 3.0 else 0.0  # look around for a first fix
            else:
                xr, yr, yawr = _plane(T_nav_map, pose)
                while True:
                    gx, gy, _ = _plane(T_nav_map, node_base[path[wp]])
                    dist = math.hypot(gx - xr, gy - yr)
                    last = wp == len(path) - 1
                    if not last and dist < 0.2:
                        wp += 1
                        continue
                    break
                if last and dist < 0.06:
                    done = True
                    v, w = 0.0, 0.0
                else:
                    err = (math.atan2(gy - yr, gx - xr) - yawr + math.pi) % (2 * math.pi) - math.pi
                    w = float(np.clip(2.0 * err, -1.0, 1.0))
                    v = speed * max(0.0, math.cos(err)) ** 2 if abs(err) < 0.7 else 0.0
                    if last:
                        v = min(v, 0.5 * dist + 0.02)
            ep.robot.command(v, w, dt)
            p.stepSimulation(physicsClientId=ep.client)
            if done:
                # let the robot come to rest
                for _ in range(int(0.5 / dt)):
                    ep.robot.command(0.0, 0.0, dt)
                    p.stepSimulation(physicsClientId=ep.client)
                trace.append(ep.robot.T_world_base()[:3, 3].copy())
                break
        T_end = ep.robot.T_world_base()
        sim_seconds = (k + 1) * dt
    trace = np.asarray(trace)
    end_xy = T_end[:2, 3]
    report.update({
        "reached": done, "start_pose_world": sc.robot.start,
        "final_distance_m": float(np.linalg.norm(end_xy - true_node_base[target][:2, 3])),
        "distance_to_object_m": float(np.linalg.norm(end_xy - obj.T_world_obj[:2, 3])),
        "target_node_to_object_m": float(np.linalg.norm(true_node_base[target][:2, 3] - obj.T_world_obj[:2, 3])),
        "target_node_shows_object": stream.object_in_view(topo.nodes[target].frame, k_obj, 0.3),
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(trace[:, :2], axis=0), axis=1))),
        "sim_seconds": sim_seconds, "wall_seconds": time.perf_counter() - wall0,
        "localisation": {"attempts": loc_calls, "fixes": len(fix_log), "accepted": tracker.fixes,
                         "seconds_per_attempt": loc_seconds / max(1, loc_calls),
                         "fix_error_m_median": float(np.median([f["error_m"] for f in fix_log])) if fix_log else None},
    })
    report["success"] = bool(report["final_distance_m"] <= SUCCESS_M)
    write_json(out / "navigate.json", report)
    _plot(out / "navigate.png", topo, stream, true_node_base, trace, target, report, obj)
    return report


def _plot(path, topo, stream, true_node_base, trace, target, report, obj) -> None:
    from testbed.plots import plt, save

    fig, ax = plt.subplots(figsize=(8, 5.5))
    gt = stream.T_world_base[:, :2, 3]
    ax.plot(gt[:, 0], gt[:, 1], "-", color="0.7", lw=1, label="mapping drive")
    nb = np.array([true_node_base[n.id][:2, 3] for n in topo.nodes])
    ax.plot(nb[:, 0], nb[:, 1], "o", color="tab:blue", ms=4, label="nodes (true positions)")
    for n in topo.nodes:
        if topo.attributes(n):
            ax.annotate(",".join(a.cls for a in topo.attributes(n)), true_node_base[n.id][:2, 3], fontsize=6,
                        xytext=(3, -8), textcoords="offset points", color="tab:blue")
    ax.plot(trace[:, 0], trace[:, 1], "r-", lw=1.5, label="navigation")
    ax.plot(*true_node_base[target][:2, 3], "*", color="gold", ms=14, mec="k", label=f"target node {target}")
    for o in stream.objects:
        ax.plot(*o.T_world_obj[:2, 3], "ks" if o.name == obj.name else "k.", ms=6)
        ax.annotate(o.name, o.T_world_obj[:2, 3], fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="best")
    ax.set_title(f"navigate to {report['object']} ({report['scenario']}, seed {report['seed']}): "
                 f"{report['final_distance_m']:.2f} m from the node", fontsize=9)
    save(fig, path)


def main_args(args) -> int:
    report = navigate(args.object, args.scenario, args.out, args.seed, args.max_seconds)
    fd = report["final_distance_m"]
    print(json.dumps({k: report[k] for k in ("object", "scenario", "seed", "target_node", "success",
                                             "final_distance_m", "distance_to_object_m", "path_length_m")}, indent=1))
    print(f"wrote {args.out}/navigate.json" + ("" if fd is None else f" ({fd:.2f} m from the target node)"))
    return 0 if report["success"] else 1


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def batch(scenarios=("experiment3_columns", "shelf_corridor"), seeds=range(10), out_dir="out/seed2/navigate") -> dict:
    """Ten seeded navigation runs per scenario, the object asked for cycling through the objects the
    map holds (seed k asks for the k mod n-th; those without a node are listed). Writes
    ``navigate_batch.json``."""
    from testbed.simulate import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tree = load_tree()
    summary = {"success_m": SUCCESS_M, "scenarios": {}}
    for name in scenarios:
        topo, stream = scenario_map(name)
        # the objects the map holds (a class the detector never attributed has no node to drive to)
        held = [o for o in stream.objects if topo.target_node(o.cls) is not None]
        summary.setdefault("objects_without_node", {})[name] = [o.name for o in stream.objects if o not in held]
        rows = []
        for seed in seeds:
            if not held:
                break
            obj = held[seed % len(held)]
            r = navigate(obj.name, name, out / name / f"seed{seed}", seed, topo=topo, stream=stream, tree=tree)
            rows.append({k: r.get(k) for k in ("object", "seed", "target_node", "success", "reached", "final_distance_m",
                                               "distance_to_object_m", "target_node_to_object_m",
                                               "target_node_shows_object", "path_length_m", "sim_seconds", "wall_seconds")})
            log.info("%s seed %d -> %s: %s m", name, seed, obj.name, rows[-1]["final_distance_m"])
            summary["scenarios"][name] = {"runs": rows, "successes": sum(bool(x["success"]) for x in rows),
                                          "map": {"nodes": len(topo), "segments": topo.meta.get("segments")}}
            write_json(out / "navigate_batch.json", summary)
    return summary


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m testbed.seed2.navigate")
    ap.add_argument("--scenarios", default="experiment3_columns,shelf_corridor")
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--out", default="out/seed2/navigate")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    lo, _, hi = a.seeds.partition("-")
    res = batch(a.scenarios.split(","), range(int(lo), int(hi or lo) + 1), a.out)
    for name, s in res["scenarios"].items():
        print(f"{name}: {s['successes']}/{len(s['runs'])} within {SUCCESS_M} m of the target node")
        for r in s["runs"]:
            fd = r["final_distance_m"]
            print(f"  seed {r['seed']}: {r['object']:<12} node {r['target_node']}  "
                  f"{_fmt(fd)} m from the node, "
                  f"{_fmt(r['distance_to_object_m'])} m from the object")
