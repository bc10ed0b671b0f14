"""Steps per second of ``DopeSlamLabelling-v0`` in cached mode (target: at least 2,000 on 2 cores).

    python benchmarks/bench_gym_env.py [--scenario S] [--seconds 3] [--detector dope|double]

The episode's perception is built first if it is not cached (minutes with DOPE). ``--detector
double`` uses the noisy ground-truth test double of the test suite instead of DOPE (for machines
without trained weights; the step rate depends on the number of detections per frame, not on
where they come from). Measured through ``gymnasium.make`` (with its wrappers), one env, each
policy choosing the action; ``random`` samples the action space. Prints a table of steps per wall
second and per CPU second of this process (the rate one free core gives, when others share them).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gymnasium

import testbed.envs  # noqa: F401
from testbed.envs.policies import BASELINES, make_policy

ROOT = Path(__file__).resolve().parents[1]


def env_for(args):
    kw = dict(scenario=args.scenario, seeds=[args.seed], duration=args.duration, cache_dir=args.cache,
              stage_choice=args.stage_choice)
    if args.detector == "double":
        sys.path.insert(0, str(ROOT / "tests"))
        from labelling_double import NoisyOracle

        kw.update(detector_factory=NoisyOracle, detector_id="test-noisy-oracle-v1", detector_stages=range(1, 7))
    return gymnasium.make("DopeSlamLabelling-v0", **kw)


def measure(env, policy, seconds: float) -> tuple[float, int, float]:
    """(steps per wall second, steps, steps per CPU second of this process)."""
    actions = [env.action_space.sample() for _ in range(256)]
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        obs, info = env.reset(options={"episode": 0})
        if policy is not None:
            policy.reset()
        done = False
        while not done:
            a = actions[n % 256] if policy is None else policy(obs, info)
            obs, r, term, trunc, info = env.step(a)
            n += 1
            done = term or trunc
    return n / (time.perf_counter() - t0), n, n / max(time.process_time() - c0, 1e-9)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--detector", choices=["dope", "double"], default="dope")
    p.add_argument("--cache", default=None)
    p.add_argument("--seconds", type=float, default=3.0, help="time per policy")
    p.add_argument("--stage-choice", action="store_true", help="with the stage-count action")
    args = p.parse_args(argv)

    env = env_for(args)
    t0 = time.perf_counter()
    env.reset(options={"episode": 0})
    load_s = time.perf_counter() - t0
    replay = env.unwrapped.replay
    n_det = sum(int(replay.frame(k, replay.default_stage)[2] - replay.frame(k, replay.default_stage)[1])
                for k in range(replay.n_frames))
    env.action_space.seed(0)
    print(f"episode: {replay.perception.spec.scenario} seed {replay.perception.spec.seed}, {replay.n_frames} frames, "
          f"{n_det} detections at {replay.default_stage} stages ({args.detector}); load/build {load_s:.1f} s")
    print(f"{'policy':<14} {'steps/s':>9} {'steps/cpu-s':>12} {'steps':>8}")
    rates, cpu_rates = {}, {}
    for name in ["random"] + list(BASELINES):
        rate, n, cpu_rate = measure(env, None if name == "random" else make_policy(name, env), args.seconds)
        rates[name], cpu_rates[name] = rate, cpu_rate
        print(f"{name:<14} {rate:>9.0f} {cpu_rate:>12.0f} {n:>8d}")
    worst = min(rates, key=rates.get)
    print(f"slowest: {worst} at {rates[worst]:.0f} steps/s wall, {cpu_rates[worst]:.0f} per CPU second "
          f"(target >= 2000): {'ok' if rates[worst] >= 2000 else 'BELOW'} "
          "(wall rates fall when other processes share the cores; the CPU-second rate is what one free core gives)")
    env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
