"""The colour check of DOPE's FPR: a cuboid whose silhouette's colours fit another class's colour
model better fails FPR; one whose colours fit its own class passes; dark frames are not judged."""
import numpy as np
import pytest

from stack.dope.colour_names import NAMES, ColourModel
from stack.dope_fpr import DopeDetector
from stack.messages import CameraFrame, CameraInfo, Detection

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
DIMS = {"A": (0.1, 0.1, 0.1), "B": (0.1, 0.1, 0.1)}


def _model():
    red, blue = np.zeros(len(NAMES)), np.zeros(len(NAMES))
    red[NAMES.index("red")] = 1.0
    blue[NAMES.index("blue")] = 1.0
    return ColourModel({"A": red, "B": blue}, {"A": 0.5, "B": 0.5})


def _frame(colour, brightness=1.0):
    rgb = np.full((240, 320, 3), 128, np.uint8)  # grey background
    rgb[100:141, 140:181] = np.asarray(colour, float) * brightness  # the object's face, ~40 px at 0.75 m
    return CameraFrame(stamp=0.0, info=CameraInfo(width=320, height=240, K=K), rgb=rgb)


def _det(cls):
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 0.75)
    return Detection(cls=cls, stamp=0.0, T_cam_obj=T, keypoints_px=np.zeros((9, 2)), peak_scores=np.ones(9),
                     belief_sum=1.0, stages=6, fpr_pass=True)


@pytest.fixture
def detector():
    det = DopeDetector.__new__(DopeDetector)  # only the colour step is under test: no network needed
    det.dims = {c: np.asarray(d) for c, d in DIMS.items()}
    det.fpr, det.colour_check, det.colour = True, True, _model()
    det.colour_margin, det.min_colour_brightness = 0.0, 20.0
    return det


def test_wrong_colours_fail_fpr_and_right_ones_pass(detector):
    frame = _frame((220, 20, 20))  # a red object
    a, b = _det("A"), _det("B")
    detector._colour_check(frame, [a, b])
    assert a.fpr_pass and a.extra["colour"]["pass"]
    assert not b.fpr_pass and b.extra["fpr_rejected_by"] == "colour"
    assert b.extra["colour"]["distance"] > b.extra["colour"]["closest_other"]


def test_dark_frames_and_fpr_off_are_not_judged(detector):
    b = _det("B")
    detector._colour_check(_frame((220, 20, 20), brightness=0.05), [b])
    assert b.fpr_pass and "colour" not in b.extra
    detector.fpr = False
    b = _det("B")
    detector._colour_check(_frame((220, 20, 20)), [b])
    assert b.fpr_pass and b.extra["colour"]["pass"] is False  # recorded, verdict unchanged
