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


def saved_run(tmp_path):
    """A run folder as `dopeslam run` writes it: a store with one well-seen Mustard and one glimpsed
    Yogurt, the truth of the one Mustard, and the ground-truth trajectory."""
    import json

    from stack.metrics import write_tum
    from stack.object_store import ObjectStore, Observation

    store = ObjectStore({"Mustard": (0.16, 0.049, 0.065), "Yogurt": (0.054, 0.068, 0.068)})
    for k in range(12):
        cam = np.array([k * 0.1 - 0.6, -1.0, 0.3])
        store.add(Observation(0.2 * k, "Mustard", np.array([0.0, 0.0, 0.3]), np.array([0, 0, 0, 1.0]), 10.0, True, 1.0, cam))
    store.add(Observation(1.0, "Yogurt", np.array([2.0, 0.0, 0.3]), np.array([0, 0, 0, 1.0]), 10.0, True, 1.0, None))
    store.floor = (np.array([0.0, 0.0, 1.0]), 0.0)
    run = tmp_path / "run"
    run.mkdir()
    store.save(run / "labels.json")
    (run / "report.json").write_text(json.dumps({"scenario": "hand-built", "seed": 0, "policy": "robust-mean",
                                                 "labels": [{"object": "mustard", "class": "Mustard",
                                                             "truth_xyz": [0.01, 0.0, 0.3]}]}))
    write_tum(run / "groundtruth_tum.txt", np.array([0.0, 1.0]), np.stack([np.eye(4), np.eye(4)]))
    return run


def test_score_publishes_a_saved_run_again_under_other_evidence_settings(tmp_path, capsys):
    from testbed.cli import main

    run = saved_run(tmp_path)
    assert main(["score", str(run)]) == 0
    assert "1 labels, 1 correct, 0 misplaced, 0 phantom; precision 100 %" in capsys.readouterr().out
    assert main(["score", str(run), "--set", "min_observations=1", "--set", "min_span_s=0"]) == 0
    assert "2 labels, 1 correct, 0 misplaced, 1 phantom; precision 50 %" in capsys.readouterr().out


def test_score_names_a_bad_setting_or_a_missing_file_and_exits_2(tmp_path, capsys):
    from testbed.cli import main

    run = saved_run(tmp_path)
    assert main(["score", str(run), "--set", "vote_share=2"]) == 2
    assert "vote_share" in capsys.readouterr().err
    assert main(["score", str(run), "--set", "no_such_field=1"]) == 2
    assert "no_such_field" in capsys.readouterr().err
    (run / "groundtruth_tum.txt").unlink()
    assert main(["score", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert "groundtruth_tum.txt" in err and len(err.splitlines()) == 1


def test_score_never_writes_its_scores_over_a_saved_run(tmp_path, capsys):
    from testbed.cli import main

    run = saved_run(tmp_path)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    for target in (run / "report.json", run / "labels.json", run / "scores.json"):
        assert main(["score", str(run), "--out", str(target)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"dopeslam score: --out {target}: is (or holds, or lies inside) the input {run}; "
                       "choose another path")
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    assert main(["score", str(run), "--out", str(tmp_path / "scores.json")]) == 0
    assert (tmp_path / "scores.json").is_file()
