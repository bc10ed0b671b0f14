"""FPR: the belief-sum filter orders predictions as the paper says, and the calibration finds the cut."""
import math

import numpy as np
import pytest

from stack.dope_fpr import FprThresholds, belief_sum, calibrate_threshold
from stack.dope.targets import make_targets


def _cuboid_kp(cx, cy, s=1.0):
    corners = [(cx + 20 * s, cy - 30 * s), (cx - 20 * s, cy - 30 * s), (cx - 20 * s, cy + 30 * s),
               (cx + 20 * s, cy + 30 * s)]
    corners += [(x + 6 * s, y - 6 * s) for x, y in corners]
    return np.array(corners + [(cx + 3 * s, cy - 3 * s)])


def _maps(objs, sigma=1.0):
    b, _ = make_targets(np.stack(objs), np.zeros(len(objs), int), 1, (30, 40), sigma=sigma)
    return b


def test_a_sharp_single_prediction_has_the_smallest_belief_sum():
    single = belief_sum(_maps([_cuboid_kp(100, 120)]))
    two = belief_sum(_maps([_cuboid_kp(80, 120), _cuboid_kp(240, 120)]))
    smeared = belief_sum(_maps([_cuboid_kp(100, 120)], sigma=2.5))
    noisy = belief_sum(_maps([_cuboid_kp(100, 120)]) + 0.05 * np.random.default_rng(0).random((9, 30, 40)))
    assert single < two and single < smeared and single < noisy
    th = FprThresholds({"E": {"6": 0.5 * (single + min(two, smeared, noisy))}})
    assert th.passes("E", 6, single)
    assert not th.passes("E", 6, two) and not th.passes("E", 6, smeared) and not th.passes("E", 6, noisy)


def test_negative_outputs_do_not_lower_the_sum():
    m = _maps([_cuboid_kp(100, 120)])
    assert belief_sum(m - 0.2 * (m == 0)) == pytest.approx(belief_sum(m))


def test_calibration_finds_the_cut_with_largest_recall_at_target_precision():
    rng = np.random.default_rng(1)
    good = rng.uniform(10, 30, 200)  # correct predictions: small sums
    bad = rng.uniform(28, 80, 100)  # false ones: larger, overlapping 28..30
    scores = np.r_[good, bad]
    correct = np.r_[np.ones(200, bool), np.zeros(100, bool)]
    r = calibrate_threshold(scores, correct, target_precision=0.99)
    passed = scores <= r["threshold"]
    precision = correct[passed].mean()
    assert precision >= 0.99
    assert r["recall"] == pytest.approx(correct[passed].sum() / 200)
    # no larger threshold keeps the precision: the next score would break it or it is the end
    assert r["threshold"] < bad.min() or precision >= 0.99
    higher = np.sort(scores[scores > r["threshold"]])
    if len(higher):
        nxt = scores <= higher[0]
        assert correct[nxt].mean() < 0.99 or correct[nxt].sum() == correct[passed].sum()
    # a perfectly separable set passes every correct prediction
    sep = calibrate_threshold(np.r_[good, bad + 60], correct, 0.995)
    assert sep["recall"] == 1.0 and 30 <= sep["threshold"] <= 88


def test_calibration_when_nothing_reaches_the_target_rejects_everything():
    r = calibrate_threshold([1.0, 2.0, 3.0], [False, True, True], target_precision=0.9)
    assert r["threshold"] == -math.inf and r["recall"] == 0.0


def test_thresholds_per_class_and_stage_with_manual_override_and_file_round_trip(tmp_path):
    recs = [("E", 6, 10.0, True), ("E", 6, 50.0, False), ("E", 1, 20.0, True), ("E", 1, 25.0, False),
            ("Yogurt", 6, 5.0, True)]
    th = FprThresholds.calibrate(recs, target_precision=0.99)
    assert 10.0 < th.get("E", 6) < 50.0 and 20.0 < th.get("E", 1) < 25.0
    assert th.get("Mustard", 3) == math.inf  # uncalibrated: pass
    th.set("E", 6, 8.0)
    assert not th.passes("E", 6, 9.0) and th.passes("E", 1, 21.0)
    path = tmp_path / "fpr.json"
    th.save(path)
    back = FprThresholds.load(path)
    assert back.get("E", 6) == 8.0 and back.get("E", 1) == th.get("E", 1) and back.get("Mustard", 2) == math.inf


@pytest.mark.parametrize("text", ["{}", "[1, 2]", "not json", '{"table": {"Mustard": 3}}',
                                  '{"table": {"Mustard": {"6": "high"}}}', '{"table": {}, "default": "x"}', None])
def test_bad_threshold_file_names_the_file(tmp_path, text):
    from stack.dope_fpr import ThresholdsError
    from stack.errors import DopeSlamError

    p = tmp_path / "x.json"
    if text is not None:  # None: no file
        p.write_text(text)
    with pytest.raises(ThresholdsError, match="x.json") as info:
        FprThresholds.load(p)
    assert isinstance(info.value, DopeSlamError)


def test_calibration_fallback_takes_the_most_precise_cut_when_the_target_is_out_of_reach():
    scores = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    correct = [False, True, True, False, True, False]
    r = calibrate_threshold(scores, correct, target_precision=0.99, fallback=True)
    assert not r["target_met"] and r["threshold"] == pytest.approx(3.5)  # 2 of 3 correct: best precision
    assert r["precision"] == pytest.approx(2 / 3) and r["recall"] == pytest.approx(2 / 3)


def test_a_few_lucky_detections_do_not_meet_the_target():
    rng = np.random.default_rng(0)
    scores = np.arange(100.0)
    correct = np.r_[np.ones(5, bool), rng.random(95) < 0.5]  # the 5 lowest happen to be right, then chance
    r = calibrate_threshold(scores, correct, target_precision=0.995, min_passed=20)
    assert r["passed"] == 0 and r["threshold"] == -np.inf  # no cut with >= 20 passing reaches 99.5 %
    r = calibrate_threshold(scores, correct, target_precision=0.995, min_passed=5)
    assert r["target_met"] and r["passed"] == 5
    r = calibrate_threshold(scores, correct, target_precision=0.995, fallback=True, fallback_recall=0.6)
    assert not r["target_met"] and r["recall"] >= 0.6


def test_a_cut_that_keeps_too_few_true_detections_does_not_meet_the_target():
    # one false detection among many true ones: reaching 99.5 % would mean cutting below it
    scores = np.r_[np.linspace(10, 100, 80)]
    correct = np.ones(80, bool)
    correct[30] = False
    strict = calibrate_threshold(scores, correct, 0.995, min_passed=20)
    assert strict["target_met"] and strict["recall"] < 0.4  # the paper's rule alone: most true ones lost
    r = calibrate_threshold(scores, correct, 0.995, min_passed=20, min_recall=0.6, fallback=True, fallback_recall=0.95)
    assert not r["target_met"] and r["recall"] >= 0.95
    th = FprThresholds.calibrate([("E", 6, float(v), bool(c)) for v, c in zip(scores, correct)], 0.995)
    assert th.get("E", 6) >= np.quantile(scores[correct], 0.95)
    assert th.meta["min_recall"] == 0.6 and th.meta["fallback_recall"] == 0.95
