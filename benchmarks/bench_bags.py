"""Rosbag record and replay: recording overhead, replay speed of a 60 s bag, and its size.

1. Recording overhead: the default scenario's driving phase (start pause removed) for ``--duration``
   simulated seconds, run ``--repeats`` times without and with recording (interleaved), in wall and
   CPU seconds (CPU: every thread of this process and its children, e.g. the render worker, so it is
   the cost on an otherwise idle machine). Target: recording adds <= 20 %.
2. Size: the default episode (``--bag-seconds``, 60 s) recorded with the default format (ROS 2,
   MCAP, zstd chunks), total and per topic.
3. Replay: ``replay_bag`` on that bag with the real DOPE detector (the shipped weights), both passes
   at the same time (default) and one after the other; wall seconds per second of data. Target <= 1x.

    python benchmarks/bench_bags.py [--duration 10] [--repeats 2] [--bag-seconds 60] [--keep DIR [--reuse-bag]]
                                    [--skip-overhead] [--skip-dope] [--dope-every N] [--modes parallel,sequential]
                                    [--json benchmarks/results/bags.json]

Wall times depend on what else runs: the load average is printed before and after.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np


def driving_scenario(name: str | None = None):
    from sim.scenario import load_scenario

    sc = load_scenario(name)
    return sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})


def _cpu_now() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def episode_once(sc, duration: float, bag: Path | None) -> dict:
    """One episode, iterated to the end, recorded into ``bag`` when given."""
    from sim.episode import Episode
    from testbed.bags import BagWriter, bag_size
    from testbed.record import EpisodeRecorder

    w0, c0 = time.perf_counter(), _cpu_now()
    with Episode(sc, seed=0, duration=duration) as ep:
        if bag is None:
            for _ in ep.frames():
                pass
            rec_wall = rec_cpu = 0.0
            size = 0
        else:
            with BagWriter(bag) as writer:
                rec = EpisodeRecorder(writer, ep)
                for msg in ep.frames():
                    rec.write(msg)
                rec.finish()
                t_close, c_close = time.perf_counter(), time.thread_time()
            rec_wall = rec.seconds + time.perf_counter() - t_close
            rec_cpu = rec.cpu_seconds + time.thread_time() - c_close
            size = bag_size(bag)
        sim_s = ep.sim_seconds
    return {"wall_s": time.perf_counter() - w0, "cpu_s": _cpu_now() - c0, "sim_s": sim_s,
            "recording_wall_s": rec_wall, "recording_cpu_s": rec_cpu, "bytes": size}


def bench_overhead(duration: float, repeats: int, tmp: Path) -> dict:
    sc = driving_scenario()
    plain, recorded = [], []
    episode_once(sc, 1.0, tmp / "warmup")  # imports, type compilation, renderer start-up
    shutil.rmtree(tmp / "warmup", ignore_errors=True)
    for i in range(repeats):
        plain.append(episode_once(sc, duration, None))
        print(f"  plain episode {i + 1}: {plain[-1]['wall_s']:.1f} s wall", file=sys.stderr)
        bag = tmp / f"overhead_{i}"
        recorded.append(episode_once(sc, duration, bag))
        shutil.rmtree(bag, ignore_errors=True)
        print(f"  recorded episode {i + 1}: {recorded[-1]['wall_s']:.1f} s wall", file=sys.stderr)

    def med(rows, key):
        return float(np.median([r[key] for r in rows]))

    out = {"duration_s": duration, "repeats": repeats, "plain": plain, "recorded": recorded}
    for key in ("wall_s", "cpu_s"):
        out[f"plain_{key}"], out[f"recorded_{key}"] = med(plain, key), med(recorded, key)
        out[f"overhead_{key}_pct"] = 100 * (out[f"recorded_{key}"] / out[f"plain_{key}"] - 1)
    out["recording_cpu_s"] = med(recorded, "recording_cpu_s")
    out["recording_cpu_pct"] = 100 * out["recording_cpu_s"] / out["plain_cpu_s"]
    out["recording_wall_s"] = med(recorded, "recording_wall_s")
    out["recording_wall_pct"] = 100 * out["recording_wall_s"] / out["plain_wall_s"]
    return out


def bench_size(seconds: float, bag: Path) -> dict:
    from rosbags.highlevel import AnyReader

    from testbed.record import record_episode

    summary = record_episode(None, bag, seed=0, duration=seconds)
    raw: Counter[str] = Counter()
    with AnyReader([bag]) as reader:
        for conn, _, data in reader.messages():
            raw[conn.topic] += len(data)
    summary["raw_bytes_by_topic"] = dict(raw.most_common())
    summary["raw_bytes"] = int(sum(raw.values()))
    return summary


def bench_replay(bag: Path, out: Path, parallel: bool, skip_dope: bool, dope_every: int = 1) -> dict:
    from testbed.replay import replay_bag

    detector = _NoDetections() if skip_dope else None
    c0 = _cpu_now()
    report = replay_bag(bag, out, detector=detector, parallel=parallel, dope_every=dope_every)
    cpu = _cpu_now() - c0
    return {"parallel": parallel, "dope": not skip_dope, "dope_every": dope_every, "bag_seconds": report["bag_seconds"],
            "wall_s": report["wall_seconds"], "cpu_s": cpu,
            "wall_per_bag_s": report["wall_seconds"] / report["bag_seconds"],
            "cpu_per_bag_s": cpu / report["bag_seconds"], "time_split_s": report["time_split_s"],
            "frames": report["detection"]["frames"], "poses": report["odometry"]["poses"],
            "labels": len(report["labels"])}


class _NoDetections:
    """For ``--skip-dope`` only: times reading, odometry and fusion without the network."""

    def detect(self, frame):
        return []


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per overhead episode")
    ap.add_argument("--repeats", type=int, default=2, help="overhead episodes of each kind")
    ap.add_argument("--bag-seconds", type=float, default=60.0, help="length of the size/replay bag")
    ap.add_argument("--keep", default=None, help="keep the bag and replay outputs in this folder")
    ap.add_argument("--skip-overhead", action="store_true")
    ap.add_argument("--reuse-bag", action="store_true", help="with --keep: replay the bag an earlier run left there")
    ap.add_argument("--skip-dope", action="store_true", help="replay without DOPE (e.g. no weights yet)")
    ap.add_argument("--modes", default="parallel,sequential", help="replay modes to time ('' for none)")
    ap.add_argument("--dope-every", type=int, default=1, help="replay: DOPE on every N-th image")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    cpus = sorted(os.sched_getaffinity(0))
    load0 = os.getloadavg()
    print(f"bench_bags: CPUs usable {len(cpus)} {cpus}; load average before {load0[0]:.2f} (1 min)")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_bags_"))
    work.mkdir(parents=True, exist_ok=True)
    results: dict = {"cpus": cpus, "load_before": load0}
    try:
        if not args.skip_overhead:
            o = bench_overhead(args.duration, args.repeats, work)
            results["overhead"] = o
            print()
            print(f"Recording overhead: default scenario driving, {args.duration:g} s simulated, "
                  f"median of {args.repeats}")
            print("| run | wall s | CPU s |")
            print("|---|---:|---:|")
            print(f"| episode | {o['plain_wall_s']:.1f} | {o['plain_cpu_s']:.1f} |")
            print(f"| episode + recording | {o['recorded_wall_s']:.1f} | {o['recorded_cpu_s']:.1f} |")
            print(f"| added | {o['overhead_wall_s_pct']:+.1f} % | {o['overhead_cpu_s_pct']:+.1f} % |")
            print(f"recording's own time: {o['recording_cpu_s']:.2f} CPU s = {o['recording_cpu_pct']:.1f} % of the "
                  f"episode's CPU; {o['recording_wall_s']:.2f} wall s = {o['recording_wall_pct']:.1f} % of its wall "
                  f"(target <= 20 %)")
        bag = work / "default_episode"
        if args.reuse_bag and (work / "size.json").exists() and bag.exists():
            s = json.loads((work / "size.json").read_text())  # recorded by an earlier run with --keep
        else:
            shutil.rmtree(bag, ignore_errors=True)
            s = bench_size(args.bag_seconds, bag)
            (work / "size.json").write_text(json.dumps(s, indent=2))
        results["size"] = s
        print()
        print(f"Bag of the default episode ({s['sim_seconds']:g} s, {s['format']}): {s['bytes'] / 1e6:.0f} MB "
              f"({s['bytes'] / 1e6 / s['sim_seconds']:.1f} MB/s; {s['raw_bytes'] / 1e6:.0f} MB of messages, "
              f"compressed to {100 * s['bytes'] / s['raw_bytes']:.0f} %); recorded in {s['wall_seconds']:.0f} s wall")
        print("| topic | messages | MB (uncompressed) |")
        print("|---|---:|---:|")
        for topic, n in s["raw_bytes_by_topic"].items():
            print(f"| {topic} | {s['messages'][topic]} | {n / 1e6:.1f} |")
        results["replay"] = []
        print()
        dope = "without DOPE" if args.skip_dope else "DOPE with the shipped weights" + \
            (f" on every {args.dope_every}th image" if args.dope_every > 1 else "")
        print(f"Replay of that bag ({dope}):")
        print("| passes | wall s | wall s / bag s | CPU s / bag s | odometry s | DOPE s | reading s |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for mode in [m for m in args.modes.split(",") if m]:
            r = bench_replay(bag, work / f"replay_{mode}", mode == "parallel", args.skip_dope, args.dope_every)
            results["replay"].append(r)
            ts = r["time_split_s"]
            print(f"| {'at the same time' if r['parallel'] else 'one after the other'} | {r['wall_s']:.1f} | "
                  f"{r['wall_per_bag_s']:.2f} | {r['cpu_per_bag_s']:.2f} | {ts['odometry']:.1f} | {ts['dope']:.1f} | "
                  f"{ts['odometry_reading'] + ts['image_reading']:.1f} |")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    load1 = os.getloadavg()
    results["load_after"] = load1
    print(f"load average after: {load1[0]:.2f}")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(results, indent=2, default=float))
        os.replace(tmp, path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
