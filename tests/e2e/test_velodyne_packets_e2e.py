"""Bags of the Velodyne's raw packets (``velodyne_msgs/VelodyneScan``): what a robot records when it
keeps the LiDAR's own output. They replay to the live run's sweeps bit for bit, and to the labels a
bag of the same sweeps as PointCloud2 gives (the packets themselves: ``tests/unit/test_velodyne_packets.py``)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

sys.path.insert(0, str(Path(__file__).resolve().parent))  # test_record_replay.py, beside this file


@pytest.mark.slow
@pytest.mark.parametrize("name", ["packets.bag", "packets"])  # ROS 1, ROS 2 MCAP
def test_a_bag_of_packets_replays_to_the_live_sweeps_bit_for_bit(tmp_path, name):
    from sim.episode import Episode
    from stack.messages import LidarScan
    from testbed.bags import BagReader
    from testbed.bags import topics as T
    from testbed.cli import main

    bag = tmp_path / name
    assert main(["record", "--bag", str(bag), "--seed", "4", "--duration", "1.0", "--lidar", "packets"]) == 0
    with AnyReader([bag]) as reader:  # rosbags reads it with the definitions the bag carries
        conns = [c for c in reader.connections if c.topic == T.LIDAR_PACKETS]
        assert [c.msgtype for c in conns] == ["velodyne_msgs/msg/VelodyneScan"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
        assert T.LIDAR not in {c.topic for c in reader.connections}
    assert len(msgs) == 10 and all(len(m.packets) == 151 for m in msgs)
    assert all(len(p.data) == 1206 for p in msgs[0].packets)
    with BagReader(bag) as r:
        assert r.lidar_topic == T.LIDAR_PACKETS
        replayed = list(r.scans())
    with Episode(None, seed=4, duration=1.0, camera=False, lidar_packets=True) as ep:
        live = [m for m in ep.frames() if isinstance(m, LidarScan)]
    assert len(live) == len(replayed) == 10
    for a, b in zip(live, replayed):
        assert a.stamp == b.stamp
        for field in ("points", "times_s", "ring", "intensity"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), field


@pytest.mark.slow
def test_packets_and_points_bags_of_one_episode_replay_to_the_same_labels(tmp_path):
    from test_record_replay import oracle_for, short_scenario
    from testbed.record import record_episode
    from testbed.replay import replay_bag

    sc = short_scenario()
    sc.sensors.lidar_packets = True
    out = {}
    for lidar in ("packets", "points"):
        bag = tmp_path / lidar
        summary = record_episode(sc, bag, seed=0, duration=4.0, lidar=lidar)
        rep = replay_bag(bag, tmp_path / f"out_{lidar}", detector=oracle_for(bag), write_outputs=False)
        out[lidar] = (summary["bytes"], rep)
    a, b = out["packets"][1], out["points"][1]
    for key in ("labelled", "false_labels"):
        assert a["labels_summary"][key] == b["labels_summary"][key], key
    la, lb = a["labels_summary"]["map_labels"], b["labels_summary"]["map_labels"]
    assert la and len(la) == len(lb)
    for x, y in zip(la, lb):  # PointCloud2 stores the times as float32: the same labels to well within 0.1 mm
        assert (x["class"], x["object"], x["verdict"], x["observations"]) == \
            (y["class"], y["object"], y["verdict"], y["observations"])
        assert np.allclose(x["label_xyz"], y["label_xyz"], rtol=0, atol=1e-4)
    assert out["packets"][0] < out["points"][0]


@pytest.mark.slow
def test_recording_packets_of_a_sensor_that_publishes_points_is_refused(tmp_path):
    from testbed.bags import BagWriteError, BagWriter
    from sim.episode import Episode
    from stack.messages import LidarScan

    with Episode(None, duration=0.3, camera=False) as ep:
        scan = next(m for m in ep.frames() if isinstance(m, LidarScan))
    with BagWriter(tmp_path / "b", lidar="packets") as w, pytest.raises(BagWriteError, match="carries no VLP-32C"):
        w.write(scan)
