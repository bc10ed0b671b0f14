"""A compressed bag replays to the same labels as its raw twin (the round trips of the compressed
image messages: ``tests/unit/test_compressed_images.py``)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # test_record_replay.py, beside this file


@pytest.mark.slow
def test_compressed_and_raw_bags_replay_to_the_same_labels(tmp_path):
    from test_record_replay import oracle_for, short_scenario
    from testbed.bags import BagReader
    from testbed.bags import topics as T
    from testbed.record import record_episode
    from testbed.replay import replay_bag

    out = {}
    for images in ("raw", "compressed"):
        bag = tmp_path / images
        summary = record_episode(short_scenario(), bag, seed=0, duration=4.0, images=images)
        with BagReader(bag) as r:
            assert (r.rgb_topic, r.depth_topic) == ((T.RGB, T.DEPTH) if images == "raw"
                                                    else (T.RGB_COMPRESSED, T.DEPTH_COMPRESSED))
        det = oracle_for(bag)
        rep = replay_bag(bag, tmp_path / f"out_{images}", detector=det, write_outputs=False)
        out[images] = (summary["bytes"], det.seen, rep["labels_summary"])
    assert out["raw"][1] and out["raw"][1] == out["compressed"][1]  # the same pixels, stamps, intrinsics
    for key in ("labelled", "false_labels"):
        assert out["raw"][2][key] == out["compressed"][2][key], key
    raw_l, comp_l = out["raw"][2]["map_labels"], out["compressed"][2]["map_labels"]
    assert raw_l and len(raw_l) == len(comp_l)
    for a, b in zip(raw_l, comp_l):  # same labels; positions to rounding (KISS-ICP's threads sum in any order)
        assert (a["class"], a["object"], a["verdict"], a["observations"]) == \
            (b["class"], b["object"], b["verdict"], b["observations"])
        assert np.allclose(a["label_xyz"], b["label_xyz"], rtol=0, atol=1e-9)
    assert out["compressed"][0] < out["raw"][0]


@pytest.mark.slow
def test_a_bag_is_the_same_bytes_whichever_process_renders(tmp_path, monkeypatch):
    """``dopeslam record`` renders the camera in a second process; rendered in its own loop the bag
    is the same, file for file and byte for byte."""
    from test_record_replay import short_scenario
    from testbed.record import record_episode

    files = {}
    for worker in ("0", "1"):
        monkeypatch.setenv("DOPESLAM_RENDER_WORKER", worker)
        bag = tmp_path / f"worker_{worker}" / "bag"  # the same name: the MCAP file is named after it
        bag.parent.mkdir()
        record_episode(short_scenario(), bag, seed=0, duration=2.0)
        files[worker] = {p.relative_to(bag): p.read_bytes() for p in sorted(bag.rglob("*")) if p.is_file()}
    assert files["0"] and files["0"].keys() == files["1"].keys()
    for name in files["0"]:
        assert files["0"][name] == files["1"][name], name
