"""How the package's child processes start and end (``sim.child``): what a child prints is not lost to
its quick exit, an error ends it with status 1 and its traceback, ``SystemExit`` keeps its status."""
import subprocess
import sys
import textwrap

from sim.child import child_command, package_env


def _run(tmp_path, body: str, *args: str) -> subprocess.CompletedProcess:
    (tmp_path / "childmod.py").write_text(textwrap.dedent(body))
    env = package_env()
    env["PYTHONPATH"] = f"{tmp_path}{':' + env['PYTHONPATH'] if env.get('PYTHONPATH') else ''}"
    return subprocess.run(child_command("childmod", "main", *args), capture_output=True, text=True, env=env,
                          timeout=60)


def test_buffered_output_reaches_the_parent(tmp_path):
    done = _run(tmp_path, """
        import sys
        def main():
            sys.stdout.write("out " + sys.argv[1] + "\\n")  # a pipe: block-buffered, not yet written
            sys.stderr.write("err\\n")
        """, "arg1")
    assert done.returncode == 0
    assert done.stdout == "out arg1\n"
    assert done.stderr == "err\n"


def test_an_error_ends_the_child_with_status_1_and_its_traceback(tmp_path):
    done = _run(tmp_path, """
        def main():
            print("before")
            raise RuntimeError("no weights here")
        """)
    assert done.returncode == 1
    assert done.stdout == "before\n"
    assert "RuntimeError: no weights here" in done.stderr and "Traceback" in done.stderr


def test_system_exit_keeps_its_status(tmp_path):
    assert _run(tmp_path, "import sys\ndef main():\n    sys.exit(3)\n").returncode == 3
    assert _run(tmp_path, "import sys\ndef main():\n    sys.exit()\n").returncode == 0
    done = _run(tmp_path, "import sys\ndef main():\n    sys.exit('bad input')\n")
    assert done.returncode == 1 and done.stderr == "bad input\n"


def test_the_command_runs_this_interpreter():
    cmd = child_command("sim.render", "_render_worker_main", "7")
    assert cmd[0] == sys.executable and cmd[-1] == "7"
