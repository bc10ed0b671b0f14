"""The topological-map paper's semantic topological map (sections 2-3.4): nodes are key frames (visual words,
pose, object attributes), edges carry relative poses; built from a monocular image stream, saved
and loaded, used to localise by retrieval (``stack.topomap.localisation``) and to plan to the node
holding an object.

Building (``TopoMapper``): every image goes through the monocular pose pipeline
(``stack.topomap.mono_pose``, ORPE by default); each of its key frames becomes a node (at most one image in
ten, none while the robot stands still). A node keeps

* its key frame's visual words (``stack.loops.place_recognition``: Shi-Tomasi + SIFT quantised by the
  vocabulary tree; the node's TF-IDF vector goes into the retrieval database),
* its pose ``T_map_camera`` (map = the first key frame's camera, metric from the given baseline),
* its pose-pipeline features with their triangulated points (for a metric fix against the node),
* object attributes: the colour-verified HOG detections in its image (small boxes dropped, as the
  seed does: they are objects far from the node).

Edges join consecutive nodes with ``T_a_b`` (camera a <- camera b). When tracking is lost (five
failed frames) the pipeline re-initialises from the next two key frames with the baseline given by
wheel odometry (the seed has no such restart: its map would end there; the map's ``segments`` say
where it happened). The new segment's first key frame is placed in the map by relocalising it
against the last nodes (a ``relocalised`` edge); when that fails, by the wheel odometry's relative
pose (an ``odometry`` edge).

Files: ``DIR/topo_map.json`` (nodes, edges, attributes, poses, camera) + ``DIR/topo_map.npz``
(per-node features, points and place descriptors; arrays only), written atomically.
"""
from __future__ import annotations

import heapq
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stack.io import atomic_path, write_json
from stack.topomap.mono_pose import Features, MonoConfig, detect_features, match_features
from stack.topomap.mono_vo import MonoVO
from stack.transforms import inv

log = logging.getLogger(__name__)
FORMAT_VERSION = 1
REVISIT = "revisit"  # the edge kind joining a node to the same place on an earlier pass


@dataclass
class ObjectAttribute:
    cls: str
    score: float
    box: list  # x0 y0 x1 y1, pixels of the node's image
    colour_distance: float | None = None

    @property
    def height_px(self) -> float:
        return float(self.box[3] - self.box[1])


@dataclass
class Node:
    id: int
    frame: int  # index of the image in the mapping stream
    stamp: float
    T_map_camera: np.ndarray
    segment: int = 0
    attributes: list[ObjectAttribute] = field(default_factory=list)
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # pose-pipeline features
    desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 128), np.float32))
    points_map: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # NaN where no 3D point
    place_desc: np.ndarray | None = None  # place-recognition descriptors (None: no description, e.g. dark)
    words: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # visual word ids (TF-IDF vector)
    word_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def features(self) -> Features:
        return Features(self.uv, self.desc.astype(np.float32))


@dataclass
class Edge:
    a: int
    b: int
    T_a_b: np.ndarray  # camera a <- camera b
    kind: str = "visual"  # visual (the pose pipeline) | odometry (a bridge over lost tracking)

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.T_a_b[:3, 3]))


class TopoMap:
    def __init__(self, K: np.ndarray, width: int, height: int, T_base_camera: np.ndarray, meta: dict | None = None):
        self.K = np.asarray(K, dtype=float)
        self.width, self.height = int(width), int(height)
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        self.nodes: list[Node] = []
        self.edges: list[Edge] = []
        self.meta = dict(meta or {})
        self._db = None
        self._db_ids: list[int] = []

    def __len__(self) -> int:
        return len(self.nodes)

    # -- graph
    def add_edge(self, a: int, b: int, kind: str = "visual", T_a_b: np.ndarray | None = None) -> Edge:
        if T_a_b is None:
            T_a_b = inv(self.nodes[a].T_map_camera) @ self.nodes[b].T_map_camera
        e = Edge(a, b, T_a_b, kind)
        self.edges.append(e)
        return e

    def neighbours(self, forward_only: bool = False) -> dict[int, list[tuple[int, float]]]:
        """Adjacency with edge costs. ``forward_only``: the mapping run's edges only the way it drove
        them (``revisit`` edges, joining one place seen on two passes, stay both ways)."""
        adj: dict[int, list[tuple[int, float]]] = {n.id: [] for n in self.nodes}
        for e in self.edges:
            w = e.length_m + 0.05  # a small cost per edge: fewer hops among equal lengths
            adj[e.a].append((e.b, w))
            if not forward_only or e.kind == REVISIT:
                adj[e.b].append((e.a, w))
        return adj

    def shortest_path(self, start: int, goal: int, forward_only: bool = False) -> list[int] | None:
        """Dijkstra over the graph (undirected unless ``forward_only``), edge cost = translation
        length (+ 5 cm per hop)."""
        adj = self.neighbours(forward_only)
        dist = {start: 0.0}
        prev: dict[int, int] = {}
        heap = [(0.0, start)]
        while heap:
            d, u = heapq.heappop(heap)
            if u == goal:
                break
            if d > dist.get(u, np.inf):
                continue
            for v, w in adj[u]:
                nd = d + w
                if nd < dist.get(v, np.inf):
                    dist[v] = nd
                    prev[v] = u
                    heapq.heappush(heap, (nd, v))
        if goal not in dist:
            return None
        path = [goal]
        while path[-1] != start:
            path.append(prev[path[-1]])
        return path[::-1]

    @property
    def min_score(self) -> float:
        """Detections are kept in the nodes from the detector's threshold; the map's object attributes
        are those scoring at least this (``meta['attribute_min_score']``)."""
        return float(self.meta.get("attribute_min_score", 0.0))

    def attributes(self, node: Node) -> list[ObjectAttribute]:
        return [a for a in node.attributes if a.score >= self.min_score]

    def nodes_with(self, cls: str, min_height_px: float = 0.0) -> list[tuple[int, ObjectAttribute]]:
        """(node id, attribute) of class ``cls``, largest box first."""
        out = [(n.id, a) for n in self.nodes for a in self.attributes(n) if a.cls == cls and a.height_px >= min_height_px]
        return sorted(out, key=lambda x: -x[1].height_px)

    def target_node(self, cls: str) -> int | None:
        """The node holding ``cls``: the one where its box is largest (the robot is nearest it there)."""
        found = self.nodes_with(cls)
        return found[0][0] if found else None

    def semantic_matrix(self) -> list[dict]:
        """The paper's Table 1: per node its visual words, object attributes and pose."""
        from stack.transforms import to_xyz_quat

        rows = []
        for n in self.nodes:
            xyz, q = to_xyz_quat(n.T_map_camera)
            rows.append({"node": n.id, "visual_words": int(len(n.words)),
                         "objects": sorted({a.cls for a in self.attributes(n)}),
                         "xyz": [round(float(v), 4) for v in xyz], "quat_xyzw": [round(float(v), 5) for v in q]})
        return rows

    # -- retrieval
    def retrieval_database(self, tree):
        """The nodes' TF-IDF vectors in a place database (``stack.loops.place_recognition``)."""
        from stack.loops.place_recognition import PlaceDatabase

        if self._db is None or self._db.tree is not tree:
            self._db = PlaceDatabase(tree)
            self._db_ids = []
            for n in self.nodes:
                self._db.add(n.place_desc)
                self._db_ids.append(n.id)
        return self._db

    def retrieve(self, tree, place_desc: np.ndarray | None, k: int = 3) -> list[tuple[int, float]]:
        if place_desc is None:
            return []
        db = self.retrieval_database(tree)
        return [(self._db_ids[m.key_frame], m.score) for m in db.query(place_desc, k=k)]

    # -- files
    def save(self, out_dir: str | Path) -> Path:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        meta = {"format_version": FORMAT_VERSION, "K": self.K.tolist(), "width": self.width, "height": self.height,
                "T_base_camera": self.T_base_camera.tolist(), "meta": self.meta,
                "nodes": [{"id": n.id, "frame": n.frame, "stamp": n.stamp, "segment": n.segment,
                           "T_map_camera": n.T_map_camera.tolist(),
                           "attributes": [{"cls": a.cls, "score": a.score, "box": [float(v) for v in a.box],
                                           "colour_distance": a.colour_distance} for a in n.attributes],
                           "has_place_desc": n.place_desc is not None} for n in self.nodes],
                "edges": [{"a": e.a, "b": e.b, "kind": e.kind, "T_a_b": e.T_a_b.tolist()} for e in self.edges],
                "semantic_matrix": self.semantic_matrix()}
        arrays = {}
        for n in self.nodes:
            arrays[f"n{n.id}_uv"] = n.uv.astype(np.float32)
            arrays[f"n{n.id}_desc"] = n.desc.astype(np.float16)
            arrays[f"n{n.id}_points"] = n.points_map.astype(np.float32)
            arrays[f"n{n.id}_words"] = n.words.astype(np.int64)
            arrays[f"n{n.id}_word_weights"] = n.word_weights.astype(np.float32)
            if n.place_desc is not None:
                arrays[f"n{n.id}_place"] = n.place_desc.astype(np.float16)
        with atomic_path(out / "topo_map.npz") as tmp:
            np.savez_compressed(tmp, **arrays)
        write_json(out / "topo_map.json", meta, indent=1)  # last: its presence says the arrays are complete
        return out / "topo_map.json"

    @staticmethod
    def load(path: str | Path) -> "TopoMap":
        """From ``DIR`` or ``DIR/topo_map.json`` (with ``topo_map.npz`` beside it)."""
        path = Path(path)
        if path.is_dir():
            path = path / "topo_map.json"
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: unreadable topological map ({exc})") from exc
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"{path}: field 'format_version': expected {FORMAT_VERSION}, got {meta.get('format_version')}")
        npz = path.with_suffix(".npz")
        try:
            arrays = np.load(npz, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{npz}: unreadable topological map arrays ({exc})") from exc
        m = TopoMap(np.array(meta["K"]), meta["width"], meta["height"], np.array(meta["T_base_camera"]), meta.get("meta"))
        for i, nd in enumerate(meta["nodes"]):
            nid = nd["id"]
            if nid != i:
                raise ValueError(f"{path}: field 'nodes.{i}.id': expected {i}, got {nid}")
            try:
                n = Node(nid, nd["frame"], nd["stamp"], np.array(nd["T_map_camera"]), nd.get("segment", 0),
                         [ObjectAttribute(a["cls"], a["score"], a["box"], a.get("colour_distance"))
                          for a in nd["attributes"]],
                         arrays[f"n{nid}_uv"].astype(np.float64), arrays[f"n{nid}_desc"].astype(np.float32),
                         arrays[f"n{nid}_points"].astype(np.float64),
                         arrays[f"n{nid}_place"].astype(np.float32) if nd.get("has_place_desc") else None,
                         arrays[f"n{nid}_words"], arrays[f"n{nid}_word_weights"].astype(np.float64))
            except KeyError as exc:
                raise ValueError(f"{npz}: missing array {exc.args[0]} for node {nid}") from None
            m.nodes.append(n)
        for j, e in enumerate(meta["edges"]):
            if not (0 <= e["a"] < len(m.nodes) and 0 <= e["b"] < len(m.nodes)):
                raise ValueError(f"{path}: field 'edges.{j}': node ids out of range")
            m.edges.append(Edge(e["a"], e["b"], np.array(e["T_a_b"]), e.get("kind", "visual")))
        return m


# --- building -----------------------------------------------------------------------------------------

@dataclass
class MapperConfig:
    method: str = "orpe"
    init_min_flow_frac: float = 0.03  # median image motion (of max(width, height)) before initialising
    init_min_baseline_m: float = 0.1
    init_max_frames: int = 40  # give up on an initial key frame after this many frames (start again)
    min_attribute_height_px: float = 20.0  # the seed drops small boxes (objects far from the node); 320x240 px
    detector_threshold: float = 0.0  # detections kept in the nodes
    attribute_min_score: float = 0.7  # ... and those counted as the node's object attributes
    relocalise_nodes: int = 6  # a new segment is first relocalised against this many last nodes
    relocalise_min_inliers: int = 20
    seed: int = 0


def camera_motion_from_odometry(T_odom_base_a: np.ndarray, T_odom_base_b: np.ndarray, T_base_camera: np.ndarray) -> np.ndarray:
    """T_cam_a_cam_b from two wheel-odometry poses."""
    return inv(T_base_camera) @ inv(T_odom_base_a) @ T_odom_base_b @ T_base_camera


class TopoMapper:
    """Feed images in order with ``add``; ``topo`` is the map so far."""

    def __init__(self, K, image_size, T_base_camera, tree=None, detector=None, cfg: MapperConfig | None = None,
                 mono_cfg: MonoConfig | None = None, meta: dict | None = None):
        self.cfg = cfg or MapperConfig()
        self.mono_cfg = mono_cfg or MonoConfig()
        self.K = np.asarray(K, dtype=float)
        self.size = tuple(image_size)
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        self.tree = tree
        self.detector = detector
        self.topo = TopoMap(self.K, self.size[0], self.size[1], self.T_base_camera, meta)
        self.topo.meta.setdefault("method", self.cfg.method)
        self.topo.meta.setdefault("attribute_min_score", self.cfg.attribute_min_score)
        self.vo: MonoVO | None = None
        self.segment = -1
        self.T_map_seg = np.eye(4)
        self._cand = None  # (index, stamp, feats, rgb, odom) candidate first key frame
        self._kf_nodes = 0  # VO key frames already turned into nodes (current segment)
        self._last_ok = None  # (index, T_map_camera, odom) of the last tracked frame
        self.frames = 0
        self.failed_frames = 0
        self.seconds = {"features": 0.0, "pose": 0.0, "place": 0.0, "detector": 0.0}
        self.segments: list[dict] = []
        self._images: dict[int, tuple] = {}  # frame -> (rgb, odom) kept until its key frame is decided
        self._bridge = "odometry"

    def add(self, index: int, stamp: float, rgb: np.ndarray, T_odom_base: np.ndarray | None = None) -> None:
        import cv2

        self.frames += 1
        t0 = time.perf_counter()
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        feats = detect_features(gray, self.mono_cfg)
        self.seconds["features"] += time.perf_counter() - t0
        t1 = time.perf_counter()
        self._images[index] = (rgb, T_odom_base)
        if self.vo is None or self.vo.failed:
            self._try_initialise(index, stamp, feats, rgb, T_odom_base)
        else:
            res = self.vo.process(feats, index, stamp)
            if res.ok:
                self._last_ok = (index, self.T_map_seg @ res.T_world_camera, T_odom_base)
            else:
                self.failed_frames += 1
            if self.vo.failed:
                log.info("tracking lost at frame %d (%d nodes so far)", index, len(self.topo))
                self.segments[-1]["end_frame"] = index
                self._cand = None
        self.seconds["pose"] += time.perf_counter() - t1
        self._emit_nodes()
        # images are needed until their key frame is decided; keep the last few
        for k in [k for k in self._images if k < index - 60]:
            del self._images[k]

    def _try_initialise(self, index, stamp, feats, rgb, odom) -> None:
        cfg = self.cfg
        if self._cand is None or index - self._cand[0] > cfg.init_max_frames:
            self._cand = (index, stamp, feats, rgb, odom)
            return
        ci, cs, cf, _, co = self._cand
        i0, i1, _ = match_features(cf, feats, 2 * self.mono_cfg.search_radius_frac * max(self.size),
                                   self.mono_cfg.max_descriptor_distance)
        if len(i0) < 20:
            self._cand = (index, stamp, feats, rgb, odom)
            return
        flow = float(np.median(np.linalg.norm(feats.uv[i1] - cf.uv[i0], axis=1)))
        if flow < cfg.init_min_flow_frac * max(self.size):
            return
        if odom is None or co is None:
            raise ValueError("TopoMapper.add: the given baseline needs wheel odometry (T_odom_base) with the images")
        T_c0_c1 = camera_motion_from_odometry(co, odom, self.T_base_camera)
        baseline = float(np.linalg.norm(T_c0_c1[:3, 3]))
        if baseline < cfg.init_min_baseline_m:
            return
        vo = MonoVO(self.K, self.size, cfg.method, self.mono_cfg, cfg.seed + len(self.segments))
        if not vo.initialise(cf, feats, baseline, ci, index, cs, stamp):
            return
        # the new segment's frame in the map: its first key frame relocalised against the last nodes
        # (their points, in RANSAC); failing that, where the wheel odometry puts it
        self._bridge = "odometry"
        if not self.topo.nodes:
            self.T_map_seg = np.eye(4)
        else:
            from stack.topomap.localisation import localise

            fix = localise(self.topo, self._cand[3], None, cfg=self.mono_cfg, feats=cf, method=cfg.method,
                           rng=np.random.default_rng(cfg.seed + index),
                           candidates=[n.id for n in self.topo.nodes[-cfg.relocalise_nodes:]][::-1])
            if fix is not None and fix.inliers >= cfg.relocalise_min_inliers:
                self.T_map_seg = fix.T_map_camera
                self._bridge = "relocalised"
            else:
                li, T_map_last, lo = self._last_ok if self._last_ok is not None else (None, self.topo.nodes[-1].T_map_camera, None)
                if lo is not None and co is not None:
                    self.T_map_seg = T_map_last @ camera_motion_from_odometry(lo, co, self.T_base_camera)
                else:
                    self.T_map_seg = T_map_last
        self.vo = vo
        self.segment += 1
        self._kf_nodes = 0
        self.segments.append({"segment": self.segment, "start_frame": ci, "end_frame": None, "baseline_m": baseline,
                              "bridge": self._bridge if self.segment > 0 else None})
        self._last_ok = (index, self.T_map_seg @ inv(vo.keyframes[-1].T_cw), odom)
        log.info("segment %d initialised on frames %d-%d (baseline %.2f m)", self.segment, ci, index, baseline)

    def _emit_nodes(self) -> None:
        """Key frames of the current segment not yet nodes become nodes (after BA had a look at them:
        a key frame is emitted once the next one exists, or at ``finish``)."""
        if self.vo is None:
            return
        kfs = self.vo.keyframes
        upto = len(kfs) - 1 if not self.vo.failed else len(kfs)
        while self._kf_nodes < upto:
            self._add_node(kfs[self._kf_nodes], bridge=self._kf_nodes == 0)
            self._kf_nodes += 1

    def finish(self) -> TopoMap:
        if self.vo is not None:
            while self._kf_nodes < len(self.vo.keyframes):
                self._add_node(self.vo.keyframes[self._kf_nodes], bridge=self._kf_nodes == 0)
                self._kf_nodes += 1
        self.topo.meta.update({"segments": self.segments, "frames": self.frames, "failed_frames": self.failed_frames,
                               "seconds": self.seconds})
        return self.topo

    def _add_node(self, kf, bridge: bool) -> None:
        from stack.loops.place_recognition import describe

        rgb, odom = self._images.get(kf.index, (None, None))
        T_map_cam = self.T_map_seg @ inv(kf.T_cw)
        P = self.vo.point_array()
        pts = np.full((len(kf.feats), 3), np.nan)
        has = kf.pid >= 0
        if has.any():
            pts[has] = (self.T_map_seg[:3, :3] @ P[kf.pid[has]].T).T + self.T_map_seg[:3, 3]
        node = Node(len(self.topo.nodes), kf.index, kf.stamp, T_map_cam, self.segment, [], kf.feats.uv.copy(),
                    kf.feats.desc.copy(), pts)
        if rgb is not None:
            t0 = time.perf_counter()
            f = describe(rgb)
            node.place_desc = None if f is None else f.descriptors
            if f is not None and self.tree is not None:
                node.words, node.word_weights = self.tree.bow(f.descriptors)
            self.seconds["place"] += time.perf_counter() - t0
            if self.detector is not None:
                t0 = time.perf_counter()
                node.attributes = node_attributes(self.detector, rgb, self.cfg.detector_threshold,
                                                  self.cfg.min_attribute_height_px)
                self.seconds["detector"] += time.perf_counter() - t0
        prev = self.topo.nodes[-1] if self.topo.nodes else None
        self.topo.nodes.append(node)
        self.topo._db = None
        if prev is not None:
            self.topo.add_edge(prev.id, node.id, self._bridge if bridge else "visual")


def node_attributes(detector, rgb: np.ndarray, threshold: float = 0.0, min_height_px: float = 20.0) -> list[ObjectAttribute]:
    """Colour-verified detections in a node's image, one per class (its best), small boxes dropped.
    Box heights are compared at the detector's working width (320 px)."""
    scale = detector.width / rgb.shape[1]
    best: dict[str, ObjectAttribute] = {}
    for d in detector.detect(rgb, threshold=threshold, colour_step=True):
        if (d.box[3] - d.box[1]) * scale < min_height_px:
            continue
        if d.cls not in best or d.score > best[d.cls].score:
            best[d.cls] = ObjectAttribute(d.cls, float(d.score), [float(v) for v in d.box], d.colour_distance)
    return list(best.values())


# --- scoring against ground truth ---------------------------------------------------------------------

def score_map(topo: TopoMap, objects, node_T_world_camera: dict[int, np.ndarray], visible: dict[int, set],
              T_world_map: np.ndarray | None = None) -> dict:
    """Per object: is its class attributed to a node whose view contains it, and how far is that node
    from the object. ``node_T_world_camera``: true camera pose of each node's image; ``visible``:
    the object names in view (enough of them visible) in each node's image; ``T_world_map``: the map
    frame in world (to report the nodes' pose errors).

    A false attribution is an attribute on a node whose view holds no object of that class."""
    rows = []
    false_attr = 0
    n_attr = 0
    names_by_cls: dict[str, list[str]] = {}
    for o in objects:
        names_by_cls.setdefault(o.cls, []).append(o.name)
    for n in topo.nodes:
        for a in topo.attributes(n):
            n_attr += 1
            if not any(name in visible.get(n.id, set()) for name in names_by_cls.get(a.cls, [])):
                false_attr += 1
    for o in objects:
        obj_xyz = o.T_world_obj[:3, 3]
        att = topo.nodes_with(o.cls)
        correct = [(nid, a) for nid, a in att if o.name in visible.get(nid, set())]
        target = topo.target_node(o.cls)
        row = {"object": o.name, "class": o.cls, "attributed_nodes": len(att), "correct_nodes": len(correct),
               "found": bool(correct), "target_node": target}
        if target is not None:
            Tw = node_T_world_camera[target]
            row["target_node_contains_object"] = o.name in visible.get(target, set())
            row["target_node_distance_m"] = float(np.linalg.norm(Tw[:3, 3] - obj_xyz))
            row["target_node_distance_xy_m"] = float(np.linalg.norm(Tw[:2, 3] - obj_xyz[:2]))
            if T_world_map is not None:
                est = T_world_map @ topo.nodes[target].T_map_camera
                row["target_node_pose_error_m"] = float(np.linalg.norm(est[:3, 3] - Tw[:3, 3]))
        rows.append(row)
    pose_err = []
    if T_world_map is not None:
        for n in topo.nodes:
            est = T_world_map @ n.T_map_camera
            pose_err.append(float(np.linalg.norm(est[:3, 3] - node_T_world_camera[n.id][:3, 3])))
    summary = {"nodes": len(topo.nodes), "edges": len(topo.edges),
               "odometry_edges": sum(e.kind == "odometry" for e in topo.edges),
               "relocalised_edges": sum(e.kind == "relocalised" for e in topo.edges),
               "objects": len(objects), "found": sum(r["found"] for r in rows),
               "attributes": n_attr, "false_attributions": false_attr,
               "node_position_rmse_m": float(np.sqrt(np.mean(np.square(pose_err)))) if pose_err else None,
               "node_position_max_m": float(np.max(pose_err)) if pose_err else None}
    return {"objects": rows, "summary": summary}
