"""The gym snippet of docs/install.md runs as written in a fresh interpreter: Gymnasium's
``module:EnvId`` form imports ``testbed.envs``, which registers the ids."""
import os
import re
import subprocess
import sys

from helpers import ROOT


def snippet() -> str:
    text = (ROOT / "docs" / "install.md").read_text()
    m = re.search(r"<!-- gym-snippet -->\s*```python\n(.*?)```", text, re.S)
    assert m, "docs/install.md: the gym snippet (after <!-- gym-snippet -->) is missing"
    return m.group(1)


def test_the_documented_snippet_runs_in_a_fresh_interpreter():
    code = snippet()
    assert "import testbed" not in code  # Gymnasium itself imports the module
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("DopeSlamLabelling-v0 (16, "), r.stdout


def test_short_ids_need_the_module_first():
    code = ("import gymnasium\n"
            "try:\n    gymnasium.spec('DopeSlamLabelling-v0')\nexcept gymnasium.error.Error:\n    print('unregistered')\n"
            "import testbed.envs\n"
            "print(gymnasium.spec('DopeSlamLabelling-v0').entry_point, gymnasium.spec('DopeSlamActiveLabelling-v0').id)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[:2] == ["unregistered",
                                        "testbed.envs.labelling:DopeSlamLabellingEnv DopeSlamActiveLabelling-v0"]
