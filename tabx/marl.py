"""A JaxMARL-compatible adapter: `MultiAgentEnv` semantics over `TabxEnv`.

JaxMARL-style training code runs on it unmodified: `reset(key) -> (obs, state)` and
`step(key, state, actions) -> (obs, state, rewards, dones, infos)` with dicts keyed by agent
name, `"__all__"` in dones, auto-reset on episode end, `get_avail_actions(state)`,
`observation_space(agent)`, `action_space(agent)`, `agents`, `num_agents`, and
`obs["world_state"]` (one global state per env) for MAPPO.

Agents are the unit slots of the learner's team: `team="ally"` gives `ally_0 .. ally_{A-1}`,
`team="enemy"` (the flipped wrapper: a learner on the enemy side) gives `enemy_0 ..`, and
`team="both"` gives both (self-play, policy vs policy). The other team is driven by the
`opponent` controller (tabx.controllers): "heuristic:TIER" (the scripted opponent at a tier),
"heuristic" (the level's own heuristic parameters, as UED varies them), "random" or "idle".
Observations are ego-centric, so a policy trained on one side plays the other unchanged.
Padded and dead slots stay agents (fixed agent set, as in JaxMARL's SMAX): their observation is
zeros and IDLE is their only legal action.

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
from tabx.controllers import Controller, controlled_actions, with_tiers
from tabx.env import TabxEnv
from tabx.params import EnvConfig, EnvParams
from tabx.wrappers import AutoResetEnv, AutoResetState

LEARNER_TEAMS = ("ally", "enemy", "both")


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
                 team: str = "ally", opponent: str = "heuristic:medium"):
        if (level is None) == (level_sampler is None):
            raise ValueError("give exactly one of `level` or `level_sampler`")
        if team not in LEARNER_TEAMS:
            raise ValueError(f"unknown learner team {team!r}; expected one of {LEARNER_TEAMS}")
        other = Controller.parse(opponent) if team != "both" else Controller("external")
        if other.kind == "external" and team != "both":
            raise ValueError("the opponent must be heuristic[:TIER], random or idle; use "
                             "team='both' for two learner-controlled teams")
        self.config = config
        self.env = AutoResetEnv(TabxEnv(config))
        self.team = team
        learner = Controller("external")
        self.controllers = ((learner, other) if team == "ally" else
                            (other, learner) if team == "enemy" else (learner, learner))
        self.level = None if level is None else with_tiers(level, self.controllers)
        self.level_sampler = level_sampler
        ally_names = [f"ally_{i}" for i in range(config.max_allies)]
        enemy_names = [f"enemy_{i}" for i in range(config.max_enemies)]
        self.all_unit_names = ally_names + enemy_names
        self.agents = {"ally": ally_names, "enemy": enemy_names,
                       "both": ally_names + enemy_names}[team]
        self.num_agents = len(self.agents)
        first = config.max_allies if team == "enemy" else 0
        self.agent_slots = jnp.arange(first, first + self.num_agents)
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
        if self.level_sampler is None:
            return self.level
        return with_tiers(self.level_sampler(key), self.controllers)

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], AutoResetState]:
        obs, state = self.env.reset(key, self._new_level(key))
        return self._obs_dict(obs, state), state

    def step(self, key: jax.Array, state: AutoResetState, actions: dict[str, jax.Array]
             ) -> tuple[dict, AutoResetState, dict, dict, dict]:
        key_other, key_level, key_step = jax.random.split(key, 3)
        slot_actions, state = self._fill_actions(key_other, state, actions)
        next_level = None if self.level_sampler is None else self._new_level(key_level)
        obs, state, reward, done, info = self.env.step(key_step, state, slot_actions, next_level)
        rewards = {a: reward[C.ALLY if a.startswith("ally") else C.ENEMY] for a in self.agents}
        dones = {a: done for a in self.agents}
        dones["__all__"] = done
        learner_team = C.ENEMY if self.team == "enemy" else C.ALLY
        infos = {"won": info["won"], "returned_win": info["won"][learner_team] & done,
                 "terminated": info["terminated"], "truncated": info["truncated"],
                 "dead_units": info["dead_units"]}
        return self._obs_dict(obs, state), state, rewards, dones, infos

    def get_avail_actions(self, state: AutoResetState) -> dict[str, jax.Array]:
        mask = self.env.action_mask(state)
        return {a: mask[slot] for a, slot in zip(self.agents, self._slots(), strict=True)}

    # --- helpers -----------------------------------------------------------------------------

    def _obs_dict(self, obs: jax.Array, state: AutoResetState) -> dict[str, jax.Array]:
        out = {a: obs[slot] for a, slot in zip(self.agents, self._slots(), strict=True)}
        out["world_state"] = self.env.world_state(state)
        return out

    def _slots(self) -> range:
        first = self.config.max_allies if self.team == "enemy" else 0
        return range(first, first + self.num_agents)

    def _fill_actions(self, key: jax.Array, state: AutoResetState,
                      actions: dict[str, jax.Array]) -> tuple[jax.Array, AutoResetState]:
        """Every slot's action: the agents' own, the opponent controller's for the rest."""
        n = self.config.num_units
        external = jnp.full((n,), C.IDLE, jnp.int32)
        chosen = jnp.stack([jnp.asarray(actions[a], jnp.int32) for a in self.agents])
        external = external.at[self.agent_slots].set(chosen)
        slot_actions, env_state = controlled_actions(key, state.env_state, state.level, external,
                                                     self.controllers)
        return slot_actions, state.replace(env_state=env_state)
