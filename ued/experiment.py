"""What a `TrainConfig` builds: the EnvConfig and levels of its scenarios, and its learner.

Every consumer of a config (the drivers in `workers`, `tabx eval`, `tabx levels sample`, the
run folder's policy loader) builds these the same way, through this module.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp

from tabx.params import EnvConfig, EnvParams, stack_levels
from ued.config import ConfigError, TrainConfig
from ued.learners import make_learner
from ued.learners.ppo import PPOLearner
from ued.registry import learner_entry


def scenario_levels(config: TrainConfig) -> tuple[EnvConfig, list[EnvParams]]:
    """The EnvConfig that fits every scenario of the config, and one level per scenario
    (playing the config's behaviour profile)."""
    from tabx.profiles import with_profile
    from tabx.scenarios import ScenarioError, config_for, load_named

    scenarios = []
    for name in config.env.scenario:
        try:
            scenarios.append(load_named(name))
        except ScenarioError as err:
            raise ConfigError(f"env.scenario: {err}") from None
    env_config = config_for(scenarios, max_steps=config.env.max_steps)
    return env_config, [with_profile(s.to_level(env_config), config.env.profile)
                        for s in scenarios]


def training_levels(config: TrainConfig) -> tuple[EnvConfig, EnvParams]:
    """The batch of `num_envs` levels: the scenarios in turn (env i plays scenario i mod n)."""
    env_config, levels = scenario_levels(config)
    n = config.learner.num_envs
    batch = stack_levels([levels[i % len(levels)] for i in range(n)])
    return env_config, jax.tree.map(jnp.asarray, batch)


def learner_for(config: TrainConfig, env_config: EnvConfig | None = None) -> PPOLearner:
    """The (per-process cached) learner of a config (its `ued.registry` entry says which
    config section, beside `learner`, it reads)."""
    if env_config is None:
        env_config = scenario_levels(config)[0]
    settings = learner_entry(config.algorithm).settings
    q = None if settings is None else getattr(config, settings)
    return make_learner(config.algorithm, env_config, config.learner, config.env.team,
                        config.env.opponent, q=q)


def seed_keys(seeds: Sequence[int]) -> jax.Array:
    """One PRNG key per seed, stacked on a leading axis: entry i is `jax.random.key(seeds[i])`,
    the key a single-seed run of that seed starts its key chain from."""
    return jax.random.wrap_key_data(jnp.stack([jax.random.key_data(jax.random.key(s))
                                               for s in seeds]))


@jax.jit
def split_seed_keys(keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`key, k = jax.random.split(key)` of every seed's key chain at once (keys stacked on a
    leading seed axis, `seed_keys`): (the chains' next keys, the keys to use now)."""
    pairs = jax.vmap(jax.random.split)(keys)
    return pairs[:, 0], pairs[:, 1]


def check_devices(config: TrainConfig) -> None:
    """ConfigError if this machine has fewer devices than `learner.num_devices` asks for."""
    from ued.learners.ppo import local_devices

    try:
        local_devices(config.learner.num_devices)
    except ValueError as err:
        raise ConfigError(str(err)) from None


__all__ = ["check_devices", "learner_for", "scenario_levels", "seed_keys",
           "split_seed_keys", "training_levels"]
