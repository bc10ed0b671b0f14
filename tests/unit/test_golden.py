"""The golden-output comparison (``tests/golden_record.py``) finds any change. (``dopeslam run`` and
the gym env's perception cache fuse every detection with the same pose:
``tests/e2e/test_golden_e2e.py``.)
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import golden_record  # tests/golden_record.py, a script (tests/ is on sys.path: tests/conftest.py)

# --- the comparison finds every kind of difference --------------------------------------------------


def _recording(root: Path, labels: str = '{"objects": []}', xyz=(1.0, 2.0, 3.0), fps: float = 10.0) -> Path:
    for sub in ("run", "replay"):
        d = root / sub
        d.mkdir(parents=True)
        (d / "labels.json").write_text(labels)
        (d / "estimate_tum.txt").write_text("0.0 0 0 0 0 0 0 1\n")
        (d / "groundtruth_tum.txt").write_text("0.0 0 0 0 0 0 0 1\n")
        (d / "report.json").write_text(json.dumps({"detection": {"frames": 3, "fps": fps}, "labels": []}))
    cache = root / "cache"
    cache.mkdir()
    np.savez(cache / "scene-seed0-rgb-abc.npz", det_xyz=np.array([xyz]), frame_detect_s=np.array([fps]),
             frame_T_map_base=np.full((1, 4, 4), np.nan))
    (cache / "scene-seed0-rgb-abc.thumbs.npz").write_bytes(b"")
    (cache / "scene-seed0-rgb-abc.json").write_text(json.dumps({"frames": 1, "detections": 1}))
    return root


def test_identical_recordings_compare_equal_and_timings_are_ignored(tmp_path):
    a = _recording(tmp_path / "a")
    b = _recording(tmp_path / "b", fps=99.0)  # fps and detection seconds: wall clock, not results
    assert golden_record.compare(a, b) == []  # NaN poses (frames before the first scan) equal NaN


def test_a_changed_label_file_report_value_or_cache_array_is_named(tmp_path):
    a = _recording(tmp_path / "a")
    b = _recording(tmp_path / "b", labels='{"objects": [1]}', xyz=(1.0, 2.0, 3.0 + 1e-15))
    (b / "replay" / "report.json").write_text(json.dumps({"detection": {"frames": 4}, "labels": []}))
    diffs = golden_record.compare(a, b)
    assert "run/labels.json: differs" in diffs and "replay/labels.json: differs" in diffs
    assert "replay/report.json: 'detection' differs" in diffs
    assert any(d.startswith("cache: array 'det_xyz' differs") for d in diffs)
    assert len(diffs) == 4, diffs
