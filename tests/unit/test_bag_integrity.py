"""Damage inside a recorded bag is detected, passed over and reported, never used.

Our MCAP chunks carry the CRC32 of their records, so bytes overwritten inside a chunk's data are
caught on read: the chunk is skipped, named in the report with the span and messages it held, and
the replay scores what is left. Bad messages met by the detector's reader count in the same report
as the others, with or without ``--sequential``.
"""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from stack.messages import CameraFrame
from testbed.bags import BagReader, BagWriter
from testbed.bags import topics as T
from testbed.bags.errors import MissingTopicError, TooManyBadMessagesError
from testbed.bags.salvage import zstd
from testbed.record import write_image_truth
from testbed.replay import BagTopics, replay_bag

from test_rosbag_io import (OBJECTS, T_BASE_CAMERA, T_BASE_VELODYNE, T0, T_world_base, episode, make_scan,
                            record)


class NoDetections:
    """A detector that finds nothing (the replay's scoring and bookkeeping still run per image)."""

    def detect(self, frame):
        return []


def mcap_chunks(path):
    """(record offset, record length, start ns, end ns, crc, compression, data) of each chunk, in file order."""
    target = path if path.is_file() else next(path.glob("*.mcap"))
    data = target.read_bytes()
    out, pos = [], 8
    while pos < len(data):
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if op == 0x06:
            start, end, _usize, crc = struct.unpack_from("<QQQI", data, pos + 9)
            (clen,) = struct.unpack_from("<I", data, pos + 9 + 28)
            compression = data[pos + 9 + 32:pos + 9 + 32 + clen].decode()
            (rlen,) = struct.unpack_from("<Q", data, pos + 9 + 32 + clen)
            body = data[pos + 9 + 40 + clen:pos + 9 + 40 + clen + rlen]
            out.append((pos, length, start, end, crc, compression, body))
        if op in (0x02, 0x0F):  # footer, data end
            break
        pos += 9 + length
    return target, out


def scribble(target, chunk, seed=0, n=4096):
    """Overwrite ``n`` bytes in the middle of a chunk's data with seeded random bytes."""
    pos, length = chunk[0], chunk[1]
    with target.open("r+b") as f:
        f.seek(pos + 9 + length // 2 - n // 2)
        f.write(np.random.default_rng(seed).bytes(n))


@pytest.mark.parametrize("compress", [True, False])
def test_recorded_mcap_chunks_carry_the_crc_of_their_records(tmp_path, compress):
    path = tmp_path / "run"
    with BagWriter(path, compress=compress) as bag:
        rng = np.random.default_rng(0)
        bag.write_extrinsics(T_BASE_VELODYNE, T_BASE_CAMERA, stamp=T0)
        for i in range(8):
            bag.write(make_scan(rng, T0 + 0.1 * i, 20000))
    _, chunks = mcap_chunks(path)
    assert len(chunks) >= 2
    for *_, crc, compression, body in chunks:
        raw = zstd.decompress(body) if compression == "zstd" else body
        assert crc != 0 and crc == zlib.crc32(raw)
    with BagReader(path, require_camera=False) as bag:
        assert len(list(bag.scans())) == 8 and not bag.salvaged


def test_random_bytes_inside_a_chunk_are_detected_skipped_and_reported(tmp_path, caplog):
    msgs = episode(seed=13, n_scans=12, n_points=20000)  # 5 MB: several 1 MB chunks
    path = tmp_path / "run_mcap"
    record(path, "ros2", "mcap", msgs)
    target, chunks = mcap_chunks(path)
    assert len(chunks) >= 4
    damaged = chunks[2]
    scribble(target, damaged)
    with BagReader(path) as bag:
        got = list(bag.frames())
        skipped = bag.skipped_chunks
        assert "CRC mismatch" in bag.salvaged
    (chunk,) = skipped
    assert chunk["byte"] == damaged[0] and "CRC mismatch" in chunk["reason"]
    assert (chunk["start_s"], chunk["end_s"]) == (pytest.approx(damaged[2] * 1e-9), pytest.approx(damaged[3] * 1e-9))
    assert chunk["messages"][T.LIDAR] >= 1 and chunk["messages"][T.GT_BASE_POSE] >= 1
    lost = sum(n for topic, n in chunk["messages"].items() if topic in (T.LIDAR, T.WHEEL_ODOM))
    assert 0 < len(got) < len(msgs)
    by_stamp = {(type(m).__name__, round(m.stamp, 6)): m for m in msgs}
    for msg in got:  # what comes back is what was written: nothing of the damaged chunk is used
        want = by_stamp[(type(msg).__name__, round(msg.stamp, 6))]
        if hasattr(want, "points"):
            np.testing.assert_array_equal(msg.points, want.points.astype(np.float32))
        elif isinstance(want, CameraFrame):
            np.testing.assert_array_equal(msg.rgb, want.rgb)
    sensors = sum(not isinstance(m, CameraFrame) for m in msgs)
    assert sum(not isinstance(m, CameraFrame) for m in got) == sensors - lost
    assert any("CRC" in r.getMessage() and "\n" not in r.getMessage() for r in caplog.records)


def _bag_with_image_truth(path, pad_after: int | None = None, bad_image: int | None = None):
    """A synthetic drive with per-image ground truth. ``pad_after``: after that image a 1.1 MB
    message closes the chunk, so the image's truth opens the next one. ``bad_image``: that image is
    written 10 rows short (it cannot be converted)."""
    msgs = episode(seed=21, n_scans=12, n_points=20000)
    frames = [m for m in msgs if isinstance(m, CameraFrame)]
    with BagWriter(path) as bag:
        bag.write_metadata(T0, {"scenario": "synthetic", "seed": 0})
        bag.write_extrinsics(T_BASE_VELODYNE, T_BASE_CAMERA, stamp=T0)
        bag.write_ground_truth_objects(T0, OBJECTS)
        for msg in msgs:
            k = frames.index(msg) if isinstance(msg, CameraFrame) else None
            if k is not None and k == bad_image:
                bag.write(CameraFrame(msg.stamp, msg.info, rgb=msg.rgb[10:], depth_m=msg.depth_m))
            else:
                bag.write(msg)
            bag.write_ground_truth_pose(msg.stamp, T_world_base(msg.stamp))
            if k is not None:
                if k == pad_after:
                    bag.write_message("/padding", "std_msgs/msg/String", msg.stamp,
                                      bag.dialect.make("std_msgs/msg/String", data="x" * 1_100_000))
                write_image_truth(bag, msg.stamp, [])
    return msgs, frames


def test_replay_scores_what_is_left_when_a_middle_chunk_is_skipped(tmp_path):
    path = tmp_path / "run"
    msgs, frames = _bag_with_image_truth(path, pad_after=15)
    t_pad = frames[15].stamp
    target, chunks = mcap_chunks(path)
    # the chunk after the padding: it opens with the truth of image 15, whose pixels stay intact before it
    k = max(i for i, c in enumerate(chunks) if c[2] <= round(t_pad * 1e9))
    assert 0 < k < len(chunks) - 1 and chunks[k][2] == round(t_pad * 1e9)
    scribble(target, chunks[k], seed=1)
    reports = {}
    for parallel in (True, False):
        reports[parallel] = report = replay_bag(path, tmp_path / f"out{parallel}", detector=NoDetections(),
                                                odometry="wheel", parallel=parallel)
        (chunk,) = report["skipped_chunks"]
        assert chunk["byte"] == chunks[k][0] and "CRC mismatch" in chunk["reason"]
        assert chunk["messages"][T.GT_IMAGE_OBJECTS] >= 1 and chunk["messages"][T.GT_BASE_POSE] >= 1
        assert chunk["start_s"] == pytest.approx(t_pad)
        assert "skipped a damaged chunk" in report["salvaged"]
        d = report["detection"]
        assert d["frames_without_ground_truth"] >= 1  # image 15: its pixels survived, its truth did not
        assert d["frames"] == len(frames) - chunk["messages"][T.RGB] and "precision" in d
        o = report["odometry"]
        assert "poses_unscored" in o and o["ate_rmse_m"] < 1e-6  # wheel odometry is the truth here
        assert report["wheel_odometry"]["ate_rmse_m"] < 1e-6
        assert (tmp_path / f"out{parallel}" / "report.json").exists()
    assert reports[True]["skipped_chunks"] == reports[False]["skipped_chunks"]
    assert reports[True]["detection"]["frames"] == reports[False]["detection"]["frames"]


def test_a_bad_image_counts_the_same_with_and_without_sequential(tmp_path):
    path = tmp_path / "run"
    msgs, frames = _bag_with_image_truth(path, bad_image=10)
    summaries = {}
    for parallel in (True, False):
        report = replay_bag(path, tmp_path / f"out{parallel}", detector=NoDetections(), odometry="wheel",
                            parallel=parallel, write_outputs=False)
        summaries[parallel] = report["bad_messages"]
        assert report["detection"]["frames"] == len(frames) - 1
    (topic, entry), = summaries[True].items()
    assert topic == T.RGB and entry["count"] == 1
    assert entry["first_stamps_s"] == [pytest.approx(frames[10].stamp)]
    assert summaries[True] == summaries[False]
    for parallel in (True, False):  # --max-bad-messages holds for the detector's reader too
        with pytest.raises(TooManyBadMessagesError, match="1 bad messages on /camera/color/image_raw"):
            replay_bag(path, tmp_path / f"stop{parallel}", detector=NoDetections(), odometry="wheel",
                       parallel=parallel, write_outputs=False, topics=BagTopics(max_bad_messages=0))


def test_damage_met_mid_stream_goes_on_from_the_intact_chunks(tmp_path):
    """A bag without ground truth opens without reading every chunk: the damaged one is met while
    the scans stream, and the stream goes on from the intact chunks, nothing twice."""
    path = tmp_path / "scans"
    rng = np.random.default_rng(3)
    with BagWriter(path) as bag:
        bag.write_extrinsics(T_BASE_VELODYNE, T_BASE_CAMERA, stamp=T0)
        for i in range(12):
            bag.write(make_scan(rng, T0 + 0.1 * i, 20000))
    target, chunks = mcap_chunks(path)
    scribble(target, chunks[1], seed=2)
    with BagReader(path, require_camera=False) as bag:
        assert not bag.salvaged  # nothing read at open touched the damaged chunk
        stamps = [round(s.stamp, 6) for s in bag.scans()]
        (chunk,) = bag.skipped_chunks
    lost = chunk["messages"][T.LIDAR]
    assert lost >= 1 and len(stamps) == 12 - lost and stamps == sorted(set(stamps))
    assert not [s for s in stamps if chunk["start_s"] - 1e-6 <= s <= chunk["end_s"] + 1e-6]


def test_a_damaged_first_chunk_loses_its_messages_only(tmp_path):
    """The first chunk also holds the channel definitions; the summary repeats them, so the later
    chunks' messages are still read (here /tf_static went with the first chunk: the extrinsics are given)."""
    msgs = episode(seed=13, n_scans=12, n_points=20000)
    path = tmp_path / "run"
    record(path, "ros2", "mcap", msgs)
    target, chunks = mcap_chunks(path)
    scribble(target, chunks[0], seed=4)
    with BagReader(path, T_base_lidar=T_BASE_VELODYNE, T_base_camera=T_BASE_CAMERA) as bag:
        got = list(bag.frames())
        (chunk,) = bag.skipped_chunks
    assert chunk["byte"] == chunks[0][0] and chunk["messages"][T.TF_STATIC] == 1
    sensors = sum(not isinstance(m, CameraFrame) for m in msgs)
    lost = sum(n for topic, n in chunk["messages"].items() if topic in (T.LIDAR, T.WHEEL_ODOM))
    assert sum(not isinstance(m, CameraFrame) for m in got) == sensors - lost > 0


def test_the_mcap_summary_carries_its_crc_and_damage_there_sends_the_reader_to_the_chunks(tmp_path, caplog):
    from testbed.bags.errors import CorruptBagError
    from testbed.bags.mcap_summary import _footer, summary_crc_problem

    path = tmp_path / "run"
    with BagWriter(path) as bag:
        rng = np.random.default_rng(0)
        bag.write_extrinsics(T_BASE_VELODYNE, T_BASE_CAMERA, stamp=T0)
        for i in range(8):
            bag.write(make_scan(rng, T0 + 0.1 * i, 20000))
    target = next(path.glob("*.mcap"))
    with target.open("rb") as f:
        footer_at, start, _offsets, crc = _footer(f, target.stat().st_size)
    data = bytearray(target.read_bytes())
    assert crc != 0 and crc == zlib.crc32(bytes(data[start:footer_at + 1 + 8 + 16]))
    assert summary_crc_problem(target) is None
    data[start + 20] ^= 0xFF  # one byte inside the summary section (a schema definition)
    target.write_bytes(bytes(data))
    assert "summary CRC mismatch" in summary_crc_problem(target)
    with caplog.at_level("WARNING"), BagReader(path, require_camera=False) as bag:
        assert len(list(bag.scans())) == 8  # every scan, from the intact chunks
        assert bag.salvaged
    assert "summary CRC mismatch" in caplog.text
    with pytest.raises(CorruptBagError, match="summary CRC mismatch"):
        BagReader(path, require_camera=False, salvage="never").open()


def test_the_detection_process_counts_a_bad_image_as_the_thread_does(tmp_path, monkeypatch):
    """Replay's detector process (a DOPE detector ``make_detector`` made) reads the images on a reader
    of its own: its bad messages count in the report as the thread's do, and ``--max-bad-messages``
    stops it with the same error."""
    from testbed.run import make_detector

    path = tmp_path / "run"
    _bag_with_image_truth(path, bad_image=10)
    reports = {}
    for mode in ("2", "1", "0"):
        monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", mode)
        reports[mode] = replay_bag(path, tmp_path / f"out{mode}", detector=make_detector("rgb", 1, True),
                                   odometry="wheel", write_outputs=False)
        with pytest.raises(TooManyBadMessagesError, match="1 bad messages on /camera/color/image_raw"):
            replay_bag(path, tmp_path / f"stop{mode}", detector=make_detector("rgb", 1, True), odometry="wheel",
                       write_outputs=False, topics=BagTopics(max_bad_messages=0))
    assert [reports[m]["detector_processes"] for m in ("2", "1", "0")] == [2, 1, 0]
    assert reports["2"]["bad_messages"] == reports["1"]["bad_messages"] == reports["0"]["bad_messages"]
    assert reports["2"]["detection"]["frames"] == reports["1"]["detection"]["frames"] == \
        reports["0"]["detection"]["frames"]
    # the process starts before the bag is opened here: a bag this process cannot open stops it too
    with pytest.raises(MissingTopicError, match="/no/such/topic"):
        replay_bag(path, tmp_path / "missing", detector=make_detector("rgb", 1, True), odometry="wheel",
                   write_outputs=False, topics=BagTopics(rgb="/no/such/topic"))


def test_the_detection_process_sends_other_sizes_inline_and_stops_when_closed(tmp_path):
    """Images of another size than the camera the slots were made for come back inline, the same
    pixels; closing before the last image stops the child at once."""
    import time

    from stack.messages import CameraInfo
    from testbed.detection_process import build_detector
    from testbed.replay_detection import DetectionReaderProcess
    from testbed.run import detector_kwargs

    path = tmp_path / "run"
    msgs, frames = _bag_with_image_truth(path)
    kwargs = detector_kwargs("rgb", 1, True)
    other = CameraInfo(8, 6, np.eye(3))
    ahead = DetectionReaderProcess(path, BagTopics(), "rgb", kwargs, other, dope_every=2)
    got = list(ahead)
    ahead.close()
    assert [round(f.stamp, 6) for f, _, _ in got] == [round(f.stamp, 6) for f in frames]
    for (f, dets, _), want in zip(got, frames):
        np.testing.assert_array_equal(f.rgb, want.rgb)
    assert [dets is not None for _, dets, _ in got] == [i % 2 == 0 for i in range(len(frames))]
    detector = build_detector(kwargs, 1)
    assert [len(d) for _, d, _ in got[::2]] == [len(detector.detect(f)) for f, _, _ in got[::2]]
    assert ahead.gate is None and ahead.reader.bad_message_summary() == {}
    ahead = DetectionReaderProcess(path, BagTopics(), "rgb", kwargs, None)  # the camera told later: none here
    ahead.camera(None)
    assert [f.rgb.tobytes() for f, _, _ in ahead] == [f.rgb.tobytes() for f in frames]
    ahead.close()
    with BagReader(path) as bag:
        info = bag.camera_info
    ahead = DetectionReaderProcess(path, BagTopics(), "rgb", kwargs, info, slots=2)
    first = next(iter(ahead))
    t0 = time.perf_counter()
    ahead.close()
    assert time.perf_counter() - t0 < 5 and first[0].rgb.shape == frames[0].rgb.shape


def test_a_failure_in_the_detection_process_names_the_bag(tmp_path):
    """An error in replay's detector process that is not the bag's comes back as one error that
    names the bag and what the child said, and the child is gone."""
    from stack.messages import CameraInfo
    from testbed.replay_detection import DetectionReaderProcess
    from testbed.run import detector_kwargs

    path = tmp_path / "run"
    _bag_with_image_truth(path)
    kwargs = {**detector_kwargs("rgb", 1, True), "no_such_argument": 1}
    ahead = DetectionReaderProcess(path, BagTopics(), "rgb", kwargs, CameraInfo(8, 6, np.eye(3)))
    child = ahead._proc
    with pytest.raises(RuntimeError, match=rf"^{path}: replay's detection process: TypeError: .*no_such_argument"):
        list(ahead)
    assert child.poll() is not None and ahead._proc is None
