"""The topological-map paper's navigation end to end (short): a 1.6 m mapping drive at 320 x 240, its
topological map, then a fresh episode that localises by retrieval and drives to the last node (routes,
the pose tracker and the commands' arguments: ``tests/unit/test_topomap_navigate.py``)."""
import json

import numpy as np
import pytest

from helpers import DATA

SCENARIO = str(DATA / "topomap_short.toml")


@pytest.mark.slow
def test_navigate_to_a_node_of_a_short_map(tmp_path, monkeypatch):
    monkeypatch.setenv("DOPESLAM_CACHE", str(tmp_path / "cache"))
    from stack.loops.place_recognition import VocabularyTree
    from testbed.topomap.navigate import build_map, navigate
    from testbed.topomap.stream import camera_stream

    stream = camera_stream(SCENARIO)
    assert stream.info.width == 320 and len(stream) == 81
    topo = build_map(stream)
    assert len(topo) >= 3 and topo.meta["segments"][0]["start_frame"] == 0
    # a small vocabulary from the mapping run's own nodes (the bundled one takes minutes to build)
    tree = VocabularyTree.train([n.place_desc for n in topo.nodes if n.place_desc is not None], branching=4, depth=3)
    topo.save(tmp_path / "map")
    report = navigate("Mustard", SCENARIO, tmp_path / "nav", seed=5, topo=topo, stream=stream, tree=tree,
                      target_node=len(topo) - 1, max_seconds=20)
    saved = json.loads((tmp_path / "nav" / "navigate.json").read_text())
    assert saved["final_distance_m"] == pytest.approx(report["final_distance_m"])
    assert report["reached"]
    assert report["final_distance_m"] < 0.5
    assert 0.8 < report["path_length_m"] < 3.0
    assert report["localisation"]["accepted"] >= 3
    assert np.isfinite(report["distance_to_object_m"])
    assert (tmp_path / "nav" / "navigate.png").exists()
