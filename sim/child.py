"""Child processes of this package (the render worker, the harness's detector process): the
environment they start in and how they are stopped."""
from __future__ import annotations

import os


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
