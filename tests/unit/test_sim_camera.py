"""The simulated D435i: geometry of the rendered image, the depth noise model, darkness."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.camera import DepthNoise, default_camera_info, render_rgbd
from sim.episode import Episode
from sim.scenario import load_scenario
from stack.messages import CameraFrame

ONE_OBJECT = """
name = "one_object"
duration = 0.05
[room]
size = [6.0, 6.0]
[[objects]]
class = "{cls}"
position = [{x}, {y}]
height = {height}
yaw_deg = {yaw}
[robot]
start = [0.0, 0.0, 0.0]
[route]
start_pause = 100.0
waypoints = [[1.0, 0.0]]
[sensors]
lidar = false
noise = false
"""

KEYPOINT_NAMES = ("FrontTopRight", "FrontTopLeft", "FrontBottomLeft", "FrontBottomRight", "RearTopRight",
                  "RearTopLeft", "RearBottomLeft", "RearBottomRight", "Center")

EMPTY_ROOM = """
name = "empty_room"
duration = 0.05
[room]
size = [6.0, 4.0]
[robot]
start = [0.0, 0.0, 0.0]
[route]
start_pause = 100.0
waypoints = [[1.0, 0.0]]
[sensors]
lidar = false
"""


def first_camera_frame(ep: Episode) -> CameraFrame:
    return next(m for m in ep.frames() if isinstance(m, CameraFrame))


@pytest.mark.parametrize("cls,x,y,height,yaw,axes", [
    ("Cookies", 1.1, 0.12, 0.25, 180, (0, 1)),     # faces square to the camera
    ("Yogurt", 0.8, -0.08, 0.1, 180, (0, 1)),
    ("OrangeJuice", 0.9, -0.1, 0.1, 150, (0, )),   # turned: only its vertical edges are axis-parallel
])
def test_object_corners_project_to_the_ground_truth_key_points(scenario_file, cls, x, y, height, yaw, axes):
    """The silhouette's extreme pixels are at the ground-truth key points of the extreme corners.

    The camera is level, so vertical cuboid edges are image columns, and with a face square to the
    camera its horizontal edges are image rows: each extreme of the silhouette is then an edge
    through a corner, and the outermost covered pixel centre lies within 1 px of the corner's key point.
    """
    path = scenario_file(ONE_OBJECT.format(cls=cls, x=x, y=y, height=height, yaw=yaw))
    with Episode(load_scenario(path), seed=0) as ep:
        frame = first_camera_frame(ep)
        (truth,) = ep.image_truth(frame)
        body = ep.world.object_bodies[truth["name"]]
    assert truth["in_front"] and truth["visible_fraction"] > 0.9
    mask = (frame.extra["segmentation"] & ((1 << 24) - 1)) == body
    rows, cols = np.nonzero(mask)
    assert len(rows) > 300
    kp = truth["keypoints_px"]  # (9, 2) (u, v), DOPE order: corners then the centroid
    cu, cv = np.rint(kp[8]).astype(int)
    assert mask[cv, cu]  # the centroid projects inside the silhouette
    for axis in axes:
        pixels = (cols, rows)[axis]
        assert abs(pixels.min() - kp[:8, axis].min()) < 1.0
        assert abs(pixels.max() - kp[:8, axis].max()) < 1.0
    if len(axes) == 2:
        # one named corner in both coordinates: the lowest corner furthest left is the left end of the
        # silhouette's (horizontal) bottom edge, i.e. the covered pixel furthest left on the lowest row
        lowest = np.flatnonzero(kp[:8, 1] > kp[:8, 1].max() - 0.5)
        k = lowest[np.argmin(kp[lowest, 0])]
        bottom_row = rows.max()
        assert abs(bottom_row - kp[k, 1]) < 1.0
        assert abs(cols[rows == bottom_row].min() - kp[k, 0]) < 1.0, f"key point {KEYPOINT_NAMES[k]}"


def camera_facing_wall(distance: float, wall_x: float, height: float = 1.2) -> np.ndarray:
    """Optical frame (z forward, x right, y down) looking along world +x at a wall ``distance`` away."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = [wall_x - distance, 0.0, height]
    return T


@pytest.mark.parametrize("distance", [1.0, 2.0])
def test_depth_noise_on_a_flat_wall_matches_the_d435i_model(scenario_file, distance):
    with Episode(load_scenario(scenario_file(EMPTY_ROOM)), seed=0) as ep:
        T = camera_facing_wall(distance, wall_x=3.0)
        _, clean, _ = render_rgbd(ep.client, T, ep.camera_info, noise=False, renderer=ep.renderer)
        _, noisy, _ = render_rgbd(ep.client, T, ep.camera_info, rng=np.random.default_rng(7), noise=True,
                                  renderer=ep.renderer)
    # the rendered wall is flat at the true distance along the optical axis
    assert np.all(np.abs(clean - distance) < 1e-3)
    valid = noisy > 0
    assert valid.mean() > 0.99  # only the random dropouts (0.3 %): no edges, in range
    residual = (noisy - clean)[valid].astype(float)
    sigma = DepthNoise.from_hardware().sigma(distance)
    assert sigma == pytest.approx(distance**2 * 0.08 / (384 * 0.05))
    assert residual.std() == pytest.approx(sigma, rel=0.15)
    assert abs(residual.mean()) < 0.05 * sigma


def test_darkness_blacks_out_rgb_but_leaves_depth_unchanged():
    frames = {}
    for name in ("experiment3_columns", "experiment3_columns_dark"):
        with Episode(name, seed=0, duration=0.05, lidar=False) as ep:
            frames[ep.light] = first_camera_frame(ep)
    lit, dark = frames[1.0], frames[0.0]
    assert lit.rgb.mean() > 40
    assert dark.rgb.mean() < 5  # out of 255: read noise only
    assert dark.rgb.std() > 0.3  # and it is noise, not a constant
    lit_valid, dark_valid = (lit.depth_m > 0).mean(), (dark.depth_m > 0).mean()
    assert lit_valid > 0.5
    assert dark_valid == lit_valid
    np.testing.assert_array_equal(dark.depth_m, lit.depth_m)  # the active projector does not need light


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="reads a child's environment from /proc")
def test_render_processes_rasterise_in_the_calling_thread_unless_the_user_says(monkeypatch):
    """A render process is started with ``LP_NUM_THREADS=0`` (Mesa's rasteriser without threads of its
    own), unless the user set the variable; this process's own environment is left as it is."""
    import os
    import time

    from sim.render import RASTERISER_THREADS, RenderWorker, rasterise_in_the_calling_thread
    from sim.scenario import load_scenario

    assert RASTERISER_THREADS == "LP_NUM_THREADS"
    assert rasterise_in_the_calling_thread({"A": "1"}) == {"A": "1", RASTERISER_THREADS: "0"}
    assert rasterise_in_the_calling_thread({RASTERISER_THREADS: "3"}) == {RASTERISER_THREADS: "3"}

    def child_setting():
        sc = load_scenario(None)
        worker = RenderWorker(sc, default_camera_info())
        try:
            # the file reads empty for a moment on a busy machine (the child just started): read it again
            for _ in range(100):
                raw = open(f"/proc/{worker._proc.pid}/environ", "rb").read()
                if raw:
                    break
                time.sleep(0.05)
            assert raw, "the render process's environment could not be read"
        finally:
            worker.close()
        environ = raw.split(b"\0")
        return [e.split(b"=", 1)[1].decode() for e in environ if e.startswith(RASTERISER_THREADS.encode() + b"=")]

    monkeypatch.delenv(RASTERISER_THREADS, raising=False)
    assert child_setting() == ["0"] and RASTERISER_THREADS not in os.environ
    monkeypatch.setenv(RASTERISER_THREADS, "2")
    assert child_setting() == ["2"]
