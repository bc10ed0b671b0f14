"""The labelling envs' test scene and helpers, shared by tests/e2e/test_gym_env.py and
tests/unit/test_gym_env_unit.py. DOPE is replaced by a noisy ground-truth double
(tests/labelling_double.py)."""
from helpers import DATA
from labelling_double import NoisyOracle
from testbed.envs.policies import make_policy, run_episode
from testbed.envs.slots import RewardConfig

SCENE = str(DATA / "labelling_small.toml")
DURATION = 6.0
DETECTOR_ID = "test-noisy-oracle-v1"


def env_kwargs(cache, **kw):
    base = dict(scenario=SCENE, seeds=[0, 1], duration=DURATION, detector_factory=NoisyOracle,
                detector_id=DETECTOR_ID, detector_stages=range(1, 7), cache_dir=str(cache), renderer="tiny")
    base.update(kw)
    return base


def cost_of_score(r, reward=RewardConfig()):
    """The env's cost recomputed from ``score_map``'s verdicts on the final map."""
    rows, labels = r["labels"], r["map_labels"]
    matched = [m for m in labels if m["verdict"] != "phantom"]
    return (sum(m["error_m"] + (reward.false_label_penalty if m["verdict"] == "misplaced" else 0.0) for m in matched)
            + reward.missing_cost_m * sum(row["id"] is None for row in rows)
            + reward.extra_label_penalty * sum(m["verdict"] == "phantom" for m in labels))


def run_policy(env, name, episode):
    return run_episode(env, make_policy(name, env), options={"episode": episode})
