"""Experiment 3's per-object picks: original (last), FPR (last passing), best and worst with ground truth."""
from types import SimpleNamespace

import numpy as np

from stack.object_store import Observation
from testbed.experiments.localization import per_object_rows, summarise


def _obs(t, x, fpr=True, rng=1.0):
    return Observation(float(t), "E", np.array([x, 0.0, 0.0]), np.array([0, 0, 0, 1.0]), 1.0, fpr, rng)


def test_picks_and_the_range_limit_on_best_and_worst():
    obj = SimpleNamespace(name="E", cls="E", T_world_obj=np.eye(4))
    obs = [_obs(0, 0.01), _obs(1, 0.5), _obs(2, 600.0, fpr=False, rng=600.0), _obs(3, 0.3, fpr=False)]
    rows = per_object_rows(obs, [obj], np.eye(4))
    assert abs(rows["original"][0]["distance_cm"] - 30) < 1e-9  # the last detection, passed or not
    assert abs(rows["fpr"][0]["distance_cm"] - 50) < 1e-9  # the last one FPR passed
    assert abs(rows["best"][0]["distance_cm"] - 1) < 1e-9
    assert abs(rows["worst"][0]["distance_cm"] - 50) < 1e-9  # the 600 m PnP blow-up is out of the camera's range
    s = summarise(rows)
    assert s["fpr"]["false_labels"] == 1 and s["best"]["false_labels"] == 0
