"""Scoring of the whole map: every published label is matched one to one to a true object of its class."""
from types import SimpleNamespace

import numpy as np
import pytest

from testbed.scoring import FALSE_LABEL_M, assign, score_map


def truth(name, cls, xyz):
    T = np.eye(4)
    T[:3, 3] = xyz
    return SimpleNamespace(name=name, cls=cls, T_world_obj=T)


def label(i, cls, xyz, n=10):
    return SimpleNamespace(id=i, cls=cls, xyz=np.asarray(xyz, dtype=float), observations=n)


def scored(labels, objects):
    return score_map(labels, objects, np.eye(4))


def test_two_labels_of_one_class_near_one_object_make_one_correct_and_one_phantom():
    objects = [truth("mustard", "Mustard", (1.0, 0.0, 0.3))]
    rows, map_rows, s = scored([label(1, "Mustard", (1.02, 0, 0.3)), label(2, "Mustard", (1.10, 0, 0.3))], objects)
    assert [r["verdict"] for r in map_rows] == ["correct", "phantom"]
    assert rows[0]["id"] == 1 and rows[0]["error_m"] == pytest.approx(0.02)
    assert (s["labels_in_map"], s["correct_labels"], s["false_labels"], s["phantom"]) == (2, 1, 1, 1)
    assert s["map_precision"] == 0.5 and s["map_recall"] == 1.0


def test_a_label_between_two_objects_takes_the_one_the_other_label_leaves():
    """Nearest-per-object gives object a the middle label and leaves b a label 60 cm off; the
    assignment gives each object a label within the threshold."""
    objects = [truth("a", "Yogurt", (0.0, 0.0, 0.0)), truth("b", "Yogurt", (0.4, 0.0, 0.0))]
    labels = [label(1, "Yogurt", (0.18, 0.0, 0.0)), label(2, "Yogurt", (-0.2, 0.0, 0.0))]
    rows, map_rows, s = scored(labels, objects)
    assert {r["object"]: r["id"] for r in rows} == {"a": 2, "b": 1}
    assert s["correct_labels"] == 2 and s["false_labels"] == 0


def test_a_phantom_far_from_everything_is_a_false_label_and_a_far_match_is_misplaced():
    objects = [truth("e", "E", (0.0, 0.0, 0.0)), truth("cookies", "Cookies", (2.0, 0.0, 0.0))]
    labels = [label(1, "E", (0.01, 0.0, 0.0)), label(2, "Cookies", (2.0, 0.6, 0.0)), label(3, "Raisins", (9.0, 9.0, 0.0))]
    rows, map_rows, s = scored(labels, objects)
    assert [r["verdict"] for r in map_rows] == ["correct", "misplaced", "phantom"]
    assert map_rows[2]["object"] is None and map_rows[2]["nearest_object_m"] > 9
    assert rows[1]["false_label"] and rows[1]["missing"]
    assert (s["misplaced"], s["phantom"], s["false_labels"], s["labelled"], s["missing"]) == (1, 1, 2, 1, 1)
    assert s["map_precision"] == pytest.approx(1 / 3)


def test_a_wrong_class_on_a_real_object_is_a_phantom():
    objects = [truth("oj", "OrangeJuice", (1.0, 1.0, 0.4))]
    _, map_rows, s = scored([label(1, "Mustard", (1.0, 1.0, 0.4))], objects)
    assert map_rows[0]["verdict"] == "phantom" and s["correct_labels"] == 0 and s["missing"] == 1


def test_assignment_prefers_more_matches_within_the_threshold_over_a_smaller_total():
    # one label near both objects, another only within reach of the first: both must be correct
    within = assign(["X", "X"], [(0.2, 0, 0), (-0.2, 0, 0)], ["X", "X"], [(0.0, 0, 0), (0.4, 0, 0)])
    assert sorted(within) == [0, 1] and all(d <= FALSE_LABEL_M for _, d in within.values())


def test_an_empty_map_has_no_precision_and_no_recall():
    _, _, s = scored([], [truth("e", "E", (0, 0, 0))])
    assert s["map_precision"] is None and s["map_recall"] == 0.0 and s["missing"] == 1
