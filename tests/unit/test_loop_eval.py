"""The place-recognition evaluation's parts: lap split, truth, precision-recall, the SeqSLAM baseline."""
import numpy as np

from testbed.loop_eval import pr_curve, same_place, seqslam, split_laps


def test_pr_curve_by_hand():
    # four matches, confidence 0.9 (right), 0.8 (wrong), 0.7 (right), 0.2 (right); five queries could match
    r = pr_curve(np.array([0.7, 0.9, 0.2, 0.8, 0.0]), np.array([True, True, True, False, False]), positives=5)
    np.testing.assert_allclose(r["precision"], [1.0, 0.5, 2 / 3, 3 / 4])
    np.testing.assert_allclose(r["recall"], [0.2, 0.2, 0.4, 0.6])
    assert r["recall_at_precision_100"] == 0.2 and r["recall_at_precision_95"] == 0.2
    assert r["precision_at_recall"]["0.50"] == 0.75 and r["precision_at_recall"]["0.75"] is None
    assert r["threshold_at_precision_95"] == 0.9
    np.testing.assert_allclose(r["average_precision"], 0.2 * 1.0 + 0.2 * 2 / 3 + 0.2 * 3 / 4)


def test_laps_and_truth():
    t = np.linspace(0, 4 * np.pi, 81)[:-1]  # a 10 m radius circle, twice
    pos = np.column_stack([10 * np.cos(t), 10 * np.sin(t), np.zeros_like(t)])
    assert split_laps(pos) == 40
    heading = t + np.pi / 2
    truth = same_place(pos[:40], heading[:40], pos[40:], heading[40:], 2.0, 45.0)
    assert truth[np.arange(40), np.arange(40)].all()  # the same index of each lap is the same place
    assert not truth[0, 20]  # the other side of the circle is not
    assert not same_place(pos[:1], heading[:1] + np.pi, pos[:1], heading[:1], 2.0, 45.0).any()  # facing away


def test_seqslam_follows_a_repeated_sequence():
    rng = np.random.default_rng(0)
    places = [rng.integers(0, 255, (48, 64, 3)).astype(np.uint8) for _ in range(30)]
    db = [np.clip(p + rng.normal(0, 20, p.shape), 0, 255).astype(np.uint8) for p in places]
    queries = [np.clip(p + rng.normal(0, 20, p.shape), 0, 255).astype(np.uint8) for p in places]
    match, conf = seqslam(db, queries, ds=5, window=3)
    assert (match[:4] == -1).all()  # not enough history for a sequence yet
    np.testing.assert_array_equal(match[4:], np.arange(4, 30))
    assert (conf[4:] > 1.0).all()


def test_loop_commands_are_dopeslam_subcommands():
    from testbed.cli import build_parser

    a = build_parser().parse_args(["loop-eval", "--duration", "5", "--out", "x"])
    assert a.func.__name__ == "run_args" and a.func.__module__ == "testbed.loop_eval" and a.duration == 5.0
    a = build_parser().parse_args(["loop-closure", "office_loop", "--proximity", "never"])
    assert a.func.__module__ == "testbed.loop_closing" and a.proximity == "never"
