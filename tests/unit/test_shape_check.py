"""The shape check of DOPE's FPR on depth input: on a depth image rendered analytically (a pinhole
camera, an upright box on a slimmer stand, a wall behind, the D435i's depth noise), the box's own
class explains the depth and passes; a class of clearly different size fails; the settings reach the
detector from the config."""
import numpy as np
import pytest

from stack.config import DetectorConfig
from stack.dope.depth_refine import _ray_box_depth
from stack.dope.shape_check import closing_3x3, column_medians, footprint_residuals, observe, shape_verdict
from stack.dope_fpr import DopeDetector
from stack.messages import CameraFrame, CameraInfo, Detection

W, H = 640, 480
K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
# object frame: x right, y up, z front; sizes in metres
DIMS = {"Slim": (0.065, 0.16, 0.049), "Wide": (0.123, 0.167, 0.040), "Tall": (0.073, 0.192, 0.072)}


def _pose(xyz, yaw_deg: float) -> np.ndarray:
    """Upright object (its y axis along the camera's -y) at ``xyz`` in the camera, turned by ``yaw``."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T = np.eye(4)
    T[:3, :3] = Ry @ np.diag([1.0, -1.0, -1.0])  # object y up = camera -y; its front (z) faces the camera
    T[:3, 3] = xyz
    return T


def _render(cls: str, xyz, yaw_deg: float, noise: bool = True, seed: int = 0) -> np.ndarray:
    """Depth image (m): the box, a stand of 80 % of its footprint below it to the floor, a wall at 3 m."""
    T = _pose(xyz, yaw_deg)
    d = np.asarray(DIMS[cls])
    vv, uu = np.mgrid[0:H, 0:W]
    us, vs = uu.ravel().astype(float), vv.ravel().astype(float)
    z = np.full(us.shape, 3.0)
    box = _ray_box_depth(T, d, K, us, vs)
    z = np.where(np.isfinite(box), np.minimum(z, box), z)
    floor_y = 0.35  # camera frame: y down, the floor 35 cm below the camera
    stand_h = floor_y - (xyz[1] + d[1] / 2)
    Ts = T.copy()
    Ts[:3, 3] = [xyz[0], xyz[1] + d[1] / 2 + stand_h / 2, xyz[2]]
    stand = _ray_box_depth(Ts, [0.8 * d[0], stand_h, 0.8 * d[2]], K, us, vs)
    z = np.where(np.isfinite(stand), np.minimum(z, stand), z).reshape(H, W)
    if noise:  # sigma_z = z^2 * subpixel / (f * baseline), the D435i's
        z = z + np.random.default_rng(seed).standard_normal(z.shape) * z * z * 0.08 / (384 * 0.05)
    return z.astype(np.float32)


def _det(cls, T):
    return Detection(cls=cls, stamp=0.0, T_cam_obj=T, keypoints_px=np.zeros((9, 2)), peak_scores=np.ones(9),
                     belief_sum=1.0, stages=6, fpr_pass=True)


@pytest.mark.parametrize("truth,yaw", [("Slim", 20.0), ("Wide", -25.0), ("Tall", 35.0)])
def test_own_class_passes_and_clearly_different_classes_fail(truth, yaw):
    xyz = (0.1, -0.05, 1.3)
    depth = _render(truth, xyz, yaw)
    T = _pose(xyz, yaw)
    dims = {c: np.asarray(d) for c, d in DIMS.items()}
    own = shape_verdict(depth, K, T, dims, truth)
    assert own is not None and own.ok and own.own_m < 0.004 and own.best_other != truth
    for other in DIMS:
        if other == truth:
            continue
        # the network's wrong class: the other cuboid at the same place and turn
        v = shape_verdict(depth, K, T, dims, other)
        assert v is not None and v.best_other == truth and v.own_m > 2.5 * own.own_m, (other, v)
        if "Wide" in (truth, other):  # footprints 5 cm or more apart: clearly different
            assert not v.ok and v.own_m > 0.015, (other, v)


def test_outline_and_exact_fit_without_noise():
    xyz, yaw = (0.0, -0.05, 1.2), 30.0
    depth = _render("Wide", xyz, yaw, noise=False)
    obs = observe(depth, K, _pose(xyz, yaw), DIMS["Wide"])
    assert obs is not None and abs(obs.z_front - np.median(obs.z_cols)) < 0.05
    width_px = obs.right_u - obs.left_u
    a, b, c = DIMS["Wide"][0], DIMS["Wide"][2], DIMS["Slim"][0]
    assert 610 * 0.04 / 1.25 < width_px < 610 * 0.14 / 1.15
    own, slim = footprint_residuals(obs, K, [(a, b), (c, DIMS["Slim"][2])])
    assert own < 0.002 < 0.006 < slim  # the true footprint fits to a couple of millimetres


def test_no_verdict_when_the_object_is_cut_or_hidden():
    xyz, yaw = (0.0, -0.05, 1.2), 10.0
    T = _pose(xyz, yaw)
    depth = _render("Slim", xyz, yaw)
    hidden = depth.copy()
    hidden[:, :322] = 0.5  # a nearer surface covers the object's left half
    assert observe(hidden, K, T, DIMS["Slim"]) is None
    high = _render("Slim", (0.0, -0.45, 1.2), yaw)  # the object's top is above the image
    assert observe(high, K, _pose((0.0, -0.45, 1.2), yaw), DIMS["Slim"]) is None
    assert observe(np.zeros_like(depth), K, T, DIMS["Slim"]) is None
    behind = T.copy()
    behind[2, 3] = -1.0
    assert observe(depth, K, behind, DIMS["Slim"]) is None


@pytest.fixture
def detector():
    det = DopeDetector.__new__(DopeDetector)  # only the shape step is under test: no network needed
    det.dims = {c: np.asarray(d) for c, d in DIMS.items()}
    det.fpr, det.shape_check, det.shape_min_residual_m, det.shape_ratio = True, True, 0.006, 1.5
    return det


def test_detector_fails_the_wrong_class_and_records_the_verdict(detector):
    xyz, yaw = (0.1, -0.05, 1.3), 20.0
    frame = CameraFrame(0.0, CameraInfo(width=W, height=H, K=K), None, _render("Slim", xyz, yaw))
    right, wrong = _det("Slim", _pose(xyz, yaw)), _det("Wide", _pose(xyz, yaw))
    detector._shape_check(frame, [right, wrong])
    assert right.fpr_pass and right.extra["shape"]["pass"]
    assert not wrong.fpr_pass and wrong.extra["fpr_rejected_by"] == "shape"
    assert wrong.extra["shape"]["best_other"] in ("Slim", "Tall")
    detector.fpr = False  # FPR off: recorded, the verdict unchanged
    wrong = _det("Wide", _pose(xyz, yaw))
    detector._shape_check(frame, [wrong])
    assert wrong.fpr_pass and wrong.extra["shape"]["pass"] is False


def test_config_keys_reach_the_detector():
    cfg = DetectorConfig(input="depth", shape_check=True, shape_min_residual_m=0.02, shape_ratio=3.0)
    kw = cfg.dope_kwargs()
    assert (kw["shape_check"], kw["shape_min_residual_m"], kw["shape_ratio"]) == (True, 0.02, 3.0)
    det = DopeDetector(dims=DIMS, **kw)
    assert det.shape_check and det.shape_min_residual_m == 0.02 and det.shape_ratio == 3.0
    assert not DopeDetector(dims=DIMS, **DetectorConfig(input="depth", shape_check=False).dope_kwargs()).shape_check
    assert not DopeDetector(dims=DIMS, **DetectorConfig(input="rgb").dope_kwargs()).shape_check  # depth input only


def test_the_closing_is_scipys_binary_closing():
    from scipy import ndimage

    rng = np.random.default_rng(4)
    for _ in range(500):
        h, w = rng.integers(1, 40, 2)
        mask = rng.random((h, w)) < rng.uniform(0.05, 0.95)
        want = ndimage.binary_closing(mask, np.ones((3, 3), bool))  # a border of zeros: edges erode
        got = closing_3x3(mask)
        assert got.dtype == bool and np.array_equal(got, want)
    assert not closing_3x3(np.ones((5, 5), bool))[0].any()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_column_medians_are_numpys_nanmedian(dtype):
    rng = np.random.default_rng(5)
    for i in range(2000):
        rows, cols = rng.integers(1, 40), rng.integers(1, 10)
        x = rng.normal(1.5, 0.01, (rows, cols)).astype(dtype)
        if i % 4 == 0:
            x = np.round(x, 2)  # ties
        x[rng.random((rows, cols)) < rng.uniform(0, 0.7)] = np.nan
        x[rng.integers(0, rows, cols), np.arange(cols)] = 1.5 + i * 1e-4  # a number in every column
        got, want = column_medians(x), np.nanmedian(x, axis=0)
        assert got.dtype == want.dtype and np.array_equal(got, want)
