"""Writes that never leave a half-written file or folder under its final name.

- ``write_bytes`` / ``write_text`` / ``write_json``: a temporary file in the same folder, flushed
  to disk, then ``os.replace`` onto the final name (one step: a reader sees the old file or the
  new one, never part of one).
- ``atomic_path``: the same for writers that need a file name (pandas, matplotlib, numpy).
- ``strict_json``: JSON that strict readers accept: NaN and +-inf become ``null``, numpy scalars
  and arrays become numbers and lists, keys keep their order.
- ``read_user_text``: a file a user named, as text, or one line that says why it cannot be read.
- ``output_dir``: a whole output folder written into a hidden sibling and renamed into place when
  it is complete. Entries of an existing folder that the new run does not write are kept. A
  sibling left by a killed run is finished (if it was complete) or removed on the next start.

The staging names are ``.NAME.partial-PID-*`` (being written), ``.NAME.ready-PID`` (complete,
being moved into place) and ``.NAME.old-PID`` (the folder it replaces); PID is the writer's
process id, so a later run can tell a dead writer's leftovers from a live one's.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from stack.errors import OutputError

_STAGE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>partial|ready|old)-(?P<pid>\d+)(?:-.*)?$")


# --- JSON ---------------------------------------------------------------------------------------

def strict(obj: Any) -> Any:
    """``obj`` with NaN/inf turned into None and numpy types into Python ones (recursively)."""
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, (str, int, float, bool)) and k is not None else k: strict(v)
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def strict_json(obj: Any, indent: int | None = 1, sort_keys: bool = False) -> str:
    """Strict JSON text (``allow_nan=False``): NaN and inf as ``null``; a TypeError names what
    cannot be written."""
    return json.dumps(strict(obj), indent=indent, sort_keys=sort_keys, allow_nan=False)


# --- files ----------------------------------------------------------------------------------------

@contextmanager
def atomic_path(path: str | os.PathLike, mode: int | None = None) -> Iterator[str]:
    """Yield a temporary file name beside ``path`` (same suffix); when the block ends without an
    exception the file is flushed to disk and replaces ``path`` in one step, else it is removed.
    ``mode``: the new file's permissions (default: those of the file it replaces, else 0644)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; expected a file name")
    _make_parent(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    try:
        if mode is None:
            mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
        os.chmod(tmp, mode)  # mkstemp makes it 0600
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, data: Any, indent: int | None = 2, sort_keys: bool = False) -> Path:
    """``data`` as strict JSON (NaN/inf -> null), atomically, with a final newline."""
    return write_text(path, strict_json(data, indent=indent, sort_keys=sort_keys) + "\n")


def read_user_text(path: str | os.PathLike, error: type[Exception], expected: str) -> str:
    """The UTF-8 text of a file a user named; else ``error`` with one line that names the file and
    says what was expected (missing, a folder, unreadable, not UTF-8)."""
    try:
        return Path(path).read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except IsADirectoryError:
        raise error(f"{path}: is a folder; expected {expected}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror}); expected {expected}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.start}); expected {expected}") from None


def nearest_existing(path: str | os.PathLike) -> Path:
    """``path`` itself or the nearest path above it that exists (a folder, or the file in the way)."""
    path = Path(path)
    while not os.path.lexists(path) and path != path.parent:
        path = path.parent
    return path


def _make_parent(path: Path) -> None:
    """``path.parent`` and the folders above it, or an OutputError when a file stands in the way."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise OutputError(f"{path}: {nearest_existing(path.parent)} is a file, not a folder") from None


# --- folders --------------------------------------------------------------------------------------

def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _rmtree(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _commit(ready: Path, final: Path) -> None:
    """Move a complete staging folder to ``final``: entries of the old ``final`` it lacks move
    into it first; the old folder is set aside, the new one renamed into place, the old removed.
    Every step can be repeated after a kill (``clean_stale`` calls this for a dead writer)."""
    pid = _STAGE.match(ready.name)["pid"]
    old = final.parent / f".{final.name}.old-{pid}"
    if final.exists() or final.is_symlink():
        if not final.is_dir() or final.is_symlink():
            raise OutputError(f"{final}: exists and is not a folder; not replacing it")
        for entry in list(final.iterdir()):
            if not os.path.lexists(ready / entry.name):
                os.rename(entry, ready / entry.name)
        if os.path.lexists(old):
            _rmtree(old)
        os.rename(final, old)
    os.rename(ready, final)
    if os.path.lexists(old):
        _rmtree(old)


def staging_entries(final: str | os.PathLike) -> list[tuple[Path, str, int]]:
    """(path, kind, pid) of every staging sibling of ``final``."""
    final = Path(final)
    if not final.parent.is_dir():
        return []
    out = []
    for p in final.parent.iterdir():
        m = _STAGE.match(p.name)
        if m and m["name"] == final.name:
            out.append((p, m["kind"], int(m["pid"])))
    return out


def clean_stale(final: str | os.PathLike) -> list[Path]:
    """Finish or remove what dead writers left beside ``final``; returns what was removed.

    A ``ready`` folder (complete) is moved into place; a ``partial`` one (incomplete) and an
    ``old`` one are removed."""
    final = Path(final)
    removed = []
    entries = sorted(staging_entries(final), key=lambda e: {"ready": 0, "old": 1, "partial": 2}[e[1]])
    for path, kind, pid in entries:
        if _alive(pid) or not os.path.lexists(path):
            continue
        if kind == "ready":  # complete: finish moving it into place
            _commit(path, final)
            continue
        _rmtree(path)
        removed.append(path)
    return removed


@contextmanager
def output_dir(final: str | os.PathLike) -> Iterator[Path]:
    """Yield a hidden staging folder beside ``final``; when the block ends without an exception
    it becomes ``final`` in one rename (entries of an existing ``final`` that were not written
    anew are kept in it). On an exception the staging folder is removed and ``final`` is as it
    was. Leftovers of killed writers are cleaned first (``clean_stale``)."""
    final = Path(final)
    if os.path.lexists(final) and (not final.is_dir() or final.is_symlink()):
        raise OutputError(f"{final}: exists and is not a folder; choose another --out")
    _make_parent(final)
    clean_stale(final)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.partial-{os.getpid()}-", dir=final.parent))
    os.chmod(tmp, 0o755)
    try:
        yield tmp
        ready = final.parent / f".{final.name}.ready-{os.getpid()}"
        if os.path.lexists(ready):
            _rmtree(ready)
        os.rename(tmp, ready)
        tmp = ready
        _commit(ready, final)
    except BaseException:
        if os.path.lexists(tmp):
            _rmtree(tmp)
        raise
