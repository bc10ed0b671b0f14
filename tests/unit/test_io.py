"""Atomic writes, strict JSON and whole output folders (stack.io, testbed.io)."""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from stack.errors import DopeSlamError, OutputError
from stack.io import (atomic_path, clean_stale, output_dir, read_user_text, staging_entries, strict_json, write_json,
                      write_text)
from testbed.io import check_new_output, check_output_path


def test_strict_json_has_no_nan_or_infinity():
    doc = {"a": math.nan, "b": [1.0, math.inf, -math.inf], "c": np.float64("nan"), "d": np.arange(3),
           "e": np.int64(4), "f": np.bool_(True), "g": {"h": np.array([0.5, np.nan])}}
    text = strict_json(doc)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [1.0, None, None], "c": None, "d": [0, 1, 2], "e": 4, "f": True,
                                "g": {"h": [0.5, None]}}


def test_write_json_replaces_in_one_step_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "r.json"
    write_json(p, {"x": 1})
    write_json(p, {"x": float("nan")})
    assert json.loads(p.read_text()) == {"x": None}
    assert sorted(q.name for q in tmp_path.iterdir()) == ["r.json"]
    assert oct(p.stat().st_mode & 0o777) == "0o644"


def test_failed_write_keeps_the_old_file(tmp_path):
    p = tmp_path / "a.txt"
    write_text(p, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("disk full")
    assert p.read_text() == "old"
    assert [q.name for q in tmp_path.iterdir()] == ["a.txt"]
    with pytest.raises(TypeError):
        write_json(p, {"x": object()})
    assert p.read_text() == "old"


def test_output_dir_appears_whole_and_keeps_other_entries(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "report.json").write_text("{}")
    with output_dir(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".run.partial-")
        (tmp / "report.json").write_text('{"new": 1}')
        assert json.loads((out / "report.json").read_text()) == {}  # not visible before the end
    assert json.loads((out / "report.json").read_text()) == {"new": 1}
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_output_dir_failure_leaves_the_old_folder(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(ValueError):
        with output_dir(out) as tmp:
            (tmp / "report.json").write_text("{}")
            raise ValueError("crash")
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_output_dir_refuses_a_file(tmp_path):
    f = tmp_path / "run"
    f.write_text("a file of the user's")
    with pytest.raises(OutputError, match="not a folder"):
        with output_dir(f):
            pass
    assert f.read_text() == "a file of the user's"
    assert issubclass(OutputError, DopeSlamError)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_siblings_of_a_killed_writer_are_finished_or_removed(tmp_path):
    out = tmp_path / "run"
    pid = _dead_pid()
    partial = tmp_path / f".run.partial-{pid}-abc"
    partial.mkdir()
    (partial / "half.bin").write_bytes(b"x")
    clean_stale(out)
    assert not partial.exists() and not out.exists()
    # killed after the folder was complete, between setting the old one aside and the rename
    ready, old = tmp_path / f".run.ready-{pid}", tmp_path / f".run.old-{pid}"
    ready.mkdir()
    (ready / "report.json").write_text("{}")
    old.mkdir()
    (old / "report.json").write_text("old")
    clean_stale(out)
    assert (out / "report.json").read_text() == "{}"
    assert staging_entries(out) == []


def test_a_live_writers_staging_folder_is_left_alone(tmp_path):
    out = tmp_path / "run"
    mine = tmp_path / f".run.partial-{os.getpid()}-x"
    mine.mkdir()
    clean_stale(out)
    assert mine.exists()


def test_check_new_output(tmp_path):
    bag = tmp_path / "field.bag"
    bag.write_bytes(b"data")
    with pytest.raises(OutputError, match="input"):
        check_new_output(bag, "--results-bag", force=True, inputs=[bag])
    with pytest.raises(OutputError, match="input"):
        check_new_output(tmp_path, "--results-bag", force=True, inputs=[bag])
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(OutputError, match="--force"):
        check_new_output(other, "--results-bag", inputs=[bag])
    assert check_new_output(other, "--results-bag", force=True, inputs=[bag]) == other
    assert check_new_output(tmp_path / "new", "--results-bag", inputs=[bag]) == tmp_path / "new"


def test_a_file_in_the_way_of_an_output_is_named(tmp_path):
    blocker = tmp_path / "notes"
    blocker.write_text("the user's")
    for target in (blocker / "run", blocker / "a" / "b" / "run"):
        with pytest.raises(OutputError, match=f"{blocker} is a file, not a folder"):
            with output_dir(target):
                pass
        with pytest.raises(OutputError, match=f"{blocker} is a file, not a folder"):
            write_text(target / "x.json", "{}")
    folder = tmp_path / "report.json"
    folder.mkdir()
    with pytest.raises(OutputError, match="is a folder; expected a file name"):
        write_text(folder, "{}")
    assert blocker.read_text() == "the user's" and folder.is_dir() and not any(folder.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes", "report.json"]  # no staging left


def test_check_output_path(tmp_path):
    blocker = tmp_path / "notes"
    blocker.write_text("x")
    (tmp_path / "runs").mkdir()
    check_output_path(tmp_path / "runs", "--out")  # an existing folder
    check_output_path(tmp_path / "new" / "deeper" / "run", "--out")  # folders made later
    check_output_path(tmp_path / "new" / "junit.xml", "--junit", "file")
    check_output_path(blocker, "--store", "file")  # an existing file, replaced later
    with pytest.raises(OutputError, match=r"^--out .*notes: exists and is not a folder"):
        check_output_path(blocker, "--out")
    with pytest.raises(OutputError, match=r"^--junit .*runs: is a folder; expected a file name"):
        check_output_path(tmp_path / "runs", "--junit", "file")
    with pytest.raises(OutputError, match=r"^--out .*notes/a/b: .*notes is a file, not a folder"):
        check_output_path(blocker / "a" / "b", "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes", "runs"]  # the check leaves nothing
    if os.path.isdir("/proc/self"):  # a folder nobody can create entries in, even root
        with pytest.raises(OutputError, match=r"^--out /proc/dopeslam-run: cannot write in /proc"):
            check_output_path("/proc/dopeslam-run", "--out")


def test_read_user_text(tmp_path):
    class Bad(DopeSlamError):
        pass

    good = tmp_path / "a.toml"
    good.write_text("name = 'caf\u00e9'\n", encoding="utf-8")
    assert read_user_text(good, Bad, "a TOML file") == "name = 'caf\u00e9'\n"
    latin = tmp_path / "b.toml"
    latin.write_bytes("name = 'caf\u00e9'\n".encode("latin-1"))
    for path, says in ((tmp_path / "missing.toml", "file not found"), (tmp_path, "is a folder; expected a TOML file"),
                       (latin, r"not UTF-8 text \(byte 11\); expected a TOML file")):
        with pytest.raises(Bad, match=f"^{re.escape(str(path))}: {says}"):
            read_user_text(path, Bad, "a TOML file")
