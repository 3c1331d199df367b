"""A JaxMARL-compatible adapter: `MultiAgentEnv` semantics over `TabxEnv`.

JaxMARL-style training code runs on it unmodified: `reset(key) -> (obs, state)` and
`step(key, state, actions) -> (obs, state, rewards, dones, infos)` with dicts keyed by agent
name, `"__all__"` in dones, auto-reset on episode end, `get_avail_actions(state)`,
`observation_space(agent)`, `action_space(agent)`, `agents`, `num_agents`, and
`obs["world_state"]` (one global state per env) for MAPPO.

Agents are the unit slots of the controlled team(s): `ally_0 .. ally_{A-1}` and, when the enemy
is also learner-controlled, `enemy_0 ..`. An uncontrolled enemy team is driven by the
`enemy` controller ("random": uniform legal actions; "idle"). Padded and dead slots stay
agents (fixed agent set, as in JaxMARL's SMAX): their observation is zeros and IDLE is their
only legal action.

Levels come from a fixed `EnvParams` or a `level_sampler(key) -> EnvParams`; with a sampler
every episode starts in a fresh level.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.env import TabxEnv, random_legal_actions
from tabx.params import EnvConfig, EnvParams
from tabx.wrappers import AutoResetEnv, AutoResetState

ENEMY_CONTROLLERS = ("agents", "random", "idle")


@dataclass(frozen=True)
class Discrete:
    """A discrete space with `n` values (JaxMARL's Discrete interface)."""

    n: int
    dtype: Any = jnp.int32

    @property
    def shape(self) -> tuple[int, ...]:
        return ()

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, (), 0, self.n, dtype=self.dtype)

    def contains(self, x: jax.Array) -> jax.Array:
        return jnp.logical_and(x >= 0, x < self.n)


@dataclass(frozen=True)
class Box:
    """A box space (JaxMARL's Box interface)."""

    low: float
    high: float
    shape: tuple[int, ...]
    dtype: Any = jnp.float32

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.uniform(key, self.shape, self.dtype, self.low, self.high)

    def contains(self, x: jax.Array) -> jax.Array:
        return jnp.logical_and(jnp.all(x >= self.low), jnp.all(x <= self.high))


class TabxMarlEnv:
    """JaxMARL `MultiAgentEnv`-style wrapper (no JaxMARL dependency)."""

    def __init__(self, config: EnvConfig, level: EnvParams | None = None,
                 level_sampler: Callable[[jax.Array], EnvParams] | None = None,
                 enemy: str = "random"):
        if (level is None) == (level_sampler is None):
            raise ValueError("give exactly one of `level` or `level_sampler`")
        if enemy not in ENEMY_CONTROLLERS:
            raise ValueError(f"unknown enemy controller {enemy!r}; expected one of "
                             f"{ENEMY_CONTROLLERS}")
        self.config = config
        self.env = AutoResetEnv(TabxEnv(config))
        self.level = level
        self.level_sampler = level_sampler
        self.enemy = enemy
        ally_names = [f"ally_{i}" for i in range(config.max_allies)]
        enemy_names = [f"enemy_{i}" for i in range(config.max_enemies)]
        self.all_unit_names = ally_names + enemy_names
        self.agents = ally_names + (enemy_names if enemy == "agents" else [])
        self.num_agents = len(self.agents)
        self.agent_slots = jnp.arange(self.num_agents)  # agents are the first slots
        obs_box = Box(-jnp.inf, jnp.inf, (config.obs_size,))
        self.observation_spaces = {a: obs_box for a in self.agents}
        self.action_spaces = {a: Discrete(C.NUM_ACTIONS) for a in self.agents}
        self.world_state_size = config.state_size

    def observation_space(self, agent: str) -> Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> Discrete:
        return self.action_spaces[agent]

    # --- JaxMARL API -------------------------------------------------------------------------

    def _new_level(self, key: jax.Array) -> EnvParams:
        return self.level if self.level_sampler is None else self.level_sampler(key)

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], AutoResetState]:
        obs, state = self.env.reset(key, self._new_level(key))
        return self._obs_dict(obs, state), state

    def step(self, key: jax.Array, state: AutoResetState, actions: dict[str, jax.Array]
             ) -> tuple[dict, AutoResetState, dict, dict, dict]:
        key_enemy, key_level, key_step = jax.random.split(key, 3)
        slot_actions = self._slot_actions(key_enemy, state, actions)
        next_level = None if self.level_sampler is None else self.level_sampler(key_level)
        obs, state, reward, done, info = self.env.step(key_step, state, slot_actions, next_level)
        rewards = {a: reward[C.ALLY if a.startswith("ally") else C.ENEMY] for a in self.agents}
        dones = {a: done for a in self.agents}
        dones["__all__"] = done
        infos = {"won": info["won"], "returned_win": info["won"][C.ALLY] & done,
                 "terminated": info["terminated"], "truncated": info["truncated"],
                 "dead_units": info["dead_units"]}
        return self._obs_dict(obs, state), state, rewards, dones, infos

    def get_avail_actions(self, state: AutoResetState) -> dict[str, jax.Array]:
        mask = self.env.action_mask(state)
        return {a: mask[i] for i, a in enumerate(self.agents)}

    # --- helpers -----------------------------------------------------------------------------

    def _obs_dict(self, obs: jax.Array, state: AutoResetState) -> dict[str, jax.Array]:
        out = {a: obs[i] for i, a in enumerate(self.agents)}
        out["world_state"] = self.env.world_state(state)
        return out

    def _slot_actions(self, key: jax.Array, state: AutoResetState,
                      actions: dict[str, jax.Array]) -> jax.Array:
        n = self.config.num_units
        chosen = jnp.stack([jnp.asarray(actions[a], jnp.int32) for a in self.agents])
        if self.enemy == "agents":
            return chosen
        if self.enemy == "random":
            others = random_legal_actions(key, self.env.action_mask(state))
        else:
            others = jnp.full((n,), C.IDLE, jnp.int32)
        return others.at[: self.num_agents].set(chosen)
