"""One cell in its own process (``python -m testbed.testing.worker SPEC.json``), so that a crash of
the simulator or renderer fails that cell only. SPEC: {"scenario", "seed", "options", "out_dir",
"result"}; the report is written to ``result`` (JSON, temp file then rename)."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from testbed.testing.jsonout import dumps
    from testbed.testing.options import run_one

    spec = json.loads(Path(argv[0]).read_text())
    result = Path(spec["result"])
    try:
        data = {"report": run_one(spec["scenario"], int(spec["seed"]), spec["options"], spec["out_dir"])}
    except Exception as exc:  # the cell's error, for the JUnit file; the traceback goes to the log
        logging.getLogger(__name__).exception("cell failed")
        data = {"error": f"{type(exc).__name__}: {exc}"}
    tmp = result.with_name(result.name + ".tmp")
    tmp.write_text(dumps(data))
    os.replace(tmp, result)
    return 0 if "report" in data else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
