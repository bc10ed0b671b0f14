"""``dopeslam navigate OBJECT [SCENARIO] --out DIR --seed N``: the topological-map paper's navigation (its
section 4.4) in the simulator, as teach and repeat over the topological map.

1. The map (the teach run): the scenario's scripted drive (its own seed, lit); its camera stream
   (cached) goes through ``stack.topomap.topological_map.TopoMapper`` (ORPE poses, vocabulary-tree words,
   colour-verified HOG attributes), then places seen on two passes are joined by ``revisit``
   edges (``stack.topomap.topological_map.add_revisit_edges``). The map is cached by scenario and settings. The
   mapping run's dead reckoning is kept beside it (``teach_odometry``: the wheels' travel, the
   gyro's heading).
2. The navigation run (the repeat): a fresh episode of the same scenario whose start pose is
   perturbed by the seed (up to +-0.15 m, +-8 deg) and whose sensor noise is the paper's. The robot
   software sees the camera, its wheel odometry and its gyro only:
   - localise by retrieval (vocabulary tree -> candidate nodes, verified by ORPE against a node's
     points), the first candidate along the mapping run that verifies;
   - plan over the topological graph (Dijkstra, the mapping run's edges the way it drove them,
     revisit edges both ways) to the node holding OBJECT (``route_target``: of the nodes whose box
     of OBJECT is at least half its largest, the nearest over the graph);
   - repeat the mapping run's trajectory along the path: its dead reckoning between consecutive
     nodes, chained through revisit edges by their visual relative pose (the route frame); a
     pure-pursuit controller follows it on the robot's own dead reckoning, corrected by fixes
     against the route's images nearest the predicted pose (its nodes, and the mapping run's
     images every 0.5 m or 10 deg between them): metric fixes (ORPE against an image's points: a
     node's, scaled by its segment's odometry, or points triangulated from two mapping images on
     a straight) and, where those fail, fixes up to scale (essential matrix on all of an image's
     features: the heading, and the position along the visual direction). Each fix is relative to
     one image, so the map's segments need not agree with each other;
   - the last metres converge on the target node's key frame (a fix every frame); done once a fix
     confirms the arrival.
   Dead reckoning: the skid-steer base's wheel odometry over-counts turns two- to five-fold (the
   wheels slip sideways, most at low yaw rates: ``benchmarks/bench_dead_reckoning.py``), and
   differently in each turn, so between fixes the heading is the gyro's
   (``sim.imu.Gyro``, ``stack.dead_reckoning``), as the Jackal's own odometry fuses its IMU;
   ``gyro=False`` (``--wheels-only``) keeps the wheels' heading.
3. Scored with ground truth: ``final_distance_m`` (robot base to the target node's true base
   position, in the plane), ``distance_to_object_m`` (to the object, in the plane),
   ``path_length_m`` (driven); the report's ``tracking`` log is the estimate's error along and
   across the route.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stack.topomap.mono_pose import MonoConfig, detect_features
from stack.topomap.topological_map import (REVISIT, MapperConfig, TopoMap, TopoMapper, add_revisit_edges, localise,
                            points_from_pair, pose_against_points, relative_pose_up_to_scale)
from stack.dead_reckoning import DeadReckoning
from stack.transforms import inv, wrap_angle, yaw_of
from testbed.topomap.stream import CameraStream, cache_root, camera_stream

log = logging.getLogger(__name__)
SUCCESS_M = 0.5
MIN_FIX_INLIERS = 12  # ORPE inliers (reprojection < 2 px) for a full fix against a node


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
        log.warning("%s missing: the map gets no object attributes (train with python -m testbed.topomap.detector train)",
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
    raise SystemExit(f"OBJECT: expected one of the scenario's objects {[o.name for o in objects]}, got {name!r}")


class PoseTracker:
    """The robot's pose in the route frame: visual fixes, dead reckoning in between."""

    def __init__(self):
        self.T_route_base_fix: np.ndarray | None = None
        self.T_odom_fix: np.ndarray | None = None
        self.fix_time = -np.inf
        self.any_fix_time = -np.inf
        self.fixes = 0
        self.rejected = 0

    def predict(self, T_odom_base: np.ndarray) -> np.ndarray | None:
        if self.T_route_base_fix is None:
            return None
        return self.T_route_base_fix @ inv(self.T_odom_fix) @ T_odom_base

    def correct(self, T_route_base: np.ndarray, T_odom_base: np.ndarray, t: float, weak: bool = False) -> bool:
        """Take a visual fix unless it disagrees with the prediction by more than odometry can have
        drifted since the last fix (the gate widens with the time since it). ``weak``: a fix
        up to scale (``relative_fix``); it does not reset the age of the last metric fix."""
        pred = self.predict(T_odom_base)
        if pred is not None:
            age = t - self.fix_time
            d = float(np.linalg.norm(pred[:2, 3] - T_route_base[:2, 3]))
            dyaw = math.degrees(abs(wrap_angle(yaw_of(T_route_base) - yaw_of(pred))))
            if weak:  # already blended with the prediction; noisier than a metric fix
                outlier = d > 0.75 or dyaw > min(30.0, 6.0 + 2.0 * (t - self.any_fix_time))
            else:
                outlier = d > 0.4 + 0.1 * age or dyaw > 12.0 + 2.0 * age
            if outlier:  # keep the odometry
                self.rejected += 1
                return False
        self.T_route_base_fix = T_route_base.copy()
        self.T_odom_fix = T_odom_base.copy()
        self.any_fix_time = t
        if weak:
            return True
        self.fix_time = t
        self.fixes += 1
        return True


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


def segment_scales(topo: TopoMap, T_odom_node: dict[int, np.ndarray], min_length_m: float = 2.0) -> dict[int, float]:
    """Per map segment, metres of the mapping run's wheel odometry per map unit along its visual
    edges (the monocular scale drifts along a segment; 1.0 for a segment shorter than
    ``min_length_m``)."""
    num: dict[int, float] = {}
    den: dict[int, float] = {}
    for e in topo.edges:
        a, b = topo.nodes[e.a], topo.nodes[e.b]
        if e.kind != "visual" or a.segment != b.segment:
            continue
        num[a.segment] = num.get(a.segment, 0.0) + float(np.linalg.norm(T_odom_node[b.id][:2, 3] - T_odom_node[a.id][:2, 3]))
        den[a.segment] = den.get(a.segment, 0.0) + e.length_m
    # a segment starts metric (its baseline is the odometry's); a short one keeps that scale
    return {s: (num[s] / den[s] if den[s] > 1e-6 and num[s] >= min_length_m else 1.0) for s in num}


def route_target(topo: TopoMap, cls: str, start: int, T_odom_node: dict[int, np.ndarray],
                 size_frac: float = 0.5) -> int | None:
    """The node to drive to for ``cls``: of the nodes holding it with a box at least ``size_frac`` of
    its largest (the object seen from near), the one nearest the start over the graph, driven the
    way the mapping run drove."""
    found = topo.nodes_with(cls)
    if not found:
        return None
    h_max = found[0][1].height_px
    best, best_len = None, np.inf
    for nid in {nid for nid, a in found if a.height_px >= size_frac * h_max}:
        path = topo.shortest_path(start, nid, forward_only=True)
        if path is None:
            continue
        length = route_length(topo, T_odom_node, path)
        if length < best_len:
            best, best_len = nid, length
    return best


def _edges(topo: TopoMap) -> dict[tuple[int, int], object]:
    out = {}
    for e in topo.edges:
        out.setdefault((e.a, e.b), e)
        out.setdefault((e.b, e.a), e)
    return out


def route_length(topo: TopoMap, T_odom_node: dict[int, np.ndarray], path: list[int]) -> float:
    """Metres along the path: the mapping run's odometry between consecutive nodes, ~0 at a revisit."""
    edges = _edges(topo)
    return sum(0.0 if edges[(a, b)].kind == REVISIT else
               float(np.linalg.norm(T_odom_node[b][:2, 3] - T_odom_node[a][:2, 3])) for a, b in zip(path, path[1:]))


def route_poses(topo: TopoMap, T_odom_node: dict[int, np.ndarray], path: list[int],
                scales: dict[int, float]) -> dict[int, np.ndarray]:
    """Each path node's base pose in the route frame (the mapping run's odometry frame at the path's
    first node): chained by the odometry between consecutive nodes of one pass, by the revisit
    edge's visual relative pose (scaled) where the path jumps to another pass."""
    edges = _edges(topo)
    T_bc = topo.T_base_camera
    R = {path[0]: T_odom_node[path[0]]}
    for u, v in zip(path, path[1:]):
        e = edges[(u, v)]
        if e.kind == REVISIT:
            T_cam = e.T_a_b.copy()
            T_cam[:3, 3] *= scales.get(topo.nodes[e.a].segment, 1.0)
            T_u_v = T_cam if e.a == u else inv(T_cam)
            R[v] = R[u] @ T_bc @ T_u_v @ inv(T_bc)
        else:
            R[v] = R[u] @ inv(T_odom_node[u]) @ T_odom_node[v]
    return R


def teach_route(topo: TopoMap, T_odom_teach: np.ndarray, path: list[int], R: dict[int, np.ndarray],
                spacing: float = 0.1) -> np.ndarray:
    """The route to repeat: the mapping run's dead-reckoned trajectory through the path's nodes
    (x, y, yaw in the route frame), one point every ``spacing`` metres."""
    edges = _edges(topo)
    pts = [R[path[0]]]
    for a, b in zip(path, path[1:]):
        if edges[(a, b)].kind == REVISIT:
            pts.append(R[b])
            continue
        G = R[a] @ inv(T_odom_teach[topo.nodes[a].frame])
        fa, fb = topo.nodes[a].frame, topo.nodes[b].frame
        step = 1 if fb >= fa else -1
        pts.extend(G @ T_odom_teach[f] for f in range(fa + step, fb + step, step))
    xy = [(float(T[0, 3]), float(T[1, 3]), yaw_of(T)) for T in pts]
    out = [xy[0]]
    for q in xy[1:-1]:
        if math.hypot(q[0] - out[-1][0], q[1] - out[-1][1]) >= spacing:
            out.append(q)
    if len(xy) > 1:
        out.append(xy[-1])
    return np.asarray(out)


@dataclass
class RouteImage:
    """An image of the mapping run along the route: its frame, base pose in the route frame, features,
    3D points and, for the report only, its true base pose."""
    frame: int
    T: np.ndarray
    feats: object
    T_world: np.ndarray
    points: np.ndarray | None = None  # its features' 3D points in its camera frame (NaN where none)
    scale: float = 1.0  # metres per unit of ``points`` (a node's: its segment's; an image's are metric)
    node: int | None = None  # the map node it is, if it is one


def route_references(topo: TopoMap, stream: CameraStream, T_odom_teach: np.ndarray, path: list[int],
                     R: dict[int, np.ndarray], cfg: MonoConfig, scales: dict[int, float], spacing: float = 0.5,
                     turn_deg: float = 10.0) -> list[RouteImage]:
    """The mapping run's images along the path, one every ``spacing`` metres or ``turn_deg`` of its
    odometry (visual teach and repeat keeps them: the map's nodes are sparse where tracking was
    lost, in turns and along bare walls). The path's nodes are among them, with their own features
    and points; the other images get points triangulated against a later (or earlier) image of the
    mapping run on a straight (``image_points``)."""
    edges = _edges(topo)
    T_bc = stream.T_base_camera

    def node_image(nid: int) -> RouteImage:
        n = topo.nodes[nid]
        T_cm = inv(n.T_map_camera)
        return RouteImage(n.frame, R[nid], n.features, stream.T_world_camera[n.frame] @ inv(T_bc),
                          n.points_map @ T_cm[:3, :3].T + T_cm[:3, 3], scales.get(n.segment, 1.0), nid)

    out = [node_image(path[0])]
    for a, b in zip(path, path[1:]):
        fa, fb = topo.nodes[a].frame, topo.nodes[b].frame
        if edges[(a, b)].kind != REVISIT and abs(fb - fa) > 1:
            G = R[a] @ inv(T_odom_teach[fa])
            step = 1 if fb >= fa else -1
            last = T_odom_teach[fa]
            for f in range(fa + step, fb, step):
                To = T_odom_teach[f]
                turned = abs(wrap_angle(yaw_of(To) - yaw_of(last))) > math.radians(turn_deg)
                if not turned and (np.linalg.norm(To[:2, 3] - last[:2, 3]) < spacing or
                                   np.linalg.norm(To[:2, 3] - T_odom_teach[fb][:2, 3]) < 0.5 * spacing):
                    continue
                last = To
                feats = detect_features(cv2.cvtColor(stream.rgb[f], cv2.COLOR_RGB2GRAY), cfg)
                out.append(RouteImage(f, G @ To, feats, stream.T_world_camera[f] @ inv(T_bc),
                                      image_points(stream, T_odom_teach, f, feats, cfg)))
        out.append(node_image(b))
    return out


def image_points(stream: CameraStream, T_odom_teach: np.ndarray, f: int, feats, cfg: MonoConfig,
                 baseline_m: tuple[float, float] = (0.35, 0.8), max_turn_deg: float = 10.0) -> np.ndarray | None:
    """3D points (metres, image ``f``'s camera frame) for a mapping image's features: triangulated
    against the first image after it (else before it) that the mapping run's dead reckoning puts
    ``baseline_m`` away on a straight; None where there is none (a turn in place) or the pair does
    not verify."""
    T_bc = stream.T_base_camera
    To = T_odom_teach
    for step in (1, -1):
        g = f + step
        while 0 <= g < len(stream):
            d = float(np.linalg.norm(To[g][:2, 3] - To[f][:2, 3]))
            if abs(wrap_angle(yaw_of(To[g]) - yaw_of(To[f]))) > math.radians(max_turn_deg) or d > baseline_m[1]:
                break
            if d >= baseline_m[0]:
                T_cam = inv(T_bc) @ inv(To[f]) @ To[g] @ T_bc
                other = detect_features(cv2.cvtColor(stream.rgb[g], cv2.COLOR_RGB2GRAY), cfg)
                pts = points_from_pair(stream.info.K, feats, other, float(np.linalg.norm(T_cam[:3, 3])), cfg)
                if pts is not None:
                    return pts
                break
            g += step
    return None


def navigate(object_name: str, scenario=None, out_dir="out/navigate", seed: int = 0, max_seconds: float | None = None,
             localise_every: int = 3, speed: float = 0.5, topo: TopoMap | None = None,
             stream: CameraStream | None = None, tree=None, target_node: int | None = None, gyro: bool = True) -> dict:
    """Teach and repeat over the topological map: the path is planned over the graph, the robot
    repeats the mapping run's trajectory along it (its dead reckoning between the path's nodes,
    the route frame) and corrects its pose in that frame with visual fixes against the route's
    images (each fix is relative to one image, so the map's segments need not agree with each
    other); the last metres converge on the target node's key frame. ``gyro``: dead reckoning
    with the gyro's heading (else the wheel odometry's)."""
    import pybullet as p

    from sim.camera import render_rgbd
    from sim.episode import Episode
    from sim.imu import Gyro
    from sim.scenario import load_scenario
    from testbed.io import write_json

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
    T_bc = topo.T_base_camera
    T_odom_teach = teach_odometry(stream) if gyro else stream.T_odom_base
    T_odom_node = {n.id: T_odom_teach[n.frame] for n in topo.nodes}
    scales = segment_scales(topo, T_odom_node)
    true_node_base = {n.id: stream.T_world_camera[n.frame] @ inv(stream.T_base_camera) for n in topo.nodes}

    R = dict(T_odom_node)  # node poses in the route frame (until a path is planned: the odometry's)

    def metric_fix(feats, pose, near_end: bool):
        """ORPE against the 3D points of the route images nearest the predicted pose (near the end, the
        target node's first): (the image, T_route_base, T_image_base, inliers) of the best, or None."""
        cands = _nearest_refs(refs, pose, with_points=True)
        if near_end:
            cands = [len(refs) - 1] + [c for c in cands if c != len(refs) - 1][:1]
        best = None
        for k in cands:
            res = pose_against_points(topo.K, refs[k].feats, refs[k].points, feats, rng, mono_cfg)
            if res is not None and (best is None or res[1] > best[3]):
                T_ref_base = _base_relative(res[0], refs[k].scale, T_bc)
                best = (refs[k], refs[k].T @ T_ref_base, T_ref_base, res[1])
        return best

    def relative_fix(feats, pose, T_odom, t, T_world_base) -> bool:
        """No metric fix: the pose up to scale against the route's images nearest the predicted pose
        (essential matrix on all their features). The heading is taken; the position too where the
        robot is far enough from the image for the direction to tell (the scale from the image's
        points, else from the prediction); both part of the way, by the fix's inliers (noisier than
        a metric fix)."""
        near = _nearest_refs(refs, pose, n=4)
        # the direction tells the position best from a reference some way off: those first
        far = [k for k in near if np.linalg.norm(refs[k].T[:2, 3] - pose[:2, 3]) >= 0.7]
        rel = None
        for k in (far + [k for k in near if k not in far])[:2]:
            rel = relative_pose_up_to_scale(topo.K, refs[k].feats, feats, mono_cfg, min_inliers=20,
                                            points=refs[k].points)
            if rel is not None:
                ref = refs[k]
                break
        if rel is None:
            return False
        R_nc, c_dir, inliers, scale = rel
        T_node_cam = np.eye(4)
        T_node_cam[:3, :3] = R_nc
        T0 = T_bc @ T_node_cam @ inv(T_bc)  # the node-relative base pose with the camera on the node's
        d = (T_bc[:3, :3] @ c_dir)[:2]
        pred_rel = inv(ref.T) @ pose
        s = max(0.0, float(d @ (pred_rel[:2, 3] - T0[:2, 3])) / max(float(d @ d), 1e-9))
        if scale and scale[1] >= 5 and 0.0 < scale[0] < 10.0:  # the scale from the image's points
            s = scale[0] * ref.scale
        T_rel = T0.copy()
        T_rel[:2, 3] = T0[:2, 3] + s * d
        if np.linalg.norm(s * d) < 0.7 and not scale:  # too near for the direction: the heading alone
            T_rel[:3, 3] = pred_rel[:3, 3]
        T_fix = ref.T @ T_rel
        # weighted by its inliers: 0.1 of the way at 20 or fewer, half-way from 45
        alpha = float(np.clip((inliers - 15) / 60.0, 0.1, 0.5))
        blend = pose.copy()
        blend[:2, 3] = pose[:2, 3] + alpha * (T_fix[:2, 3] - pose[:2, 3])
        yaw_b = yaw_of(pose) + alpha * wrap_angle(yaw_of(T_fix) - yaw_of(pose))
        c, sn = math.cos(yaw_b), math.sin(yaw_b)
        blend[:3, :3] = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
        ok = tracker.correct(blend, T_odom, t, weak=True)
        true_rel = inv(ref.T_world) @ T_world_base
        relative_log.append({"t": round(t, 2), "frame": ref.frame, "inliers": inliers, "accepted": ok,
                            "error_deg": math.degrees(wrap_angle(yaw_of(T_rel) - yaw_of(true_rel))),
                            "error_m": float(np.linalg.norm(T_rel[:2, 3] - true_rel[:2, 3]))})
        return ok

    sc = load_scenario(scenario if scenario is not None else stream.scenario)
    rng = np.random.default_rng(seed)
    x, y, yaw = sc.robot.start
    sc.robot.start = [x + float(rng.uniform(-0.15, 0.15)), y + float(rng.uniform(-0.15, 0.15)),
                      yaw + float(rng.uniform(-8, 8))]
    sc.sensors.camera_width, sc.sensors.camera_height = topo.width, topo.height
    sc.sensors.lidar = False
    mono_cfg = MonoConfig()
    tracker = PoseTracker()
    path: list[int] | None = None
    route = None
    refs: list[RouteImage] = []
    target = target_node
    progress = 0
    trace = []
    fix_log = []
    relative_log = []
    tracking_log = []
    loc_seconds = 0.0
    loc_calls = 0
    done = False
    limit = 60.0 if max_seconds is None else float(max_seconds)
    last_log = time.perf_counter()
    arrived_t = None
    with Episode(sc, seed=seed, light=None) as ep:
        dt = ep.dt
        cam_every = max(1, int(round(1.0 / (sc.sensors.camera_rate * dt))))
        v = w = 0.0
        frame_no = 0
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
            pose = tracker.predict(T_odom)
            near_end = route is not None and pose is not None and progress >= len(route) - 15
            if k % cam_every == 0:
                if refs and pose is not None:  # the estimate's error (ground truth, for the report only)
                    tracking_log.append(_tracking_error(refs, pose, T_world_base, t))
                if frame_no % (1 if near_end else localise_every) == 0:
                    T_world_cam = T_world_base @ ep.T_base_camera
                    rgb, _, _ = render_rgbd(ep.client, T_world_cam, ep.camera_info, ep.light_at(t), ep.rng_camera,
                                            sc.sensors.noise, ep.renderer)
                    t0 = time.perf_counter()
                    feats = detect_features(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), mono_cfg)
                    mfix = None
                    if path is None:  # where am I: retrieval over the whole map
                        fix = _first_fix(topo, rgb, tree, rng, mono_cfg, feats)
                        if fix is not None:
                            node = topo.nodes[fix.node]
                            T_node_base = _base_relative(inv(node.T_map_camera) @ fix.T_map_camera,
                                                         scales.get(node.segment, 1.0), T_bc)
                            mfix = (RouteImage(node.frame, R[node.id], None, true_node_base[node.id], node=node.id),
                                    R[node.id] @ T_node_base, T_node_base, fix.inliers)
                    elif pose is not None:  # the route's images nearest the predicted pose, facing the same way
                        mfix = metric_fix(feats, pose, near_end)
                    loc_seconds += time.perf_counter() - t0
                    loc_calls += 1
                    if (mfix is None or mfix[3] < MIN_FIX_INLIERS) and path is not None and pose is not None:
                        relative_fix(feats, pose, T_odom, t, T_world_base)
                    log.debug("t %.1f: -> %s; %s", t, None if mfix is None else (mfix[0].frame, mfix[3]),
                              relative_log[-1:] if relative_log else "")
                    if mfix is not None and mfix[3] >= MIN_FIX_INLIERS:
                        ref, T_route_base, T_ref_base, inliers = mfix
                        accepted = tracker.correct(T_route_base, T_odom, t)
                        true_rel = inv(ref.T_world) @ T_world_base
                        fix_log.append({"t": round(t, 2), "node": ref.node, "frame": ref.frame, "inliers": inliers,
                                        "accepted": accepted,
                                        "error_m": float(np.linalg.norm(true_rel[:2, 3] - T_ref_base[:2, 3]))})
                        if path is None and accepted:
                            start = ref.node
                            if target is None:
                                target = route_target(topo, cls, start, T_odom_node)
                            report["target_node"] = target
                            path = None if target is None else topo.shortest_path(start, target, forward_only=True)
                            if path is None:
                                if target is not None:
                                    report["reason"] = f"no path from node {start} to node {target}"
                                break
                            R = route_poses(topo, T_odom_node, path, scales)
                            route = teach_route(topo, T_odom_teach, path, R)
                            refs = route_references(topo, stream, T_odom_teach, path, R, mono_cfg, scales)
                            progress = 0
                            route_m = float(np.sum(np.linalg.norm(np.diff(route[:, :2], axis=0), axis=1)))
                            report.update({"start_node": start, "path": path, "route_m": route_m})
                            if max_seconds is None:
                                limit = t + 30.0 + 2.5 * route_m / speed
                frame_no += 1
            # control: pure pursuit along the route in the route frame
            pose = tracker.predict(T_odom)
            if route is None or pose is None:
                v, w = 0.0, 0.3 if t > 10.0 else 0.0  # look around for a first fix
            else:
                xr, yr, yawr = float(pose[0, 3]), float(pose[1, 3]), yaw_of(pose)
                window = route[progress:progress + 40, :2]
                progress += int(np.argmin(np.linalg.norm(window - [xr, yr], axis=1)))
                gx, gy = route[-1, 0], route[-1, 1]
                dist_end = math.hypot(gx - xr, gy - yr)
                last = progress >= len(route) - 3
                if last and dist_end < 0.05:
                    # arrived by the estimate: done once a fix near the node confirms it (waiting
                    # up to 5 s for one, localising every frame)
                    arrived_t = t if arrived_t is None else arrived_t
                    v, w = 0.0, 0.0
                    done = t - tracker.any_fix_time < 1.0 or t - arrived_t > 5.0
                else:
                    look = progress
                    while look < len(route) - 1 and math.hypot(route[look, 0] - xr, route[look, 1] - yr) < 0.5:
                        look += 1
                    lx, ly = (gx, gy) if last else (route[look, 0], route[look, 1])
                    err = wrap_angle(math.atan2(ly - yr, lx - xr) - yawr)
                    w = float(np.clip(2.0 * err, -1.0, 1.0))
                    v = speed * max(0.0, math.cos(err)) ** 2 if abs(err) < 0.7 else 0.0
                    if progress >= len(route) - 15:
                        v = min(v, 0.5 * dist_end + 0.03)
            ep.robot.command(v, w, dt)
            p.stepSimulation(physicsClientId=ep.client)
            k += 1
            if time.perf_counter() - last_log > 30.0:
                last_log = time.perf_counter()
                log.info("navigate to %s: t = %.0f s, route %s, %d fixes", object_name, t,
                         "-" if route is None else f"{progress}/{len(route)}", tracker.fixes)
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
    report.setdefault("target_node", target)
    report.update({"reached": done, "start_pose_world": sc.robot.start,
                   "path_length_m": float(np.sum(np.linalg.norm(np.diff(trace[:, :2], axis=0), axis=1))),
                   "sim_seconds": sim_seconds, "wall_seconds": time.perf_counter() - wall0,
                   "localisation": {"attempts": loc_calls, "fixes": len(fix_log), "accepted": tracker.fixes,
                                    "rejected": tracker.rejected, "relative_fixes": sum(h["accepted"] for h in relative_log),
                                    "relative_heading_error_deg_median": float(np.median(np.abs(
                                        [h["error_deg"] for h in relative_log if h["accepted"]])))
                                    if any(h["accepted"] for h in relative_log) else None,
                                    "seconds_per_attempt": loc_seconds / max(1, loc_calls),
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


def _first_fix(topo: TopoMap, rgb, tree, rng, cfg: MonoConfig, feats, k: int = 10):
    """Retrieval proposes ``k`` nodes; the first of them along the mapping run that verifies (a route
    driven twice has twins of its start; teach and repeat starts at the first)."""
    from stack.loops.place_recognition import describe

    f = describe(rgb)
    if f is None:
        return None
    for nid in sorted(c for c, _ in topo.retrieve(tree, f.descriptors, k)):
        fix = localise(topo, rgb, tree, rng=rng, cfg=cfg, feats=feats, candidates=[nid])
        if fix is not None and fix.inliers >= 20:
            return fix
    return None


def _base_relative(T_ref_cam: np.ndarray, scale: float, T_bc: np.ndarray) -> np.ndarray:
    """A camera pose relative to a reference camera (translation in map units) as the base's pose
    relative to the reference's base, in metres (``scale``: metres per map unit)."""
    T = T_ref_cam.copy()
    T[:3, 3] *= scale
    return T_bc @ T @ inv(T_bc)


def _tracking_error(refs: list[RouteImage], pose: np.ndarray, T_world_base: np.ndarray, t: float) -> dict:
    """The pose estimate's error relative to the route image nearest it, in that image's base frame:
    along (x, forward) and across (y, left) the route, and in heading (ground truth: the report only)."""
    k = int(np.argmin([np.linalg.norm(r.T[:2, 3] - pose[:2, 3]) for r in refs]))
    est = inv(refs[k].T) @ pose
    true = inv(refs[k].T_world) @ T_world_base
    return {"t": round(t, 2), "frame": refs[k].frame, "along_m": round(float(est[0, 3] - true[0, 3]), 3),
            "across_m": round(float(est[1, 3] - true[1, 3]), 3),
            "yaw_deg": round(math.degrees(wrap_angle(yaw_of(est) - yaw_of(true))), 2)}


def _nearest_refs(refs: list[RouteImage], pose: np.ndarray, n: int = 2, max_m: float = 4.0,
                  with_points: bool = False) -> list[int]:
    """The route images nearest the predicted pose (within ``max_m``) and facing within 50 deg of it;
    ``with_points``: only those with 3D points."""
    yaw = yaw_of(pose)
    scored = sorted((float(np.linalg.norm(r.T[:2, 3] - pose[:2, 3])), k) for k, r in enumerate(refs)
                    if abs(wrap_angle(yaw_of(r.T) - yaw)) < math.radians(50) and
                    (not with_points or (r.points is not None and int(np.isfinite(r.points[:, 0]).sum()) >= 8)))
    return [k for d, k in scored[:n] if d < max_m]


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


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m testbed.topomap.navigate")
    ap.add_argument("--scenarios", default="experiment3_columns,shelf_corridor,office_loop_twice")
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--out", default="out/topomap/navigate")
    ap.add_argument("--wheels-only", action="store_true", help="dead reckoning from the wheel odometry alone")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    lo, _, hi = a.seeds.partition("-")
    res = batch(a.scenarios.split(","), range(int(lo), int(hi or lo) + 1), a.out, gyro=not a.wheels_only)
    for name, s in res["scenarios"].items():
        print(f"{name}: {s['successes']}/{len(s['runs'])} within {SUCCESS_M} m of the target node")
        for r in s["runs"]:
            fd = r["final_distance_m"]
            print(f"  seed {r['seed']}: {r['object']:<12} node {r['target_node']}  "
                  f"{_fmt(fd)} m from the node, "
                  f"{_fmt(r['distance_to_object_m'])} m from the object")
