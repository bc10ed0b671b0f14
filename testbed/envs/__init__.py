"""Gymnasium environments for labelling policies over DOPESLAM episodes.

``import testbed.envs`` registers them; ``gymnasium.make("testbed.envs:DopeSlamLabelling-v0")``
imports and registers in one go.

- ``DopeSlamLabelling-v0``: per camera frame, what each detection does to its object's label, on
  cached perception (thousands of steps per second); ``testbed.envs.labelling``.
- ``DopeSlamActiveLabelling-v0``: the same, live, with the policy also driving the robot
  (velocity commands); ``testbed.envs.active``.
"""
from gymnasium.envs.registration import register, registry

ENV_IDS = {
    "DopeSlamLabelling-v0": "testbed.envs.labelling:DopeSlamLabellingEnv",
    "DopeSlamActiveLabelling-v0": "testbed.envs.active:DopeSlamActiveLabellingEnv",
}

for _id, _entry in ENV_IDS.items():
    if _id not in registry:
        register(id=_id, entry_point=_entry, disable_env_checker=False)
