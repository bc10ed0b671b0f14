"""KISS-ICP in a child process, for ``dopeslam run``'s pipeline: the LiDAR odometry registers the
sweeps beside the simulator, as a robot's odometry runs beside its world.

In the command's own process KISS-ICP holds the interpreter's lock for the whole of each call, and
with the detector in a process of its own and images nobody looks at not rendered, the simulator
and KISS-ICP in one process were the longest path of a run. Here the parent sends each sweep as it
is made (its points and per-point times as raw bytes after a JSON line, written by a thread of its
own, so the simulator never waits for the pipe) and, when the pipeline reaches the sweep, reads
what the registration changed (a :meth:`stack.lidar_slam.LidarOdometry.step` record, JSON: no
pickling) and feeds it to a :meth:`~stack.lidar_slam.LidarOdometry.follower`, which the pipeline
uses as its odometry: the same poses, the same bits. A sweep's registered points
(``last_points_base``) come back only for the sweeps the pipeline draws into its LiDAR map.
"""
from __future__ import annotations

import fcntl
import json
import os
import queue
import sys
import threading

import numpy as np

from sim.child import ChildOwner
from stack.lidar_slam import LidarOdometry, LidarOdometryConfig
from stack.messages import LidarScan
from testbed.detection_process import error_json, start_child

_PIPE_BYTES = 1 << 20  # the pipes' room (Linux), where the system allows


def _widen(fd: int) -> None:
    """Give a pipe ``_PIPE_BYTES`` of room where the system allows (else it keeps its own)."""
    try:
        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), _PIPE_BYTES)
    except OSError:
        pass


def _array_header(a: np.ndarray | None):
    return None if a is None else [a.dtype.str, list(a.shape)]


def _read_array(stream, header) -> np.ndarray | None:
    if header is None:
        return None
    dtype, shape = np.dtype(header[0]), tuple(int(n) for n in header[1])
    n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = stream.read(n)
    if len(raw) != n:
        raise EOFError("a sweep's bytes ended early")
    return np.frombuffer(raw, dtype=dtype).reshape(shape)


class OdometryProcess(ChildOwner):
    """:class:`stack.lidar_slam.LidarOdometry` with ``config`` for a LiDAR mounted at
    ``T_base_lidar``, registering in a child process.

    ``odometry``: the pipeline's odometry (a follower). ``submit(scan)`` hands a sweep over and returns
    at once; ``take()`` waits for the oldest sweep submitted and not yet taken, feeds its result to
    ``odometry`` (whose ``process`` of that sweep then gives it) and returns it. ``points_every``:
    the child sends the registered points of the 1st, (n+1)-th, (2n+1)-th... registered sweep (the
    pipeline's ``MAP_EVERY``; 0: never). ``close()`` ends the child (also on errors, which are
    raised as ``RuntimeError('odometry process: ...')``)."""

    def __init__(self, T_base_lidar: np.ndarray, config: LidarOdometryConfig | None = None, points_every: int = 0):
        config = config or LidarOdometryConfig()
        self.odometry = LidarOdometry.follower(T_base_lidar, config)
        self._proc, self._replies = start_child("testbed.odometry_process")
        _widen(self._replies.fileno())
        _widen(self._proc.stdin.fileno())
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._write_all, name="odometry-process-writer", daemon=True)
        self._writer.start()
        self._in_flight: list[LidarScan] = []
        self._outbox.put((json.dumps({"T_base_lidar": np.asarray(T_base_lidar, dtype=float).ravel().tolist(),
                                      "config": config.model_dump(), "points_every": int(points_every)}), ()))

    def _write_all(self) -> None:
        """The writer thread: each request's line, then its arrays' bytes, in order (None: stop)."""
        stdin = self._proc.stdin
        try:
            while True:
                item = self._outbox.get()
                if item is None:
                    break
                line, arrays = item
                stdin.write(line.encode() + b"\n")
                for a in arrays:
                    stdin.write(a.reshape(-1).view(np.uint8))
                stdin.flush()
            stdin.close()  # all it gets: it ends after the last sweep
        except (BrokenPipeError, OSError, ValueError):
            pass  # it has gone: take() says why

    def submit(self, scan: LidarScan) -> None:
        points = np.ascontiguousarray(scan.points) if scan.points is not None else None
        times = np.ascontiguousarray(scan.times_s) if scan.times_s is not None else None
        if points is not None and points.dtype.hasobject or times is not None and times.dtype.hasobject:
            raise ValueError("odometry process: a sweep's points and times must be numeric arrays")
        head = {"stamp": float(scan.stamp), "points": _array_header(points), "times": _array_header(times)}
        self._outbox.put((json.dumps(head), tuple(a for a in (points, times) if a is not None)))
        self._in_flight.append(scan)

    @property
    def in_flight(self) -> int:
        """Sweeps submitted and not yet taken."""
        return len(self._in_flight)

    def take(self) -> LidarScan:
        if not self._in_flight:
            raise RuntimeError("odometry process: take() with no sweep submitted")
        line = self._replies.readline() if self._replies is not None else b""
        if not line:
            self._fail("it exited")
        reply = json.loads(line)
        if "error" in reply or "user_error" in reply:
            self._fail(reply.get("error") or reply["user_error"])
        points = None
        if reply["points"] is not None:
            try:
                points = _read_array(self._replies, ["<f8", [int(reply["points"]), 3]]).copy()
            except EOFError:
                self._fail("it exited")
        self.odometry.feed(reply["step"], points)
        return self._in_flight.pop(0)

    def _fail(self, why: str):
        self.close()
        raise RuntimeError(f"odometry process: {why}")

    def close(self) -> None:
        outbox = getattr(self, "_outbox", None)
        if outbox is not None:
            outbox.put(None)
        replies, self._replies = getattr(self, "_replies", None), None
        if replies is not None:  # first, so a child blocked writing to it stops at once
            replies.close()
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None and self._in_flight:
            proc.kill()  # stopped early (an error upstream): its work is not wanted
        writer = getattr(self, "_writer", None)
        if writer is not None and writer is not threading.current_thread():
            writer.join(timeout=10)
        super().close()


def _child_main() -> None:
    out = os.fdopen(int(sys.argv[1]), "wb")
    requests = sys.stdin.buffer

    def reply(obj, payload: bytes = b""):
        out.write(json.dumps(obj).encode() + b"\n" + payload)
        out.flush()

    try:
        line = requests.readline()
        if not line:
            return  # the parent stopped first
        setup = json.loads(line)
        T = np.asarray(setup["T_base_lidar"], dtype=float).reshape(4, 4)
        odom = LidarOdometry(T, LidarOdometryConfig(**setup["config"]))
        every = int(setup["points_every"])
        registered = 0
        for line in requests:
            head = json.loads(line)
            points = _read_array(requests, head["points"])
            times = _read_array(requests, head["times"])
            pose = odom.process(LidarScan(stamp=head["stamp"], points=points, times_s=times))
            payload = b""
            if pose is not None:
                registered += 1
                if every and registered % every == 1 % every and odom.last_points_base is not None:
                    payload = np.ascontiguousarray(odom.last_points_base, dtype=np.float64).tobytes()
            reply({"step": odom.step(), "points": len(payload) // 24 if payload else None}, payload)
    except (BrokenPipeError, KeyboardInterrupt):
        return  # the parent stopped reading
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        try:
            reply(error_json(exc))
        except (BrokenPipeError, OSError):
            pass
