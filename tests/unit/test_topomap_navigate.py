"""The topological-map paper's navigation without an episode: object names, routes through a revisit
edge, the pose tracker's gate and the commands' arguments (a short mapping drive and navigation end to
end: ``tests/e2e/test_topomap_navigate_e2e.py``)."""
import numpy as np
import pytest


def test_object_names_and_classes_resolve():
    from stack.messages import ObjectTruth
    from testbed.topomap import InputError
    from testbed.topomap.navigate import resolve_object

    objs = [ObjectTruth("Mustard_3", "Mustard", np.eye(4), np.ones(3)), ObjectTruth("E", "E", np.eye(4), np.ones(3))]
    assert resolve_object("Mustard_3", objs)[0] == "Mustard"
    assert resolve_object("Mustard", objs)[1].name == "Mustard_3"
    with pytest.raises(InputError, match="Mustard_3"):
        resolve_object("Cookies", objs)


def _two_pass_map():
    """Pass 1: nodes 0-2 at x = 0, 1, 2 m; pass 2: nodes 3-5 at the same places, but the mapping run's
    odometry has drifted 0.5 m sideways and 0.1 rad by then. Map poses at half scale."""
    from stack.topomap.topological_map import REVISIT, Node, TopoMap
    from stack.transforms import make_T

    def rot_z(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])

    T_bc = make_T(np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]]), [0.2, 0, 0.3])
    m = TopoMap(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), 640, 480, T_bc)
    odom = {}
    for i in range(6):
        x = float(i % 3)
        T_map_base = make_T(None, [0.5 * x, 0, 0])
        m.nodes.append(Node(i, 10 * i, float(i), T_map_base @ T_bc, i // 3))
        drift = make_T(rot_z(0.1), [0, 0.5, 0]) if i >= 3 else np.eye(4)
        odom[i] = drift @ make_T(None, [x, 0, 0])
        if i:
            m.add_edge(i - 1, i, "visual" if i != 3 else "odometry")
    m.add_edge(0, 3, REVISIT, np.eye(4))
    return m, odom


def test_route_jumps_passes_through_a_revisit_edge():
    from stack.topomap.topological_map import ObjectAttribute
    from stack.topomap.navigation import route_length, route_poses, route_target, segment_scales, teach_route

    m, odom = _two_pass_map()
    scales = segment_scales(m, odom)
    assert scales == {0: pytest.approx(2.0), 1: pytest.approx(2.0)}  # odometry metres per map unit
    path = m.shortest_path(3, 2, forward_only=True)
    assert path == [3, 0, 1, 2]
    assert route_length(m, odom, path) == pytest.approx(2.0)
    R = route_poses(m, odom, path, scales)
    # in the route frame (pass 2's odometry at node 3) node 2 lies 2 m ahead of node 3
    np.testing.assert_allclose((np.linalg.inv(R[3]) @ R[2])[:3, 3], [2, 0, 0], atol=1e-9)
    # the mapping run's odometry at 10 frames per metre (frame 10 i is node i)
    T_odom = np.stack([odom[f // 10] @ np.array([[1, 0, 0, (f % 10) / 10], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
                       for f in range(60)])
    route = teach_route(m, T_odom, path, R)
    steps = np.linalg.norm(np.diff(route[:, :2], axis=0), axis=1)
    assert steps.max() < 0.25  # no jump (the drift is 0.5 m) where the path changes passes
    np.testing.assert_allclose(route[-1, :2], R[2][:2, 3])
    m.nodes[2].attributes.append(ObjectAttribute("Mustard", 1.0, [0, 0, 9, 50]))
    assert route_target(m, "Mustard", 3, odom) == 2


def test_pose_tracker_gates_outlying_fixes():
    from stack.topomap.navigation import PoseTracker

    tr = PoseTracker()
    T = np.eye(4)
    assert tr.correct(T, np.eye(4), 0.0)
    far = np.eye(4)
    far[0, 3] = 2.0
    assert not tr.correct(far, np.eye(4), 1.0)  # 2 m off one second after a fix
    assert tr.correct(far, np.eye(4), 30.0)  # odometry may have drifted that much in 30 s
    np.testing.assert_allclose(tr.predict(np.eye(4)), far)


def test_topomap_commands_parse_and_bad_input_is_one_line_exit_2(tmp_path, capsys):
    from testbed.cli import build_parser, main

    p = build_parser()
    a = p.parse_args(["navigate-batch", "--scenarios", "shelf_corridor", "--seeds", "2-4"])
    assert a.func.__name__ == "_navigate_batch" and a.seeds == "2-4"
    a = p.parse_args(["pose-eval", "--runs", "3"])
    assert a.func.__name__ == "_pose_eval" and a.runs == 3
    a = p.parse_args(["hog-detector", "eval", "--no-streams"])
    assert a.hog_command == "eval" and a.no_streams
    assert main(["navigate-batch", "--seeds", "x-y"]) == 2
    assert main(["hog-detector", "table", str(tmp_path / "missing.json")]) == 2
    (tmp_path / "bad.json").write_text("{")
    assert main(["pose-eval", "--table", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and err[0].startswith("dopeslam navigate-batch: --seeds")
    assert "missing.json" in err[1] and "bad.json" in err[2]


def test_a_saved_report_of_the_wrong_shape_prints_one_line_and_no_table(tmp_path, capsys):
    """The tables of ``hog-detector table`` and ``pose-eval --table`` go to stdout; a JSON file that
    is not such a report (an object without the fields, a list) is one line, exit 2, no partial table."""
    from testbed.cli import main

    (tmp_path / "empty.json").write_text("{}")
    (tmp_path / "list.json").write_text("[1, 2]")
    for argv, says in [(["hog-detector", "table", "empty.json"], "no field 'sets'"),
                       (["hog-detector", "table", "list.json"], "list indices must be integers"),
                       (["pose-eval", "--table", "empty.json"], "no field 'scenarios'"),
                       (["pose-eval", "--table", "list.json"], "list indices must be integers")]:
        argv = [str(tmp_path / a) if a.endswith(".json") else a for a in argv]
        assert main(argv) == 2
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and says in err and err.startswith(f"dopeslam {argv[0]}: ")
    from testbed.cli import build_parser

    args = build_parser().parse_args(["hog-detector", "table", "detector.json"])
    assert str(args.report) == "detector.json" and not getattr(args, "json", False)  # not --json's stdout mode


def test_relative_fix_on_an_unmoved_image_is_no_fix():
    """The robot standing where a route image was taken: the same pixels in both images make OpenCV's
    five-point solver fail (its polynomial vanishes); that is no fix, not an error."""
    from stack.topomap.localisation import relative_pose_up_to_scale
    from stack.topomap.mono_pose import Features

    rng = np.random.default_rng(0)
    desc = rng.normal(size=(60, 128)).astype(np.float32)
    feats = Features(uv=rng.uniform((0, 0), (640, 480), (60, 2)), desc=desc / np.linalg.norm(desc, axis=1, keepdims=True))
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    assert relative_pose_up_to_scale(K, feats, feats) is None
