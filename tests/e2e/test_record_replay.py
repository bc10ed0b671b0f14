"""Record and replay: a live run recorded while it runs, replayed offline in passes, gives the
same results; other clients read our bags; the stack runs on a bag our recorder did not write.

One short episode (8 s, 320x240 camera, the default scene with the robot started near the objects)
is run live once per module, with a ground-truth detector double, and recorded; the tests replay it.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from itertools import islice
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

import sim.episode
from oracle import OracleDetector
from sim.scenario import load_scenario
from stack.lidar_slam import LidarOdometry, LidarOdometryConfig
from stack.transforms import inv
from testbed.bags import BagReader, BagWriter, MissingTopicError
from testbed.bags import topics as T
from testbed.record import RESULTS_BAG_NAME
from testbed.replay import BagImageTruth, BagTopics, replay_bag
from testbed.run import run_episode

pytestmark = pytest.mark.slow

DURATION = 8.0


class _CapturingEpisode(sim.episode.Episode):
    """The Episode that ``run_episode`` builds, kept so the detector double can read its truth."""

    last = None

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _CapturingEpisode.last = self


class _Truth:
    """``image_truth(frame)`` from whatever source is set (the live episode, or a bag)."""

    def __init__(self, source=None):
        self.source = source

    def image_truth(self, frame):
        src = self.source if self.source is not None else _CapturingEpisode.last
        return src.image_truth(frame)


class _RecordingOracle(OracleDetector):
    """The oracle, noting what it was shown: stamp, intrinsics, colour pixels, depth in millimetres."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.seen = []

    def detect(self, frame):
        mm = np.rint(np.asarray(frame.depth_m, dtype=np.float64) * 1000).astype(np.uint16)
        self.seen.append((round(frame.stamp, 6), frame.info.K.round(9).tolist(),
                          hashlib.sha1(np.ascontiguousarray(frame.rgb)).hexdigest(), hashlib.sha1(mm).hexdigest()))
        return super().detect(frame)


def short_scenario():
    sc = load_scenario(None)
    sc.sensors.camera_width, sc.sensors.camera_height = 320, 240
    sc.robot.start = [0.0, 0.0, 0.0]  # the objects stand at x = 1.6-2.6 m, 0.55 m either side
    sc.route.start_pause = 0.5
    return sc


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A live run (odometry, oracle detections, fusion, store) recorded into a ROS 2 MCAP bag."""
    root = tmp_path_factory.mktemp("live")
    bag = root / "episode"
    mp = pytest.MonkeyPatch()
    mp.setattr(sim.episode, "Episode", _CapturingEpisode)
    detector = _RecordingOracle(_Truth())
    try:
        with BagWriter(bag) as writer:
            report = run_episode(short_scenario(), root / "run", seed=0, duration=DURATION,
                                 detector=detector, bag_writer=writer, keep_detections=True)
    finally:
        mp.undo()
    return {"root": root, "bag": bag, "report": report, "counts": dict(writer.counts), "detector": detector}


def oracle_for(bag_path: Path) -> _RecordingOracle:
    with BagReader(bag_path) as bag:
        return _RecordingOracle(_Truth(BagImageTruth(bag)))


@pytest.fixture(scope="module")
def replayed(live):
    out = live["root"] / "replay"
    detector = oracle_for(live["bag"])
    report = replay_bag(live["bag"], out, detector=detector, keep_detections=True)
    return {"out": out, "report": report, "detector": detector}


def tum(path: Path) -> np.ndarray:
    return np.loadtxt(path)


def test_replay_reproduces_the_live_run(live, replayed):
    run_dir, rep_dir = live["root"] / "run", replayed["out"]
    a, b = live["report"], replayed["report"]
    # the same trajectory to well within a millimetre
    ta, tb = tum(run_dir / "estimate_tum.txt"), tum(rep_dir / "estimate_tum.txt")
    assert ta.shape == tb.shape and len(ta) >= 70
    assert np.abs(ta[:, 0] - tb[:, 0]).max() < 1e-6
    assert np.linalg.norm(ta[:, 1:4] - tb[:, 1:4], axis=1).max() < 1e-3
    assert np.abs(tum(run_dir / "groundtruth_tum.txt") - tum(rep_dir / "groundtruth_tum.txt")).max() < 1e-6
    # the detector is shown the same images: colour bit for bit, depth to the millimetre (16UC1), the
    # same intrinsics and stamps; so any deterministic detector (DOPE included) detects the same
    assert live["detector"].seen == replayed["detector"].seen and len(live["detector"].seen) == 81
    # the same labels: ids, classes, positions, observation counts
    sa, sb = list(a["_store"]), list(b["_store"])
    assert len(sa) == 6, "the oracle should label all six objects in this episode"
    assert [(m.id, m.cls, m.observations) for m in sa] == [(m.id, m.cls, m.observations) for m in sb]
    for ma, mb in zip(sa, sb):
        np.testing.assert_allclose(ma.xyz, mb.xyz, atol=1e-4)
    # the same scores, computed from the bag's ground truth
    for key in ("labelled", "false_labels", "missing"):
        assert a["labels_summary"][key] == b["labels_summary"][key]
    assert abs(a["labels_summary"]["mean_error_m"] - b["labels_summary"]["mean_error_m"]) < 1e-4
    for key in ("frames", "predictions", "false_positives", "instances", "correct"):
        assert a["detection"][key] == b["detection"][key]
    assert b["detection"]["instances"] > 0 and b["detection"]["detections_without_pose"] == 0
    assert abs(a["odometry"]["ate_rmse_m"] - b["odometry"]["ate_rmse_m"]) < 1e-4
    assert abs(a["wheel_odometry"]["ate_rmse_m"] - b["wheel_odometry"]["ate_rmse_m"]) < 1e-4
    # the outputs of `dopeslam run`
    for name in ("report.json", "labels.xlsx", "labels.json", "estimate_tum.txt", "groundtruth_tum.txt", "map.png"):
        assert (rep_dir / name).stat().st_size > 0, name
    assert json.loads((rep_dir / "report.json").read_text())["ground_truth"] == \
        {"trajectory": True, "objects": True, "images": True}


def test_results_bag_holds_labels_map_and_trajectory(live, replayed):
    for out_dir, report in ((live["root"] / "run", live["report"]), (replayed["out"], replayed["report"])):
        results, store = out_dir / RESULTS_BAG_NAME, report["_store"]
        with BagReader(results, lidar_topic=T.MAP, require_camera=False, T_base_lidar=np.eye(4)) as bag:
            frame, labels = bag.labels()
            points = bag.map_points()
            assert frame == T.MAP_FRAME
            assert [(c.cls, c.name) for c in labels] == [(m.cls, f"{m.cls}_{m.id}") for m in store]
            for c, m in zip(labels, store):
                np.testing.assert_allclose(c.T_frame_obj[:3, 3], m.xyz, atol=1e-9)
                np.testing.assert_allclose(c.dims, m.size)
            assert points is not None and len(points) > 1000
            (_, _, path_msg), = bag.messages([T.TRAJECTORY])
            assert len(path_msg.poses) == len(tum(out_dir / "estimate_tum.txt"))
            assert bag.groundtruth is None and len(bag.topics) == 5  # tf_static, labels, map, path, truth


def test_recorded_bag_is_read_by_rosbags_own_reader(live):
    seen: dict[str, int] = {}
    with AnyReader([live["bag"]]) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
    assert seen == live["counts"]
    physics_steps = int(round(DURATION * 240)) + 1
    assert seen[T.GT_BASE_POSE] == physics_steps
    assert seen[T.LIDAR] == 80 and seen[T.RGB] == seen[T.DEPTH] == seen[T.GT_IMAGE_OBJECTS] == 81
    assert seen[T.TF_STATIC] == seen[T.GT_OBJECTS] == seen[T.METADATA] == 1


def test_record_command_writes_a_ros1_bag_rosbags_reads(tmp_path, capsys):
    from testbed.cli import main

    bag = tmp_path / "short.bag"
    assert main(["record", "--bag", str(bag), "--seed", "3", "--duration", "1.0"]) == 0
    seen: dict[str, int] = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
    assert seen[T.LIDAR] == 10 and seen[T.GT_BASE_POSE] == 241
    assert seen[T.RGB_COMPRESSED] == seen[T.DEPTH_COMPRESSED] == 11 and T.RGB not in seen  # compressed by default
    with BagReader(bag) as r:
        assert r.metadata["seed"] == 3 and r.metadata["scenario"] == "experiment3_columns"
        assert r.camera_info.width == 640 and r.groundtruth is not None and len(r.groundtruth.objects) == 6
    capsys.readouterr()
    assert main(["record", "--bag", str(tmp_path / "x"), "--format", "ros1", "--duration", "1"]) == 2
    assert capsys.readouterr().err.strip().endswith("a ROS 1 bag's name must end in .bag")


def test_replay_of_a_foreign_bag_without_ground_truth(live, replayed, tmp_path):
    """ROS 1, another LiDAR topic name, depth as 32FC1 metres, the extrinsics through an intermediate
    frame, no ground truth: the same trajectory and labels, and no scores (not faked)."""
    foreign = tmp_path / "robot.bag"
    lidar_topic = "/sensors/lidar/points"
    with BagReader(live["bag"]) as src, BagWriter(foreign, depth_encoding="32FC1") as dst:
        T_base_mount = np.eye(4)
        T_base_mount[:3, 3] = [0.0, 0.0, 0.184]
        dst.write_tf_static(0.0, [(T.BASE, "mid_mount", T_base_mount),
                                  ("mid_mount", T.VELODYNE, inv(T_base_mount) @ src.T_base_velodyne),
                                  ("mid_mount", T.CAMERA, inv(T_base_mount) @ src.T_base_camera)])
        for msg in src.frames():
            if hasattr(msg, "points"):
                dst.write_scan(msg, topic=lidar_topic)
            else:
                dst.write(msg)
    out = tmp_path / "out"
    with pytest.raises(MissingTopicError, match=lidar_topic):  # a topic the bag lacks: named, with the bag's
        replay_bag(foreign, out, detector=oracle_for(live["bag"]), topics=BagTopics(lidar=T.LIDAR))
    report = replay_bag(foreign, out, detector=oracle_for(live["bag"]), topics=BagTopics(lidar=lidar_topic),
                        parallel=False, keep_detections=True)
    assert report["ground_truth"] == {"trajectory": False, "objects": False, "images": False}
    assert "ate_rmse_m" not in report["odometry"] and "wheel_odometry" not in report
    assert "precision" not in report["detection"] and "recall" not in report["detection"]
    assert "mean_error_m" not in report["labels_summary"] and all("error_m" not in r for r in report["labels"])
    assert not (out / "groundtruth_tum.txt").exists()
    for name in ("report.json", "labels.xlsx", "labels.json", "estimate_tum.txt", "map.png", RESULTS_BAG_NAME):
        assert (out / name).exists(), name
    # same stack, same data: the same trajectory (in map) and labels as the replay of our own bag
    s_ref, P_ref = replayed["report"]["_trajectory"]
    s, P = report["_trajectory"]
    np.testing.assert_allclose(s, s_ref, atol=1e-6)
    assert np.linalg.norm(P[:, :3, 3] - P_ref[:, :3, 3], axis=1).max() < 1e-3
    ref = list(replayed["report"]["_store"])
    assert [(m.id, m.cls) for m in report["_store"]] == [(m.id, m.cls) for m in ref]
    for m, r in zip(report["_store"], ref):
        np.testing.assert_allclose(m.xyz, r.xyz, atol=1e-3)


def test_replay_names_a_missing_image_topic(live, tmp_path):
    lidar_only = tmp_path / "lidar_only"
    with BagReader(live["bag"]) as src, BagWriter(lidar_only) as dst:
        dst.write_extrinsics(src.T_base_velodyne, src.T_base_camera)
        for scan in src.scans():
            dst.write(scan)
            if scan.stamp > 1.0:
                break
        frame = next(src.camera_frames())
        frame.depth_m = None  # colour only
        dst.write(frame)
    with pytest.raises(MissingTopicError) as err:
        replay_bag(lidar_only, tmp_path / "out", detector=object(), input_mode="depth")
    text = str(err.value)
    assert "--input depth" in text and "--depth-topic" in text and T.RGB in text and T.LIDAR in text


def test_kiss_icp_own_command_reads_our_bag(live, tmp_path):
    """``kiss_icp_pipeline --topic /velodyne_points BAG`` on the recorded bag agrees with our odometry.

    Both run KISS-ICP with the stack's settings (``--config``: KISS-ICP's default 1 m voxels are for
    outdoor ranges) and without the stack's floor constraint, which KISS-ICP does not have, so any
    difference left is in how the bag is read (points, per-point times, order).
    """
    exe = shutil.which("kiss_icp_pipeline") or str(Path(sys.executable).parent / "kiss_icp_pipeline")
    cfg = LidarOdometryConfig(floor_constraint=False)
    kiss = cfg.to_kiss()
    kiss.out_dir = str(tmp_path / "kiss")
    from kiss_icp.config import write_config

    write_config(kiss, str(tmp_path / "kiss.yaml"))
    n = 50  # of the 80 scans, to keep the test short
    proc = subprocess.run([exe, "--config", str(tmp_path / "kiss.yaml"), "--topic", T.LIDAR, "--n-scans", str(n),
                           str(live["bag"])],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    theirs = np.load(tmp_path / "kiss" / "latest" / f"{live['bag'].name}_poses.npy")  # velodyne at scan 0
    with BagReader(live["bag"]) as bag:
        odom = LidarOdometry(bag.T_base_velodyne, cfg)
        for scan in islice(bag.scans(), n):
            assert odom.process(scan) is not None
        T_bv = bag.T_base_velodyne
    _, P = odom.trajectory()
    ours = inv(T_bv) @ P @ T_bv
    assert theirs.shape == ours.shape == (n, 4, 4)
    gap = np.linalg.norm(theirs[:, :3, 3] - ours[:, :3, 3], axis=1)
    travelled = np.linalg.norm(ours[-1, :3, 3])
    assert travelled > 0.5
    assert gap.max() < 0.05, f"KISS-ICP's command and ours differ by up to {gap.max():.3f} m"


def test_replay_of_a_truncated_bag_uses_its_complete_messages(live, replayed, tmp_path):
    """A recording cut off mid-file (no MCAP footer or index): the intact chunks are replayed."""
    cut = tmp_path / "cut"
    shutil.copytree(live["bag"], cut)
    (mcap,) = cut.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    report = replay_bag(cut, tmp_path / "out", detector=oracle_for(live["bag"]), keep_detections=True)
    assert report["salvaged"]
    s, P = report["_trajectory"]
    s_ref, P_ref = replayed["report"]["_trajectory"]
    assert 20 <= len(s) < len(s_ref)
    np.testing.assert_allclose(s, s_ref[: len(s)], atol=1e-6)  # a prefix of the full bag's trajectory
    assert np.linalg.norm(P[:, :3, 3] - P_ref[: len(s), :3, 3], axis=1).max() < 1e-3


def test_replay_with_loop_closure(live, replayed, tmp_path):
    """``--loop-closure`` on a bag: key frames from the bag's colour images, the corrected trajectory
    places the labels; on this short straight drive nothing may be closed falsely or moved far."""
    from stack.loops.place_recognition import VocabularyTree, describe

    with BagReader(live["bag"]) as bag:
        feats = [describe(f.rgb) for f in islice(bag.camera_frames(), 0, None, 4)]
    tree = VocabularyTree.train([f.descriptors for f in feats if f is not None], branching=4, depth=2)
    report = replay_bag(live["bag"], tmp_path / "lc", detector=oracle_for(live["bag"]), loop_closure=True,
                        vocabulary=tree)
    assert report["loop_closure"] is True
    o, base = report["odometry"], replayed["report"]["odometry"]
    assert o["loop_closure"]["key_frames"] > 0 and o["false_loop_closures"] == 0
    assert o["ate_rmse_odometry_only_m"] == pytest.approx(base["ate_rmse_m"], abs=1e-6)
    assert abs(o["ate_rmse_m"] - base["ate_rmse_m"]) < 0.02
    assert report["labels_summary"]["labelled"] == replayed["report"]["labels_summary"]["labelled"]
    assert (tmp_path / "lc" / "map.png").exists()


def test_odometry_only_replay_reads_no_images(live, replayed, tmp_path):
    """``dopeslam replay --odometry-only``: no detector, no image read; the same trajectory."""
    out = tmp_path / "odo"
    proc = subprocess.run([sys.executable, "-m", "testbed.cli", "-q", "replay", str(live["bag"]), "--odometry-only",
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["odometry_only"] and report["detector"] == "none"
    assert report["detection"]["frames"] == 0 and report["labels_summary"]["labels_in_map"] == 0
    assert report["time_split_s"]["image_reading"] == 0.0
    ta, tb = tum(replayed["out"] / "estimate_tum.txt"), tum(out / "estimate_tum.txt")
    assert ta.shape == tb.shape
    assert np.abs(ta[:, 1:4] - tb[:, 1:4]).max() < 1e-6


def test_replay_applies_the_odometry_settings(live, replayed, tmp_path):
    """``dopeslam replay --set odometry.KEY=V`` tunes KISS-ICP on a bag: another voxel size gives another
    trajectory (near the default's), and the run's config.toml keeps the setting."""
    out = tmp_path / "odo_voxel"
    proc = subprocess.run([sys.executable, "-m", "testbed.cli", "-q", "replay", str(live["bag"]), "--odometry-only",
                           "--set", "odometry.voxel_size_m=0.35", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "voxel_size_m = 0.35" in (out / "config.toml").read_text()
    ta, tb = tum(replayed["out"] / "estimate_tum.txt"), tum(out / "estimate_tum.txt")
    assert ta.shape == tb.shape
    d = np.abs(ta[:, 1:4] - tb[:, 1:4]).max()
    assert 1e-9 < d < 0.2, d


def test_replay_with_the_keyframe_gate_detects_the_same_images_either_way(live, tmp_path):
    """``[detector] keyframe_*``: the detector sees only the images the robot moved enough for (by the
    bag's wheel odometry) or one per ``keyframe_max_s``; the detection thread (the default) and the
    message loop (``--sequential``) pass the same images."""
    from stack.keyframes import KeyframeSettings

    gate = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=1.0)
    seen, reports = [], []
    for parallel in (True, False):
        detector = oracle_for(live["bag"])
        reports.append(replay_bag(live["bag"], tmp_path / f"gated_{parallel}", detector=detector, parallel=parallel,
                                  keyframes=gate))
        seen.append(detector.seen)
    assert seen[0] == seen[1]
    frames = reports[0]["detection"]["frames"]
    assert frames == len(seen[0]) == reports[1]["detection"]["frames"]
    # 8 s: standing 0.5 s, then 0.25 m/s: about one image per 10 cm of 81
    assert 15 <= frames <= 40
    assert frames + reports[0]["detection"]["keyframe_held_images"] == 81
    assert reports[1]["detection"]["keyframe_held_images"] == reports[0]["detection"]["keyframe_held_images"]


def test_replay_detection_process_gives_the_thread_s_results(live, tmp_path, monkeypatch):
    """A DOPE detector that ``make_detector`` made reads, decodes, gates and detects in a child process
    (``DOPESLAM_DETECTOR_PROCESS``, on by default), two where it detects every image (every other
    image in the second); one process, two, or a thread find the same detections, so the map, the
    trajectory and the counts are the same bytes, with the keyframe gate and without. Each case runs
    the default (unset: two processes without the gate, one with it), the other count and the thread."""
    from stack.keyframes import KeyframeSettings
    from testbed.run import make_detector

    gated = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=1.0)
    for gate, modes, counts in ((None, ("", "1", "0"), [2, 1, 0]), (gated, ("", "2", "0"), [1, 2, 0])):
        reports = {}
        for mode in modes:
            monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", mode)
            out = tmp_path / f"process{mode}_gate{gate is not None}"
            reports[mode] = replay_bag(live["bag"], out, detector=make_detector("rgb", 2, True), keyframes=gate)
        assert [reports[m]["detector_processes"] for m in modes] == counts
        assert reports[modes[1]]["detector_process"] and not reports["0"]["detector_process"]
        outs = [tmp_path / f"process{m}_gate{gate is not None}" for m in modes]
        for name in ("labels.json", "estimate_tum.txt"):
            assert len({(o / name).read_bytes() for o in outs}) == 1, name
        da, db, dc = (dict(reports[m]["detection"], fps=None) for m in modes)
        assert da == db == dc and da["frames"] > 0
        assert reports[modes[1]]["time_split_s"]["image_reading"] > 0
        if gate is not None:
            assert 0 < da["keyframe_held_images"] < 81


def test_replay_with_depth_input_reads_no_colour_pixels_and_gives_the_thread_s_results(live, tmp_path, monkeypatch):
    """With depth input nothing reads the colour images' pixels, so the detector process reads them for
    their stamps only; the thread (which decodes them) finds the same detections and map."""
    import testbed.replay
    from testbed.run import make_detector

    seen = []  # per mode: whether each image the pipeline got had colour pixels
    real = testbed.replay.DopeSlam.on_image
    monkeypatch.setattr(testbed.replay.DopeSlam, "on_image",
                        lambda self, frame, *a: seen[-1].append(frame.rgb is not None) or real(self, frame, *a))
    reports, outs = {}, {}
    for mode in ("1", "0"):
        monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", mode)
        outs[mode] = tmp_path / f"depth{mode}"
        seen.append([])
        reports[mode] = replay_bag(live["bag"], outs[mode], detector=make_detector("depth", 2, True),
                                   input_mode="depth")
    assert seen[0] and not any(seen[0]) and seen[1] and all(seen[1])  # the process read no colour pixels
    assert reports["1"]["detector_process"] and not reports["0"]["detector_process"]
    for name in ("labels.json", "estimate_tum.txt"):
        assert (outs["1"] / name).read_bytes() == (outs["0"] / name).read_bytes(), name
    d1, d0 = (dict(reports[m]["detection"], fps=None) for m in ("1", "0"))
    assert d1 == d0 and d1["frames"] > 0


def test_replay_command_builds_its_network_in_the_detector_process_only(live, tmp_path, monkeypatch, capsys):
    """``dopeslam replay`` builds the DOPE network only where it runs: in the detector process, none in
    the command's own process, which still names the detector, its precision and the weights' hash;
    in a thread (``DOPESLAM_DETECTOR_PROCESS=0``) one, here. The same bytes either way. A weights
    file that is not one ends in one line and exit status 2 either way, nothing written."""
    from stack import dope_fpr
    from stack.dope_fpr import default_weights, file_sha256, refinement_memory_order
    from testbed.cli import main

    built = []
    real_init = dope_fpr.DopeDetector.__init__

    def counting_init(self, *a, **kw):
        built.append(1)
        real_init(self, *a, **kw)

    monkeypatch.setattr(dope_fpr.DopeDetector, "__init__", counting_init)
    reports = {}
    for mode, here in (("1", 0), ("0", 1)):
        monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", mode)
        built.clear()
        out = tmp_path / f"cli{mode}"
        assert main(["replay", "-q", str(live["bag"]), "--set", "detector.stages=2", "--out", str(out)]) == 0
        assert len(built) == here
        reports[mode] = report = json.loads((out / "report.json").read_text())
        assert report["detector_processes"] == int(mode)
        assert report["detector"] == "stack.dope_fpr:DopeDetector" and report["network_precision"] == "fp32"
        assert report["network_refinement_order"] == refinement_memory_order()  # what ran: auto, resolved here
        assert report["provenance"]["weights_sha256"] == file_sha256(default_weights("rgb"))
        assert report["provenance"]["fpr_thresholds_sha256"] is not None
    for name in ("labels.json", "estimate_tum.txt"):
        assert (tmp_path / "cli1" / name).read_bytes() == (tmp_path / "cli0" / name).read_bytes(), name
    assert reports["1"]["detection"]["frames"] == reports["0"]["detection"]["frames"] > 0

    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00not a network" * 64)
    capsys.readouterr()
    for mode in ("1", "0"):
        monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", mode)
        out = tmp_path / f"bad{mode}"
        rc = main(["replay", "-q", str(live["bag"]), "--set", f"detector.weights={junk}", "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and err and err[-1].startswith("dopeslam replay: ") and str(junk) in err[-1], err[-3:]
        assert "Traceback" not in "\n".join(err) and not out.exists()
