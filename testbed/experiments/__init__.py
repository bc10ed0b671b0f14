"""The paper's experiments, the darkness sweep and the faults sweep (``dopeslam experiment NAME``).

Each module has ``run(out_dir, **options)``, ``table(result)`` and ``APPLIES``: the config sections
(``detector``) and keys (``store.gate_m``) it honours from ``--config`` / ``--set`` / the environment;
any other setting changed from its default is refused before anything runs.
"""
from __future__ import annotations

# what every episode experiment honours of the config ([run] and the policy come from its own options)
EPISODE_APPLIES = {"detector", "odometry", "evidence", "store.gate_m", "store.evidence_gate", "retire", "components"}


def episode_config(config, input_mode: str, stages: int, weights, policy: str | None = None):
    """``config`` (a ``testbed.settings.RunConfig``, or None: the stack as shipped, None back) with the
    experiment's detector input, stages and weights (and labelling policy, when given) set."""
    if config is None:
        return None
    detector = config.detector.model_copy(update={"input": input_mode, "stages": stages, "weights": weights})
    update = {"detector": detector}
    if policy is not None:
        update["store"] = config.store.model_copy(update={"policy": policy})
    return config.model_copy(update=update)
