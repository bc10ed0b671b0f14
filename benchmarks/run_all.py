"""Run every ``benchmarks/bench_*.py`` in turn and print their tables.

Each benchmark runs in its own process with its default arguments (so one's threads or renderer do
not colour the next one's timings); the start-up chatter of PyBullet's EGL renderer is filtered out.
The exit status is non-zero when any benchmark failed.

    python benchmarks/run_all.py [--only sim,dope] [--list]
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# printed to stdout by PyBullet's EGL plugin and Mesa when a renderer starts or stops
CHATTER = re.compile(r"^(Loaded EGL|GL_VENDOR|GL_RENDERER|GL_VERSION|GL_SHADING_LANGUAGE_VERSION|Version = |Vendor = |"
                     r"Renderer = |ven = |Destroy EGL|EGL device choice|pybullet build time|argv\[)")


def benchmarks() -> list[Path]:
    return sorted(HERE.glob("bench_*.py"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated names, e.g. sim,dope (bench_<name>.py)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = ap.parse_args(argv)
    found = benchmarks()
    if args.only:
        wanted = {n.strip() for n in args.only.split(",")}
        unknown = wanted - {p.stem.removeprefix("bench_") for p in found}
        if unknown:
            print(f"unknown benchmark(s): {', '.join(sorted(unknown))}; have: "
                  f"{', '.join(p.stem.removeprefix('bench_') for p in found)}", file=sys.stderr)
            return 2
        found = [p for p in found if p.stem.removeprefix("bench_") in wanted]
    if args.list:
        for p in found:
            print(p.stem.removeprefix("bench_"))
        return 0
    failed = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for path in found:
        print(f"== {path.name} ==", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, str(path)], cwd=HERE.parent, env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        for line in proc.stdout:
            if not CHATTER.match(line):
                print(line, end="", flush=True)
        rc = proc.wait()
        status = "ok" if rc == 0 else f"FAILED (exit {rc})"
        print(f"== {path.name}: {status} in {time.perf_counter() - t0:.0f} s ==\n", flush=True)
        if rc != 0:
            failed.append(path.name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
