"""Heading of the simulated Jackal's dead reckoning while it turns: the wheel odometry's against the
gyro's (``sim.imu.Gyro``, fused as ``stack.dead_reckoning.DeadReckoning``), for turns in place and
arcs at several commanded yaw rates. Each case: ``--seconds`` of the command after a stop, then the
true turn, the wheel odometry's and the dead reckoning's (wheels' travel, gyro's heading), in
degrees, and the wheel odometry's over-count (its turn / the true turn).

    python benchmarks/bench_dead_reckoning.py [--seed 1] [--seconds 3] [--json benchmarks/results/dead_reckoning.json]

It prints a table; the skid-steer base's wheels slip sideways, most at low yaw rates, so the wheel
odometry's heading is worth little through a corner while the gyro's stays within its bias.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

CASES = [(0.0, 0.5), (0.0, 1.0), (0.0, 1.5), (0.0, 2.0), (0.3, 0.5), (0.3, 1.0), (0.3, 1.5)]


def measure(seed: int, seconds: float) -> list[dict]:
    import pybullet as p

    from sim.episode import Episode
    from sim.imu import Gyro
    from sim.scenario import load_scenario
    from stack.dead_reckoning import DeadReckoning
    from stack.transforms import wrap_angle, yaw_of

    sc = load_scenario("experiment3_columns")
    sc.sensors.lidar = False
    rows = []
    for v, w in CASES:
        with Episode(sc, seed=seed, light=None) as ep:
            dt = ep.dt
            gyro = Gyro(np.random.default_rng([seed, 1]))
            dr = DeadReckoning()
            true = odo = 0.0
            yaw_w, yaw_o = yaw_of(ep.robot.T_world_base()), yaw_of(ep.robot.T_odom_base)
            for _ in range(int(seconds / dt)):
                T_prev = ep.robot.T_odom_base.copy()
                ep.robot.command(v, w, dt)
                p.stepSimulation(physicsClientId=ep.client)
                ep.robot.update_odometry(dt)
                yw, yo = yaw_of(ep.robot.T_world_base()), yaw_of(ep.robot.T_odom_base)
                d_true = wrap_angle(yw - yaw_w)
                true += d_true
                odo += wrap_angle(yo - yaw_o)
                dr.step_wheels(T_prev, ep.robot.T_odom_base, gyro.measure(d_true / dt, dt) * dt)
                yaw_w, yaw_o = yw, yo
            fused = math.degrees(math.atan2(dr.T[1, 0], dr.T[0, 0]))
            rows.append({"v": v, "w_cmd": w, "true_deg": math.degrees(true), "wheels_deg": math.degrees(odo),
                         "wheels_over_true": odo / true if abs(true) > 1e-6 else None,
                         "gyro_deg": fused, "gyro_error_deg": wrap_angle(math.radians(fused) - true) * 180 / math.pi})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/bench_dead_reckoning.py")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = measure(a.seed, a.seconds)
    print(f"{a.seconds:g} s of each command (seed {a.seed}):")
    print("| v (m/s) | w cmd (rad/s) | true turn | wheel odometry | over-count | wheels + gyro | its error |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        oc = "-" if r["wheels_over_true"] is None else f"{r['wheels_over_true']:.2f}x"
        print(f"| {r['v']:.1f} | {r['w_cmd']:.1f} | {r['true_deg']:.1f} deg | {r['wheels_deg']:.1f} deg | {oc} | "
              f"{r['gyro_deg']:.1f} deg | {r['gyro_error_deg']:+.2f} deg |")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"seed": a.seed, "seconds": a.seconds, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
