"""The semantic topological map: graph, planning, target node, save/load, scoring against truth."""
import numpy as np
import pytest

from stack.messages import ObjectTruth
from stack.topomap.topological_map import Node, ObjectAttribute, TopoMap, score_map
from stack.transforms import make_T

K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
T_BASE_CAM = make_T(np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]]), [0.2, 0, 0.3])


def small_map():
    m = TopoMap(K, 640, 480, T_BASE_CAM, {"scenario": "test"})
    rng = np.random.default_rng(0)
    for i in range(5):
        T = np.eye(4)
        T[2, 3] = 0.5 * i  # the camera moves forward (optical z)
        pts = rng.normal(size=(30, 3))
        pts[::3] = np.nan
        n = Node(i, 10 * i, 1.0 * i, T, 0, [], rng.uniform(0, 600, (30, 2)),
                 rng.normal(size=(30, 128)).astype(np.float32), pts,
                 rng.normal(size=(40, 128)).astype(np.float32) if i != 2 else None,
                 np.arange(5, dtype=np.int64), np.full(5, 0.2))
        m.nodes.append(n)
        if i:
            m.add_edge(i - 1, i, "visual" if i != 3 else "odometry")
    m.nodes[1].attributes.append(ObjectAttribute("Mustard", 0.4, [10, 10, 30, 60], 0.05))
    m.nodes[3].attributes.append(ObjectAttribute("Mustard", 0.9, [10, 10, 50, 110], 0.03))
    m.nodes[4].attributes.append(ObjectAttribute("Yogurt", 0.2, [100, 100, 120, 125], None))
    return m


def test_planning_and_the_node_holding_an_object():
    m = small_map()
    assert m.shortest_path(0, 4) == [0, 1, 2, 3, 4]
    assert m.shortest_path(4, 1) == [4, 3, 2, 1]
    m.add_edge(0, 4)  # a shortcut (2 m) is cheaper than four hops of 0.5 m + 5 cm each
    assert m.shortest_path(0, 4) == [0, 4]
    assert m.target_node("Mustard") == 3  # the largest box
    assert m.target_node("Cookies") is None
    assert [n for n, _ in m.nodes_with("Mustard", min_height_px=60)] == [3]
    assert m.edges[0].length_m == pytest.approx(0.5)


def test_save_and_load_round_trip(tmp_path):
    m = small_map()
    m.save(tmp_path)
    m2 = TopoMap.load(tmp_path)
    assert len(m2) == 5 and len(m2.edges) == 4
    assert [e.kind for e in m2.edges] == [e.kind for e in m.edges]
    for a, b in zip(m.nodes, m2.nodes):
        np.testing.assert_allclose(a.T_map_camera, b.T_map_camera)
        np.testing.assert_allclose(a.uv, b.uv, atol=1e-3)
        np.testing.assert_allclose(a.desc, b.desc, atol=2e-3)
        np.testing.assert_array_equal(np.isnan(a.points_map), np.isnan(b.points_map))
        assert (a.place_desc is None) == (b.place_desc is None)
        assert [x.cls for x in a.attributes] == [x.cls for x in b.attributes]
    assert m2.target_node("Mustard") == 3
    assert m2.semantic_matrix()[3]["objects"] == ["Mustard"]
    (tmp_path / "topo_map.npz").unlink()
    with pytest.raises(ValueError, match="topo_map.npz"):
        TopoMap.load(tmp_path)


def test_scoring_against_ground_truth():
    m = small_map()
    objects = [ObjectTruth("Mustard", "Mustard", make_T(None, [1.0, 0.2, 1.4]), np.ones(3) * 0.1),
               ObjectTruth("Yogurt", "Yogurt", make_T(None, [0.0, 0.0, 9.0]), np.ones(3) * 0.1)]
    truth = {n.id: n.T_map_camera for n in m.nodes}
    visible = {0: set(), 1: {"Mustard"}, 2: set(), 3: {"Mustard"}, 4: set()}  # Yogurt is in no node's view
    res = score_map(m, objects, truth, visible, T_world_map=np.eye(4))
    rows = {r["object"]: r for r in res["objects"]}
    assert rows["Mustard"]["found"] and rows["Mustard"]["correct_nodes"] == 2
    assert rows["Mustard"]["target_node"] == 3
    assert rows["Mustard"]["target_node_distance_m"] == pytest.approx(np.linalg.norm([1.0, 0.2, 1.4 - 1.5]))
    assert not rows["Yogurt"]["found"]
    assert res["summary"]["false_attributions"] == 1  # the Yogurt attribute on node 4
    assert res["summary"]["found"] == 1
    assert res["summary"]["node_position_rmse_m"] == pytest.approx(0.0)


def test_forward_only_planning_and_revisit_edges(tmp_path):
    from stack.topomap.topological_map import REVISIT

    m = small_map()
    assert m.shortest_path(4, 1, forward_only=True) is None  # the mapping run never drove 4 -> 1
    assert m.shortest_path(1, 4, forward_only=True) == [1, 2, 3, 4]
    m.add_edge(1, 4, REVISIT, np.eye(4))  # node 4 is node 1's place seen again: both ways
    assert m.shortest_path(4, 2, forward_only=True) == [4, 1, 2]
    m2 = TopoMap.load(m.save(tmp_path))
    assert m2.shortest_path(4, 2, forward_only=True) == [4, 1, 2]


def test_relative_pose_up_to_scale_from_all_features_of_a_node():
    """The heading fix: rotation of the current camera against a node's view from 2D-2D matches
    (no 3D points needed), on synthetic correspondences with a known 6 deg turn."""
    from stack.topomap.mono_pose import Features
    from stack.topomap.localisation import relative_pose_up_to_scale

    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-4, 4, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(3, 12, 200)]  # node camera
    a = np.radians(6.0)
    R_cur_node = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # about camera y
    t = np.array([0.1, 0.0, -0.5])
    Xc = X @ R_cur_node.T + t

    def project(P):
        return (P[:, :2] / P[:, 2:]) * 610.0 + [319.5, 239.5]

    desc = rng.normal(size=(200, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    m = TopoMap(K, 640, 480, T_BASE_CAM)
    m.nodes.append(Node(0, 0, 0.0, np.eye(4), 0, [], project(X), desc, np.full((200, 3), np.nan)))
    cur = Features(project(Xc) + rng.normal(0, 0.3, (200, 2)), desc)
    R, direction, inliers, scale = relative_pose_up_to_scale(K, m.nodes[0].features, cur)
    assert inliers > 150
    np.testing.assert_allclose(R, R_cur_node.T, atol=2e-3)  # R_node_cur
    centre = -R_cur_node.T @ t  # the current camera in the node camera's frame
    np.testing.assert_allclose(direction, centre / np.linalg.norm(centre), atol=2e-2)
    assert scale is None  # no points given
    assert relative_pose_up_to_scale(K, m.nodes[0].features, Features(cur.uv[:10], desc[:10])) is None  # too few matches
    # with some of the node's 3D points, the translation's metric scale (ORPE's one-point scale)
    pts = np.full_like(X, np.nan)
    pts[::4] = X[::4]
    scale = relative_pose_up_to_scale(K, m.nodes[0].features, cur, points=pts)[3]
    assert scale is not None and scale[1] >= 30
    assert scale[0] == pytest.approx(np.linalg.norm(t), rel=0.05)


def test_points_from_an_image_pair_then_a_metric_pose_against_them():
    """Route images without a node's points: triangulated from a second image 0.4 m further on (the
    baseline given, as the wheel odometry gives it on a straight), then ORPE of a third view against
    them recovers its metric pose."""
    from stack.topomap.mono_pose import Features
    from stack.topomap.localisation import points_from_pair, pose_against_points

    rng = np.random.default_rng(7)
    X = np.c_[rng.uniform(-4, 4, 300), rng.uniform(-1.5, 1.5, 300), rng.uniform(3, 10, 300)]  # reference camera

    def view(R, t):  # pixels of X in a camera with x_cam = R x_ref + t
        P = X @ R.T + t
        return (P[:, :2] / P[:, 2:]) * 610.0 + [319.5, 239.5]

    desc = rng.normal(size=(300, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    ref = Features(view(np.eye(3), np.zeros(3)) + rng.normal(0, 0.2, (300, 2)), desc)
    a = np.radians(2.0)
    R2 = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    other = Features(view(R2, np.array([0.05, 0.0, -0.4])) + rng.normal(0, 0.2, (300, 2)), desc)
    pts = points_from_pair(K, ref, other, baseline_m=float(np.hypot(0.05, 0.4)))
    assert pts is not None and pts.shape == X.shape
    ok = np.isfinite(pts[:, 0])
    assert ok.sum() > 150
    assert np.median(np.linalg.norm(pts[ok] - X[ok], axis=1) / np.linalg.norm(X[ok], axis=1)) < 0.03
    # a third view 1 m on and 0.2 m to the side: its pose against the triangulated points, in metres
    t3 = np.array([-0.2, 0.0, -1.0])
    cur = Features(view(np.eye(3), t3) + rng.normal(0, 0.2, (300, 2)), desc)
    T_ref_cur, inliers = pose_against_points(K, ref, pts, cur, np.random.default_rng(0))
    assert inliers > 100
    np.testing.assert_allclose(T_ref_cur[:3, 3], -t3, atol=0.05)
    assert pose_against_points(K, ref, np.full_like(pts, np.nan), cur, np.random.default_rng(0)) is None
    with pytest.raises(ValueError, match="baseline_m"):
        points_from_pair(K, ref, other, baseline_m=0.0)
