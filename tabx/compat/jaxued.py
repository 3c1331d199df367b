"""jaxued's `UnderspecifiedEnv` interface over our levels, for jaxued-style DR / PLR / ACCEL loops.

jaxued (github.com/DramaCow/jaxued) drives an environment through a level it is handed:

    obs, state = env.reset_to_level(rng, level, params)
    obs, state, reward, done, info = env.step(rng, state, action, params)
    env.action_space(params).n

and its example loops wrap it in `AutoReplayWrapper`, which restarts a finished episode in the
same level. Here a level is our `EnvParams` (one `EnvConfig` for all of them, so new levels
never recompile), `params` is `TabxUEDParams` (nothing a level varies; accepted and ignored as
in jaxued's own environments), and the learner is one team of units playing the other team's
controller, as in `tabx.marl`:

- `action`: int array `(num_agents,)`, one action per learner unit slot (`action_space(params)`
  is one agent's: `Discrete(8)`);
- `obs`: `(num_agents, obs_size)`; `reward`: the learner team's (a scalar); `done`: the
  episode's end; `info`: `won`, `terminated`, `truncated`, `dead_units` and `legal_actions`
  (`(num_agents, 8)`, for masked policies).

`reset_to_level` draws the level's randomised start from `rng` where the level asks for one
(`tabx.starts`). No jaxued dependency: jaxued 0.0.1 on the package index calls the removed
`jax.tree_map`; the interface was checked against its `environments/underspecified_env.py`
and `wrappers/autoreplay.py` (docs/ecosystem.md).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from tabx import constants as C
from tabx.controllers import Controller, controlled_actions, with_tiers
from tabx.env import Info, TabxEnv
from tabx.marl import Box, Discrete
from tabx.params import EnvConfig, EnvParams
from tabx.state import EnvState

LEARNER_TEAMS = ("ally", "enemy")


@struct.dataclass
class TabxUEDParams:
    """jaxued's per-environment `params`: nothing here, since every setting of a battle is
    level data (`EnvParams`) or compiled in (`EnvConfig`)."""


@struct.dataclass
class TabxUEDState:
    """The battle's state and the level it plays (the opponent tier applied)."""

    env_state: EnvState
    level: EnvParams


class UnderspecifiedEnv:
    """jaxued's base: `reset_to_level` and `step` fill in `params` and call the
    `reset_env_to_level` and `step_env` of the environment or wrapper."""

    @property
    def default_params(self) -> TabxUEDParams:
        return TabxUEDParams()

    def reset_to_level(self, rng: jax.Array, level: EnvParams,
                       params: TabxUEDParams | None = None) -> tuple[jax.Array, Any]:
        params = self.default_params if params is None else params
        return self.reset_env_to_level(rng, level, params)

    def step(self, rng: jax.Array, state: Any, action: jax.Array,
             params: TabxUEDParams | None = None
             ) -> tuple[jax.Array, Any, jax.Array, jax.Array, Info]:
        params = self.default_params if params is None else params
        return self.step_env(rng, state, action, params)

    def reset_env_to_level(self, rng: jax.Array, level: EnvParams, params: TabxUEDParams
                           ) -> tuple[jax.Array, Any]:
        raise NotImplementedError

    def step_env(self, rng: jax.Array, state: Any, action: jax.Array, params: TabxUEDParams
                 ) -> tuple[jax.Array, Any, jax.Array, jax.Array, Info]:
        raise NotImplementedError


class TabxUnderspecifiedEnv(UnderspecifiedEnv):
    """The TABX battle behind jaxued's `UnderspecifiedEnv` methods; vmap them over envs."""

    def __init__(self, config: EnvConfig, team: str = "ally",
                 opponent: str = "heuristic:novice"):
        if team not in LEARNER_TEAMS:
            raise ValueError(f"unknown learner team {team!r}; expected one of {LEARNER_TEAMS}")
        other = Controller.parse(opponent)
        if other.kind == "external":
            raise ValueError("the opponent must be heuristic[:TIER], random or idle")
        self.config = config
        self.env = TabxEnv(config)
        learner = Controller("external")
        self.controllers = (learner, other) if team == "ally" else (other, learner)
        self.team = C.ALLY if team == "ally" else C.ENEMY
        self.num_agents = config.max_allies if team == "ally" else config.max_enemies
        first = 0 if team == "ally" else config.max_allies
        self.agent_slots = jnp.arange(first, first + self.num_agents)

    def reset_env_to_level(self, rng: jax.Array, level: EnvParams, params: TabxUEDParams
                           ) -> tuple[jax.Array, TabxUEDState]:
        """A new episode in `level`, its randomised start (if any) drawn from `rng`."""
        del params
        level = with_tiers(level, self.controllers)
        env_state = self.env.start_state(rng, level)
        state = TabxUEDState(env_state=env_state, level=level)
        return self.get_obs(state), state

    def step_env(self, rng: jax.Array, state: TabxUEDState, action: jax.Array,
                 params: TabxUEDParams) -> tuple[jax.Array, TabxUEDState, jax.Array,
                                                 jax.Array, Info]:
        """One step: the learner's units take `action` (num_agents,), the other team its
        controller's. No reset (a finished episode stays frozen): `AutoReplayWrapper` adds it."""
        del params
        key_other, key_step = jax.random.split(rng)
        external = jnp.full((self.config.num_units,), C.IDLE, jnp.int32)
        external = external.at[self.agent_slots].set(jnp.asarray(action, jnp.int32))
        slot_actions, env_state = controlled_actions(key_other, state.env_state, state.level,
                                                     external, self.controllers)
        _, env_state, reward, done, info = self.env.step(key_step, env_state, slot_actions,
                                                         state.level)
        state = state.replace(env_state=env_state)
        info = {**info, "won": info["won"][self.team],
                "legal_actions": self.legal_actions(state)}
        return self.get_obs(state), state, reward[self.team], done, info

    def get_obs(self, state: TabxUEDState) -> jax.Array:
        """(num_agents, obs_size): the learner units' ego-centric observations."""
        return self.env.observe(state.env_state, state.level)[self.agent_slots]

    def legal_actions(self, state: TabxUEDState) -> jax.Array:
        """(num_agents, 8) bool."""
        return self.env.action_mask(state.env_state, state.level)[self.agent_slots]

    def action_space(self, params: TabxUEDParams | None = None) -> Discrete:
        """One agent's actions (an action of the env is one per agent)."""
        return Discrete(C.NUM_ACTIONS)

    def observation_space(self, params: TabxUEDParams | None = None) -> Box:
        return Box(-jnp.inf, jnp.inf, (self.num_agents, self.config.obs_size))


@struct.dataclass
class AutoReplayState:
    """jaxued's auto-replay state: the inner state and the level it replays."""

    env_state: Any
    level: EnvParams


class AutoReplayWrapper(UnderspecifiedEnv):
    """Restarts a finished episode in the same level (a fresh start drawn where the level
    randomises it), like jaxued's wrapper of the same name: obs and state are the new
    episode's, reward, done and info the step that ended."""

    def __init__(self, env: TabxUnderspecifiedEnv):
        self._env = env

    def __getattr__(self, name: str) -> Any:
        return getattr(self._env, name)

    @property
    def default_params(self) -> TabxUEDParams:
        return self._env.default_params

    def reset_env_to_level(self, rng: jax.Array, level: EnvParams, params: TabxUEDParams
                           ) -> tuple[jax.Array, AutoReplayState]:
        obs, env_state = self._env.reset_to_level(rng, level, params)
        return obs, AutoReplayState(env_state=env_state, level=level)

    def step_env(self, rng: jax.Array, state: AutoReplayState, action: jax.Array,
                 params: TabxUEDParams) -> tuple[jax.Array, AutoReplayState, jax.Array,
                                                 jax.Array, Info]:
        rng_reset, rng_step = jax.random.split(rng)
        obs, env_state, reward, done, info = self._env.step(rng_step, state.env_state, action,
                                                            params)
        obs_re, env_state_re = self._env.reset_to_level(rng_reset, state.level, params)
        pick = lambda new, old: jax.tree.map(lambda n, o: jax.lax.select(done, n, o), new, old)
        return (pick(obs_re, obs), state.replace(env_state=pick(env_state_re, env_state)),
                reward, done, info)

    def action_space(self, params: TabxUEDParams | None = None) -> Discrete:
        return self._env.action_space(params)


__all__ = ["AutoReplayState", "AutoReplayWrapper", "TabxUEDParams", "TabxUEDState",
           "TabxUnderspecifiedEnv", "UnderspecifiedEnv"]
