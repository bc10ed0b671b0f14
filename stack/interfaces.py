"""What the pipeline (:mod:`stack.pipeline`) needs of each component it joins, as ``typing.Protocol``s.

A component is any object with these methods; it need not inherit from anything. The bundled ones
satisfy them: :class:`stack.lidar_slam.LidarOdometry` is an :class:`Odometry`,
:class:`stack.dope_fpr.DopeDetector` a :class:`Detector`, the functions registered in
:mod:`stack.object_store` (``last``, ``robust-mean``, ...) are each a :class:`LabellingPolicy` and the
harness's loop closing (``testbed/loop_closing.py``) is a :class:`LoopCloser`.

Other people's components are named by import path, ``MODULE:ATTRIBUTE`` (``my_pkg.dets:MyDetector``),
or by the name an installed package registers for them as an entry point (groups
``dopeslam.detectors``, ``dopeslam.odometry``, ``dopeslam.policies``; in that package's
``pyproject.toml``: ``[project.entry-points."dopeslam.detectors"] mine = "my_pkg.dets:MyDetector"``),
and loaded with :func:`load_detector`, :func:`load_odometry` and :func:`resolve_policy`. The bundled
odometries have short names too: ``kiss-icp`` (the default, LiDAR) and ``wheel`` (wheel odometry
only, :class:`stack.wheel_odometry.WheelOnlyOdometry`).

Frames and units as in ``DESIGN.md``: poses are ``T_map_base`` (4x4, ``map`` = ``base_link`` at the
first registered scan), times are float seconds.
"""
from __future__ import annotations

import importlib
import math
from collections.abc import Sequence
from importlib.metadata import entry_points
from typing import Protocol, runtime_checkable

import numpy as np

from stack.errors import ComponentError, DopeSlamError
from stack.messages import CameraFrame, Detection, LidarScan
from stack.object_store import POLICIES, Label, Observation, register


@runtime_checkable
class Odometry(Protocol):
    """Robot poses in ``map`` from LiDAR sweeps, given in time order.

    Named on the command line (``--odometry MODULE:CLASS``), the class is called with one argument,
    the LiDAR's mounting ``T_base_lidar`` (4x4, the sensor frame in ``base_link``).

    Optional: ``floor_plane_map() -> (n, d) | None``, the floor as a plane in ``map`` (unit normal n
    up, n.x + d = 0 on the floor); the object store's evidence uses it to reject labels below the
    floor. Optional: ``last_points_base``, the last sweep's points in ``base_link`` (N, 3), which
    the pipeline collects into a LiDAR map. Optional: ``on_wheel_odometry(msg)``, given every
    :class:`~stack.messages.WheelOdometry` message in time order with the scans. Optional:
    ``last_stamp() -> float | None``, the newest registered pose's stamp (else the pipeline reads it
    from ``trajectory()``, a copy of the whole trajectory at every sweep).
    """

    def process(self, scan: LidarScan) -> np.ndarray | None:
        """Register one sweep; ``T_map_base`` of its pose, or None when the sweep was skipped."""

    def pose_at(self, t: float) -> np.ndarray | None:
        """``T_map_base`` at time ``t`` (interpolated between registered poses), or None where unknown."""

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), T_map_base (N, 4, 4)) of every registered sweep, in time order."""


@runtime_checkable
class Detector(Protocol):
    """Objects in a camera image: each :class:`~stack.messages.Detection` has the image's ``stamp``,
    the class, ``T_cam_obj`` (4x4, camera optical frame: z forward, x right, y down; origin at the
    cuboid centroid) and its FPR verdict in ``fpr_pass``. ``belief_sum`` is the detection's
    certainty (lower = more certain; some policies choose by it)."""

    def detect(self, frame: CameraFrame) -> list[Detection]:
        ...


@runtime_checkable
class LabellingPolicy(Protocol):
    """A map object's observations (map frame, time order) -> its label, or None when none qualifies
    (e.g. no observation passed FPR). Registered by name in :mod:`stack.object_store`."""

    def __call__(self, observations: Sequence[Observation]) -> Label | None:
        ...


@runtime_checkable
class LoopCloser(Protocol):
    """Rides along the pipeline, then corrects the trajectory at the end and places the map again.

    During the run it sees every registered sweep (``on_scan``, after ``odometry.process``), every
    image (``on_image``) and every detection fused into the map (``on_fused``). At ``finish`` the
    pipeline asks it for the corrected trajectory, for the object store built again from the fused
    detections with the corrected poses (``refuse``, into the fresh store it is given), and for the
    LiDAR map placed with them (``map_points``).
    """

    def on_scan(self, odometry: Odometry, T_map_base: np.ndarray | None) -> None: ...

    def on_image(self, frame: CameraFrame) -> None: ...

    def on_fused(self, detection: Detection) -> None: ...

    def finish(self, stamps: np.ndarray, T_map_base: np.ndarray) -> np.ndarray: ...

    def refuse(self, store, pose_at, T_base_cam: np.ndarray): ...

    def map_points(self) -> list[np.ndarray]: ...


def component_name(component) -> str:
    """``MODULE:CLASS`` of a component, as an error names it."""
    cls = type(component)
    return f"{cls.__module__}:{cls.__qualname__}"


def detect(detector: Detector, frame: CameraFrame) -> list[Detection]:
    """``detector.detect(frame)`` as a list, each item checked against the :class:`Detector` protocol:
    a :class:`stack.messages.Detection` with a class name and a finite rigid ``T_cam_obj`` (4x4,
    a rotation and a translation). Anything else is a :class:`stack.errors.ComponentError` naming
    the detector, the image's stamp and what was wrong, instead of a failure deep in the fusion.
    What the detector raises itself is left as it is (its traceback shows where)."""
    result = detector.detect(frame)
    try:
        detections = list(result)
    except TypeError:
        raise ComponentError(f"detector {component_name(detector)}: detect() on the image at "
                             f"t={float(frame.stamp):.3f} s returned {type(result).__name__}; expected a list of "
                             "stack.messages.Detection") from None
    for i, d in enumerate(detections):
        why = _not_a_detection(d)
        if why:
            raise ComponentError(f"detector {component_name(detector)}: detect() on the image at "
                                 f"t={float(frame.stamp):.3f} s returned item {i}: {why}")
    return detections


def _not_a_detection(d) -> str:
    """Why ``d`` is not a usable detection ('' when it is one)."""
    if not isinstance(d, Detection):
        return f"a {type(d).__name__}; expected stack.messages.Detection"
    if not isinstance(d.cls, str) or not d.cls:
        return f"class {d.cls!r}; expected a class name"
    why = _not_rigid(d.T_cam_obj)
    return f"{d.cls} with a T_cam_obj that is {why}" if why else ""


def _not_rigid(T) -> str:
    """What ``T`` is, when it is not a finite rigid 4x4 transform ('' when it is one). In plain floats:
    a few microseconds, as it runs on every detection and pose."""
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        return f"a {type(T).__name__}, not a 4x4 transform"
    if T.shape != (4, 4):
        return f"an array of shape {T.shape}, not a 4x4 transform"
    rows = T.tolist()
    if not all(math.isfinite(x) for row in rows for x in row):
        return "a 4x4 array with NaN or inf in it"
    r0, r1, r2 = (row[:3] for row in rows[:3])
    dot = lambda u, v: u[0] * v[0] + u[1] * v[1] + u[2] * v[2]  # noqa: E731
    off = max(abs(dot(r0, r0) - 1), abs(dot(r1, r1) - 1), abs(dot(r2, r2) - 1),
              abs(dot(r0, r1)), abs(dot(r0, r2)), abs(dot(r1, r2)))
    det = r0[0] * (r1[1] * r2[2] - r1[2] * r2[1]) - r0[1] * (r1[0] * r2[2] - r1[2] * r2[0]) \
        + r0[2] * (r1[0] * r2[1] - r1[1] * r2[0])
    if off > 1e-2 or det < 0 or max(abs(x - y) for x, y in zip(rows[3], (0.0, 0.0, 0.0, 1.0))) > 1e-6:
        return "a 4x4 array that is not a rigid transform (a rotation, a translation, last row 0 0 0 1)"
    return ""


def check_pose(odometry: Odometry, t: float, T):
    """``T``, what ``odometry.pose_at(t)`` returned, if it is None or a finite rigid 4x4 transform;
    else a :class:`stack.errors.ComponentError` naming the odometry and ``t``."""
    if T is None:
        return None
    why = _not_rigid(T)
    if why:
        raise ComponentError(f"odometry {component_name(odometry)}: pose_at({float(t):.3f}) returned {why}; "
                             "expected None or T_map_base")
    return T


def check_trajectory(odometry: Odometry, result) -> tuple[np.ndarray, np.ndarray]:
    """What ``odometry.trajectory()`` returned, if it is ``(stamps (N,), T_map_base (N, 4, 4))``: finite,
    one pose per stamp, stamps in time order; else a :class:`stack.errors.ComponentError`."""
    where = f"odometry {component_name(odometry)}: trajectory()"
    try:
        stamps, poses = result
        stamps, poses = np.asarray(stamps, dtype=float), np.asarray(poses, dtype=float)
    except (TypeError, ValueError):
        raise ComponentError(f"{where} returned {type(result).__name__}; "
                             "expected (stamps (N,), T_map_base (N, 4, 4))") from None
    if stamps.ndim != 1 or poses.shape != (len(stamps), 4, 4):
        raise ComponentError(f"{where} returned stamps of shape {stamps.shape} and poses of shape {poses.shape}; "
                             "expected (N,) and (N, 4, 4)")
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(poses))) or np.any(np.diff(stamps) < 0):
        raise ComponentError(f"{where}: expected finite stamps in time order and finite poses")
    return stamps, poses


class ImportPathError(DopeSlamError, ValueError):
    """An import path (``MODULE:ATTRIBUTE``) that does not name something loadable; the message says
    which part is wrong."""


def load_import_path(spec: str, what: str = "component"):
    """The object that ``MODULE:ATTRIBUTE`` names (``ATTRIBUTE`` may be dotted: ``mod:Outer.Inner``).

    Raises :class:`ImportPathError` with a one-line message when the path is malformed, the module
    cannot be imported or has no such attribute.
    """
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ImportPathError(f"{what} {spec!r}: expected MODULE:ATTRIBUTE, e.g. my_package.detectors:MyDetector")
    try:
        obj = importlib.import_module(module_name)
    except ImportError as e:
        raise ImportPathError(f"{what} {spec!r}: cannot import module {module_name!r} ({e})") from None
    except Exception as e:  # the module itself failed while loading: say so on one line
        raise ImportPathError(f"{what} {spec!r}: importing {module_name!r} failed: "
                              f"{type(e).__name__}: {e}".splitlines()[0]) from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ImportPathError(f"{what} {spec!r}: module {module_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    return obj


ENTRY_POINT_GROUPS = {"detector": "dopeslam.detectors", "odometry": "dopeslam.odometry",
                      "policy": "dopeslam.policies"}
ODOMETRIES = {"kiss-icp": "stack.lidar_slam:LidarOdometry", "wheel": "stack.wheel_odometry:WheelOnlyOdometry"}
DEFAULT_ODOMETRY = "kiss-icp"


def entry_point_names(what: str) -> list[str]:
    """The names installed packages register in ``what``'s entry-point group (``detector``, ...)."""
    return sorted({ep.name for ep in entry_points(group=ENTRY_POINT_GROUPS[what])})


def _load_named(spec: str, what: str, builtin: dict[str, str] | None = None):
    """``MODULE:ATTRIBUTE``, a bundled short name (``builtin``) or an entry point's name -> the object."""
    if ":" in spec:
        return load_import_path(spec, what)
    if builtin and spec in builtin:
        return load_import_path(builtin[spec], what)
    group = ENTRY_POINT_GROUPS[what]
    found = [ep for ep in entry_points(group=group) if ep.name == spec]
    if not found:
        names = sorted({*(builtin or {}), *entry_point_names(what)})
        known = f"one of {names} or " if names else ""
        raise ImportPathError(f"{what} {spec!r}: expected {known}MODULE:ATTRIBUTE (no entry point {spec!r} "
                              f"in group {group!r})")
    ep = found[0]
    try:
        return ep.load()
    except Exception as e:  # the package's module failed while loading: say so on one line
        raise ImportPathError(f"{what} {spec!r}: loading entry point {ep.value!r} failed: "
                              f"{type(e).__name__}: {e}".splitlines()[0]) from None


def _construct(cls, spec: str, what: str, args: tuple, how: str):
    if not callable(cls):
        raise ImportPathError(f"{what} {spec!r}: {type(cls).__name__} object is not a class")
    try:
        return cls(*args)
    except Exception as e:  # a user's constructor: report it on one line rather than a traceback
        raise ImportPathError(f"{what} {spec!r}: constructing it {how} failed: "
                              f"{type(e).__name__}: {e}".splitlines()[0]) from None


def load_detector(spec: str) -> Detector:
    """A detector from ``MODULE:CLASS`` or an entry point's name (group ``dopeslam.detectors``): the
    class is constructed with no arguments and must have ``detect(frame)``. Raises
    :class:`ImportPathError` (one line) otherwise."""
    cls = _load_named(spec, "detector")
    if isinstance(cls, type) and not callable(getattr(cls, "detect", None)):
        raise ImportPathError(f"detector {spec!r}: class {cls.__name__} has no detect(frame) method")
    detector = _construct(cls, spec, "detector", (), "with no arguments")
    if not isinstance(detector, Detector):
        raise ImportPathError(f"detector {spec!r}: {type(detector).__name__} has no detect(frame) method")
    return detector


def odometry_factory(spec: str | None):
    """The class (or callable) a bundled odometry name, ``MODULE:CLASS`` or an entry point's name
    (group ``dopeslam.odometry``) names, not yet constructed; None means ``kiss-icp``. Raises
    :class:`ImportPathError` (one line)."""
    spec = DEFAULT_ODOMETRY if spec is None else spec
    cls = _load_named(spec, "odometry", ODOMETRIES)
    if not callable(cls):
        raise ImportPathError(f"odometry {spec!r}: {type(cls).__name__} object is not a class")
    if isinstance(cls, type):
        missing = [m for m in ("process", "pose_at", "trajectory") if not callable(getattr(cls, m, None))]
        if missing:
            raise ImportPathError(f"odometry {spec!r}: class {cls.__name__} has no {', '.join(missing)} method")
    return cls


def load_odometry(spec: str | None, T_base_lidar: np.ndarray) -> Odometry:
    """An odometry from a bundled name (``kiss-icp``, the default for None; ``wheel``), ``MODULE:CLASS``
    or an entry point's name (group ``dopeslam.odometry``): the class is called with the LiDAR's
    mounting ``T_base_lidar`` and must have ``process``, ``pose_at`` and ``trajectory``. Raises
    :class:`ImportPathError` (one line) otherwise."""
    spec = DEFAULT_ODOMETRY if spec is None else spec
    cls = odometry_factory(spec)
    odometry = _construct(cls, spec, "odometry", (np.asarray(T_base_lidar, dtype=float),), "with T_base_lidar")
    if not isinstance(odometry, Odometry):
        missing = [m for m in ("process", "pose_at", "trajectory") if not callable(getattr(odometry, m, None))]
        raise ImportPathError(f"odometry {spec!r}: {type(odometry).__name__} has no {', '.join(missing)} method")
    return odometry


def resolve_policy(name: str) -> str:
    """A labelling policy's registered name for ``name``: a registered name as it is, or a
    ``MODULE:FUNCTION`` or an entry point's name (group ``dopeslam.policies``) loaded and registered
    under that name. Raises :class:`ImportPathError`."""
    if name in POLICIES:
        return name
    if ":" not in name and name not in entry_point_names("policy"):
        raise ImportPathError(f"policy {name!r}: expected one of {sorted({*POLICIES, *entry_point_names('policy')})} "
                              "or MODULE:FUNCTION")
    fn = _load_named(name, "policy")
    if not callable(fn):
        raise ImportPathError(f"policy {name!r}: {type(fn).__name__} object is not callable")
    register(name)(fn)
    return name
