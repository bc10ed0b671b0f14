"""Replay that degrades, not dies: a bad message is skipped, counted and named; too many stop
with a clear error; a topic with no good message at all says why."""
from __future__ import annotations

import numpy as np
import pytest

from testbed.bags import BagReader
from testbed.bags.errors import TooManyBadMessagesError, UnsupportedEncodingError

from test_rosbag_io import write_custom_lidar  # the bag writer helpers of the rosbag tests

N = 200


def _fields(bad_stamps):
    xyz = np.random.default_rng(0).normal(size=(N, 3)).astype(np.float32) + 2.0

    def fields_of(stamp):
        t = np.linspace(0, 0.099, N).astype(np.float32)
        if round(stamp, 3) in bad_stamps:
            t = np.linspace(0, 1e10, N).astype(np.float32)  # garbage per-point time: fits no unit
        return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "time": t}

    return fields_of


def test_one_garbage_scan_is_skipped_counted_and_named(tmp_path):
    path = tmp_path / "one_bad.bag"
    stamps = [100.0 + 0.1 * i for i in range(8)]
    write_custom_lidar(path, stamps, _fields({100.3}))
    with BagReader(path) as bag:
        scans = list(bag.scans())
        summary = bag.bad_message_summary()
    assert len(scans) == 7 and 100.3 not in [round(s.stamp, 3) for s in scans]
    (topic, entry), = summary.items()
    assert entry["count"] == 1 and entry["first_stamps_s"] == [pytest.approx(100.3)]
    assert "'time'" in entry["reason"]


def test_too_many_bad_messages_stop_with_a_clear_error(tmp_path):
    path = tmp_path / "many_bad.bag"
    stamps = [100.0 + 0.1 * i for i in range(8)]
    write_custom_lidar(path, stamps, _fields({round(s, 3) for s in stamps[2:]}))
    with BagReader(path, max_bad_messages=3) as bag, pytest.raises(TooManyBadMessagesError,
                                                                   match="4 bad messages on .*max-bad-messages"):
        list(bag.scans())


def test_a_topic_with_no_good_message_says_why(tmp_path):
    path = tmp_path / "all_bad.bag"
    stamps = [100.0, 100.1]
    write_custom_lidar(path, stamps, _fields({100.0, 100.1}))
    with BagReader(path) as bag, pytest.raises(UnsupportedEncodingError, match="'time'"):
        list(bag.scans())


def test_a_stray_future_stamp_is_skipped_and_reported(tmp_path):
    from test_rosbag_io import T_BASE_CAMERA, T_BASE_VELODYNE
    from testbed.bags import BagWriter
    from testbed.bags import topics as T
    from testbed.bags.convert import pointcloud2

    path = tmp_path / "stray.bag"
    fields_of = _fields(set())
    with BagWriter(path) as bag:
        bag.write_extrinsics(T_BASE_VELODYNE, T_BASE_CAMERA, stamp=100.0, lidar_frame="os_sensor")
        for i in range(8):
            t = 100.0 + 0.1 * i
            header_t = t + (100.0 if i == 4 else 0.0)  # one scan stamped 100 s in the future
            msg = pointcloud2(bag.dialect, round(header_t * 1e9), "os_sensor", fields_of(t))
            bag._put(T.LIDAR, "sensor_msgs/msg/PointCloud2", round(t * 1e9), msg)
    with BagReader(path, require_camera=False) as reader:
        scans = list(reader.scans())
        summary = reader.bad_message_summary()
    assert len(scans) == 7 and max(s.stamp for s in scans) < 101.0
    (entry,) = summary.values()
    assert entry["count"] == 1 and "+100.0 s off" in entry["reason"]
