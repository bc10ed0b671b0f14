"""The DOPE backends benchmark's comparison of decoded detections (its run on a rendered frame:
``tests/e2e/test_bench_dope_backends_e2e.py``)."""
import importlib.util

import numpy as np

from helpers import ROOT
from stack.messages import Detection


def _load():
    spec = importlib.util.spec_from_file_location("bench_dope_backends", ROOT / "benchmarks" / "bench_dope_backends.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _det(cls="E", shift=0.0, fpr=True, missing=()):
    kp = np.arange(18, dtype=float).reshape(9, 2) + shift
    kp[list(missing)] = np.nan
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 1.0 + shift]
    return Detection(cls=cls, stamp=0.0, T_cam_obj=T, keypoints_px=kp, peak_scores=np.ones(9), belief_sum=1.0,
                     fpr_pass=fpr)


def test_compare_detections():
    cmp = _load().compare_detections
    ref = {1: [_det()], 6: [_det("Mustard", missing=(3,))]}
    same, n, dkp, dt = cmp(ref, {1: [_det(shift=1e-5)], 6: [_det("Mustard", missing=(3,))]})
    assert same and n == 2 and abs(dkp - 1e-5) < 1e-9 and abs(dt - 1e-2) < 1e-6
    assert not cmp(ref, {1: [_det(shift=1e-2)], 6: ref[6]})[0]  # key points 0.01 px apart
    assert not cmp(ref, {1: [_det("Yogurt")], 6: ref[6]})[0]  # another class
    assert not cmp(ref, {1: [_det(fpr=False)], 6: ref[6]})[0]  # another FPR verdict
    assert not cmp(ref, {1: [_det()], 6: [_det("Mustard")]})[0]  # another key point set
    assert not cmp(ref, {1: [], 6: ref[6]})[0]  # a detection missing
