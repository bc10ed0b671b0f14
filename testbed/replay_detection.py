"""Replay's detector side in a child process: it opens the bag on a reader of its own, reads and
decodes the images (and the wheel odometry the keyframe gate reads), gates them, runs the DOPE
detector, and hands each image with its detections to the pipeline in the parent.

In a thread of the parent this work shares the interpreter's lock with the pipeline, and KISS-ICP
keeps that lock for the whole of each registration call, so the detector's Python steps (the bag's
parser, peak decoding, PnP, FPR) wait for the odometry and the odometry for them. In a process of its
own it waits only for a core (docs/speed.md). The images come back through shared memory (a ring of
slots the parent frees as it copies them out); everything else as JSON lines (no pickling); a
detection decodes to the same values and types the detector made.
"""
from __future__ import annotations

import json
import os
import sys
from multiprocessing import shared_memory
from types import SimpleNamespace

import numpy as np

from sim.child import ChildOwner
from stack.messages import CameraFrame, CameraInfo
from testbed.detection_process import (BuiltDetector, decode_detection, decode_value, encode_detection,
                                      encode_value, error_json, frame_fits, slot_arrays, slot_bytes,
                                      start_child)

_TOPIC_FIELDS = ("lidar", "rgb", "depth", "camera_info", "base_frame", "max_bad_messages")
_POSE_FIELDS = ("T_base_lidar", "T_base_camera")


def _topics_json(topics) -> dict:
    out = {f: getattr(topics, f) for f in _TOPIC_FIELDS}
    out.update({f: None if getattr(topics, f) is None else np.asarray(getattr(topics, f), float).tolist()
                for f in _POSE_FIELDS})
    return out


def _topics_from_json(d: dict):
    from testbed.replay import BagTopics

    return BagTopics(**{f: d[f] for f in _TOPIC_FIELDS},
                     **{f: None if d[f] is None else np.asarray(d[f], dtype=float) for f in _POSE_FIELDS})


def _error_json(exc: BaseException) -> dict:
    from testbed.bags.errors import BagError

    if isinstance(exc, BagError):
        return {"bag_error": type(exc).__name__, "path": str(exc.path), "message": exc.message}
    return error_json(exc)


def _raise_error(reply: dict, bag: str):
    """The child's error raised here: a bag error as the same class with the same text, another error
    in what the user gave as a DopeSlamError (so the command prints the one line it would have
    printed), anything else as a RuntimeError naming ``bag``."""
    from stack.errors import DopeSlamError
    from testbed.bags import errors

    if "user_error" in reply:
        raise DopeSlamError(reply["user_error"])
    name = reply.get("bag_error")
    if name is not None:
        cls = getattr(errors, name, None)
        if not (isinstance(cls, type) and issubclass(cls, errors.BagError)):
            cls = errors.BagReadError
        exc = cls.__new__(cls)
        errors.BagError.__init__(exc, reply["path"], reply["message"])
        raise exc
    raise RuntimeError(f"{bag}: replay's detection process: {reply.get('error', 'exited')}")


class DetectionReaderProcess(ChildOwner):
    """The twin of :class:`testbed.replay.DetectionAhead` in a child process.

    ``kwargs``: the DOPE detector's (:func:`testbed.run.detector_kwargs`); ``info``: the bag's camera
    (the shared slots' size; an image of another size comes back inline), or None and ``camera(info)``
    before iterating (the child meanwhile builds its detector and opens the bag). Iterating gives ``(frame,
    detections or None when not detected, seconds)`` in image order. After the last image: ``gate``
    (``.held``: images the keyframe gate kept from the detector; None without a gate), ``reader``
    (the child reader's ``salvaged``, ``skipped_chunks`` and ``bad_message_summary()``) and
    ``read_seconds`` (the child's time reading and decoding). ``helper``: the child starts a second
    detector process (:class:`testbed.detection_process.DetectionProcess`) that detects every other
    detected image while the child detects the next (:func:`testbed.replay.detected_images`). Once
    the child has replied ready (at the first image): ``built``, the :class:`BuiltDetector` it runs.
    ``colour`` False: the child reads the colour images for their stamps only (frames without ``rgb``)."""

    def __init__(self, bag_path, topics, input_mode: str, kwargs: dict, info: CameraInfo | None,
                 dope_every: int = 1, keyframes=None, threads: int | None = 1, slots: int = 8, helper: bool = False,
                 colour: bool = True):
        self._shm, self._shape, self._slots = None, None, int(slots)
        self.helper = bool(helper)
        self._bag = str(bag_path)
        self._proc, self._replies = start_child("testbed.replay_detection")
        ks = None if keyframes is None else {"min_motion_m": keyframes.min_motion_m,
                                             "min_turn_deg": keyframes.min_turn_deg,
                                             "max_interval_s": keyframes.max_interval_s}
        self._send({"bag": self._bag, "topics": _topics_json(topics), "input": input_mode,
                    "kwargs": encode_value(kwargs), "threads": threads, "every": int(dope_every), "keyframes": ks,
                    "helper": self.helper, "colour": bool(colour)})
        self.gate = None
        self.reader = None
        self.built: BuiltDetector | None = None
        self.read_seconds = 0.0
        if info is not None:
            self.camera(info)

    def camera(self, info: CameraInfo | None) -> None:
        """The slots for images of ``info``'s size (None: no slots, every image inline)."""
        H, W = (info.height, info.width) if info is not None else (0, 0)
        self._shape = (H, W)
        slots = self._slots if H * W else 0
        if slots:
            self._shm = shared_memory.SharedMemory(create=True, size=slot_bytes(H, W) * slots)
        self._send({"shm": None if self._shm is None else self._shm.name, "height": H, "width": W, "slots": slots})

    def _send(self, obj) -> bool:
        """False when the child has gone (what it left on the reply pipe says why)."""
        try:
            self._proc.stdin.write(json.dumps(obj).encode() + b"\n")
            self._proc.stdin.flush()
            return True
        except (BrokenPipeError, OSError, AttributeError):
            return False

    def _fail(self, reply: dict):
        self.close()
        _raise_error(reply, self._bag)

    def __iter__(self):
        if self._shape is None:
            raise RuntimeError("DetectionReaderProcess: camera(info) first")
        H, W = self._shape
        while True:
            line = self._replies.readline() if self._replies is not None else b""
            if not line:
                self._fail({"error": "exited"})
            reply = json.loads(line)
            if {"error", "bag_error", "user_error"} & reply.keys():
                self._fail(reply)
            if "end" in reply:
                end = reply["end"]
                self.read_seconds = float(end["read_seconds"])
                self.gate = None if end["held"] is None else SimpleNamespace(held=int(end["held"]))
                bad = end["bad_messages"]
                self.reader = SimpleNamespace(salvaged=end["salvaged"], skipped_chunks=end["skipped_chunks"],
                                              bad_message_summary=lambda bad=bad: bad)
                return
            f = reply.get("frame")
            if f is None:  # "ready", with the detector it built
                self.built = BuiltDetector.from_json(reply["detector"])
                continue
            slot = f["slot"]
            if slot is None:  # not the slots' size: sent inline
                rgb, depth = decode_value(f["rgb"]), decode_value(f["depth"])
            else:
                rgb, depth = slot_arrays(self._shm.buf, slot, H, W)
                rgb = rgb.copy() if f["rgb"] else None
                depth = depth.copy() if f["depth"] else None
                self._send({"free": slot})
            info = CameraInfo(int(f["width"]), int(f["height"]), decode_value(f["K"]), f["frame_id"])
            frame = CameraFrame(f["stamp"], info, rgb, depth, decode_value(f["T"]), decode_value(f["extra"]))
            dets = None if f["dets"] is None else [decode_detection(d) for d in f["dets"]]
            self.read_seconds = float(f["read_seconds"])
            yield frame, dets, float(f["seconds"])

    def close(self) -> None:
        replies, self._replies = getattr(self, "_replies", None), None
        if replies is not None:  # first, so a child blocked writing to it stops at once
            replies.close()
        super().close()


def _child_main() -> None:
    from multiprocessing import resource_tracker

    from stack.keyframes import KeyframeSettings, keyframe_gate
    from testbed.detection_process import DetectionProcess, build_detector
    from testbed.replay import detected_images, open_bag

    out = os.fdopen(int(sys.argv[1]), "wb")
    requests = sys.stdin.buffer

    def reply(obj):
        out.write(json.dumps(obj).encode() + b"\n")
        out.flush()

    reader = helper = None
    try:
        setup = json.loads(requests.readline())
        kwargs = decode_value(setup["kwargs"])
        reader = open_bag(setup["bag"], _topics_from_json(setup["topics"]), setup["input"], ground_truth=False,
                          colour_pixels=setup.get("colour", True))
        if setup.get("helper") and reader.camera_info is not None:  # started first: it builds its network meanwhile
            helper = DetectionProcess(kwargs, reader.camera_info, setup["threads"], quiet=True)  # warned below
        detector = build_detector(kwargs, setup["threads"])
        gate = keyframe_gate(None if setup["keyframes"] is None else KeyframeSettings(**setup["keyframes"]))
        every = max(1, int(setup["every"]))
        line = requests.readline()  # the slots, once the parent has opened the bag too
        if not line:
            return  # the parent stopped first
        slots_setup = json.loads(line)
        H, W, slots = slots_setup["height"], slots_setup["width"], slots_setup["slots"]
        shm = None
        if slots:
            shm = shared_memory.SharedMemory(name=slots_setup["shm"])
            resource_tracker.unregister(shm._name, "shared_memory")  # the parent owns (and unlinks) it
        free = list(range(slots))
        reply({"ready": True, "detector": BuiltDetector.json_of(detector)})
        read_s = 0.0
        for frame, dets, reading, seconds in detected_images(reader, detector, every, gate, helper):
            read_s += reading
            info = frame.info
            rgb, depth = frame.rgb, frame.depth_m
            fits = slots > 0 and frame_fits(frame, H, W)
            msg = {"stamp": frame.stamp, "width": info.width, "height": info.height,
                   "K": encode_value(np.asarray(info.K)), "frame_id": info.frame_id,
                   "T": encode_value(frame.T_world_camera), "extra": encode_value(frame.extra),
                   "dets": None if dets is None else [encode_detection(d) for d in dets],
                   "seconds": seconds, "read_seconds": read_s}
            if fits:
                while not free:  # every slot still being copied out: wait for the parent
                    line = requests.readline()
                    if not line:
                        return  # the parent is gone
                    free.append(int(json.loads(line)["free"]))
                slot = free.pop(0)
                rgb_slot, depth_slot = slot_arrays(shm.buf, slot, H, W)
                if rgb is not None:
                    rgb_slot[...] = rgb
                if depth is not None:
                    depth_slot[...] = depth
                msg.update(slot=slot, rgb=rgb is not None, depth=depth is not None)
            else:
                msg.update(slot=None, rgb=encode_value(rgb), depth=encode_value(depth))
            reply({"frame": msg})
        reply({"end": {"held": None if gate is None else gate.held, "read_seconds": read_s,
                       "salvaged": reader.salvaged, "skipped_chunks": reader.skipped_chunks,
                       "bad_messages": reader.bad_message_summary()}})
        for _ in requests:  # the parent's last "free" lines, until it closes the pipe
            pass
    except (BrokenPipeError, KeyboardInterrupt):
        return  # the parent stopped reading
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        try:
            reply(_error_json(exc))
        except (BrokenPipeError, OSError):
            pass
    finally:
        if helper is not None:
            helper.close()
        if reader is not None:
            reader.close()
