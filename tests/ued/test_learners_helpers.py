"""Shared builders for the learner tests (no tests of its own): a tiny 2 archers v 1 farmer
scenario file, a tiny training config on it, and the matching learner and level batch.

Every test that trains uses `tiny_config()` unchanged where it can, so all of them share one
compiled update (the learner is cached per process by its static settings).
"""

from __future__ import annotations

import functools
import math
import tempfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from tabx.params import EnvConfig, EnvParams, make_level, repeat_level
from ued.config import TrainConfig, apply_overrides, config_from_dict

ENV_CONFIG = EnvConfig(max_allies=2, max_enemies=1, max_zones=0, max_steps=8)
TINY = {
    "algorithm": "mappo",
    "seed": 3,
    "env": {"team": "ally", "opponent": "random", "max_steps": 8},
    "learner": {"num_envs": 4, "num_steps": 16, "total_timesteps": 256, "hidden_dim": 16,
                "num_minibatches": 2, "update_epochs": 2},
    "run": {"checkpoint_every": 1, "keep_checkpoints": 2},
}


def duel_level(ally_x: float = -12.0, farmer_health: float = 60.0,
               config: EnvConfig = ENV_CONFIG) -> EnvParams:
    """2 archers facing +x; a farmer above them, out of their field of view."""
    return make_level(
        config,
        [dict(unit="archer", position=(ally_x, -4.0), heading=0.0),
         dict(unit="archer", position=(ally_x, 4.0), heading=0.0)],
        [dict(unit="farmer", position=(-8.0, 18.0), heading=math.pi, health=farmer_health)])


@functools.lru_cache(maxsize=1)
def scenario_file() -> str:
    """The duel as a scenario file (written once per test session)."""
    from tabx.scenarios import level_to_scenario, save_scenario

    folder = Path(tempfile.mkdtemp(prefix="tabx-learner-tests-"))
    path = folder / "duel2a1f.json"
    save_scenario(path, level_to_scenario(duel_level(), name="duel2a1f"))
    return str(path)


def tiny_config(**overrides: Any) -> TrainConfig:
    data = apply_overrides({**TINY, "env": {**TINY["env"], "scenario": scenario_file()},
                            "run": {**TINY["run"], "dir": tempfile.gettempdir()}},
                           [f"{k}={v}" for k, v in overrides.items()])
    return config_from_dict(data, source="tiny config")


def tiny_learner():
    from ued.experiment import learner_for

    return learner_for(tiny_config())


def tiny_levels() -> EnvParams:
    return jax.tree.map(jnp.asarray, repeat_level(duel_level(), TINY["learner"]["num_envs"]))


def restore_both_and_compare(full: Path, part: Path, template: Any,
                             key_template: Any = None) -> tuple[Any, int]:
    """Restore the newest checkpoints of two run folders (`full` and `part`) against
    `template` (and `key_template`: a multi-seed run's keys), assert that their train states
    and keys are equal bit for bit, and return (train state of `full`, its update)."""
    import numpy as np

    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR

    with Checkpoints(full / CHECKPOINT_DIR) as a, Checkpoints(part / CHECKPOINT_DIR) as b:
        state_a, key_a, n_a = a.restore(template, key_template=key_template)
        state_b, key_b, n_b = b.restore(template, key_template=key_template)
    assert n_a == n_b
    for x, y in zip(jax.tree.leaves(state_a), jax.tree.leaves(state_b), strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    assert np.array_equal(jax.random.key_data(key_a), jax.random.key_data(key_b))
    return state_a, n_a


def learning_duel(max_steps: int = 64) -> tuple[EnvConfig, EnvParams]:
    """The learning tests' battle: two archers face +x, a farmer stands above them, outside
    their field of view."""
    config = EnvConfig(max_allies=2, max_enemies=1, max_zones=0, max_steps=max_steps)
    return config, make_level(
        config,
        [dict(unit="archer", position=(-12.0, -4.0), heading=0.0),
         dict(unit="archer", position=(-12.0, 4.0), heading=0.0)],
        [dict(unit="farmer", position=(-8.0, 18.0), heading=math.pi)])


# bfloat16 keeps 8 significant bits: rounding an input to it is exact to a relative 2**-8.
BFLOAT16_STEP = 2.0**-8


def rounding_bound(ppo: Any, updates: int = 1) -> float:
    """How far two correct computations of the same PPO updates may leave a parameter apart
    when they add the same products in another order (a batch split over devices, seeds
    vmapped side by side): the bound the cross-program tests compare against, derived from the
    arithmetic rather than measured on one CPU.

    The two programs sum in float32 in another order, so an activation may differ in its last
    float32 bit, and a last bit may round a bfloat16 matrix-product input to the neighbouring
    bfloat16 value: a relative change of up to 2**-8 in that product. Adam moves a parameter by
    `lr` times a ratio of its gradient's moments, which a relative change r of the gradient
    moves by at most r; so each of the update's `update_epochs x num_minibatches` optimizer
    steps may differ by `lr x 2**-8`, and the differences add. (float32 products land far
    inside it; bfloat16 was measured at 1-7 % of it on an Intel Xeon and an AMD EPYC.) A wrong
    split (a shard's gradient left out, or not averaged) changes whole Adam steps, `lr` per
    step: 256 times the bound.

    It holds while both programs play the same episodes: later updates, whose rollouts follow
    the slightly different parameters, can sample another action and part further; tests
    compare a single update from the same state."""
    return updates * ppo.update_epochs * ppo.num_minibatches * ppo.lr * BFLOAT16_STEP
