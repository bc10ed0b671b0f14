"""The command line's conventions: --version, a parser that imports no simulator, network or
odometry, every option's default in --help, progress bars only where asked, and stdout free of
the simulator's banner."""
import json
import os
import subprocess
import sys

import pytest

from helpers import ROOT

HEAVY = ("pybullet", "torch", "kiss_icp", "gtsam", "rerun", "cv2", "pandas", "gymnasium", "sim")


def _python(code: str, **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=120, **kw)


def test_version():
    from importlib.metadata import version

    r = _python("import sys; from testbed.cli import main; sys.exit(main(['--version']))")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"dopeslam {version('dopeslam-testbed')}"


def test_building_the_parser_imports_nothing_heavy():
    r = _python("import json, sys; from testbed.cli import build_parser; p = build_parser(); p.format_help(); "
                "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))")
    assert r.returncode == 0, r.stderr
    loaded = set(json.loads(r.stdout))
    assert not loaded & set(HEAVY), f"building the parser imported {sorted(loaded & set(HEAVY))}"
    assert "numpy" not in loaded


def _subcommands(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                yield from ((f"{name} {n}", s) for n, s in _subcommands(sub))


def test_every_option_shows_its_default():
    import argparse

    from testbed.cli import build_parser

    missing = []
    for name, sub in _subcommands(build_parser()):
        formatter = sub._get_formatter()
        for action in sub._actions:
            if not action.option_strings or action.help == argparse.SUPPRESS or action.default == argparse.SUPPRESS:
                continue
            if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
                continue
            text = formatter._get_help_string(action) or ""
            if "default" not in text.lower():
                missing.append(f"{name} {action.option_strings[0]}")
    assert not missing, "options without a default in --help: " + ", ".join(missing)


def test_help_text_is_complete():
    from testbed.cli import build_parser

    text = build_parser().format_help()
    assert "--version" in text and "--quiet" in text
    assert "dopeslam run" in text and "ground truth" in text  # the description is whole, not one cut line
    run = dict(_subcommands(build_parser()))["run"].format_help()
    assert "(default: out/run)" in run and "--view" in run and "--view-save" in run


def test_quiet_after_the_command_and_before():
    from testbed.cli import build_parser

    p = build_parser()
    assert p.parse_args(["run", "--quiet"]).quiet is True
    assert p.parse_args(["-q", "run"]).quiet is True
    assert p.parse_args(["run"]).quiet is False


def test_progress_bars_only_on_a_terminal(monkeypatch):
    from testbed import progress

    monkeypatch.delenv("DOPESLAM_PROGRESS", raising=False)
    try:
        progress.configure(quiet=False)
        assert not progress.enabled()  # pytest's stderr is not a terminal
        monkeypatch.setenv("DOPESLAM_PROGRESS", "1")
        assert progress.enabled()
        progress.configure(quiet=True)
        assert not progress.enabled()
    finally:
        progress.configure(quiet=True)


def test_seconds_bar_reports_an_eta(monkeypatch, capsys):
    from testbed import progress

    monkeypatch.setenv("DOPESLAM_PROGRESS", "1")
    progress.configure(quiet=False)
    try:
        bar = progress.SecondsBar(10.0, "episode")
        for t in (1.0, 2.5, 5.0):
            bar.update_to(t, images=3)
        assert bar._bar.n == pytest.approx(5.0)
        bar.close()
    finally:
        progress.configure(quiet=True)
    err = capsys.readouterr().err
    assert "episode" in err and "5.0/10.0 s" in err and "<" in err  # elapsed<remaining


def test_loop_closure_without_gtsam_is_one_line(monkeypatch):
    r = _python("import sys; sys.modules['gtsam'] = None\n"  # as if not installed
                "from testbed.commands.run import check_loop_closure\n"
                "sys.exit(check_loop_closure(True, 'run'))")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'dopeslam-testbed[loops]'" in lines[0], r.stderr


def test_a_reader_that_has_gone_ends_the_command_quietly():
    """``dopeslam scenes | head -0``: stdout's reader has gone before the command prints. No
    traceback, nothing on stderr, and the status a shell gives a writer that SIGPIPE stopped."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "testbed.cli", "scenes"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=ROOT, env=env)
    proc.stdout.close()  # before the child has started: its first print finds no reader
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert err == "", err


def test_simulator_banner_goes_to_stderr():
    """What every command runs inside: PyBullet's banner (C-level stdout) goes to stderr, Python's
    prints still to stdout."""
    code = ("import sys\nfrom testbed.cli import main, c_stdout_to_stderr\n"
            "with c_stdout_to_stderr():\n"
            "    import pybullet as p\n"
            "    cid = p.connect(p.DIRECT)\n"
            "    print('result line')\n"
            "    p.disconnect(cid)\n")
    r = _python(code)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "result line\n", r.stdout
    assert "pybullet build time" in r.stderr  # the banner went to stderr, not away
