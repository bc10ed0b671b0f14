"""``dopeslam navigate OBJECT [SCENARIO] --out DIR --seed N``: the topological-map paper's navigation (its
section 4.4) in the simulator, as teach and repeat over the topological map. The robot software is
``stack.topomap.navigation.Navigator``; this module is its harness.

1. The map (the teach run): the scenario's scripted drive (its own seed, lit); its camera stream
   (cached) goes through ``stack.topomap.topological_map.TopoMapper`` (ORPE poses, vocabulary-tree words,
   colour-verified HOG attributes), then places seen on two passes are joined by ``revisit``
   edges (``stack.topomap.localisation.add_revisit_edges``). The map is cached by scenario and settings. The
   mapping run's dead reckoning is kept beside it (``teach_odometry``: the wheels' travel, the
   gyro's heading).
2. The navigation run (the repeat): a fresh episode of the same scenario whose start pose is
   perturbed by the seed (up to +-0.15 m, +-8 deg) and whose sensor noise is the paper's. The
   navigator sees the camera, the robot's dead reckoning and the map only; this loop renders its
   images, steps the physics with its velocity commands and keeps the ground truth for the report.
   Dead reckoning: the skid-steer base's wheel odometry over-counts turns two- to five-fold (the
   wheels slip sideways, most at low yaw rates: ``benchmarks/bench_dead_reckoning.py``), and
   differently in each turn, so between fixes the heading is the gyro's
   (``sim.imu.Gyro``, ``stack.dead_reckoning``), as the Jackal's own odometry fuses its IMU;
   ``gyro=False`` (``--wheels-only``) keeps the wheels' heading.
3. Scored with ground truth: ``final_distance_m`` (robot base to the target node's true base
   position, in the plane), ``distance_to_object_m`` (to the object, in the plane),
   ``path_length_m`` (driven); the report's ``tracking`` log is the estimate's error along and
   across the route.

``dopeslam navigate-batch`` runs ten seeded runs per scenario (``batch``).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from stack.dead_reckoning import DeadReckoning
from stack.topomap.mono_pose import MonoConfig
from stack.topomap.navigation import Navigator, RouteImage
from stack.topomap.localisation import add_revisit_edges
from stack.topomap.topological_map import MapperConfig, TopoMap, TopoMapper
from stack.transforms import inv, wrap_angle, yaw_of
from testbed.topomap import InputError
from testbed.topomap.stream import CameraStream, cache_root, camera_stream

log = logging.getLogger(__name__)
SUCCESS_M = 0.5


def _weights_tag() -> str:
    from stack.topomap.hog_detector import DEFAULT_COLOUR, DEFAULT_WEIGHTS

    h = hashlib.sha1()
    for p in (DEFAULT_WEIGHTS, DEFAULT_COLOUR):
        if p.exists():
            h.update(p.read_bytes())
    return h.hexdigest()[:8]


def load_detector():
    from stack.topomap.hog_detector import DEFAULT_WEIGHTS, HogDetector

    if not DEFAULT_WEIGHTS.exists():
        log.warning("%s missing: the map gets no object attributes (train with dopeslam hog-detector train)",
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
    topo = None
    if cache and (d / "topo_map.json").exists():
        try:
            topo = TopoMap.load(d)
        except ValueError as exc:
            log.warning("rebuilding the map: %s", exc)
    if topo is None:
        log.info("building the topological map of %s", stream.scenario)
        topo = build_map(stream, load_tree(), load_detector(), cfg)
    if "revisits" not in topo.meta:  # places seen on two passes joined (a map cached before they were)
        log.info("%s: %d revisit edges", stream.scenario, add_revisit_edges(topo, load_tree()))
        if cache:
            topo.save(d)
    topo.meta["attribute_min_score"] = cfg.attribute_min_score
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
    raise InputError(f"OBJECT: expected one of the scenario's objects {[o.name for o in objects]}, got {name!r}")


GYRO_STREAM = 0x6779  # the gyro's random stream, beside the episode's others (seeded by the run's seed)


def teach_odometry(stream: CameraStream) -> np.ndarray:
    """The mapping run's dead reckoning at its camera frames: the wheels' travel between frames (the
    stream's wheel odometry) with the heading of its gyro (simulated on the run's true yaw, seeded
    by the run's seed)."""
    from sim.imu import Gyro

    gyro = Gyro(np.random.default_rng([stream.seed, GYRO_STREAM]))
    keep = np.r_[True, np.diff(stream.gt_stamps) > 0]  # repeated stamps carry no interval
    stamps = stream.gt_stamps[keep]
    yaw_true = np.unwrap([yaw_of(T) for T in stream.T_world_base])[keep]
    dts = np.diff(stamps)
    rates = [gyro.measure(float(dy / dt), float(dt)) for dy, dt in zip(np.diff(yaw_true), dts)]
    yaw_at = np.interp(stream.stamps, stamps, np.r_[0.0, np.cumsum(np.asarray(rates) * dts)])
    To = stream.T_odom_base
    dr = DeadReckoning(To[0])
    return np.asarray([To[0].copy()] + [dr.step_wheels(To[f - 1], To[f], float(yaw_at[f] - yaw_at[f - 1]))
                                         for f in range(1, len(To))])


def navigate(object_name: str, scenario=None, out_dir="out/navigate", seed: int = 0, max_seconds: float | None = None,
             localise_every: int = 3, speed: float = 0.5, topo: TopoMap | None = None,
             stream: CameraStream | None = None, tree=None, target_node: int | None = None, gyro: bool = True) -> dict:
    """One navigation run (``stack.topomap.navigation.Navigator``) in a fresh episode: the path is
    planned over the graph, the robot repeats the mapping run's trajectory along it and corrects its
    pose with visual fixes against the route's images; the last metres converge on the target node's
    key frame. ``gyro``: dead reckoning with the gyro's heading (else the wheel odometry's). Writes
    ``navigate.json`` and ``navigate.png`` under ``out_dir``; returns the report."""
    import pybullet as p

    from sim.camera import render_rgbd
    from sim.episode import Episode
    from sim.imu import Gyro
    from sim.scenario import load_scenario
    from testbed.io import write_json

    if stream is None and not hasattr(scenario, "objects"):  # OBJECT checked before the mapping episode
        resolve_object(object_name, load_scenario(scenario).objects)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    if topo is None or stream is None:
        topo, stream = scenario_map(scenario)
    if stream.T_odom_base is None:
        raise ValueError(f"{stream.scenario}: the mapping stream has no wheel odometry (T_odom_base) to repeat")
    tree = tree or load_tree()
    cls, obj = resolve_object(object_name, stream.objects)
    k_obj = [o.name for o in stream.objects].index(obj.name)
    report = {"object": object_name, "class": cls, "scenario": stream.scenario, "seed": seed,
              "dead_reckoning": "wheels+gyro" if gyro else "wheels",
              "map": {"nodes": len(topo), "edges": len(topo.edges), "segments": len(topo.meta.get("segments") or [])}}
    T_odom_teach = teach_odometry(stream) if gyro else stream.T_odom_base
    true_node_base = {n.id: stream.T_world_camera[n.frame] @ inv(stream.T_base_camera) for n in topo.nodes}

    def true_base(frame: int) -> np.ndarray:  # a mapping image's true base pose (the report only)
        return stream.T_world_camera[frame] @ inv(stream.T_base_camera)

    sc = load_scenario(scenario if scenario is not None else stream.scenario)
    rng = np.random.default_rng(seed)  # the start pose's perturbation, then the navigator's RANSAC
    x, y, yaw = sc.robot.start
    sc.robot.start = [x + float(rng.uniform(-0.15, 0.15)), y + float(rng.uniform(-0.15, 0.15)),
                      yaw + float(rng.uniform(-8, 8))]
    sc.sensors.camera_width, sc.sensors.camera_height = topo.width, topo.height
    sc.sensors.lidar = False
    nav = Navigator(topo, stream, T_odom_teach, cls, tree, rng, target_node=target_node,
                    localise_every=localise_every, speed=speed, mono_cfg=MonoConfig())
    trace = []
    fix_log = []
    relative_log = []
    tracking_log = []
    done = False
    limit = 60.0 if max_seconds is None else float(max_seconds)
    last_log = time.perf_counter()
    with Episode(sc, seed=seed, light=None) as ep:
        dt = ep.dt
        cam_every = max(1, int(round(1.0 / (sc.sensors.camera_rate * dt))))
        k = 0
        imu = Gyro(np.random.default_rng([seed, GYRO_STREAM])) if gyro else None
        dr = DeadReckoning(ep.robot.T_odom_base)
        while k * dt < limit:
            t = k * dt
            T_world_base = ep.robot.T_world_base()
            if k > 0:
                T_wheels = ep.robot.T_odom_base.copy()
                ep.robot.update_odometry(dt)
                if imu is None:
                    T_odom = ep.robot.T_odom_base.copy()
                else:  # the wheels' travel, the gyro's heading
                    rate = imu.measure(wrap_angle(yaw_of(T_world_base) - yaw_prev) / dt, dt)
                    T_odom = dr.step_wheels(T_wheels, ep.robot.T_odom_base, rate * dt)
            else:
                T_odom = dr.T.copy()
            yaw_prev = yaw_of(T_world_base)
            trace.append(T_world_base[:3, 3].copy())
            if k % cam_every == 0:
                pose = nav.predict(T_odom)
                if nav.refs and pose is not None:  # the estimate's error (ground truth, for the report only)
                    tracking_log.append(_tracking_error(nav.refs, pose, T_world_base, true_base, t))
                if nav.wants_image(T_odom):
                    T_world_cam = T_world_base @ ep.T_base_camera
                    rgb, _, _ = render_rgbd(ep.client, T_world_cam, ep.camera_info, ep.light_at(t), ep.rng_camera,
                                            sc.sensors.noise, ep.renderer)
                    loc = nav.on_image(t, rgb, T_odom)
                    for fix in loc.fixes:
                        true_rel = inv(true_base(fix.frame)) @ T_world_base
                        err_m = float(np.linalg.norm(true_rel[:2, 3] - fix.T_ref_base[:2, 3]))
                        if fix.kind == "metric":
                            fix_log.append({"t": round(t, 2), "node": fix.node, "frame": fix.frame,
                                            "inliers": fix.inliers, "accepted": fix.accepted, "error_m": err_m})
                        else:
                            relative_log.append({"t": round(t, 2), "frame": fix.frame, "inliers": fix.inliers,
                                                 "accepted": fix.accepted, "error_deg": math.degrees(
                                                     wrap_angle(yaw_of(fix.T_ref_base) - yaw_of(true_rel))),
                                                 "error_m": err_m})
                    log.debug("t %.1f: -> %s", t, [(f.kind, f.frame, f.inliers) for f in loc.fixes])
                    if loc.planned or loc.stop:
                        report["target_node"] = nav.target
                    if loc.stop:
                        if nav.reason:
                            report["reason"] = nav.reason
                        break
                    if loc.planned:
                        report.update({"start_node": nav.start, "path": nav.path, "route_m": nav.route_m})
                        if max_seconds is None:
                            limit = t + 30.0 + 2.5 * nav.route_m / speed
            v, w, done = nav.control(t, T_odom)
            ep.robot.command(v, w, dt)
            p.stepSimulation(physicsClientId=ep.client)
            k += 1
            if time.perf_counter() - last_log > 30.0:
                last_log = time.perf_counter()
                log.info("navigate to %s: t = %.0f s, route %s, %d fixes", object_name, t,
                         "-" if nav.route is None else f"{nav.progress}/{len(nav.route)}", nav.tracker.fixes)
            if done:
                # let the robot come to rest
                for _ in range(int(0.5 / dt)):
                    ep.robot.command(0.0, 0.0, dt)
                    p.stepSimulation(physicsClientId=ep.client)
                trace.append(ep.robot.T_world_base()[:3, 3].copy())
                break
        T_end = ep.robot.T_world_base()
        sim_seconds = k * dt
    trace = np.asarray(trace)
    target = nav.target
    report.setdefault("target_node", target)
    tracker = nav.tracker
    report.update({"reached": done, "start_pose_world": sc.robot.start,
                   "path_length_m": float(np.sum(np.linalg.norm(np.diff(trace[:, :2], axis=0), axis=1))),
                   "sim_seconds": sim_seconds, "wall_seconds": time.perf_counter() - wall0,
                   "localisation": {"attempts": nav.attempts, "fixes": len(fix_log), "accepted": tracker.fixes,
                                    "rejected": tracker.rejected, "relative_fixes": sum(h["accepted"] for h in relative_log),
                                    "relative_heading_error_deg_median": float(np.median(np.abs(
                                        [h["error_deg"] for h in relative_log if h["accepted"]])))
                                    if any(h["accepted"] for h in relative_log) else None,
                                    "seconds_per_attempt": nav.seconds / max(1, nav.attempts),
                                    "fix_error_m_median": float(np.median([f["error_m"] for f in fix_log]))
                                    if fix_log else None},
                   "fixes": fix_log, "relative_fixes": relative_log, "tracking": tracking_log})
    if target is None:
        report.update({"success": False, "final_distance_m": None, "distance_to_object_m": None,
                       "reason": "never localised" if not tracker.fixes else f"no node of the map holds {cls}"})
        write_json(out / "navigate.json", report)
        return report
    end_xy = T_end[:2, 3]
    report.update({
        "final_distance_m": float(np.linalg.norm(end_xy - true_node_base[target][:2, 3])),
        "distance_to_object_m": float(np.linalg.norm(end_xy - obj.T_world_obj[:2, 3])),
        "target_node_to_object_m": float(np.linalg.norm(true_node_base[target][:2, 3] - obj.T_world_obj[:2, 3])),
        "target_node_shows_object": stream.object_in_view(topo.nodes[target].frame, k_obj, 0.3),
    })
    report["success"] = bool(report["final_distance_m"] <= SUCCESS_M)
    write_json(out / "navigate.json", report)
    _plot(out / "navigate.png", topo, stream, true_node_base, trace, target, report, obj)
    return report


def _tracking_error(refs: list[RouteImage], pose: np.ndarray, T_world_base: np.ndarray, true_base, t: float) -> dict:
    """The pose estimate's error relative to the route image nearest it, in that image's base frame:
    along (x, forward) and across (y, left) the route, and in heading (ground truth: the report only)."""
    k = int(np.argmin([np.linalg.norm(r.T[:2, 3] - pose[:2, 3]) for r in refs]))
    est = inv(refs[k].T) @ pose
    true = inv(true_base(refs[k].frame)) @ T_world_base
    return {"t": round(t, 2), "frame": refs[k].frame, "along_m": round(float(est[0, 3] - true[0, 3]), 3),
            "across_m": round(float(est[1, 3] - true[1, 3]), 3),
            "yaw_deg": round(math.degrees(wrap_angle(yaw_of(est) - yaw_of(true))), 2)}


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
    report = navigate(args.object, args.scenario, args.out, args.seed, args.max_seconds,
                      gyro=not getattr(args, "wheels_only", False))
    fd = report["final_distance_m"]
    print(json.dumps({k: report[k] for k in ("object", "scenario", "seed", "target_node", "success",
                                             "final_distance_m", "distance_to_object_m", "path_length_m")}, indent=1))
    print(f"wrote {args.out}/navigate.json" + ("" if fd is None else f" ({fd:.2f} m from the target node)"))
    return 0 if report["success"] else 1


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def batch(scenarios=("experiment3_columns", "shelf_corridor", "office_loop_twice"), seeds=range(10),
          out_dir="out/topomap/navigate", gyro: bool = True) -> dict:
    """Ten seeded navigation runs per scenario, the object asked for cycling through the objects the
    map holds (seed k asks for the k mod n-th; those without a node are listed). Writes
    ``navigate_batch.json``."""
    from testbed.io import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tree = load_tree()
    summary = {"success_m": SUCCESS_M, "dead_reckoning": "wheels+gyro" if gyro else "wheels", "scenarios": {}}
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
            r = navigate(obj.name, name, out / name / f"seed{seed}", seed, topo=topo, stream=stream, tree=tree, gyro=gyro)
            rows.append({k: r.get(k) for k in ("object", "seed", "target_node", "success", "reached", "final_distance_m",
                                               "distance_to_object_m", "target_node_to_object_m",
                                               "target_node_shows_object", "path_length_m", "sim_seconds", "wall_seconds")})
            log.info("%s seed %d -> %s: %s m", name, seed, obj.name, rows[-1]["final_distance_m"])
            summary["scenarios"][name] = {"runs": rows, "successes": sum(bool(x["success"]) for x in rows),
                                          "map": {"nodes": len(topo), "segments": topo.meta.get("segments")}}
            write_json(out / "navigate_batch.json", summary)
    return summary




def parse_seeds(text: str) -> range:
    """``"0-9"`` or ``"3"``: the seeds of a batch."""
    lo, _, hi = text.partition("-")
    try:
        return range(int(lo), int(hi or lo) + 1)
    except ValueError:
        raise InputError(f"--seeds: expected N or N-M (e.g. 0-9), got {text!r}") from None


def batch_args(a) -> int:
    """``dopeslam navigate-batch``: ``batch`` over the named scenarios and seeds, then its summary."""
    res = batch(a.scenarios.split(","), parse_seeds(a.seeds), a.out, gyro=not a.wheels_only)
    for name, s in res["scenarios"].items():
        print(f"{name}: {s['successes']}/{len(s['runs'])} within {SUCCESS_M} m of the target node")
        for r in s["runs"]:
            fd = r["final_distance_m"]
            print(f"  seed {r['seed']}: {r['object']:<12} node {r['target_node']}  "
                  f"{_fmt(fd)} m from the node, "
                  f"{_fmt(r['distance_to_object_m'])} m from the object")
    print(f"wrote {a.out}/navigate_batch.json")
    return 0
