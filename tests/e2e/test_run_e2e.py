"""`dopeslam run` end to end on a short drive past the default scenario's objects, with the shipped
DOPE weights, real KISS-ICP and the real object store (the experiments' options:
``tests/unit/test_run_unit.py``)."""
import json

import pytest

from stack.dope_fpr import refinement_memory_order
from stack.object_store import ObjectStore
from testbed.cli import main


@pytest.mark.slow
def test_run_in_darkness_publishes_only_labels_it_can_stand_behind(short_dark_scenario, tmp_path):
    """Depth input in the dark: the depth network often takes one object for another, so most places
    hold detections of several classes. The map must not publish those guesses: the disputed places
    stay candidates and the objects the network does tell apart are labelled, centimetres off. Seed 3
    measured the E and the Cookies (2.0 and 1.2 cm), 26 candidates, and one false label: an
    OrangeJuice that won the vote where the network sees the Yogurt and its slim stand as one
    orange-juice-sized column (docs/results.md)."""
    out = tmp_path / "dark"
    assert main(["run", str(short_dark_scenario), "--input", "depth", "--out", str(out), "--seed", "3"]) == 0
    report = json.loads((out / "report.json").read_text())
    s = report["labels_summary"]
    assert s["correct_labels"] >= 2 and s["false_labels"] <= 1, s["map_labels"]
    assert all(m["error_m"] < 0.05 for m in s["map_labels"] if m["verdict"] == "correct")
    assert s["candidates"] >= 10  # the wrong-class detections are kept, not published
    assert any("disagree" in c["reason"] or "outvoted" in c["reason"] for c in report["candidates"])


@pytest.mark.slow
def test_run_labels_the_objects_it_drives_past(short_scenario, tmp_path, capsys, monkeypatch):
    from stack import dope_fpr

    built = []  # DOPE networks built in this process: none while the detector process runs it
    real_init = dope_fpr.DopeDetector.__init__

    def counting_init(self, *a, **kw):
        built.append(1)
        real_init(self, *a, **kw)

    monkeypatch.setattr(dope_fpr.DopeDetector, "__init__", counting_init)
    # the helper processes of a long episode (this short one would start neither; test_run_ahead.py)
    monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", "2")
    monkeypatch.setenv("DOPESLAM_RENDER_WORKER", "1")
    out = tmp_path / "run"
    assert main(["run", str(short_scenario), "--out", str(out), "--seed", "3"]) == 0
    assert built == []
    report = json.loads((out / "report.json").read_text())
    for key in ("scenario", "seed", "sim_seconds", "wall_seconds", "real_time_factor", "odometry", "detection",
                "labels", "labels_summary"):
        assert key in report
    assert report["odometry"]["ate_rmse_m"] < 0.05
    s = report["labels_summary"]
    assert s["objects"] == 6
    # The target for the default scenario (all labelled, no false label, mean <= 10 cm) on this
    # short drive past all six (seeds 3 and 4 measured 1.9 and 1.7 cm); a broken transform chain, pose
    # lookup or FPR puts labels metres off or lets a wrong-class detection label an object.
    assert s["labelled"] == 6, report["labels"]
    # the whole map, not the nearest label per object: no phantom or misplaced label anywhere
    assert s["labels_in_map"] == 6 and s["false_labels"] == 0 and s["map_precision"] == 1.0, s["map_labels"]
    assert s["mean_error_m"] < 0.10
    assert report["detection"]["precision"] > 0.9
    # the spreadsheet is the store: it loads back with the same objects
    from sim.objects import load_catalog

    store = ObjectStore.load(out / "labels.xlsx", dims={c: s.dims for c, s in load_catalog().items()})
    assert len(store.labels()) == s["labels_in_map"] and len(store.candidates()) == s["candidates"]
    for name in ("map.png", "estimate_tum.txt", "groundtruth_tum.txt", "labels.json"):
        assert (out / name).stat().st_size > 0
    assert "precision 100 %" in capsys.readouterr().out
    assert report["detector"] == "stack.dope_fpr:DopeDetector" and report["network_precision"] == "fp32"
    assert report["network_refinement_order"] == refinement_memory_order()  # what ran: auto, resolved here
    assert report["odometry_process"] is False  # every image detected: KISS-ICP stays in this process
    assert report["detector_processes"] == 2  # ... and two detector processes take the images in turn
    assert report["render_processes"] == 1  # ... while a third renders the camera
    # the detector ran in a process ahead of the pipeline; in the message loop it gives the same bytes
    monkeypatch.delenv("DOPESLAM_DETECTOR_PROCESS")
    monkeypatch.delenv("DOPESLAM_RENDER_WORKER")
    seq = tmp_path / "sequential"
    assert main(["run", str(short_scenario), "--out", str(seq), "--seed", "3", "--sequential"]) == 0
    assert built == [1]
    for name in ("labels.json", "estimate_tum.txt"):
        assert (seq / name).read_bytes() == (out / name).read_bytes(), name
    assert json.loads((seq / "report.json").read_text())["detection"]["predictions"] == report["detection"]["predictions"]


@pytest.mark.slow
def test_keyframe_gate_runs_the_detector_on_fewer_images_with_the_same_bytes_ahead_or_in_the_loop(
        short_scenario, tmp_path):
    """``--set detector.keyframe_m=0.1 --set detector.keyframe_deg=5``: DOPE runs on an image once the
    robot has travelled 10 cm or turned 5 degrees since the last one it ran on (or after a second).
    The detector process ahead of the pipeline and the message loop pass the same images; ahead, the
    images held back are not rendered, and KISS-ICP registers in a process of its own: the same
    trajectory, labels and LiDAR map (the results bag), byte for byte."""
    gate = ["--set", "detector.keyframe_m=0.1", "--set", "detector.keyframe_deg=5"]
    outs = []
    for extra in ([], ["--sequential"]):
        out = tmp_path / ("loop" if extra else "ahead")
        assert main(["run", str(short_scenario), "--out", str(out), "--seed", "3", *gate, *extra]) == 0
        outs.append(out)
    for name in ("labels.json", "estimate_tum.txt", "results_bag/results_bag.mcap"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    reports = [json.loads((o / "report.json").read_text()) for o in outs]
    assert [r["odometry_process"] for r in reports] == [True, False]
    assert [r["detector_processes"] for r in reports] == [1, 0]  # some images undetected: one is enough
    assert [r["render_processes"] for r in reports] == [0, 0]  # 131 images: not worth a render process
    assert reports[0]["odometry"] == {**reports[1]["odometry"], "odometry_hz": reports[0]["odometry"]["odometry_hz"]}
    assert reports[0]["time_split_s"]["odometry"] > 0
    d = reports[0]["detection"]
    assert d == {**reports[1]["detection"], "fps": d["fps"]}
    # 13 s at 0.25 m/s: about 33 images of 131 pass
    assert 25 <= d["frames"] <= 45 and d["frames"] + d["keyframe_held_images"] == 131
    # ahead, the images the gate holds back are not rendered at all; in the loop every one is
    assert reports[0]["camera_frames_unrendered"] == d["keyframe_held_images"]
    assert reports[1]["camera_frames_unrendered"] == 0
    assert "keyframe_m = 0.1" in (outs[0] / "config.toml").read_text()
