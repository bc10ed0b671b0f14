"""The live view: a short episode logged into a file-backed Rerun recording and read back (messages
built by hand and the view's options: ``tests/unit/test_view.py``)."""
import pytest

pytest.importorskip("rerun")

from testbed.view import make_view, read_recording  # noqa: E402

SCENE = "tests/data/labelling_small.toml"


@pytest.mark.slow
def test_a_short_episode_logged_and_read_back(tmp_path):
    from testbed.oracle_detector import OracleDetector
    from testbed.progress import watching
    from testbed.run import run_episode

    path = tmp_path / "episode.rrd"
    view = make_view(None, str(path), recording_id="test")
    with watching(view):
        report = run_episode(SCENE, str(tmp_path / "run"), seed=0, duration=2.0, detector=OracleDetector(),
                             write_outputs=False)
    rec = read_recording(path)
    images = report["detection"]["frames"]
    assert images > 0
    assert rec["/camera/image"]["rows"] == images and rec["/camera/image/detections"]["rows"] == images
    scans = rec["/world/lidar/scan"]["rows"]
    assert scans == rec["/world/robot/estimate"]["rows"] == rec["/world/robot/truth"]["rows"] > 5
    assert "sim_time" in rec["/world/lidar/scan"]["timelines"]
    assert sum(1 for k in rec if k.startswith("/world/lidar/map/")) == (scans + 4) // 5  # every 5th sweep
    assert rec["/world/objects/truth"]["static"] and "Boxes3D:labels" in rec["/world/objects/truth"]["components"]
    assert rec["/world/objects/map"]["rows"] >= 1  # the store, during the run and at the end
    if report["labels_summary"]["map_labels"]:
        assert rec["/world/objects/verdicts"]["rows"] == 1
