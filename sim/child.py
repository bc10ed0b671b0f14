"""Child processes of this package (the render worker, the harness's detector process): the
environment they start in and how they are stopped; and the C library's memory settings its processes
run with (:func:`reuse_freed_memory`)."""
from __future__ import annotations

import ctypes
import os
import sys
import traceback

# glibc malloc's settings (mallopt parameter, value), by the environment variable glibc reads them from:
# no trimming of the heap's top below 256 MB, the heap grown 64 MB at a time, and allocations up to 32 MB
# (the largest mmap threshold glibc takes on 64-bit) from the heap rather than mapped one by one
_MALLOC_SETTINGS = {"MALLOC_TRIM_THRESHOLD_": (-1, 256 << 20), "MALLOC_TOP_PAD_": (-2, 64 << 20),
                    "MALLOC_MMAP_THRESHOLD_": (-3, 32 << 20)}


def reuse_freed_memory() -> bool:
    """Have glibc's malloc keep the memory this process frees for its next allocations, and the child
    processes it starts afterwards do the same (through the environment). Images, LiDAR sweeps and the
    network's activations are arrays of 0.5-5 MB made and dropped at every frame; by default glibc maps
    each from the kernel and hands it back when freed, so every frame faults fresh zeroed pages in. The
    results are the same bytes; the process keeps its peak heap instead of returning it. Nothing is
    changed where any of the variables is already set (the user's choice) or the C library is not glibc.
    True when the settings were applied."""
    if any(k in os.environ for k in _MALLOC_SETTINGS):
        return False
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):
            return False
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError, ValueError):  # not glibc, or no confstr name for it
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    if not all([mallopt(param, value) for param, value in _MALLOC_SETTINGS.values()]):
        return False
    os.environ.update({name: str(value) for name, (_, value) in _MALLOC_SETTINGS.items()})  # the children's
    return True


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
    reuse_freed_memory()  # inherited from a parent that applied them; applied here for any other
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
