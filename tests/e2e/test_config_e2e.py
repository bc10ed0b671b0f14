"""A short run's config.toml and provenance (the config's layers, errors and reference:
``tests/unit/test_config.py``)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers import ROOT
from helpers.config import NO_ENV
from stack.config import resolve_config
from testbed.settings import RunConfig


@pytest.mark.slow
def test_short_run_writes_config_and_provenance(tmp_path):
    out = tmp_path / "run"
    cfg = tmp_path / "c.yaml"
    cfg.write_text("detector:\n  every: 5\nevidence:\n  min_observations: 2\n")
    r = subprocess.run([sys.executable, "-m", "testbed.cli", "run", "--duration", "4", "--seed", "1", "--out", str(out),
                        "--config", str(cfg), "--set", "evidence.min_span_s=0.5"],
                       capture_output=True, text=True, cwd=ROOT, env={**_env(), "DOPESLAM_STORE__GATE_M": "0.4"},
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    written = resolve_config(out / "config.toml", None, NO_ENV, RunConfig)
    assert (written.detector.every, written.evidence.min_observations, written.evidence.min_span_s) == (5, 2, 0.5)
    assert written.store.gate_m == 0.4 and written.run.seed == 1 and written.run.duration == 4
    report = json.loads((out / "report.json").read_text())
    p = report["provenance"]
    assert {"version", "git_commit", "weights_sha256", "fpr_thresholds_sha256", "scenario_sha256", "seed",
            "command"} <= set(p)
    from stack.dope_fpr import default_thresholds_path, default_weights, file_sha256

    assert p["weights_sha256"] == file_sha256(default_weights("rgb"))
    assert p["fpr_thresholds_sha256"] == file_sha256(default_thresholds_path("rgb"))
    assert p["seed"] == 1 == report["seed"] and len(p["scenario_sha256"]) == 64
    assert "--config" in p["command"] and p["version"]
    n_images = report["detection"]["frames"]
    assert 0 < n_images <= 10  # every 5th image of ~4 s at 10 Hz


def _env() -> dict:
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("DOPESLAM_")}
    env["DOPESLAM_TORCH_THREADS"] = "1"
    return env
