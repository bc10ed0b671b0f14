"""``--json``: only JSON on stdout. While the command runs, everything written to stdout (Python's
prints and the renderer's C-level chatter on file descriptor 1) goes to stderr instead; the JSON
is written to the real stdout at the end."""
from __future__ import annotations

import contextlib
import json
import math
import os
import sys


def _clean(v):
    """NaN and infinities become null (JSON has no NaN); numpy numbers become plain ones."""
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items() if not str(k).startswith("_")}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if hasattr(v, "item") and callable(v.item) and getattr(v, "ndim", 1) == 0:
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def dumps(data) -> str:
    return json.dumps(_clean(data), indent=1, default=str, allow_nan=False)


@contextlib.contextmanager
def stdout_to_stderr(enabled: bool = True):
    """Inside: stdout (fd 1 and ``sys.stdout``) goes to stderr. Yields a function that writes
    one JSON document to the real stdout."""
    if not enabled:
        yield lambda data: print(dumps(data))
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    real = os.fdopen(os.dup(saved), "w")
    old = sys.stdout
    sys.stdout = sys.stderr
    out = []
    try:
        yield out.append
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved, 1)
        os.close(saved)
        sys.stdout = old
        for data in out:
            real.write(dumps(data) + "\n")
        real.close()
