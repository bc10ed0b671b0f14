"""Experiment 1's scoring (the rendering and detection run in `dopeslam experiment depth-grid`)."""
import numpy as np
import pytest

from testbed.experiments import depth_grid as dg


def test_point_scores_use_the_median_detection_and_the_papers_equations():
    truth = np.array([0.3, 0.1, 0.8])
    found = [truth + [0.01, 0.0, 0.02], truth + [0.01, 0.5, 0.02], truth + [0.5, 0.0, 0.5]]  # one outlier
    r = dg._score_point(30.0, 80.0, truth, found, 5)
    assert r["detected_frames"] == 3 and r["frames"] == 5
    assert r["dx_cm"] == pytest.approx(1.0) and r["dz_cm"] == pytest.approx(2.0)
    assert r["distance_cm"] == pytest.approx(np.hypot(1.0, 2.0))
    assert 0 < r["accuracy_pct"] < 100
    none = dg._score_point(0.0, 110.0, truth, [], 5)
    assert none["distance_cm"] is None and none["detected_frames"] == 0


def test_average_skips_points_without_detections_and_table_shows_both_estimates():
    truth = np.array([0.0, 0.0, 1.0])
    rows = {"P1": dg._score_point(0, 100, truth, [truth + [0.02, 0, 0]], 1),
            "P2": dg._score_point(0, 100, truth, [], 1)}
    avg = dg._average(rows)
    assert avg["detected_points"] == 1 and avg["distance_cm"] == pytest.approx(2.0)
    full = {n: dg._score_point(x, z, truth, [truth], 1) for n, (x, z) in dg.GRID_CM.items()}
    full["avg"] = dg._average(full)
    result = {"weights": "w", **full, "pnp_only": dict(full)}
    text = dg.table(result)
    assert "PnP only" in text and "depth fit" in text and text.count("avg") == 2
