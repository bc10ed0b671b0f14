"""The detector process's wire format (detections through JSON with their types) and its errors."""
import math

import numpy as np
import pytest

from stack.errors import DopeSlamError
from stack.messages import CameraInfo, Detection
from testbed.detection_process import (DetectionProcess, decode_detection, decode_value, encode_detection,
                                       encode_value)


def test_values_come_back_with_their_types():
    value = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.float64(0.1), "c": np.bool_(True),
             "d": (0.3, 1.8), "e": [1, "x", None, float("nan")], "f": {"g": np.int64(7)}, "h": 1e-300}
    back = decode_value(encode_value(value))
    assert back.keys() == value.keys()
    assert back["a"].dtype == np.float32 and np.array_equal(back["a"], value["a"])
    assert type(back["b"]) is np.float64 and back["b"] == value["b"]
    assert type(back["c"]) is np.bool_ and back["c"]
    assert back["d"] == (0.3, 1.8) and isinstance(back["d"], tuple)
    assert back["e"][:3] == [1, "x", None] and math.isnan(back["e"][3])
    assert type(back["f"]["g"]) is np.int64 and back["f"]["g"] == 7
    assert back["h"] == 1e-300


def test_a_detection_round_trips_bit_for_bit():
    rng = np.random.default_rng(0)
    kp = rng.normal(size=(9, 2))
    kp[3] = np.nan
    det = Detection("Mustard", 1.25, rng.normal(size=(4, 4)), kp, rng.random(9), 12.345678901234567, 6, False,
                    {"pnp_pose": rng.normal(size=(4, 4)), "fpr_rejected_by": "depth", "window": (0.3, 0.6),
                     "depth_fit": {"ok": True, "shift_m": np.float64(0.01), "n_pixels": 340}})
    back = decode_detection(encode_detection(det))
    assert encode_detection(back) == encode_detection(det)
    assert back.T_cam_obj.tobytes() == det.T_cam_obj.tobytes()
    assert back.extra["window"] == (0.3, 0.6)


def test_what_cannot_pass_is_named():
    with pytest.raises(TypeError, match="object"):
        encode_value({"x": object()})


@pytest.mark.parametrize("kwargs, error, says", [
    ({"weights": "missing.pt"}, DopeSlamError, "missing.pt: DOPE weights file not found"),  # the user's: one line
    ({"no_such_argument": 1}, RuntimeError, "detector process: TypeError: .*no_such_argument"),  # a bug: named
])
def test_a_detector_the_child_cannot_build_is_an_error_in_the_parent(tmp_path, kwargs, error, says):
    from stack.messages import CameraFrame

    kwargs = {"input": "rgb", "stages": 6, "fpr": True,
              **{k: str(tmp_path / v) if k == "weights" else v for k, v in kwargs.items()}}
    proc = DetectionProcess(kwargs, CameraInfo(8, 6, np.eye(3)))
    with pytest.raises(error, match=says) as info:
        proc.submit(CameraFrame(0.0, CameraInfo(8, 6, np.eye(3)), np.zeros((6, 8, 3), np.uint8))).result()
    assert error is RuntimeError or type(info.value) is DopeSlamError
    proc.close()


def test_a_frame_of_another_layout_is_refused_before_it_is_sent(tmp_path):
    from stack.messages import CameraFrame

    info = CameraInfo(8, 6, np.eye(3))
    proc = DetectionProcess({"weights": str(tmp_path / "w.pt"), "input": "rgb", "stages": 6, "fpr": True}, info)
    try:
        with pytest.raises(ValueError, match="colour image float32"):
            proc.submit(CameraFrame(0.0, info, np.zeros((6, 8, 3), np.float32)))
        with pytest.raises(ValueError, match=r"depth image float32 \(5, 8\)"):
            proc.submit(CameraFrame(0.0, info, depth_m=np.zeros((5, 8), np.float32)))
    finally:
        proc.close()


def test_a_quiet_process_keeps_the_build_warnings_to_itself(tmp_path, capfd):
    """Build-time warnings (here: no FPR thresholds beside the weights) come from the first process
    only: ``dopeslam run`` starts its second detector process quiet, with the same settings."""
    import shutil

    from stack.dope_fpr import default_weights

    weights = tmp_path / "copy.pt"  # the shipped network, without its thresholds file beside it
    shutil.copy(default_weights("rgb"), weights)
    kwargs = {"weights": str(weights), "input": "rgb", "stages": 1, "fpr": True}
    said = {}
    for quiet in (False, True):
        capfd.readouterr()
        proc = DetectionProcess(kwargs, CameraInfo(8, 6, np.eye(3)), quiet=quiet)
        try:
            assert proc.built().precision == "fp32"
        finally:
            proc.close()
        said[quiet] = capfd.readouterr().err
    assert said[False].count("no FPR thresholds beside") == 1, said[False]
    assert "no FPR thresholds" not in said[True], said[True]
