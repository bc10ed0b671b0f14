"""The processes that only detect start without the spreadsheet libraries: openpyxl is loaded where an
object store is written or read, not where one is merely named, and pandas nowhere in the stack."""
from __future__ import annotations

import subprocess
import sys


def loaded_after(code: str) -> set[str]:
    probe = code + "\nimport sys\nprint(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_detector_processes_import_no_spreadsheet_library():
    mods = loaded_after("import testbed.detection_process, testbed.replay_detection, stack.dope_fpr, stack.pipeline")
    assert "torch" in mods  # the probe did load what a detector process loads
    assert not {"pandas", "openpyxl"} & mods


def test_writing_and_reading_a_store_loads_openpyxl_only(tmp_path):
    path = tmp_path / "objects.xlsx"
    mods = loaded_after(f"""
from stack.object_store import ObjectStore, read_objects
ObjectStore().save({str(path)!r})
assert read_objects({str(path)!r}) == []
""")
    assert "openpyxl" in mods and "pandas" not in mods
