"""The live view: ``dopeslam run ... --view rerun`` (and ``replay``) shows the episode in the Rerun
viewer as it runs, ``--view-save FILE.rrd`` writes the same to a recording file (open it later with
``rerun FILE.rrd``). Needs the optional ``view`` extra: ``pip install 'dopeslam-testbed[view]'``.

What it shows, on the ``sim_time`` timeline (seconds of the episode or the bag):

- ``world/lidar/scan``: the latest LiDAR sweep where the odometry put it; ``world/lidar/map``: the
  map's key sweeps (every 5th registered one, as the pipeline keeps them);
- ``world/robot/estimate`` and ``world/robot/truth``: the odometry's path and the true one (when
  the source has ground truth), with the robot's current pose;
- ``camera/image``: the colour (or depth) image; ``camera/image/detections``: each detection's
  cuboid key points and box, green where FPR passed it, red where FPR rejected it, and with the
  harness's verdict (correct / false) in its label when the truth is known;
- ``world/objects/truth``: the true objects (boxes with their names); ``world/objects/map``: the
  map's objects as the stack holds them (labels, candidates), refreshed every second, and at the
  end the published labels with their verdicts (correct / misplaced / phantom).

Everything is in ``world`` when the source has ground truth (``T_world_map`` from the true pose at
the first registered sweep, as the scoring does), else in the odometry's ``map`` frame. This module
is the testbed's; the stack never imports it. The job calls a view through
:class:`testbed.progress.EpisodeWatch`.
"""
from __future__ import annotations

import numpy as np

from stack.transforms import transform_points

APP_ID = "dopeslam"
TIMELINE = "sim_time"
MAP_EVERY = 5  # as stack.pipeline keeps the LiDAR map
MAP_POINT_STRIDE = 4
SCAN_POINT_STRIDE = 2  # points of the live sweep sent (half: plenty to see, half the bytes)
STORE_EVERY_S = 1.0  # how often the map's objects are sent again
PASS, REJECT, FALSE = (40, 200, 60), (220, 40, 40), (255, 160, 0)
VERDICT_COLOURS = {"correct": (40, 120, 255), "misplaced": (220, 40, 40), "phantom": (220, 40, 220)}
MISSING = "the live view needs the Rerun SDK, an optional dependency: pip install 'dopeslam-testbed[view]' " \
          "(or pip install rerun-sdk)"


class ViewError(RuntimeError):
    """The live view cannot start (no Rerun SDK, no viewer)."""


VIEWER_PORT = 9876  # where rr.spawn starts the viewer, or finds one already running


def _viewer_listening(port: int = VIEWER_PORT) -> bool:
    """Whether a viewer (or anything) already listens on this machine's ``port``."""
    import socket

    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
    except OSError:
        return False
    return True


def _has_display() -> bool:
    """Whether a window can open: on Linux an X11 or Wayland display is named; elsewhere assumed."""
    import os
    import sys

    if not sys.platform.startswith("linux"):
        return True
    return any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def _rerun():
    try:
        import rerun as rr
    except ModuleNotFoundError as exc:
        if exc.name not in ("rerun", "rerun_bindings"):
            raise
        raise ViewError(MISSING) from None
    return rr


class RerunView:
    """Logs a job to Rerun. ``spawn``: start (or connect to) a viewer; ``save``: a recording file.
    At least one of them. ``recording_id``: the recording's id (default: from the source's name)."""

    def __init__(self, spawn: bool = True, save: str | None = None, recording_id: str | None = None):
        if not spawn and not save:
            raise ValueError("RerunView: spawn a viewer, save to a file, or both")
        rr = self.rr = _rerun()
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        sinks = []
        if save:
            sinks.append(rr.FileSink(str(save)))
        if spawn:
            if not _viewer_listening() and not _has_display():  # the viewer would start, find no screen and quit
                raise ViewError(f"no display to open the Rerun viewer on (DISPLAY and WAYLAND_DISPLAY are unset) and "
                                f"no viewer listening on port {VIEWER_PORT}; use --view-save FILE.rrd and open it "
                                "with `rerun FILE.rrd` where there is a screen")
            import inspect

            # this recording's spawn: rr.spawn() alone asks the global recording, which is off, and does nothing
            mine = {"recording": self.rec} if "recording" in inspect.signature(rr.spawn).parameters else {}
            try:
                rr.spawn(connect=False, hide_welcome_screen=True, port=VIEWER_PORT, **mine)
            except Exception as exc:  # no viewer binary, no display
                why = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                raise ViewError(f"cannot start the Rerun viewer ({why}); "
                                "use --view-save FILE.rrd and open it later with `rerun FILE.rrd`") from None
            sinks.append(rr.GrpcSink())
        self.rec.set_sinks(*sinks)
        self.save_path = save
        self.T_world_map: np.ndarray | None = None
        self._truth = None
        self._est: list[np.ndarray] = []
        self._true: list[np.ndarray] = []
        self._registered = 0
        self._last_store = -np.inf
        self._pipe = None

    # --- what the job calls ---------------------------------------------------------------------
    def start(self, truth=None, pipe=None, name: str = "") -> None:
        """``truth``: the source's ground truth (``T_world_base_at(t)``, ``objects``), or None.
        ``pipe``: the :class:`stack.pipeline.DopeSlam` (its store is shown as it grows)."""
        rr = self.rr
        self._truth, self._pipe = truth, pipe
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if name:
            self.rec.log("description", rr.TextDocument(name), static=True)
        objects = list(getattr(truth, "objects", None) or [])
        if objects:
            self.rec.log("world/objects/truth", rr.Boxes3D(
                centers=[o.T_world_obj[:3, 3] for o in objects], half_sizes=[np.asarray(o.dims) / 2 for o in objects],
                quaternions=[_quat_xyzw(o.T_world_obj) for o in objects], labels=[o.name for o in objects],
                colors=[(150, 150, 150)] * len(objects)), static=True)

    def scan(self, scan, T_map_base, points_base=None) -> None:
        """A LiDAR sweep and the odometry's pose for it (None: not registered). ``points_base``: the
        sweep in ``base_link`` as the odometry deskewed it (None: only the pose is shown)."""
        if T_map_base is None:
            return
        rr = self.rr
        self._time(scan.stamp)
        if self.T_world_map is None:
            self.T_world_map = self._truth.T_world_base_at(scan.stamp) if self._truth is not None else np.eye(4)
        T_world_base = self.T_world_map @ np.asarray(T_map_base, dtype=float)
        if points_base is not None:
            world = transform_points(T_world_base, np.asarray(points_base)[::SCAN_POINT_STRIDE])
            self.rec.log("world/lidar/scan", rr.Points3D(world, colors=_height_colours(world[:, 2]), radii=0.015))
            if self._registered % MAP_EVERY == 0:
                key = transform_points(T_world_base, np.asarray(points_base)[::MAP_POINT_STRIDE])
                self.rec.log(f"world/lidar/map/{self._registered // MAP_EVERY}",
                             rr.Points3D(key, colors=[(120, 120, 120)], radii=0.01), static=True)
        self._registered += 1
        self._est.append(T_world_base[:3, 3])
        self.rec.log("world/robot/estimate", rr.LineStrips3D([np.array(self._est)], colors=[(40, 90, 255)],
                                                             labels=["odometry"]))
        self.rec.log("world/robot/estimate/pose", rr.Transform3D(translation=T_world_base[:3, 3],
                                                                 mat3x3=T_world_base[:3, :3]))
        if self._truth is not None:
            T = self._truth.T_world_base_at(scan.stamp)
            if T is not None and np.all(np.isfinite(T)):
                self._true.append(np.asarray(T)[:3, 3])
                self.rec.log("world/robot/truth", rr.LineStrips3D([np.array(self._true)], colors=[(40, 180, 60)],
                                                                  labels=["ground truth"]))
        self._maybe_store(scan.stamp)

    def image(self, frame, detections, correct=None) -> None:
        """A camera image, the detections run on it (None: the detector skipped it) and, when the
        truth is known, whether each one is correct."""
        rr = self.rr
        self._time(frame.stamp)
        if frame.rgb is not None:
            self.rec.log("camera/image", rr.Image(frame.rgb))
        elif frame.depth_m is not None:
            self.rec.log("camera/image", rr.DepthImage(frame.depth_m, meter=1.0))
        if detections is None:
            return
        mins, sizes, labels, colours, kp, kp_colours = [], [], [], [], [], []
        for i, det in enumerate(detections):
            pts = np.asarray(det.keypoints_px, dtype=float)
            ok = pts[np.all(np.isfinite(pts), axis=1)]
            if not len(ok):
                continue
            lo, hi = ok.min(axis=0), ok.max(axis=0)
            verdict = "" if correct is None else (" correct" if correct[i] else " FALSE")
            colour = PASS if det.fpr_pass else REJECT
            if det.fpr_pass and correct is not None and not correct[i]:
                colour = FALSE
            mins.append(lo)
            sizes.append(hi - lo)
            labels.append(f"{det.cls} FPR {'pass' if det.fpr_pass else 'reject'} ({det.belief_sum:.1f}){verdict}")
            colours.append(colour)
            kp.append(ok)
            kp_colours.extend([colour] * len(ok))
        self.rec.log("camera/image/detections", rr.Boxes2D(mins=mins, sizes=sizes, labels=labels, colors=colours)
                     if mins else rr.Clear(recursive=False))
        self.rec.log("camera/image/keypoints", rr.Points2D(np.vstack(kp), colors=kp_colours, radii=2.0)
                     if kp else rr.Clear(recursive=False))

    def tick(self, t: float) -> None:
        self._maybe_store(t)

    def finish(self, store, T_world_map=None, map_labels=None) -> None:
        """The published map at the end; ``map_labels``: the scoring's rows (``verdict`` per label)."""
        rr = self.rr
        T = self.T_world_map if T_world_map is None else np.asarray(T_world_map, dtype=float)
        T = np.eye(4) if T is None else T
        self._log_store(store, T)
        if map_labels:
            xyz = np.array([m["label_xyz"] for m in map_labels], dtype=float)  # world, as scored
            self.rec.log("world/objects/verdicts", rr.Points3D(
                xyz, radii=0.04, colors=[VERDICT_COLOURS.get(m["verdict"], (255, 255, 255)) for m in map_labels],
                labels=[f"{m['class']} #{m['id']}: {m['verdict']}" for m in map_labels]))
        self.rec.flush()

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    # --- helpers ---------------------------------------------------------------------------------
    def _time(self, t: float) -> None:
        self.rec.set_time(TIMELINE, duration=float(t))

    def _maybe_store(self, t: float) -> None:
        if self._pipe is None or t - self._last_store < STORE_EVERY_S or self.T_world_map is None:
            return
        self._last_store = t
        self._log_store(self._pipe.store, self.T_world_map)

    def _log_store(self, store, T_world_map) -> None:
        rr = self.rr
        objs = list(store)
        if not objs:
            self.rec.log("world/objects/map", rr.Clear(recursive=False))
            return
        centers = transform_points(T_world_map, np.array([m.xyz for m in objs], dtype=float))
        quats = [_quat_xyzw(T_world_map @ m.T_map_obj) for m in objs]
        colours = [(40, 120, 255) if m.status == "label" else (170, 170, 170) for m in objs]
        labels = [f"{m.cls} #{m.id} {m.status} ({m.observations} obs)" for m in objs]
        self.rec.log("world/objects/map", rr.Boxes3D(centers=centers, half_sizes=[np.asarray(m.size) / 2 for m in objs],
                                                     quaternions=quats, labels=labels, colors=colours))


def _quat_xyzw(T: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(T, dtype=float)[:3, :3]).as_quat()


def _height_colours(z: np.ndarray) -> np.ndarray:
    """Floor blue to 2 m red."""
    a = np.clip(np.asarray(z) / 2.0, 0.0, 1.0)[:, None]
    return (np.hstack([a, 0.4 * np.ones_like(a), 1.0 - a]) * 255).astype(np.uint8)


def make_view(kind: str | None, save: str | None, recording_id: str | None = None) -> RerunView | None:
    """The view the command line asked for: ``--view rerun`` and/or ``--view-save FILE.rrd``; None
    without either. Raises :class:`ViewError` (the command prints it as one line)."""
    if kind is None and not save:
        return None
    if kind not in (None, "rerun"):
        raise ViewError(f"--view: expected rerun, got {kind!r}")
    if save and not str(save).endswith(".rrd"):
        raise ViewError(f"--view-save {save}: expected a file name ending in .rrd")
    return RerunView(spawn=kind == "rerun", save=save, recording_id=recording_id)


def read_recording(path) -> dict[str, dict]:
    """What a recording file holds: per entity path, its rows and timelines (for checks and tests).
    Works with the Rerun SDK's chunk reader (0.29 and later) or its dataframe API (earlier)."""
    rr = _rerun()
    out: dict[str, dict] = {}
    try:
        from rerun.chunk import RrdReader
    except ImportError:
        recording = rr.dataframe.load_recording(str(path))
        for col in recording.schema().component_columns():
            e = out.setdefault(col.entity_path, {"rows": 0, "timelines": set(), "components": set()})
            e["components"].add(str(col.component))
        return out
    for chunk in RrdReader(path).stream():
        e = out.setdefault(chunk.entity_path, {"rows": 0, "timelines": set(), "components": set(), "static": False})
        e["rows"] += chunk.num_rows
        e["timelines"].update(chunk.timeline_names)
        e["static"] = e["static"] or chunk.is_static
        e["components"].update(n for n in chunk.to_record_batch().schema.names if ":" in n)
    return out
