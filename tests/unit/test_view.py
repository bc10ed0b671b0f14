"""The live view: its options, and messages built by hand logged into a file-backed Rerun recording
and read back (a short episode: ``tests/e2e/test_view_e2e.py``)."""
import numpy as np
import pytest

pytest.importorskip("rerun")

from testbed.view import RerunView, ViewError, make_view, read_recording  # noqa: E402


def test_make_view_checks_its_options(tmp_path):
    assert make_view(None, None) is None
    with pytest.raises(ViewError, match="expected a file name ending in .rrd"):
        make_view(None, str(tmp_path / "x.txt"))
    with pytest.raises(ViewError, match="expected rerun"):
        make_view("foxglove", None)


def test_detections_and_store_round_trip(tmp_path):
    """Messages built by hand: what is logged is what the file holds."""
    from types import SimpleNamespace

    from stack.messages import CameraFrame, CameraInfo, Detection, LidarScan

    path = tmp_path / "hand.rrd"
    view = RerunView(spawn=False, save=str(path), recording_id="hand")
    truth = SimpleNamespace(objects=[], T_world_base_at=lambda t: np.eye(4))
    view.start(truth, None, "hand-built")
    scan = LidarScan(0.1, np.random.default_rng(0).random((50, 3)), np.zeros(50))
    view.scan(scan, np.eye(4), scan.points)
    info = CameraInfo(64, 48, np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]))
    frame = CameraFrame(0.15, info, rgb=np.zeros((48, 64, 3), np.uint8))
    kp = np.array([[10, 10], [20, 10], [20, 20], [10, 20], [12, 12], [18, 12], [18, 18], [12, 18], [15, 15.0]])
    dets = [Detection("Cookies", 0.15, np.eye(4), kp, np.ones(9), 12.0, fpr_pass=True),
            Detection("Yogurt", 0.15, np.eye(4), kp + 5, np.ones(9), 1.0, fpr_pass=False)]
    view.image(frame, dets, [True, False])
    view.close()
    rec = read_recording(path)
    assert rec["/camera/image/detections"]["rows"] == 1
    assert rec["/world/lidar/scan"]["rows"] == 1 and rec["/world/robot/estimate"]["rows"] == 1
    assert {"Boxes2D:labels", "Boxes2D:colors"} <= rec["/camera/image/detections"]["components"]


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="the display check is Linux's")
def test_no_display_and_no_viewer_is_one_line_and_the_spawn_is_this_recording_s(monkeypatch, tmp_path):
    """Without a screen the viewer would start, fail to open a window and quit, and the run would end
    in a traceback once the stream gave up (15 s later). With one, the viewer is spawned for this
    recording: ``rr.spawn()`` without it asks the global recording, which is off, and does nothing."""
    import rerun as rr

    import testbed.view as view

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(view, "_viewer_listening", lambda port=view.VIEWER_PORT: False)
    with pytest.raises(ViewError, match="^no display to open the Rerun viewer on .* use --view-save FILE.rrd"):
        RerunView(spawn=True)
    spawned = []

    def spawn(*, connect=True, hide_welcome_screen=False, port=9876, recording=None):
        spawned.append(recording)

    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(rr, "spawn", spawn)
    monkeypatch.setattr(rr, "GrpcSink", lambda: rr.FileSink(str(tmp_path / "viewer.rrd")))  # no viewer here
    live = RerunView(spawn=True)
    live.close()
    assert spawned == [live.rec]
