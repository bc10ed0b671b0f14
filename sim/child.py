"""Child processes of this package (the render worker, the harness's detector process): the
environment they start in and how they are stopped."""
from __future__ import annotations

import os
import sys
import traceback


def child_command(module: str, function: str, *args: str) -> list[str]:
    """The command line of a child that runs ``module.function()`` (with ``args`` in its ``sys.argv``)
    under :func:`run_child`."""
    code = f"from sim.child import run_child; from {module} import {function}; run_child({function})"
    return [sys.executable, "-c", code, *args]


def run_child(main) -> None:
    """Run a child's ``main()``, then end the process at once: its replies are written and flushed by
    then, and the interpreter's own clean-up (torch's, EGL's) would keep the parent waiting for a
    third of a second or more per child. An exception is printed, and the exit status is 1."""
    status = 0
    try:
        main()
    except SystemExit as exc:  # as Python ends on it: an int is the status, anything else is printed
        status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if exc.code is not None and not isinstance(exc.code, int):
            print(exc.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - printed where the parent's logs go, as Python would
        traceback.print_exc()
        status = 1
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    os._exit(status)


def package_env() -> dict:
    """This process's environment, with the folder this package was imported from first on
    PYTHONPATH, so a child imports the same code wherever the parent found it."""
    env = dict(os.environ)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(x for x in (root, env.get("PYTHONPATH", "")) if x)
    return env


def stop_child(proc, replies, shm) -> None:
    """Stop a child that exits at the end of its requests (its stdin closed; killed if it has not
    within 10 s), close its reply pipe, and free the shared memory this process created for it.
    Any of them may be None (already stopped, or never started)."""
    if proc is not None:
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=10)
        except Exception:  # noqa: BLE001 - a child that will not stop is killed
            proc.kill()
            proc.wait()
    if replies is not None:
        replies.close()
    if shm is not None:
        shm.close()
        shm.unlink()


class ChildOwner:
    """``close()`` (and the same when collected) for an object that keeps its child process in
    ``_proc``, the child's reply pipe in ``_replies`` and the shared memory it created in ``_shm``:
    :func:`stop_child` on them, once."""

    def close(self) -> None:
        proc, replies, shm = (getattr(self, k, None) for k in ("_proc", "_replies", "_shm"))
        self._proc = self._replies = self._shm = None
        stop_child(proc, replies, shm)

    def __del__(self):
        self.close()
