"""Rendering machinery for the simulated cameras: PyBullet clients (EGL when it loads, else
TinyRenderer), the optical-frame camera's GL matrices, the noise-free render (colour, depth along
the optical axis, segmentation), and ``RenderWorker``, which renders in a second process so the
physics and the camera overlap. The sensor model (the D435i's noise, ``render_rgbd``) is
``sim.camera``.
"""
from __future__ import annotations

import logging
import os
import pkgutil

import cv2
import numpy as np
import pybullet as p

from sim.child import ChildOwner, child_command, package_env
from stack.messages import CameraInfo

log = logging.getLogger(__name__)
NEAR, FAR = 0.05, 30.0
RASTERISER_THREADS = "LP_NUM_THREADS"  # Mesa llvmpipe's own variable: its rasteriser threads (0: none)


def rasterise_in_the_calling_thread(env: dict) -> dict:
    """``env`` (a child's environment, changed in place and returned) with Mesa's software rasteriser
    (llvmpipe, behind PyBullet's EGL plugin) drawing in the thread that asks for the image instead of
    handing tiles to threads of its own. For the render processes: they share the cores with processes
    as busy as they are (the simulator, the stack, the network, another render process), where those
    threads cost about a sixth more CPU per frame for nothing (``benchmarks/bench_render_threads.py``).
    The images are the same bytes. A user's own ``LP_NUM_THREADS`` is kept."""
    env.setdefault(RASTERISER_THREADS, "0")
    return env


def new_client(renderer: str = "auto") -> tuple[int, int]:
    """A DIRECT PyBullet client and the renderer flag to use: EGL (Mesa llvmpipe) when it loads, else TinyRenderer."""
    client = p.connect(p.DIRECT)
    flag = p.ER_TINY_RENDERER
    if renderer in ("auto", "egl"):
        loader = pkgutil.get_loader("eglRenderer")
        plugin = -1
        if loader is not None:
            plugin = p.loadPlugin(loader.get_filename(), "_eglRendererPlugin", physicsClientId=client)
        if plugin >= 0:
            flag = p.ER_BULLET_HARDWARE_OPENGL
        elif renderer == "egl":
            raise RuntimeError("EGL renderer requested but the eglRenderer plugin did not load")
        else:
            log.info("EGL renderer unavailable; using TinyRenderer")
    return client, flag


def gl_matrices(T_world_cam: np.ndarray, info: CameraInfo, near: float = NEAR, far: float = FAR):
    """PyBullet view and projection matrices (column-major lists) for an optical-frame camera pose."""
    T_world_gl = T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0])  # optical (z fwd, y down) -> GL (z back, y up)
    view = np.linalg.inv(T_world_gl)
    W, H = info.width, info.height
    fx, fy, cx, cy = info.fx, info.fy, info.cx + 0.5, info.cy + 0.5  # pixel index -> continuous coordinate
    proj = np.array([
        [2 * fx / W, 0, 1 - 2 * cx / W, 0],
        [0, 2 * fy / H, 2 * cy / H - 1, 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])
    return view.T.reshape(-1).tolist(), proj.T.reshape(-1).tolist()


def render_raw(client: int, T_world_cam: np.ndarray, info: CameraInfo, renderer: int = p.ER_TINY_RENDERER,
               light_direction=(0.3, 0.4, 1.0), shadow: bool = False, segmentation: bool = True):
    """Noise-free (rgb uint8 HxWx3, depth_m float32 HxW, segmentation int32 HxW or None).

    ``segmentation=False`` skips the segmentation pass (about 40 % of the renderer's time with EGL):
    the colour and depth are the same, the segmentation is None."""
    view, proj = gl_matrices(T_world_cam, info)
    _, _, rgba, zbuf, seg = p.getCameraImage(
        info.width, info.height, view, proj, renderer=renderer, lightDirection=list(light_direction),
        shadow=int(shadow), flags=0 if segmentation else p.ER_NO_SEGMENTATION_MASK, physicsClientId=client)
    # the alpha channel dropped by OpenCV: the same bytes as a strided NumPy copy, at a thirtieth of its cost
    rgb = cv2.cvtColor(np.asarray(rgba, dtype=np.uint8).reshape(info.height, info.width, 4), cv2.COLOR_RGBA2RGB)
    zbuf = np.asarray(zbuf, dtype=np.float32).reshape(info.height, info.width)
    # depth buffer -> distance along the optical axis: near * far / (far - (far - near) * zbuf), written
    # as far * (1 - zbuf) + near * zbuf so float32 does not cancel where zbuf is near 1 (far surfaces)
    den = np.float32(1.0) - zbuf
    den *= np.float32(FAR)
    den += np.float32(NEAR) * zbuf
    depth = np.divide(np.float32(FAR * NEAR), den, out=np.zeros_like(den), where=zbuf < 1.0)
    if not segmentation:
        return rgb, depth, None
    segm = np.asarray(seg, dtype=np.int32).reshape(info.height, info.width)
    return rgb, depth, segm


# --- rendering in a second process -----------------------------------------------------------------

def render_worker_wanted(default: bool) -> bool:
    """Whether to render in a second process: ``DOPESLAM_RENDER_WORKER`` (``1`` or ``0``) when it is
    set, else ``default`` (the caller's choice for its own loop)."""
    value = os.environ.get("DOPESLAM_RENDER_WORKER", "").strip()
    return value == "1" if value else bool(default)


_REQUEST = np.dtype([("T_world_cam", "<f8", (4, 4)), ("T_world_base", "<f8", (4, 4)), ("light", "<f8"),
                     ("seed", "<u8"), ("noise", "u1")])


class RenderWorker(ChildOwner):
    """Renders D435i frames in a child process that holds the same static world and a copy of the robot.

    PyBullet keeps the GIL while it renders, so a thread cannot overlap rendering with the physics and
    the LiDAR; a process can, on the second core. Requests and replies are fixed-size binary records on
    pipes and the images come back through shared memory (no pickling). ``submit`` returns at once;
    ``collect`` waits for that frame. One frame is in flight at a time.
    """

    def __init__(self, scenario, info: CameraInfo, renderer: str = "auto", segmentation: bool = True):
        import json
        import subprocess
        from multiprocessing import shared_memory

        self.info = info
        H, W = info.height, info.width
        self._sizes = (H * W * 3, H * W * 4, H * W * 4)
        self._shm = shared_memory.SharedMemory(create=True, size=sum(self._sizes))
        reply_r, reply_w = os.pipe()
        cmd = child_command("sim.render", "_render_worker_main", str(reply_w))
        self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, pass_fds=(reply_w,),
                                      env=rasterise_in_the_calling_thread(package_env()))
        os.close(reply_w)
        self._replies = os.fdopen(reply_r, "rb", buffering=0)
        setup = {"scenario": scenario.model_dump(mode="json", by_alias=True), "width": W, "height": H,
                 "K": info.K.tolist(), "frame_id": info.frame_id, "renderer": renderer, "shm": self._shm.name,
                 "segmentation": bool(segmentation)}
        self.segmentation = bool(segmentation)
        self._proc.stdin.write(json.dumps(setup).encode() + b"\n")
        self._proc.stdin.flush()
        self._in_flight = False
        self._started = False  # the worker's "world built" reply is read with the first frame's
        self.worker_cpu_seconds = 0.0  # the worker's CPU time so far, as of its last reply

    def _expect_reply(self) -> None:
        status = self._replies.read(1)
        if status == b"\x01":
            self.worker_cpu_seconds = float(np.frombuffer(self._replies.read(8), dtype="<f8")[0])
            return
        detail = self._replies.read().decode(errors="replace").strip() if status == b"\x00" else "worker exited"
        self.close()
        raise RuntimeError(f"render worker failed: {detail}")

    def submit(self, T_world_cam: np.ndarray, T_world_base: np.ndarray, light: float, noise: bool, seed: int) -> None:
        if self._in_flight:
            raise RuntimeError("RenderWorker.submit: collect the frame in flight first")
        req = np.zeros((), dtype=_REQUEST)
        req["T_world_cam"], req["T_world_base"], req["light"] = T_world_cam, T_world_base, light
        req["seed"], req["noise"] = seed, bool(noise)
        self._proc.stdin.write(req.tobytes())
        self._proc.stdin.flush()
        self._in_flight = True

    def collect(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb, depth_m, segmentation) of the frame in flight, copied out of the shared buffer."""
        if not self._in_flight:
            raise RuntimeError("RenderWorker.collect: no frame in flight")
        self._in_flight = False
        if not self._started:
            self._expect_reply()
            self._started = True
        self._expect_reply()
        rgb, depth, seg = _views(self._shm.buf, self.info, copy=True)
        return rgb, depth, seg if self.segmentation else None


def _views(buf, info: CameraInfo, copy: bool):
    H, W = info.height, info.width
    rgb = np.ndarray((H, W, 3), np.uint8, buf, 0)
    depth = np.ndarray((H, W), np.float32, buf, H * W * 3)
    seg = np.ndarray((H, W), np.int32, buf, H * W * 7)
    return (rgb.copy(), depth.copy(), seg.copy()) if copy else (rgb, depth, seg)


def _render_worker_main() -> None:
    """The child process of ``RenderWorker``: build the world, then render each request."""
    import json
    import sys
    import time
    from multiprocessing import resource_tracker, shared_memory

    from sim.camera import render_rgbd  # the D435i's noise on top of this module's rendering
    from sim.robot import Jackal
    from sim.scenario import Scenario
    from sim.world import build_world
    from stack.transforms import to_xyz_quat

    replies = os.fdopen(int(sys.argv[1]), "wb", buffering=0)
    requests = sys.stdin.buffer
    try:
        setup = json.loads(requests.readline())
        shm = shared_memory.SharedMemory(name=setup["shm"])
        resource_tracker.unregister(shm._name, "shared_memory")  # the parent owns (and unlinks) it
        info = CameraInfo(setup["width"], setup["height"], np.array(setup["K"]), setup["frame_id"])
        sc = Scenario.model_validate(setup["scenario"])
        client, renderer = new_client(setup["renderer"])
        build_world(client, sc)
        x, y, yaw_deg = sc.robot.start
        robot = Jackal(client, (x, y, np.radians(yaw_deg)), np.random.default_rng(0))
        rgb_out, depth_out, seg_out = _views(shm.buf, info, copy=False)
        segmentation = bool(setup.get("segmentation", True))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        replies.write(b"\x00" + f"{type(exc).__name__}: {exc}".encode())
        return
    replies.write(b"\x01" + np.float64(time.process_time()).tobytes())
    while True:
        data = requests.read(_REQUEST.itemsize)
        if len(data) < _REQUEST.itemsize:
            break  # the parent closed the pipe
        req = np.frombuffer(data, dtype=_REQUEST)[0]
        try:
            pos, quat = to_xyz_quat(req["T_world_base"])
            p.resetBasePositionAndOrientation(robot.body, list(pos), list(quat), physicsClientId=client)
            rng = np.random.default_rng(int(req["seed"]))
            rgb, depth, seg = render_rgbd(client, req["T_world_cam"], info, float(req["light"]), rng,
                                          bool(req["noise"]), renderer, segmentation=segmentation)
            rgb_out[...], depth_out[...] = rgb, depth
            if seg is not None:
                seg_out[...] = seg
        except Exception as exc:  # noqa: BLE001
            replies.write(b"\x00" + f"{type(exc).__name__}: {exc}".encode())
            return
        replies.write(b"\x01" + np.float64(time.process_time()).tobytes())
    shm.close()
