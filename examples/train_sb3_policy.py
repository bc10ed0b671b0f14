"""Train a small labelling policy with Stable-Baselines3 (PPO) on the cached env and report it
against the baselines on held-out seeds.

    pip install -e '.[rl]'
    python examples/train_sb3_policy.py --timesteps 50000 --out out/sb3

The policy sees what the baselines see (the ``slots`` and ``pose`` observation, never the ground
truth in ``info``) and is trained on ``--train-seeds`` episodes, then evaluated with the
baselines on ``--eval-seeds``. The first use of each episode caches its perception (minutes with
DOPE). ``--detector double`` replaces DOPE with the test suite's noisy ground-truth double, for
machines without trained weights (then the figures say nothing about DOPE).

``run(...)`` is the same as the command line, for scripts and the test suite.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def env_kwargs(scenario, seeds, duration, detector, cache, renderer="auto") -> dict:
    kw = dict(scenario=scenario, seeds=list(seeds), duration=duration, cache_dir=cache, renderer=renderer)
    if detector == "double":
        sys.path.insert(0, str(ROOT / "tests"))
        from labelling_double import NoisyOracle

        kw.update(detector_factory=NoisyOracle, detector_id="test-noisy-oracle-v1", detector_stages=range(1, 7))
    return kw


class SB3Policy:
    """A trained model as a policy for ``testbed.envs.policies.run_episode``."""

    name = "ppo"

    def __init__(self, model, vecnorm):
        self.model, self.vecnorm = model, vecnorm

    def reset(self) -> None:
        pass

    def __call__(self, obs, info):
        o = {k: v[None] for k, v in obs.items()}
        if self.vecnorm is not None:
            o = self.vecnorm.normalize_obs(o)
        action, _ = self.model.predict(o, deterministic=True)
        return action[0]


def save_policy(model, venv, out: Path) -> None:
    """The policy network's weights (torch tensors, loadable with weights_only=True) and the observation
    normalisation as JSON: no pickled objects (SB3's own save pickles parts of the model)."""
    import torch

    torch.save(model.policy.state_dict(), out / "ppo_policy.pt")
    stats = {k: {"mean": rms.mean.tolist(), "var": rms.var.tolist(), "count": float(rms.count)}
             for k, rms in venv.obs_rms.items()}
    (out / "obs_normalisation.json").write_text(json.dumps({"clip_obs": venv.clip_obs, "epsilon": venv.epsilon,
                                                            "stats": stats}))


def slot_set_extractor():
    """A features extractor that embeds every object slot with one shared MLP (the slot's row and the
    robot's pose in, 32 features out), so what the policy learns about one slot (e.g. "a detection FPR
    rejected should not move the label") holds for all of them. Built lazily: torch and SB3 are optional."""
    import torch
    from torch import nn
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class SlotSetExtractor(BaseFeaturesExtractor):
        def __init__(self, observation_space, embed: int = 32):
            n, f = observation_space["slots"].shape
            p = observation_space["pose"].shape[0]
            super().__init__(observation_space, features_dim=n * embed + p)
            self.phi = nn.Sequential(nn.Linear(f + p, 64), nn.ReLU(), nn.Linear(64, embed), nn.ReLU())

        def forward(self, obs):
            slots, pose = obs["slots"], obs["pose"]
            b, n, _ = slots.shape
            x = torch.cat([slots, pose[:, None, :].expand(b, n, pose.shape[1])], dim=-1)
            return torch.cat([self.phi(x).reshape(b, -1), pose], dim=-1)

    return SlotSetExtractor


def run(scenario=None, train_seeds=range(0, 8), eval_seeds=range(8, 10), timesteps: int = 50_000,
        duration: float | None = None, detector: str = "dope", cache=None, out="out/sb3", n_envs: int = 2,
        seed: int = 0, verbose: int = 0, renderer: str = "auto", arch: str = "mlp") -> dict:
    """``arch``: 'slots' (one MLP shared by every object slot, :func:`slot_set_extractor`) or 'mlp' (SB3's
    default flat MLP over the whole observation)."""
    try:
        from stable_baselines3 import PPO
        from stable_baselines3.common.env_util import make_vec_env
        from stable_baselines3.common.vec_env import VecNormalize
    except ImportError as e:
        raise SystemExit("this example needs Stable-Baselines3: pip install -e '.[rl]'") from e
    import gymnasium

    import testbed.envs  # noqa: F401
    from testbed.envs.policies import BASELINES, make_policy, run_episode

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    train_kw = env_kwargs(scenario, train_seeds, duration, detector, cache, renderer)
    # cache every training episode once, in this process, before the workers start
    probe = gymnasium.make("DopeSlamLabelling-v0", **train_kw)
    for i in range(len(probe.unwrapped.episodes)):
        probe.reset(options={"episode": i})
    probe.close()

    venv = make_vec_env("DopeSlamLabelling-v0", n_envs=n_envs, seed=seed, env_kwargs={**train_kw, "build": False})
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True)
    if arch == "slots":
        policy_kwargs = {"features_extractor_class": slot_set_extractor(), "net_arch": {"pi": [], "vf": [64]}}
    elif arch == "mlp":
        policy_kwargs = {"net_arch": [128, 128]}
    else:
        raise ValueError(f"arch: expected 'slots' or 'mlp', got {arch!r}")
    model = PPO("MultiInputPolicy", venv, n_steps=256, batch_size=256, learning_rate=3e-4, gamma=0.99,
                ent_coef=0.01, policy_kwargs=policy_kwargs, seed=seed, verbose=verbose, device="cpu")
    t0 = time.perf_counter()
    model.learn(total_timesteps=int(timesteps))
    train_s = time.perf_counter() - t0
    venv.training = False
    save_policy(model, venv, out)

    eval_env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(scenario, eval_seeds, duration, detector, cache,
                                                                   renderer))
    policies = {"ppo": SB3Policy(model, venv)}
    policies.update({n: make_policy(n, eval_env) for n in BASELINES})
    rows = {n: [] for n in policies}
    for i in range(len(eval_env.unwrapped.episodes)):
        for name, pol in policies.items():
            r = run_episode(eval_env, pol, options={"episode": i})
            rows[name].append(r["summary"] | {"return": r["return"]})

    def stat(name, key, scale=1.0):
        v = [scale * r[key] for r in rows[name] if r[key] is not None]
        return (float(np.mean(v)), float(np.std(v))) if v else (None, None)

    report = {"arch": arch, "timesteps": int(timesteps), "train_seconds": train_s, "train_seeds": list(train_seeds),
              "eval_seeds": list(eval_seeds), "detector": detector, "scenario": scenario, "policies": {}}
    print(f"trained PPO for {timesteps} steps in {train_s:.0f} s ({timesteps / train_s:.0f} steps/s); "
          f"evaluated on seeds {list(eval_seeds)}")
    print(f"{'policy':<14} {'error cm':>14} {'labels':>11} {'false':>11} {'missing':>11} {'precision':>11} "
          f"{'return':>13}")
    for name in policies:
        e, f, m, ret = stat(name, "mean_error_m", 100), stat(name, "false_labels"), stat(name, "missing"), stat(name, "return")
        n, prec = stat(name, "labels_in_map"), stat(name, "map_precision")
        report["policies"][name] = {"mean_error_cm": e, "labels_in_map": n, "false_labels": f, "missing": m,
                                    "map_precision": prec, "return": ret}

        def fmt(x, d=1):
            return "-" if x[0] is None else f"{x[0]:.{d}f} ± {x[1]:.{d}f}"
        print(f"{name:<14} {fmt(e):>14} {fmt(n):>11} {fmt(f, 2):>11} {fmt(m, 2):>11} {fmt(prec, 2):>11} "
              f"{fmt(ret, 2):>13}")
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default=None)
    p.add_argument("--train-seeds", type=int, nargs="+", default=list(range(0, 8)))
    p.add_argument("--eval-seeds", type=int, nargs="+", default=[8, 9])
    p.add_argument("--timesteps", type=int, default=50_000)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--detector", choices=["dope", "double"], default="dope")
    p.add_argument("--cache", default=None)
    p.add_argument("--out", default="out/sb3")
    p.add_argument("--n-envs", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--arch", choices=["slots", "mlp"], default="mlp",
                   help="slots: one MLP shared by every object slot; mlp: a flat MLP over the whole observation")
    a = p.parse_args(argv)
    run(a.scenario, a.train_seeds, a.eval_seeds, a.timesteps, a.duration, a.detector, a.cache, a.out, a.n_envs, a.seed,
        arch=a.arch)
    return 0


if __name__ == "__main__":
    sys.exit(main())
