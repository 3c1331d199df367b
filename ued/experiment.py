"""What a `TrainConfig` builds: the EnvConfig and levels of its scenarios, and its learner.

Every consumer of a config (the drivers in `workers`, `tabx eval`, `tabx levels sample`, the
run folder's policy loader) builds these the same way, through this module.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from tabx.params import EnvConfig, EnvParams, stack_levels
from ued.config import ConfigError, TrainConfig
from ued.learners import make_learner
from ued.learners.ppo import PPOLearner
from ued.registry import learner_class


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
    """The (per-process cached) learner of a config, with its own settings section if its
    class has one (`TrainConfig.learner_settings`)."""
    if env_config is None:
        env_config = scenario_levels(config)[0]
    return make_learner(config.algorithm, env_config, config.learner, config.env.team,
                        config.env.opponent, settings=config.learner_settings())


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


def memory_floor(config: TrainConfig, env_config: EnvConfig, level: EnvParams) -> int:
    """Bytes a run needs at least: every env's level and state, and (PPO learners) the
    observations of a whole rollout, `num_envs x num_steps` of them. Shapes only
    (`jax.eval_shape`): nothing is allocated or compiled. Networks, optimiser state,
    activations and a Q-learner's replay buffer come on top."""
    from tabx.env import TabxEnv
    size = lambda tree: sum(int(np.prod(x.shape)) * x.dtype.itemsize
                            for x in jax.tree.leaves(tree))
    if env_config not in _ENV_BYTES:  # tracing takes about a second; a config's shapes fixed
        env = TabxEnv(env_config)
        state = jax.eval_shape(env.initial_state, level)
        _ENV_BYTES[env_config] = (size(state), size(jax.eval_shape(env.observe, state, level)))
    state_bytes, obs_bytes = _ENV_BYTES[env_config]
    learner = config.learner
    steps = learner.num_steps if learner_class(config.algorithm).ppo_settings else 1
    return learner.num_envs * (size(level) + state_bytes + steps * obs_bytes)


_ENV_BYTES: dict[EnvConfig, tuple[int, int]] = {}  # env config -> (state, observation) bytes


def device_memory() -> tuple[str, int | None]:
    """(platform, bytes of memory its local devices have together; None: unknown)."""
    devices = jax.local_devices()
    platform = devices[0].platform
    if platform == "cpu":
        try:
            return platform, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (OSError, ValueError):
            return platform, None
    limits = [(d.memory_stats() or {}).get("bytes_limit") for d in devices]
    return platform, (sum(limits) if all(limits) else None)


def check_memory(config: TrainConfig, env_config: EnvConfig, level: EnvParams) -> None:
    """ConfigError, before a run folder exists, for a run whose envs cannot fit this machine's
    memory even at `memory_floor` (`learner.num_envs: 100000000`)."""
    need = memory_floor(config, env_config, level)
    platform, have = device_memory()
    if have is not None and need > have:
        learner = config.learner
        raise ConfigError(f"learner.num_envs: {learner.num_envs} envs x {learner.num_steps} "
                          f"steps need at least {need / 2**30:.1f} GiB (levels, states and "
                          f"a rollout's observations); this machine's {platform} memory is "
                          f"{have / 2**30:.1f} GiB: lower learner.num_envs or num_steps")


__all__ = ["check_devices", "check_memory", "device_memory", "learner_for", "memory_floor",
           "scenario_levels", "seed_keys", "split_seed_keys", "training_levels"]
