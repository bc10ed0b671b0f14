"""Seams for other people's components: the bundled parts satisfy the protocols of ``stack.interfaces``;
a detector or a labelling policy named by import path (``MODULE:ATTRIBUTE``) is loaded and runs through
the pipeline; a bad path is one line and exit status 2; ``stack/`` never imports the simulator or the
harness. (The ground-truth detector, the upper bound of ``dopeslam run``: ``tests/e2e/test_seams_e2e.py``.)"""
from __future__ import annotations

import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from helpers import ROOT
from stack.errors import ComponentError, DopeSlamError
from stack.interfaces import (Detector, ImportPathError, LabellingPolicy, LoopCloser, Odometry, check_pose,
                              check_trajectory, entry_point_names, load_detector, load_import_path, load_odometry,
                              odometry_factory, resolve_policy)
from stack.object_store import POLICIES, Label, Observation
from stack.messages import LidarScan, WheelOdometry
from stack.pipeline import DopeSlam
from test_pipeline import DIMS, T_BASE_CAM, LineOdometry, expected_xyz, image, pose_x, scan
from testbed.cli import main

STACK = ROOT / "stack"


# --- the bundled parts satisfy the protocols -----------------------------------------------------------

def test_the_lidar_odometry_is_an_odometry():
    from stack.lidar_slam import LidarOdometry

    odom = LidarOdometry(np.eye(4))
    assert isinstance(odom, Odometry)
    assert odom.pose_at(0.0) is None and odom.trajectory()[0].shape == (0,) and odom.floor_plane_map() is None


def test_dope_and_the_ground_truth_detector_are_detectors():
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector
    from testbed.oracle_detector import OracleDetector

    assert isinstance(DopeDetector(dims={c: s.dims for c, s in load_catalog().items()}), Detector)
    assert isinstance(OracleDetector(), Detector)
    assert not isinstance(object(), Detector)


def test_every_registered_policy_is_a_labelling_policy():
    obs = [Observation(0.1 * k, "Yogurt", np.array([1.0, 0.01 * k, 0.0]), np.array([0, 0, 0, 1.0]), 1.0)
           for k in range(3)]
    assert len(POLICIES) >= 5
    for name, policy in POLICIES.items():
        assert isinstance(policy, LabellingPolicy), name
        label = policy(obs)
        assert isinstance(label, Label) and label.xyz.shape == (3,), name
        assert policy([]) is None, name


def test_the_wheel_only_odometry_is_an_odometry_and_has_a_short_name():
    from stack.lidar_slam import LidarOdometry
    from stack.wheel_odometry import WheelOnlyOdometry

    assert isinstance(WheelOnlyOdometry(), Odometry)
    assert isinstance(load_odometry("wheel", np.eye(4)), WheelOnlyOdometry)
    assert isinstance(load_odometry(None, np.eye(4)), LidarOdometry)
    assert isinstance(load_odometry("kiss-icp", np.eye(4)), LidarOdometry)


def test_the_wheel_only_odometry_gives_the_wheels_pose_with_map_at_the_first_sweep():
    """Wheels report x = 2 + t (odom frame); map is base_link at the first sweep (t = 0.1)."""
    from stack.wheel_odometry import WheelOnlyOdometry

    T_base_lidar = pose_x(0.2)
    pipe = DopeSlam(WheelOnlyOdometry(T_base_lidar), _Mustard(), T_BASE_CAM, DIMS)
    assert pipe.on_scan(LidarScan(0.0, np.zeros((0, 3)), np.zeros(0))) is None  # no wheel odometry yet
    for k in range(31):
        t = 0.01 * k
        pipe.on_wheel_odometry(WheelOdometry(t, pose_x(2.0 + t), 1.0, 0.0))
        if k in (10, 20, 30):
            pts = np.array([[1.0, 0.0, 0.0]])
            pose = pipe.on_scan(LidarScan(t, pts, np.zeros(1)))
            np.testing.assert_allclose(pose, pose_x(t - 0.1), atol=1e-12)
        if k == 15:
            pipe.on_image(image(t))
    res = pipe.finish()
    np.testing.assert_allclose(res.stamps, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(res.T_map_base[:, 0, 3], [0.0, 0.1, 0.2], atol=1e-12)
    (obj,) = res.store  # the image at 0.15, between the sweeps: interpolated
    np.testing.assert_allclose(obj.xyz, expected_xyz(0.05), atol=1e-9)  # 1 m ahead of the camera at x = 0.05
    np.testing.assert_allclose(res.map_points[0], [[1.2, 0.0, 0.0]], atol=1e-12)  # the sweep's points in map
    assert res.store.floor is None


class _Mustard:
    def detect(self, frame):
        from stack.messages import Detection

        T = np.eye(4)
        T[2, 3] = 1.0
        return [Detection("Mustard", frame.stamp, T, np.zeros((9, 2)), np.ones(9), 2.0)]


def test_the_harness_loop_closing_is_a_loop_closer():
    from testbed.loop_closing import LoopClosingRun

    assert issubclass(LoopClosingRun, LoopCloser)


# --- stack/ knows nothing of the simulator or the harness ---------------------------------------------

IMPORT_OF_SIM_OR_TESTBED = re.compile(r"^\s*(from|import)\s+(sim|testbed)(\.|\s|$)", re.MULTILINE)
NAMED_IN_A_STRING = re.compile(r"""import_module\(\s*['"](sim|testbed)\b""")


def test_no_module_under_stack_imports_sim_or_testbed():
    offenders = []
    for path in sorted(STACK.rglob("*.py")):
        text = path.read_text()
        for m in list(IMPORT_OF_SIM_OR_TESTBED.finditer(text)) + list(NAMED_IN_A_STRING.finditer(text)):
            line = text.count("\n", 0, m.start()) + 1
            offenders.append(f"{path.relative_to(STACK.parent)}:{line}: {text.splitlines()[line - 1].strip()}")
    assert not offenders, "stack/ must not import the simulator or the harness:\n" + "\n".join(offenders)


def test_importing_every_stack_module_loads_neither_sim_nor_testbed():
    modules = sorted("stack." + ".".join(p.relative_to(STACK).with_suffix("").parts)
                     for p in STACK.rglob("*.py") if p.name != "__init__.py")
    code = textwrap.dedent(f"""
        import importlib, sys
        for name in {modules!r}:
            importlib.import_module(name)
        bad = sorted(m for m in sys.modules if m.split('.')[0] in ('sim', 'testbed'))
        print(','.join(bad))
    """)
    res = subprocess.run([sys.executable, "-c", code], cwd=STACK.parent, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "", f"importing stack/ loaded {res.stdout.strip()}"


# --- other people's components, named by import path --------------------------------------------------

USER_MODULE = '''
import numpy as np
from stack.messages import Detection

class MustardAhead:
    """A user's detector: one Mustard 1 m ahead of the camera in every image."""
    def detect(self, frame):
        T = np.eye(4)
        T[2, 3] = 1.0
        return [Detection("Mustard", frame.stamp, T, np.zeros((9, 2)), np.ones(9), 2.0)]

class NoDetect:
    pass

class NeedsArguments:
    def __init__(self, weights):
        self.weights = weights
    def detect(self, frame):
        return []

class StandingStill:
    """A user's odometry: the robot never moves (map = base_link throughout)."""
    def __init__(self, T_base_lidar):
        self.T_base_lidar = T_base_lidar
        self.stamps = []
    def process(self, scan):
        self.stamps.append(scan.stamp)
        return np.eye(4)
    def pose_at(self, t):
        return np.eye(4) if self.stamps and self.stamps[0] <= t <= self.stamps[-1] + 0.1 else None
    def trajectory(self):
        return np.array(self.stamps), np.tile(np.eye(4), (len(self.stamps), 1, 1))


class ReturnsNothing:
    def detect(self, frame):
        return None

class ReturnsNames:
    def detect(self, frame):
        return ["Mustard"]

def _ahead(cls, T, stamp):
    return [Detection(cls, stamp, T, np.zeros((9, 2)), np.ones(9), 2.0)]

class LostPose:
    def detect(self, frame):
        return _ahead("Mustard", np.full((4, 4), np.nan), frame.stamp)

class ScaledPose:
    def detect(self, frame):
        return _ahead("Mustard", np.diag([2.0, 2.0, 2.0, 1.0]), frame.stamp)

class BananaAhead:
    def detect(self, frame):
        T = np.eye(4)
        T[2, 3] = 1.0
        return _ahead("Banana", T, frame.stamp)

class LostOdometry(StandingStill):
    def pose_at(self, t):
        return np.full((4, 4), np.nan)

class FlatOdometry(StandingStill):
    def pose_at(self, t):
        return np.eye(3)

class NoTrajectory(StandingStill):
    def trajectory(self):
        return None

class ShortTrajectory(StandingStill):
    def trajectory(self):
        return np.array(self.stamps), np.eye(4)[None]


def names_the_class(observations):
    return observations[0].cls

def nowhere(observations):
    from stack.object_store import Label
    o = observations[0]
    return Label(np.full(3, np.nan), o.quat_xyzw.copy(), o.belief_sum)


def first_observation(observations):
    """A user's labelling policy: the first observation is the label."""
    from stack.object_store import Label
    o = observations[0] if observations else None
    return None if o is None else Label(o.xyz.copy(), o.quat_xyzw.copy(), o.belief_sum)
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    (tmp_path / "user_parts.py").write_text(USER_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "user_parts"
    sys.modules.pop("user_parts", None)


def test_a_user_detector_loaded_by_import_path_runs_through_the_pipeline(user_module):
    detector = load_detector(f"{user_module}:MustardAhead")
    assert isinstance(detector, Detector)
    pipe = DopeSlam(LineOdometry(), detector, T_BASE_CAM, DIMS)
    pipe.on_scan(scan(0.0))
    dets = pipe.on_image(image(0.08))
    pipe.on_scan(scan(0.1))
    store = pipe.finish().store
    assert [d.cls for d in dets] == ["Mustard"]
    (obj,) = store
    assert obj.cls == "Mustard"
    np.testing.assert_allclose(obj.xyz, expected_xyz(0.08), atol=1e-12)


def test_a_user_policy_loaded_by_import_path_labels_the_store(user_module):
    name = resolve_policy(f"{user_module}:first_observation")
    assert name == f"{user_module}:first_observation" and POLICIES[name].__name__ == "first_observation"
    try:
        pipe = DopeSlam(LineOdometry(), load_detector(f"{user_module}:MustardAhead"), T_BASE_CAM, DIMS, policy=name)
        pipe.on_scan(scan(0.0))
        for t in (0.06, 0.1, 0.14):
            pipe.on_image(image(t))
        pipe.on_scan(scan(0.1))
        (obj,) = pipe.finish().store
        np.testing.assert_allclose(obj.xyz, expected_xyz(0.06), atol=1e-12)  # the first, not the mean
        assert resolve_policy("robust-mean") == "robust-mean"
    finally:
        POLICIES.pop(name, None)


def test_a_user_odometry_loaded_by_import_path_is_given_the_lidar_mounting_and_drives_the_pipeline(user_module):
    T_base_lidar = pose_x(0.3)
    odom = load_odometry(f"{user_module}:StandingStill", T_base_lidar)
    assert isinstance(odom, Odometry) and np.array_equal(odom.T_base_lidar, T_base_lidar)
    pipe = DopeSlam(odom, load_detector(f"{user_module}:MustardAhead"), T_BASE_CAM, DIMS)
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.05))
    pipe.on_scan(scan(0.1))
    res = pipe.finish()
    (obj,) = res.store
    np.testing.assert_allclose(obj.xyz, expected_xyz(0.0), atol=1e-12)  # the robot stood at the origin
    np.testing.assert_allclose(res.stamps, [0.0, 0.1])


@pytest.mark.parametrize("spec, message", [
    ("user_parts:MustardAhead", "class MustardAhead has no process, pose_at, trajectory method"),
    ("user_parts:NeedsArguments", "has no process, pose_at, trajectory method"),
    ("no-such-odometry", "expected one of ['kiss-icp', 'wheel'] or MODULE:ATTRIBUTE"),
    ("user_parts:first_observation", "constructing it with T_base_lidar failed"),
])
def test_a_bad_odometry_is_one_line_and_exit_status_2(user_module, spec, message, capsys):
    with pytest.raises(ImportPathError, match=re.escape(message)):
        load_odometry(spec, np.eye(4))
    if "constructing" in message:
        odometry_factory(spec)  # the name is fine; only constructing it fails
        return
    for command in (["run"], ["replay", "no-such.bag"], ["loop-closure"]):
        assert main([*command, "--odometry", spec, "--out", "unused"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"dopeslam {command[0]}: --odometry {spec!r}: ") and message in err and "\n" not in err


@pytest.mark.parametrize("cls, message", [
    ("ReturnsNothing", "detector user_parts:ReturnsNothing: detect() on the image at t=0.080 s returned NoneType; "
                       "expected a list of stack.messages.Detection"),
    ("ReturnsNames", "returned item 0: a str; expected stack.messages.Detection"),
    ("LostPose", "returned item 0: Mustard with a T_cam_obj that is a 4x4 array with NaN or inf in it"),
    ("ScaledPose", "returned item 0: Mustard with a T_cam_obj that is a 4x4 array that is not a rigid transform"),
    ("BananaAhead", "a detection of class 'Banana' at t=0.080 s: no cuboid size for that class"),
])
def test_a_detector_that_breaks_its_contract_is_one_clear_error(user_module, cls, message):
    """Instead of a failure deep in the fusion (an SVD of NaN, a matmul of the wrong shape, a str with
    no ``cls``), the detector is named with the image and what it returned."""
    pipe = DopeSlam(LineOdometry(), load_detector(f"{user_module}:{cls}"), T_BASE_CAM, DIMS)
    pipe.on_scan(scan(0.0))
    with pytest.raises(ComponentError, match=re.escape(message)) as err:
        pipe.on_image(image(0.08))
        pipe.on_scan(scan(0.1))
        pipe.finish()
    assert "\n" not in str(err.value) and isinstance(err.value, DopeSlamError)


@pytest.mark.parametrize("cls, message", [
    ("LostOdometry", "odometry user_parts:LostOdometry: pose_at(0.080) returned a 4x4 array with NaN or inf in it"),
    ("FlatOdometry", "pose_at(0.080) returned an array of shape (3, 3), not a 4x4 transform"),
    ("NoTrajectory", "odometry user_parts:NoTrajectory: trajectory() returned NoneType; expected (stamps (N,), "
                     "T_map_base (N, 4, 4))"),
    ("ShortTrajectory", "trajectory() returned stamps of shape (2,) and poses of shape (1, 4, 4); "
                        "expected (N,) and (N, 4, 4)"),
])
def test_an_odometry_that_breaks_its_contract_is_one_clear_error(user_module, cls, message):
    pipe = DopeSlam(load_odometry(f"{user_module}:{cls}", np.eye(4)), load_detector(f"{user_module}:MustardAhead"),
                    T_BASE_CAM, DIMS)
    with pytest.raises(ComponentError, match=re.escape(message)):
        pipe.on_scan(scan(0.0))
        pipe.on_image(image(0.08))
        pipe.on_scan(scan(0.1))
        pipe.finish()


@pytest.mark.parametrize("policy, message", [
    ("names_the_class", "policy user_parts:names_the_class: for 1 observation(s) of class Mustard it returned a str; "
                        "expected None or stack.object_store.Label"),
    ("nowhere", "it returned a Label whose xyz is array([nan, nan, nan]); expected 3 finite numbers"),
])
def test_a_policy_that_breaks_its_contract_is_one_clear_error(user_module, policy, message):
    """Before, a str failed deep in the store and a NaN label went into the map (and the xlsx) silently."""
    name = resolve_policy(f"{user_module}:{policy}")
    try:
        pipe = DopeSlam(LineOdometry(), load_detector(f"{user_module}:MustardAhead"), T_BASE_CAM, DIMS, policy=name)
        pipe.on_scan(scan(0.0))
        pipe.on_image(image(0.08))
        with pytest.raises(ComponentError, match=re.escape(message)):
            pipe.on_scan(scan(0.1))
            pipe.finish()
    finally:
        POLICIES.pop(name, None)


def test_the_contract_checks_pass_what_the_protocols_allow(user_module):
    """A rigid pose with float noise, None for an unknown pose and an empty trajectory pass unchanged."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix().astype(np.float32)
    T[:3, 3] = (0.1, 0.2, 3.0)
    odom = load_odometry(f"{user_module}:StandingStill", np.eye(4))
    assert check_pose(odom, 0.0, T) is T and check_pose(odom, 0.0, None) is None
    stamps, poses = check_trajectory(odom, (np.zeros(0), np.zeros((0, 4, 4))))
    assert stamps.shape == (0,) and poses.shape == (0, 4, 4)
    with pytest.raises(ComponentError, match="time order"):
        check_trajectory(odom, (np.array([0.2, 0.1]), np.tile(np.eye(4), (2, 1, 1))))


# --- components an installed package registers by name (entry points) ---------------------------------

ENTRY_POINTS = """
[dopeslam.detectors]
mustard-ahead = user_parts:MustardAhead

[dopeslam.odometry]
standing-still = user_parts:StandingStill

[dopeslam.policies]
first-seen = user_parts:first_observation
"""


@pytest.fixture
def installed_plugin(user_module, tmp_path):
    """A package installed on sys.path that registers a detector, an odometry and a policy."""
    import importlib

    info = tmp_path / "dopeslam_user_parts-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dopeslam-user-parts\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    importlib.invalidate_caches()
    yield user_module
    POLICIES.pop("first-seen", None)


def test_components_registered_by_an_installed_package_load_by_name(installed_plugin):
    assert entry_point_names("detector") == ["mustard-ahead"]
    assert entry_point_names("odometry") == ["standing-still"] and entry_point_names("policy") == ["first-seen"]
    detector = load_detector("mustard-ahead")
    odom = load_odometry("standing-still", pose_x(0.3))
    assert type(detector).__name__ == "MustardAhead" and type(odom).__name__ == "StandingStill"
    assert resolve_policy("first-seen") == "first-seen" and POLICIES["first-seen"].__name__ == "first_observation"
    pipe = DopeSlam(odom, detector, T_BASE_CAM, DIMS, policy="first-seen")
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.05))
    pipe.on_scan(scan(0.1))
    assert [m.cls for m in pipe.finish().store] == ["Mustard"]


def test_an_unknown_name_lists_the_installed_ones(installed_plugin):
    with pytest.raises(ImportPathError, match=re.escape("expected one of ['mustard-ahead'] or MODULE:ATTRIBUTE")):
        load_detector("no-such-detector")
    with pytest.raises(ImportPathError, match=re.escape("'kiss-icp', 'standing-still', 'wheel'")):
        load_odometry("no-such-odometry", np.eye(4))
    with pytest.raises(ImportPathError, match="first-seen"):
        resolve_policy("no-such-policy")


def test_a_registered_name_whose_module_fails_is_one_line(installed_plugin, tmp_path):
    (tmp_path / "dopeslam_user_parts-1.0.dist-info" / "entry_points.txt").write_text(
        "[dopeslam.detectors]\nbroken = no_such_module_anywhere:Thing\n")
    with pytest.raises(ImportPathError, match="loading entry point 'no_such_module_anywhere:Thing' failed: "
                                              "ModuleNotFoundError"):
        load_detector("broken")


@pytest.mark.parametrize("spec, message", [
    ("user_parts", "expected MODULE:ATTRIBUTE"),
    ("no_such_module_here:Detector", "cannot import module 'no_such_module_here'"),
    ("user_parts:Missing", "module 'user_parts' has no attribute 'Missing'"),
    ("user_parts:NoDetect", "class NoDetect has no detect(frame) method"),
    ("user_parts:NeedsArguments", "constructing it with no arguments failed: TypeError"),
])
def test_a_bad_detector_path_is_one_line_and_exit_status_2(user_module, spec, message, capsys):
    with pytest.raises(ImportPathError, match=re.escape(message)):
        load_detector(spec)
    assert main(["run", "--detector", spec, "--out", "unused"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"dopeslam run: --detector {spec!r}: ") and message in err and "\n" not in err


def test_a_bad_policy_is_one_line_and_exit_status_2(user_module, capsys):
    assert main(["run", "--policy", "no-such-policy", "--out", "unused"]) == 2
    err = capsys.readouterr().err.strip()
    assert "expected one of" in err and "MODULE:FUNCTION" in err and "\n" not in err
    assert main(["run", "--policy", f"{user_module}:nothing", "--out", "unused"]) == 2
    assert "has no attribute 'nothing'" in capsys.readouterr().err


def test_a_module_that_fails_while_importing_is_reported_on_one_line(tmp_path, monkeypatch):
    (tmp_path / "broken_parts.py").write_text("raise RuntimeError('weights not found\\nsecond line')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ImportPathError) as e:
        load_import_path("broken_parts:Thing", "detector")
    assert "RuntimeError: weights not found" in str(e.value) and "\n" not in str(e.value)


def test_the_ground_truth_detector_needs_its_episode():
    from testbed.oracle_detector import OracleDetector

    with pytest.raises(RuntimeError, match="bind_episode"):
        OracleDetector().detect(image(0.0))
