"""jaxued's `UnderspecifiedEnv` interface over our levels, for jaxued-style DR / PLR / ACCEL loops.

jaxued (github.com/DramaCow/jaxued) drives an environment through a level it is handed:

    obs, state = env.reset_to_level(rng, level, params)
    obs, state, reward, done, info = env.step(rng, state, action, params)
    env.action_space(params).n

and its example loops wrap it in `AutoReplayWrapper`, which restarts a finished episode in the
same level. Here a level is our `EnvParams` (one `EnvConfig` for all of them, so new levels
never recompile; `tabx.scenarios.load_levels` loads named scenarios as one batch), and the
learner is one team of units playing the other team's controller, as in `tabx.marl`:

- `params`: `TabxUEDParams`, the compiled-in numbers a loop reads (`max_steps_in_episode`,
  `num_agents`; static, so `jax.lax.scan(..., length=params.max_steps_in_episode)` works).
  Everything a level varies is in the level. jaxued's own wrappers forward `default_params`
  and `action_space(params)` (nothing else), so both carry `num_agents`;
- `action`: int array `(num_agents,)`, one action per learner unit slot.
  `action_space(params)` says so: a `MultiAgentDiscrete` whose `n` (8) is one agent's choices,
  the size of a policy's output head, and whose `shape` is `(num_agents,)`; `step` raises a
  ValueError, when it is traced, for an action of any other shape;
- `obs`: `(num_agents, obs_size)`; `reward`: the learner team's (a scalar); `done`: the
  episode's end; `info`: `won`, `terminated`, `truncated`, `dead_units` and `legal_actions`
  (`(num_agents, 8)`, for masked policies).

`reset_to_level` draws the level's randomised start from `rng` where the level asks for one
(`tabx.starts`). No jaxued dependency: jaxued 0.0.1 on the package index calls the removed
`jax.tree_map`; the interface was checked against its `environments/underspecified_env.py`
and `wrappers/autoreplay.py` (docs/ecosystem.md).
"""

from __future__ import annotations

from dataclasses import dataclass
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
    """jaxued's per-environment `params`: what a loop reads of the compiled-in `EnvConfig`.

    Both are static (not traced), so they size scans and arrays inside `jit`. Every other
    setting of a battle is level data (`EnvParams`)."""

    max_steps_in_episode: int = struct.field(pytree_node=False)
    num_agents: int = struct.field(pytree_node=False)


@dataclass(frozen=True)
class MultiAgentDiscrete(Discrete):
    """The actions of one env step: `num_agents` choices of `n` values each.

    `n` is one agent's number of actions (what jaxued's examples size a policy head with);
    `shape`, `sample` and `contains` are the whole step's `(num_agents,)`."""

    num_agents: int = 1

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.num_agents,)

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, self.shape, 0, self.n, dtype=self.dtype)

    def contains(self, x: jax.Array) -> jax.Array:
        if jnp.shape(x) != self.shape:
            return jnp.bool_(False)
        return jnp.all((x >= 0) & (x < self.n))


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
        raise NotImplementedError

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

    @property
    def default_params(self) -> TabxUEDParams:
        return TabxUEDParams(max_steps_in_episode=self.config.max_steps,
                             num_agents=self.num_agents)

    def _check(self, params: TabxUEDParams) -> None:
        """Params of another env (other step limit or team size) are an error, not ignored."""
        if params != self.default_params:
            raise ValueError(f"params {params} are not this env's ({self.default_params}); "
                             "use env.default_params")

    def reset_env_to_level(self, rng: jax.Array, level: EnvParams, params: TabxUEDParams
                           ) -> tuple[jax.Array, TabxUEDState]:
        """A new episode in `level`, its randomised start (if any) drawn from `rng`."""
        self._check(params)
        level = with_tiers(level, self.controllers)
        env_state = self.env.start_state(rng, level)
        state = TabxUEDState(env_state=env_state, level=level)
        return self.get_obs(state), state

    def step_env(self, rng: jax.Array, state: TabxUEDState, action: jax.Array,
                 params: TabxUEDParams) -> tuple[jax.Array, TabxUEDState, jax.Array,
                                                 jax.Array, Info]:
        """One step: the learner's units take `action` (num_agents,), the other team its
        controller's. No reset (a finished episode stays frozen): `AutoReplayWrapper` adds it."""
        self._check(params)
        if jnp.shape(action) != (self.num_agents,):
            raise ValueError(
                f"an action is one per learner agent, shape ({self.num_agents},); got shape "
                f"{jnp.shape(action)} (vmap step over envs; action_space(params).n is one "
                "agent's choices)")
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

    def action_space(self, params: TabxUEDParams | None = None) -> MultiAgentDiscrete:
        """One step's actions: `(num_agents,)`, each one of `n` = 8."""
        return MultiAgentDiscrete(C.NUM_ACTIONS, num_agents=self.num_agents)

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

    def action_space(self, params: TabxUEDParams | None = None) -> MultiAgentDiscrete:
        return self._env.action_space(params)


__all__ = ["AutoReplayState", "AutoReplayWrapper", "MultiAgentDiscrete", "TabxUEDParams",
           "TabxUEDState", "TabxUnderspecifiedEnv", "UnderspecifiedEnv"]
