"""The DOPE detector in a child process, for ``dopeslam run``'s detector ahead of the pipeline.

In a thread the network shares the interpreter's lock with the simulator and the stack; in a process
of its own it waits only for a core. Frames go to the child through shared memory (a few slots, one
per image in flight) with a JSON line naming the slot; detections come back as JSON lines whose
arrays and NumPy scalars carry their dtype, so a detection decodes to the same values and types the
detector made (no pickling). The child builds its detector from the same keyword arguments as the
parent's, so it finds the same detections.
"""
from __future__ import annotations

import base64
import json
import logging
import os
import select
import subprocess
import sys
import time
from dataclasses import dataclass
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np

from sim.child import ChildOwner, child_command, package_env
from stack.interfaces import detect
from stack.messages import CameraFrame, CameraInfo, Detection


# --- values through JSON, types kept ---------------------------------------------------------------

def encode_value(v):
    """A JSON-able form of ``v`` that :func:`decode_value` turns back into the same value and type."""
    if isinstance(v, np.ndarray):
        a = np.ascontiguousarray(v)
        return {"__nd__": [a.dtype.str, list(a.shape), base64.b64encode(a.tobytes()).decode("ascii")]}
    if isinstance(v, np.generic):
        return {"__np__": [v.dtype.str, base64.b64encode(np.asarray(v).tobytes()).decode("ascii")]}
    if isinstance(v, tuple):
        return {"__tuple__": [encode_value(x) for x in v]}
    if isinstance(v, list):
        return [encode_value(x) for x in v]
    if isinstance(v, dict):
        if not all(isinstance(k, str) for k in v):
            raise TypeError("detection extras: only str keys pass to the detector process")
        return {"__dict__": {k: encode_value(x) for k, x in v.items()}}
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    raise TypeError(f"detection extras: a {type(v).__name__} cannot pass to the detector process")


def decode_value(v):
    if isinstance(v, list):
        return [decode_value(x) for x in v]
    if isinstance(v, dict):
        if "__nd__" in v:
            dtype, shape, data = v["__nd__"]
            return np.frombuffer(base64.b64decode(data), dtype=np.dtype(dtype)).reshape(shape).copy()
        if "__np__" in v:
            dtype, data = v["__np__"]
            return np.frombuffer(base64.b64decode(data), dtype=np.dtype(dtype))[0]
        if "__tuple__" in v:
            return tuple(decode_value(x) for x in v["__tuple__"])
        if "__dict__" in v:
            return {k: decode_value(x) for k, x in v["__dict__"].items()}
        raise ValueError(f"detector process: unknown record {sorted(v)}")
    return v


_FIELDS = ("cls", "stamp", "T_cam_obj", "keypoints_px", "peak_scores", "belief_sum", "stages", "fpr_pass", "extra")


def encode_detection(d: Detection) -> dict:
    return {f: encode_value(getattr(d, f)) for f in _FIELDS}


def decode_detection(d: dict) -> Detection:
    return Detection(**{f: decode_value(d[f]) for f in _FIELDS})


# --- the shared image slots -------------------------------------------------------------------------

def slot_bytes(H: int, W: int) -> int:
    """Bytes of one image slot: a colour image (uint8, H x W x 3), then a depth image (float32, H x W)."""
    return H * W * 3 + H * W * 4


def slot_arrays(buf, slot: int, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Views of slot ``slot`` of the shared buffer ``buf``: ``(colour, depth)``."""
    base = slot * slot_bytes(H, W)
    return (np.ndarray((H, W, 3), np.uint8, buf, base), np.ndarray((H, W), np.float32, buf, base + H * W * 3))


def frame_fits(frame: CameraFrame, H: int, W: int) -> bool:
    """Whether ``frame``'s colour (uint8, H x W x 3) and depth (float32, H x W) images, each or None,
    fit a slot."""
    rgb, depth = frame.rgb, frame.depth_m
    return (rgb is None or (rgb.dtype == np.uint8 and rgb.shape == (H, W, 3))) and \
        (depth is None or (depth.dtype == np.float32 and depth.shape == (H, W)))


# --- what the children report ------------------------------------------------------------------


@dataclass(frozen=True)
class BuiltDetector:
    """The detector a child process built and ran, as the report and the outputs' provenance name
    it (the parent builds no network of its own)."""

    name: str  # module:Class
    weights_path: Path | None
    thresholds_path: Path | None
    precision: str | None
    refinement_order: str | None = None  # the memory order the network's refinement stages ran in

    @staticmethod
    def json_of(detector) -> dict:
        """What the parent needs to know of ``detector``, as JSON."""
        def path(p):
            return None if p is None else str(p)

        return {"name": detector_name(detector), "weights_path": path(getattr(detector, "weights_path", None)),
                "thresholds_path": path(getattr(detector, "thresholds_path", None)),
                "precision": getattr(detector, "precision", None),
                "refinement_order": getattr(detector, "refinement_order", None)}

    @staticmethod
    def from_json(d: dict) -> "BuiltDetector":
        def path(p):
            return None if p is None else Path(p)

        return BuiltDetector(str(d["name"]), path(d["weights_path"]), path(d["thresholds_path"]), d["precision"],
                             d.get("refinement_order"))


def detector_name(detector) -> str:
    """``module:Class`` of a detector (of a :class:`BuiltDetector`, the one it names), or of any
    component, for the report."""
    if isinstance(detector, BuiltDetector):
        return detector.name
    cls = type(detector)
    return f"{cls.__module__}:{cls.__qualname__}"


def error_json(exc: BaseException) -> dict:
    """A child's error as a reply: an error in what the user gave (a :class:`stack.errors.DopeSlamError`,
    e.g. a weights file that is not one) apart, so the parent raises it as such."""
    from stack.errors import DopeSlamError

    if isinstance(exc, DopeSlamError):
        return {"user_error": str(exc)}
    return {"error": f"{type(exc).__name__}: {exc}"}


# --- the parent's side ------------------------------------------------------------------------------

def start_child(module: str):
    """``(process, reply pipe)``: ``MODULE._child_main()`` in a child Python (``sim.child.run_child``), its
    requests on its stdin, its replies on a pipe of their own (FD; nothing a library prints reaches
    it), what it prints where this process's logs go."""
    reply_r, reply_w = os.pipe()
    cmd = child_command(module, "_child_main", str(reply_w))
    try:
        out = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        out = subprocess.DEVNULL
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=out, pass_fds=(reply_w,), env=package_env())
    finally:
        os.close(reply_w)
    return proc, os.fdopen(reply_r, "rb")


class _Pending:
    """A detection job in the child: ``result()`` gives ``(detections, seconds)`` as a Future would."""

    def __init__(self, owner: "DetectionProcess", token: int):
        self._owner, self.token = owner, token

    def result(self):
        return self._owner._result(self.token)

    def done(self) -> bool:
        """Whether the child has replied to this job (reads the replies already waiting; never waits)."""
        return self._owner._replied(self.token)

    def cancel(self) -> bool:
        return False


class DetectionProcess(ChildOwner):
    """A DOPE detector (:class:`stack.dope_fpr.DopeDetector` built from ``kwargs``) in a child process.

    ``submit(frame)`` copies the frame into a free slot and returns at once; jobs are done in order,
    so ``result()`` of a later job reads the replies of the earlier ones first. At most ``slots`` jobs
    are in flight. ``close()`` ends the child (also on errors). ``built()``: the
    :class:`BuiltDetector` the child runs (waits for it to be built). An error in what the user gave
    (e.g. a weights file that is not one) is raised as a :class:`stack.errors.DopeSlamError`.
    ``quiet``: the detector's build-time warnings (its precision, FPR thresholds missing) are not
    printed: for a second process with the same settings, which would only say them again."""

    def __init__(self, kwargs: dict, info: CameraInfo, threads: int | None = 1, slots: int = 4, quiet: bool = False):
        H, W = info.height, info.width
        self._slots = int(slots)
        self._shm = shared_memory.SharedMemory(create=True, size=slot_bytes(H, W) * self._slots)
        self._shape = (H, W)
        self._proc, self._replies = start_child("testbed.detection_process")
        setup = {"kwargs": encode_value(kwargs), "threads": threads, "shm": self._shm.name,
                 "height": H, "width": W, "slots": self._slots, "quiet": bool(quiet)}
        self._send(setup)
        self._next = 0  # the next job's token
        self._done: dict[int, tuple] = {}  # replies read ahead of their turn
        self._read = 0  # replies read so far
        self._built: BuiltDetector | None = None  # from the child's first reply: its detector is built
        self._pending = bytearray()  # bytes read from the reply pipe that do not yet end a line

    def _send(self, obj) -> None:
        try:
            self._proc.stdin.write(json.dumps(obj).encode() + b"\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            self._fail("the detector process exited")

    def _line(self, wait: bool = True) -> bytes | None:
        """The child's next reply line; b"" when it has exited; None when ``wait`` is false and no whole
        line has come yet. The pipe is read in blocks here (not through the file object's buffer), so
        whether a reply is waiting can be asked without waiting for one."""
        fd = self._replies.fileno()
        while True:
            end = self._pending.find(b"\n")
            if end >= 0:
                line = bytes(self._pending[:end + 1])
                del self._pending[:end + 1]
                return line
            if not wait and not select.select([fd], [], [], 0)[0]:
                return None
            block = os.read(fd, 1 << 16)
            if not block:
                return b""
            self._pending += block

    def _reply(self, wait: bool = True) -> dict | None:
        line = self._line(wait)
        if line is None:
            return None
        if not line:
            self._fail("the detector process exited")
        reply = json.loads(line)
        if "user_error" in reply:
            from stack.errors import DopeSlamError

            self.close()
            raise DopeSlamError(reply["user_error"])
        if "error" in reply:
            self._fail(reply["error"])
        return reply

    def _fail(self, why: str):
        self.close()
        raise RuntimeError(f"detector process: {why}")

    def built(self) -> BuiltDetector:
        if self._built is None:
            self._built = BuiltDetector.from_json(self._reply()["detector"])
        return self._built

    def unfinished(self) -> int:
        """Jobs the child has not replied to yet (reads the replies already waiting; never waits)."""
        while self._read < self._next:
            reply = self._reply(wait=False)
            if reply is None:
                break
            if self._built is None:
                self._built = BuiltDetector.from_json(reply["detector"])
            else:
                self._store(reply)
        return self._next - self._read

    def _replied(self, token: int) -> bool:
        if token >= self._read:
            self.unfinished()
        return token < self._read

    def fits(self, frame: CameraFrame) -> bool:
        """Whether ``frame``'s images fit the slots (else ``submit`` raises ValueError)."""
        return frame_fits(frame, *self._shape)

    def submit(self, frame: CameraFrame) -> _Pending:
        if self._next - self._read >= self._slots:
            self._collect_one()  # every slot busy: wait for the oldest job
        H, W = self._shape
        if frame.rgb is not None and (frame.rgb.dtype != np.uint8 or frame.rgb.shape != (H, W, 3)):
            raise ValueError(f"detector process: colour image {frame.rgb.dtype} {frame.rgb.shape}, expected "
                             f"uint8 ({H}, {W}, 3)")
        if frame.depth_m is not None and (frame.depth_m.dtype != np.float32 or frame.depth_m.shape != (H, W)):
            raise ValueError(f"detector process: depth image {frame.depth_m.dtype} {frame.depth_m.shape}, "
                             f"expected float32 ({H}, {W})")
        slot = self._next % self._slots
        rgb, depth = slot_arrays(self._shm.buf, slot, H, W)
        if frame.rgb is not None:
            rgb[...] = frame.rgb
        if frame.depth_m is not None:
            depth[...] = frame.depth_m
        info = frame.info
        self._send({"slot": slot, "stamp": frame.stamp, "rgb": frame.rgb is not None,
                    "depth": frame.depth_m is not None, "K": encode_value(np.asarray(info.K)),
                    "frame_id": info.frame_id, "T": encode_value(frame.T_world_camera)})
        token = self._next
        self._next += 1
        return _Pending(self, token)

    def _collect_one(self) -> None:
        self.built()  # the child's first reply: its detector is built
        self._store(self._reply())

    def _store(self, reply: dict) -> None:
        self._done[self._read] = ([decode_detection(d) for d in reply["detections"]], float(reply["seconds"]))
        self._read += 1

    def _result(self, token: int):
        while token not in self._done:
            self._collect_one()
        return self._done.pop(token)


def build_detector(kwargs: dict, threads: int | None, quiet: bool = False):
    """The DOPE detector for the simulator's classes from ``make_detector``'s keyword arguments;
    ``quiet``: without the warnings it logs while it is built (its precision, FPR thresholds missing)."""
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector

    dims = {c: s.dims for c, s in load_catalog().items()}
    logger = logging.getLogger(DopeDetector.__module__)
    level = logger.level
    if quiet:
        logger.setLevel(logging.ERROR)
    try:
        return DopeDetector(dims=dims, threads=threads, **kwargs)
    finally:
        logger.setLevel(level)


def _child_main() -> None:
    from multiprocessing import resource_tracker

    out = os.fdopen(int(sys.argv[1]), "wb")

    def reply(obj):
        out.write(json.dumps(obj).encode() + b"\n")
        out.flush()

    try:
        setup = json.loads(sys.stdin.buffer.readline())
        shm = shared_memory.SharedMemory(name=setup["shm"])
        resource_tracker.unregister(shm._name, "shared_memory")  # the parent owns (and unlinks) it
        H, W = setup["height"], setup["width"]
        detector = build_detector(decode_value(setup["kwargs"]), setup["threads"], bool(setup.get("quiet")))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        reply(error_json(exc))
        return
    reply({"ready": True, "detector": BuiltDetector.json_of(detector)})
    for line in sys.stdin.buffer:
        try:
            job = json.loads(line)
            rgb, depth = slot_arrays(shm.buf, job["slot"], H, W)
            rgb = rgb.copy() if job["rgb"] else None
            depth = depth.copy() if job["depth"] else None
            frame = CameraFrame(job["stamp"], CameraInfo(W, H, decode_value(job["K"]), job["frame_id"]), rgb, depth,
                                decode_value(job["T"]))
            t0 = time.perf_counter()
            dets = detect(detector, frame)
            seconds = time.perf_counter() - t0
            reply({"detections": [encode_detection(d) for d in dets], "seconds": seconds})
        except Exception as exc:  # noqa: BLE001 - a detection that is not one is the user's error, as at start
            reply(error_json(exc))
            return
    shm.close()
