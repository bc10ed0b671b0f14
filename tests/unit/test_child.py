"""How the package's child processes start and end (``sim.child``): what a child prints is not lost to
its quick exit, an error ends it with status 1 and its traceback, ``SystemExit`` keeps its status; the
memory settings a process applies reach the children it starts, and a user's own settings win."""
import os
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


def _settings_run(code: str, **extra_env) -> str:
    env = {k: v for k, v in package_env().items() if not k.startswith("MALLOC_")}
    env.update(extra_env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60,
                          check=True).stdout.strip()


def test_memory_settings_apply_once_and_reach_the_children():
    if not os.confstr("CS_GNU_LIBC_VERSION"):
        import pytest

        pytest.skip("not glibc: the settings are glibc's")
    code = ("import os, subprocess, sys; from sim.child import reuse_freed_memory; "
            "print(reuse_freed_memory(), reuse_freed_memory()); "
            "print(subprocess.run([sys.executable, '-c', 'import os; print(os.environ.get(\"MALLOC_TOP_PAD_\"))'], "
            "capture_output=True, text=True).stdout.strip())")
    first, child = _settings_run(code).splitlines()
    assert first == "True False"  # applied, then already in place
    assert child == str(64 << 20)


def test_a_users_own_memory_setting_is_left_alone():
    code = ("import os; from sim.child import reuse_freed_memory; print(reuse_freed_memory()); "
            "print(os.environ.get('MALLOC_TOP_PAD_'), os.environ.get('MALLOC_MMAP_THRESHOLD_'))")
    applied, values = _settings_run(code, MALLOC_TOP_PAD_="4096").splitlines()
    assert applied == "False" and values == "4096 None"
