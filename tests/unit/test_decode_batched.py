"""The batched decoding steps give the very bits of the one-at-a-time definitions they replace:
peaks of many maps in one filter pass, the 3x3 maximum as elementwise maxima, sub-cell refinement of
many windows at once, a cuboid's silhouette drawn into its bounding box only, the depth fit reading
only the pixels it uses, and its ray casts without NumPy's NaN-aware reductions."""
import cv2
import numpy as np
import pytest
from scipy.ndimage import maximum_filter
from scipy.spatial.transform import Rotation

from stack.dope.depth_refine import _ray_box_depth, refine_translation, silhouette_pixels
from stack.dope_fpr import cuboid_points, find_peaks, map_peaks, max_3x3, refine_peak, refine_peaks, silhouette_crop
from stack.transforms import make_T

K = np.array([[615.0, 0, 319.5], [0, 615.0, 239.5], [0, 0, 1]])
DIMS = np.array([0.192483, 0.072781, 0.071583])


def _maps(rng, n=9, h=30, w=40):
    """Belief-like maps: blobs, plateaus (equal neighbours), negatives, values at the edges."""
    m = rng.normal(0, 0.05, (n, h, w)).astype(np.float32)
    for k in range(n):
        for _ in range(rng.integers(0, 5)):
            r, c = rng.integers(0, h), rng.integers(0, w)
            yy, xx = np.mgrid[0:h, 0:w]
            m[k] += (rng.uniform(0.2, 1.0) * np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / rng.uniform(0.5, 3))).astype(np.float32)
        if rng.random() < 0.3:  # a plateau
            r, c = rng.integers(1, h - 1), rng.integers(1, w - 2)
            m[k, r, c:c + 2] = 0.9
        if rng.random() < 0.3:  # a peak on the border
            m[k, 0, rng.integers(0, w)] = 0.95
    return m


def _peaks_one_map(m, threshold):
    """The definition: 3x3 local maxima above the threshold, strongest first, a plateau once."""
    mask = (m == maximum_filter(m, size=3, mode="constant", cval=-np.inf)) & (m > threshold)
    rows, cols = np.nonzero(mask)
    vals = m[rows, cols]
    out = []
    for i in np.argsort(-vals, kind="stable"):
        r, c = int(rows[i]), int(cols[i])
        if not any(abs(r - q[0]) <= 1 and abs(c - q[1]) <= 1 for q in out):
            out.append((r, c, float(vals[i])))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_peaks_of_many_maps_at_once_are_each_maps_own(seed):
    rng = np.random.default_rng(seed)
    maps = _maps(rng, n=54)
    got = map_peaks(maps, 0.1)
    for k in range(len(maps)):
        want = _peaks_one_map(maps[k], 0.1)
        assert [q[:3] for q in got[k]] == want
        assert [q[3:] for q in got[k]] == [refine_peak(maps[k], r, c) for r, c, _ in want]
        assert find_peaks(maps[k], 0.1) == want


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(54, 30, 40), (30, 40), (1, 1, 1), (3, 2, 9), (2, 7, 1), (2, 3, 4, 5)])
def test_the_3x3_maximum_is_scipys(shape, dtype):
    rng = np.random.default_rng(sum(shape))
    m = rng.normal(0, 1, shape).astype(dtype)
    m[..., ::3, ::2] = m.max()  # plateaus, on the borders too
    m.reshape(-1)[::7] = -np.inf
    want = maximum_filter(m, size=(1,) * (m.ndim - 2) + (3, 3), mode="constant", cval=-np.inf)
    got = max_3x3(m)
    assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)


def test_maps_with_nan_get_scipys_3x3_maximum():
    m = np.random.default_rng(0).normal(0, 1, (4, 6, 6)).astype(np.float32)
    m[1, 2, 3] = np.nan
    want = maximum_filter(m, size=(1, 3, 3), mode="constant", cval=-np.inf)
    assert np.array_equal(max_3x3(m), want, equal_nan=True)


def test_refining_many_windows_at_once_gives_the_same_bits():
    rng = np.random.default_rng(7)
    maps = _maps(rng, n=20)
    maps[3, 5:8, 5:8] = -0.2  # a window with nothing above zero: the cell itself
    idx = np.concatenate([rng.integers(0, 20, 400), [3]])
    rows = np.concatenate([rng.integers(0, 30, 400), [6]])
    cols = np.concatenate([rng.integers(0, 40, 400), [6]])
    got = refine_peaks(maps, idx, rows, cols)
    want = [refine_peak(maps[k], int(r), int(c)) for k, r, c in zip(idx, rows, cols)]
    assert got == want  # bit for bit, borders included
    assert got[-1] == (6.0, 6.0)


def _silhouette_whole_image(T, width=640, height=480):
    P = cuboid_points(DIMS)[:8]
    Xc = P @ T[:3, :3].T + T[:3, 3]
    mask = np.zeros((height, width), np.uint8)
    if np.any(Xc[:, 2] <= 1e-3):
        return mask.astype(bool)
    uv = Xc @ K.T
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(uv[:, :2] / uv[:, 2:]).astype(np.int32)), 1)
    return mask.astype(bool)


def test_a_silhouette_drawn_in_its_box_is_the_one_drawn_in_the_whole_image():
    rng = np.random.default_rng(3)
    partial = 0
    for _ in range(600):
        R = Rotation.from_euler("xyz", rng.uniform(-np.pi, np.pi, 3)).as_matrix()
        z = rng.uniform(0.02, 3.0)
        T = make_T(R, np.array([rng.uniform(-1.5, 1.5) * z, rng.uniform(-1.2, 1.2) * z, z]))
        want = _silhouette_whole_image(T)
        crop = silhouette_crop(DIMS, T, K, 640, 480)
        got = np.zeros_like(want)
        if crop is not None:
            (y0, x0), inside = crop
            got[y0:y0 + inside.shape[0], x0:x0 + inside.shape[1]] = inside
        assert np.array_equal(got, want)
        edge = want[0].any() or want[-1].any() or want[:, 0].any() or want[:, -1].any()
        partial += bool(edge and want.sum() < want.size)
    assert partial > 20  # silhouettes cut by the image's edges were among them


def test_the_depth_fit_reads_a_float32_image_as_it_read_it_in_float64():
    rng = np.random.default_rng(1)
    T = make_T(Rotation.from_euler("z", 0.4).as_matrix(), np.array([0.05, 0.02, 0.9]))
    depth = np.full((480, 640), 1.3, np.float32) + rng.normal(0, 0.01, (480, 640)).astype(np.float32)
    depth[200:280, 280:360] = 0.93 + rng.normal(0, 0.005, (80, 80)).astype(np.float32)
    depth[rng.random((480, 640)) < 0.05] = 0.0
    a = refine_translation(T, DIMS, K, depth)
    b = refine_translation(T, DIMS, K, depth.astype(np.float64))
    assert a.ok and np.array_equal(a.T_cam_obj, b.T_cam_obj) and (a.shift_m, a.n_pixels, a.inlier_frac) == \
        (b.shift_m, b.n_pixels, b.inlier_frac)


def _ray_box_depth_definition(T, dims, K, us, vs):
    """The ray cast as first written: rays stacked, slab entry and exit by nanmax and nanmin."""
    R, t = T[:3, :3], T[:3, 3]
    d_cam = np.stack([(us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1], np.ones_like(us, dtype=float)], axis=1)
    o = -R.T @ t
    d = d_cam @ R
    half = np.asarray(dims, dtype=float) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) * (1.0 / d)
        t2 = (half - o) * (1.0 / d)
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.nan)


def test_the_depth_fits_ray_casts_are_the_definitions_bits():
    rng = np.random.default_rng(5)
    hits = 0
    for i in range(300):
        if i < 3:  # rays in a face's plane: 0 * inf in the slabs, a NaN that the reductions leave out
            R = np.eye(3)
            t = np.array([DIMS[0] / 2 * (1 if i else -1), DIMS[1] / 2 * (i - 1), 0.8])
        else:
            R = Rotation.from_euler("xyz", rng.uniform(-np.pi, np.pi, 3)).as_matrix()
            z = rng.uniform(0.1, 3.0)
            t = np.array([rng.uniform(-0.8, 0.8) * z, rng.uniform(-0.6, 0.6) * z, z])
        T = make_T(R, t)
        us, vs = silhouette_pixels(T, DIMS, K, (480, 640), shrink=1.0)[:2]
        us = np.concatenate([us, rng.uniform(0, 639, 50), [K[0, 2]]])
        vs = np.concatenate([vs, rng.uniform(0, 479, 50), [K[1, 2]]])
        for dims in (DIMS, DIMS * 0.7):
            got, want = _ray_box_depth(T, dims, K, us, vs), _ray_box_depth_definition(T, dims, K, us, vs)
            assert np.array_equal(got, want, equal_nan=True)
            hits += int(np.isfinite(got).sum())
    assert hits > 10000


def test_the_silhouettes_pixels_are_the_whole_grids_that_hit():
    """The pixel grid, row by row, every second pixel, as np.mgrid lays it out, kept where the shrunk box is hit."""
    rng = np.random.default_rng(8)
    for _ in range(100):
        R = Rotation.from_euler("xyz", rng.uniform(-np.pi, np.pi, 3)).as_matrix()
        z = rng.uniform(0.2, 2.0)
        T = make_T(R, np.array([rng.uniform(-0.7, 0.7) * z, rng.uniform(-0.5, 0.5) * z, z]))
        us, vs, z_exp = silhouette_pixels(T, DIMS, K, (480, 640))
        P = (cuboid_points(DIMS)[:8]) @ R.T + T[:3, 3]
        uv = P[:, :2] / P[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        u0, v0 = np.clip(np.floor(uv.min(axis=0)).astype(int), 0, [639, 479])
        u1, v1 = np.clip(np.ceil(uv.max(axis=0)).astype(int), 0, [639, 479])
        vv, uu = np.mgrid[v0:v1 + 1:2, u0:u1 + 1:2]
        uu, vv = uu.ravel().astype(float), vv.ravel().astype(float)
        keep = np.isfinite(_ray_box_depth_definition(T, DIMS * 0.7, K, uu, vv))
        assert np.array_equal(us, uu[keep]) and np.array_equal(vs, vv[keep])
        assert np.array_equal(z_exp, _ray_box_depth_definition(T, DIMS, K, uu[keep], vv[keep]), equal_nan=True)
