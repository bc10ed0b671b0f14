"""The harness's writes: the same atomic helpers as the stack (``stack.io``), plus the checks an
output path must pass before any work starts.

- ``check_new_output``: refuse (``OutputError``) to write over an existing path unless ``force``,
  and never over an input, whatever ``force`` says.
- ``check_output_path``: that an output can be made where it was asked for (no file in the way of
  a folder, no folder in the way of a file, a writable folder above it), checked before the work
  whose results it would hold.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable

from stack.errors import OutputError
from stack.io import (atomic_path, clean_stale, nearest_existing, output_dir, staging_entries, strict, strict_json,
                      write_bytes, write_json, write_text)

__all__ = ["atomic_path", "check_new_output", "check_output_path", "clean_stale", "edited_objects", "output_dir",
           "same_or_inside", "staging_entries", "strict", "strict_json", "write_bytes", "write_json", "write_text"]


def same_or_inside(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether path ``a`` is ``b`` or lies inside it, or ``b`` lies inside ``a`` (resolved)."""
    ra, rb = Path(a).resolve(), Path(b).resolve()
    return ra == rb or rb in ra.parents or ra in rb.parents


def check_new_output(path: str | os.PathLike, option: str, force: bool = False,
                     inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """``path`` checked as a new output named by ``option`` (e.g. ``--results-bag``): never an
    input (or inside one, or holding one), and not an existing path unless ``force``."""
    path = Path(path)
    for src in inputs:
        if same_or_inside(path, src):
            raise OutputError(f"{option} {path}: is (or holds, or lies inside) the input {src}; "
                              "choose another path")
    if os.path.lexists(path) and not force:
        raise OutputError(f"{option} {path}: exists already; pass --force to replace it")
    return path


def check_output_path(path: str | os.PathLike, option: str, kind: str = "folder") -> None:
    """Before any work starts: ``path`` can be written as a ``kind`` ("folder" or "file"). It is not
    something of the other kind already, and the nearest folder above it that exists is a folder
    this process can create entries in (tried: an empty hidden folder made and removed); else an
    OutputError naming the option."""
    path = Path(path)
    where = f"{option} {path}"
    if kind == "folder" and os.path.lexists(path) and not path.is_dir():
        raise OutputError(f"{where}: exists and is not a folder; choose another")
    if kind == "file" and path.is_dir():
        raise OutputError(f"{where}: is a folder; expected a file name")
    parent = nearest_existing(path.parent)
    if not parent.is_dir():
        raise OutputError(f"{where}: {parent} is a file, not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".dopeslam-write-check-", dir=parent))
    except OSError as exc:
        raise OutputError(f"{where}: cannot write in {parent} ({exc.strerror})") from None


def edited_objects(out_dir: str | os.PathLike) -> list:
    """The rows marked ``edited`` in an output folder's ``labels.json`` and ``labels.xlsx`` (the
    spreadsheet's win where both have one object), to keep through a rerun into that folder. A
    store file there that does not parse raises ``ObjectStoreError`` (one line: file, row, column),
    before any work starts, and the folder is left as it is."""
    from stack.object_store import read_objects

    kept: dict[int, object] = {}
    for name in ("labels.json", "labels.xlsx"):
        path = Path(out_dir) / name
        if path.is_file():
            for obj in read_objects(path):
                if obj.edited:
                    kept[obj.id] = obj
    return list(kept.values())
