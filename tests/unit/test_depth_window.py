"""Depth preprocessing (paper 3.5): slicing, median filters, sharpening, sliding windows."""
import numpy as np
import pytest

from stack.dope.depth_window import clean, preprocess_depth, slice_depth, sliding_windows


def test_slice_bounds_map_near_far_and_invalid_to_uniform_values():
    z = np.array([[0.0, 0.5, 0.65, 0.8, 0.95, 1.2]], np.float32)
    out = slice_depth(z, 0.65, 0.95)
    assert out[0, 0] == 0.0 and out[0, 1] == 0.0  # no return and too near
    assert out[0, 2] == pytest.approx(0.1) and out[0, 3] == pytest.approx(0.5) and out[0, 4] == pytest.approx(0.9)
    assert out[0, 5] == 1.0  # beyond the window


def test_median_filters_remove_salt_noise_and_keep_a_step_edge():
    img = np.zeros((40, 40), np.float32)
    img[:, 20:] = 0.6  # a depth edge
    noisy = img.copy()
    rng = np.random.default_rng(0)
    ys, xs = rng.integers(0, 40, 60), rng.integers(0, 40, 60)
    noisy[ys, xs] = 1.0  # salt
    out = clean(noisy, medians=5, sharpen=False)
    assert np.abs(out[2:-2, 2:-2] - img[2:-2, 2:-2]).max() < 1e-6
    sharp = clean(noisy, medians=5, sharpen=True)
    assert sharp[10, 19] <= 0.0 + 1e-6 and sharp[10, 20] >= 0.6  # edge stays a step (sharpened, not blurred)


def test_preprocess_object_stands_out_from_flat_surroundings():
    depth = np.full((60, 80), 2.0, np.float32)  # wall beyond the window
    depth[20:40, 30:50] = 0.8  # object in the window
    depth[::7, ::5] = 0.0  # dropouts
    out = preprocess_depth(depth, 0.65, 0.95)
    assert np.allclose(out[25:35, 35:45], 0.1 + 0.8 * 0.5, atol=1e-5)
    assert out[5, 5] == 1.0


def test_bad_window_is_an_error():
    with pytest.raises(ValueError, match="far"):
        slice_depth(np.ones((2, 2)), 1.0, 0.5)


def test_sliding_windows_cover_the_range_with_overlap():
    w = sliding_windows(0.3, 1.8, 0.3, 0.1)
    assert w[0] == (0.3, 0.6) and w[-1][1] >= 1.8
    for (a0, a1), (b0, b1) in zip(w, w[1:]):
        assert a1 - b0 == pytest.approx(0.1)
    # any 10 cm object within range lies wholly inside one window
    for z in np.linspace(0.3, 1.7, 50):
        assert any(n <= z and z + 0.1 <= f + 1e-9 for n, f in w)


def _floor_scene(h=0.3, box=True, noise=0.0, seed=0):
    """Depth (640x480, fx 610) of a level camera ``h`` m above a floor, with a 6 x 10 cm-ish object at 1 m."""
    K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
    vv, uu = np.mgrid[0:480, 0:640].astype(float)
    y = (vv - K[1, 2]) / K[1, 1]
    with np.errstate(divide="ignore"):
        z = np.where(y > 1e-3, h / y, 0.0)
    z[z > 8.0] = 0.0  # beyond the range: no return
    if box:
        z[200:262, 290:330] = 1.0  # an object's front face at 1 m, well above the floor
    if noise:
        z = z + np.random.default_rng(seed).normal(0, noise, z.shape) * (z > 0)
    return z.astype(np.float32), K


def test_floor_is_fitted_and_only_windows_holding_something_count():
    from stack.dope.depth_window import depth_points, fit_floor, window_content

    depth, K = _floor_scene(noise=0.003)
    floor = fit_floor(depth_points(depth, K))
    assert floor is not None
    n, d = floor
    assert abs(d - 0.3) < 0.01 and n[1] < -0.99  # the camera's height, normal up (-y in the optical frame)
    wins = sliding_windows(0.3, 1.8, 0.3, 0.1)
    counts = window_content(depth, K, wins, floor)
    for (near, far), c in zip(wins, counts):
        if near <= 1.0 <= far:
            assert c > 200  # the object's pixels
        else:
            assert c < 40  # floor only
    # no floor in view (camera looking at a wall): every window counts as full
    wall = np.full((480, 640), 1.2, np.float32)
    assert min(window_content(wall, K, wins)) > 10 ** 6


def test_depth_detector_skips_floor_only_windows():
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector, default_weights
    from stack.messages import CameraFrame, CameraInfo

    if not default_weights("depth").exists():
        pytest.skip("no shipped depth weights")
    dims = {c: s.dims for c, s in load_catalog().items()}
    det = DopeDetector(input="depth", dims=dims, threads=1)
    depth, K = _floor_scene(box=False)
    frame = CameraFrame(0.0, CameraInfo(640, 480, K), depth_m=depth)
    assert det.detect(frame) == [] and det.windows_run == 0 and det.windows_skipped == len(det.depth_windows)
    depth, K = _floor_scene(box=True)
    det.detect(CameraFrame(0.0, CameraInfo(640, 480, K), depth_m=depth))
    assert det.windows_run == sum(near <= 1.0 <= far for near, far in det.depth_windows)


def test_depth_windows_range_check_uses_the_fitted_range():
    """A small object's PnP range is often tens of centimetres off; the window keeps a detection whose
    depth-fitted range lies in it, and drops one that lies outside."""
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector, default_weights
    from stack.messages import Detection

    if not default_weights("depth").exists():
        pytest.skip("no shipped depth weights")
    det = DopeDetector(input="depth", dims={c: s.dims for c, s in load_catalog().items()}, threads=1)

    def at(z):
        T = np.eye(4)
        T[2, 3] = z
        return Detection("Yogurt", 0.0, T, np.zeros((9, 2)), np.ones(9), 10.0, extra={"window": (1.1, 1.4)})

    kept = det._window_filter([at(1.25), at(1.9), at(1.42)])
    assert [d.T_cam_obj[2, 3] for d in kept] == [1.25, 1.42]
