"""Teach and repeat over the monocular topological map: the robot software of ``dopeslam navigate``
(the topological-map paper's section 4.4). It sees the camera, its own dead reckoning and the map;
the simulator (``testbed/topomap/navigate.py``) renders the images, steps the physics and scores the
run against ground truth.

- Localise by retrieval (vocabulary tree -> candidate nodes, verified by ORPE against a node's
  points), the first candidate along the mapping run that verifies.
- Plan over the topological graph (Dijkstra, the mapping run's edges the way it drove them,
  revisit edges both ways) to the node holding the object (``route_target``: of the nodes whose
  box of the object is at least half its largest, the nearest over the graph).
- Repeat the mapping run's trajectory along the path: its dead reckoning between consecutive
  nodes, chained through revisit edges by their visual relative pose (the route frame). A
  pure-pursuit controller follows it on the robot's own dead reckoning, corrected by fixes against
  the route's images nearest the predicted pose (its nodes, and the mapping run's images every
  0.5 m or 10 deg between them): metric fixes (ORPE against an image's points: a node's, scaled by
  its segment's odometry, or points triangulated from two mapping images on a straight) and, where
  those fail, fixes up to scale (essential matrix on all of an image's features: the heading, and
  the position along the visual direction). Each fix is relative to one image, so the map's
  segments need not agree with each other.
- The last metres converge on the target node's key frame (a fix every frame); done once a fix
  confirms the arrival.

``Navigator`` is the loop's state: ``wants_image`` (is this camera frame localised), ``on_image``
(the fixes, and the plan after the first), ``control`` (the velocity command).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from stack.topomap.mono_pose import MonoConfig, detect_features
from stack.topomap.localisation import localise, points_from_pair, pose_against_points, relative_pose_up_to_scale
from stack.topomap.topological_map import REVISIT, TopoMap
from stack.transforms import inv, wrap_angle, yaw_of

MIN_FIX_INLIERS = 12  # ORPE inliers (reprojection < 2 px) for a full fix against a node


class TeachRun(Protocol):
    """The mapping run's camera images, as the robot recorded them: ``rgb`` (N, H, W, 3) uint8,
    ``info.K`` the intrinsics, ``T_base_camera`` the extrinsics, ``len()`` the image count."""

    rgb: np.ndarray
    T_base_camera: np.ndarray

    def __len__(self) -> int: ...


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
    """An image of the mapping run along the route: its frame, base pose in the route frame, features
    and 3D points."""
    frame: int
    T: np.ndarray
    feats: object
    points: np.ndarray | None = None  # its features' 3D points in its camera frame (NaN where none)
    scale: float = 1.0  # metres per unit of ``points`` (a node's: its segment's; an image's are metric)
    node: int | None = None  # the map node it is, if it is one


def route_references(topo: TopoMap, teach: TeachRun, T_odom_teach: np.ndarray, path: list[int],
                     R: dict[int, np.ndarray], cfg: MonoConfig, scales: dict[int, float], spacing: float = 0.5,
                     turn_deg: float = 10.0) -> list[RouteImage]:
    """The mapping run's images along the path, one every ``spacing`` metres or ``turn_deg`` of its
    odometry (visual teach and repeat keeps them: the map's nodes are sparse where tracking was
    lost, in turns and along bare walls). The path's nodes are among them, with their own features
    and points; the other images get points triangulated against a later (or earlier) image of the
    mapping run on a straight (``image_points``)."""
    edges = _edges(topo)

    def node_image(nid: int) -> RouteImage:
        n = topo.nodes[nid]
        T_cm = inv(n.T_map_camera)
        return RouteImage(n.frame, R[nid], n.features, n.points_map @ T_cm[:3, :3].T + T_cm[:3, 3],
                          scales.get(n.segment, 1.0), nid)

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
                feats = detect_features(cv2.cvtColor(teach.rgb[f], cv2.COLOR_RGB2GRAY), cfg)
                out.append(RouteImage(f, G @ To, feats, image_points(teach, T_odom_teach, f, feats, cfg)))
        out.append(node_image(b))
    return out


def image_points(teach: TeachRun, T_odom_teach: np.ndarray, f: int, feats, cfg: MonoConfig,
                 baseline_m: tuple[float, float] = (0.35, 0.8), max_turn_deg: float = 10.0) -> np.ndarray | None:
    """3D points (metres, image ``f``'s camera frame) for a mapping image's features: triangulated
    against the first image after it (else before it) that the mapping run's dead reckoning puts
    ``baseline_m`` away on a straight; None where there is none (a turn in place) or the pair does
    not verify."""
    T_bc = teach.T_base_camera
    To = T_odom_teach
    for step in (1, -1):
        g = f + step
        while 0 <= g < len(teach):
            d = float(np.linalg.norm(To[g][:2, 3] - To[f][:2, 3]))
            if abs(wrap_angle(yaw_of(To[g]) - yaw_of(To[f]))) > math.radians(max_turn_deg) or d > baseline_m[1]:
                break
            if d >= baseline_m[0]:
                T_cam = inv(T_bc) @ inv(To[f]) @ To[g] @ T_bc
                other = detect_features(cv2.cvtColor(teach.rgb[g], cv2.COLOR_RGB2GRAY), cfg)
                pts = points_from_pair(teach.info.K, feats, other, float(np.linalg.norm(T_cam[:3, 3])), cfg)
                if pts is not None:
                    return pts
                break
            g += step
    return None


def first_fix(topo: TopoMap, rgb, tree, rng, cfg: MonoConfig, feats, k: int = 10):
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


def base_relative(T_ref_cam: np.ndarray, scale: float, T_bc: np.ndarray) -> np.ndarray:
    """A camera pose relative to a reference camera (translation in map units) as the base's pose
    relative to the reference's base, in metres (``scale``: metres per map unit)."""
    T = T_ref_cam.copy()
    T[:3, 3] *= scale
    return T_bc @ T @ inv(T_bc)


def nearest_refs(refs: list[RouteImage], pose: np.ndarray, n: int = 2, max_m: float = 4.0,
                 with_points: bool = False) -> list[int]:
    """The route images nearest the predicted pose (within ``max_m``) and facing within 50 deg of it;
    ``with_points``: only those with 3D points."""
    yaw = yaw_of(pose)
    scored = sorted((float(np.linalg.norm(r.T[:2, 3] - pose[:2, 3])), k) for k, r in enumerate(refs)
                    if abs(wrap_angle(yaw_of(r.T) - yaw)) < math.radians(50) and
                    (not with_points or (r.points is not None and int(np.isfinite(r.points[:, 0]).sum()) >= 8)))
    return [k for d, k in scored[:n] if d < max_m]


@dataclass
class Fix:
    """One visual fix: against the mapping image ``frame`` (map node ``node``, if it is one), the base's
    pose relative to that image's base (``T_ref_base``, metres), its inliers, whether the tracker took
    it. ``kind``: "metric" (ORPE against points) or "relative" (up to scale: essential matrix)."""
    kind: str
    frame: int
    node: int | None
    inliers: int
    accepted: bool
    T_ref_base: np.ndarray


@dataclass
class Localised:
    """What one localised image gave: its fixes (in the order taken), whether the path was planned on
    it, and ``stop`` where navigation cannot go on (``Navigator.reason`` says why)."""
    fixes: list[Fix] = field(default_factory=list)
    planned: bool = False
    stop: bool = False


class Navigator:
    """Teach and repeat towards the node holding ``cls``: localise, plan, follow the route.

    ``teach``: the mapping run's images; ``T_odom_teach``: its dead reckoning at each image; ``tree``:
    the vocabulary; ``rng``: the RANSAC random stream; ``target_node``: drive there instead of the
    node ``route_target`` picks; ``localise_every``: camera frames per localisation away from the end
    (every frame near it); ``speed``: the driving speed, m/s."""

    def __init__(self, topo: TopoMap, teach: TeachRun, T_odom_teach: np.ndarray, cls: str, tree, rng,
                 target_node: int | None = None, localise_every: int = 3, speed: float = 0.5,
                 mono_cfg: MonoConfig | None = None):
        self.topo, self.teach, self.T_odom_teach, self.cls, self.tree, self.rng = \
            topo, teach, T_odom_teach, cls, tree, rng
        self.localise_every, self.speed = localise_every, speed
        self.mono_cfg = mono_cfg or MonoConfig()
        self.T_bc = topo.T_base_camera
        self.T_odom_node = {n.id: T_odom_teach[n.frame] for n in topo.nodes}
        self.scales = segment_scales(topo, self.T_odom_node)
        self.R = dict(self.T_odom_node)  # node poses in the route frame (until a path is planned: the odometry's)
        self.tracker = PoseTracker()
        self.target = target_node
        self.start: int | None = None
        self.path: list[int] | None = None
        self.route: np.ndarray | None = None
        self.refs: list[RouteImage] = []
        self.route_m: float | None = None
        self.reason: str | None = None
        self.progress = 0
        self.frame_no = 0
        self.arrived_t: float | None = None
        self.attempts = 0
        self.seconds = 0.0

    def predict(self, T_odom: np.ndarray) -> np.ndarray | None:
        """The base pose in the route frame (None before the first fix)."""
        return self.tracker.predict(T_odom)

    def near_end(self, pose: np.ndarray | None) -> bool:
        return self.route is not None and pose is not None and self.progress >= len(self.route) - 15

    def wants_image(self, T_odom: np.ndarray) -> bool:
        """Call once per camera frame: whether to localise on this one (every ``localise_every``-th,
        every one near the end)."""
        near = self.near_end(self.tracker.predict(T_odom))
        want = self.frame_no % (1 if near else self.localise_every) == 0
        self.frame_no += 1
        return want

    def on_image(self, t: float, rgb: np.ndarray, T_odom: np.ndarray) -> Localised:
        """Localise on an image taken at ``t`` (odometry ``T_odom``): before a path, by retrieval over the
        whole map, then planning from the node found; after, against the route's images nearest the
        predicted pose (a fix up to scale where no metric fix works)."""
        out = Localised()
        pose = self.tracker.predict(T_odom)
        near_end = self.near_end(pose)
        t0 = time.perf_counter()
        feats = detect_features(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), self.mono_cfg)
        mfix = None
        if self.path is None:  # where am I: retrieval over the whole map
            fix = first_fix(self.topo, rgb, self.tree, self.rng, self.mono_cfg, feats)
            if fix is not None:
                node = self.topo.nodes[fix.node]
                T_node_base = base_relative(inv(node.T_map_camera) @ fix.T_map_camera,
                                            self.scales.get(node.segment, 1.0), self.T_bc)
                mfix = (RouteImage(node.frame, self.R[node.id], None, node=node.id),
                        self.R[node.id] @ T_node_base, T_node_base, fix.inliers)
        elif pose is not None:  # the route's images nearest the predicted pose, facing the same way
            mfix = self._metric_fix(feats, pose, near_end)
        self.seconds += time.perf_counter() - t0
        self.attempts += 1
        if (mfix is None or mfix[3] < MIN_FIX_INLIERS) and self.path is not None and pose is not None:
            rel = self._relative_fix(feats, pose, T_odom, t)
            if rel is not None:
                out.fixes.append(rel)
        if mfix is not None and mfix[3] >= MIN_FIX_INLIERS:
            ref, T_route_base, T_ref_base, inliers = mfix
            accepted = self.tracker.correct(T_route_base, T_odom, t)
            out.fixes.append(Fix("metric", ref.frame, ref.node, inliers, accepted, T_ref_base))
            if self.path is None and accepted:
                out.planned, out.stop = self._plan(ref.node), self.path is None
        return out

    def _plan(self, start: int) -> bool:
        """Plan from ``start`` to the target; False (``reason`` set where there is a target) if none."""
        topo = self.topo
        self.start = start
        if self.target is None:
            self.target = route_target(topo, self.cls, start, self.T_odom_node)
        self.path = None if self.target is None else topo.shortest_path(start, self.target, forward_only=True)
        if self.path is None:
            if self.target is not None:
                self.reason = f"no path from node {start} to node {self.target}"
            return False
        self.R = route_poses(topo, self.T_odom_node, self.path, self.scales)
        self.route = teach_route(topo, self.T_odom_teach, self.path, self.R)
        self.refs = route_references(topo, self.teach, self.T_odom_teach, self.path, self.R, self.mono_cfg,
                                     self.scales)
        self.progress = 0
        self.route_m = float(np.sum(np.linalg.norm(np.diff(self.route[:, :2], axis=0), axis=1)))
        return True

    def _metric_fix(self, feats, pose, near_end: bool):
        """ORPE against the 3D points of the route images nearest the predicted pose (near the end, the
        target node's first): (the image, T_route_base, T_image_base, inliers) of the best, or None."""
        refs = self.refs
        cands = nearest_refs(refs, pose, with_points=True)
        if near_end:
            cands = [len(refs) - 1] + [c for c in cands if c != len(refs) - 1][:1]
        best = None
        for k in cands:
            res = pose_against_points(self.topo.K, refs[k].feats, refs[k].points, feats, self.rng, self.mono_cfg)
            if res is not None and (best is None or res[1] > best[3]):
                T_ref_base = base_relative(res[0], refs[k].scale, self.T_bc)
                best = (refs[k], refs[k].T @ T_ref_base, T_ref_base, res[1])
        return best

    def _relative_fix(self, feats, pose, T_odom, t) -> Fix | None:
        """No metric fix: the pose up to scale against the route's images nearest the predicted pose
        (essential matrix on all their features). The heading is taken; the position too where the
        robot is far enough from the image for the direction to tell (the scale from the image's
        points, else from the prediction); both part of the way, by the fix's inliers (noisier than
        a metric fix). None where no image gives a pose."""
        refs, T_bc = self.refs, self.T_bc
        near = nearest_refs(refs, pose, n=4)
        # the direction tells the position best from a reference some way off: those first
        far = [k for k in near if np.linalg.norm(refs[k].T[:2, 3] - pose[:2, 3]) >= 0.7]
        rel = None
        for k in (far + [k for k in near if k not in far])[:2]:
            rel = relative_pose_up_to_scale(self.topo.K, refs[k].feats, feats, self.mono_cfg, min_inliers=20,
                                            points=refs[k].points)
            if rel is not None:
                ref = refs[k]
                break
        if rel is None:
            return None
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
        ok = self.tracker.correct(blend, T_odom, t, weak=True)
        return Fix("relative", ref.frame, ref.node, inliers, ok, T_rel)

    def control(self, t: float, T_odom: np.ndarray) -> tuple[float, float, bool]:
        """The velocity command (v m/s, w rad/s) and whether the robot has arrived: pure pursuit along the
        route in the route frame; before a fix, still for 10 s, then turning on the spot to find one."""
        pose = self.tracker.predict(T_odom)
        route = self.route
        if route is None or pose is None:
            return 0.0, (0.3 if t > 10.0 else 0.0), False  # look around for a first fix
        xr, yr, yawr = float(pose[0, 3]), float(pose[1, 3]), yaw_of(pose)
        window = route[self.progress:self.progress + 40, :2]
        self.progress += int(np.argmin(np.linalg.norm(window - [xr, yr], axis=1)))
        progress = self.progress
        gx, gy = route[-1, 0], route[-1, 1]
        dist_end = math.hypot(gx - xr, gy - yr)
        last = progress >= len(route) - 3
        if last and dist_end < 0.05:
            # arrived by the estimate: done once a fix near the node confirms it (waiting up to 5 s
            # for one, localising every frame)
            self.arrived_t = t if self.arrived_t is None else self.arrived_t
            return 0.0, 0.0, t - self.tracker.any_fix_time < 1.0 or t - self.arrived_t > 5.0
        look = progress
        while look < len(route) - 1 and math.hypot(route[look, 0] - xr, route[look, 1] - yr) < 0.5:
            look += 1
        lx, ly = (gx, gy) if last else (route[look, 0], route[look, 1])
        err = wrap_angle(math.atan2(ly - yr, lx - xr) - yawr)
        w = float(np.clip(2.0 * err, -1.0, 1.0))
        v = self.speed * max(0.0, math.cos(err)) ** 2 if abs(err) < 0.7 else 0.0
        if progress >= len(route) - 15:
            v = min(v, 0.5 * dist_end + 0.03)
        return v, w, False
