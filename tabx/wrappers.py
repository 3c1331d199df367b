"""Auto-reset for our own learners: the level travels in the state.

`AutoResetEnv.step` resets a finished episode into the level it is given (`next_level`), or into
the same level when none is given. The state carries the level and its start state, so
resetting into the same level is a select rather than a recomputation; JaxUED's
AutoReplayWrapper works the same way.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from tabx.env import Info, TabxEnv
from tabx.params import EnvParams
from tabx.state import EnvState


@struct.dataclass
class AutoResetState:
    env_state: EnvState
    level: EnvParams  # the level being played
    start_state: EnvState  # its start state: what a finished episode resets to


class AutoResetEnv:
    """Wraps `TabxEnv`; vmap its methods over envs like the env's own."""

    def __init__(self, env: TabxEnv):
        self.env = env

    @property
    def config(self):
        return self.env.config

    def reset(self, key: jax.Array, level: EnvParams) -> tuple[jax.Array, AutoResetState]:
        obs, state = self.env.reset(key, level)
        return obs, AutoResetState(env_state=state, level=level, start_state=state)

    def step(self, key: jax.Array, state: AutoResetState, actions: jax.Array,
             next_level: EnvParams | None = None
             ) -> tuple[jax.Array, AutoResetState, jax.Array, jax.Array, Info]:
        """Step; a finished episode restarts in `next_level` (default: the same level, from
        the same start state; a new level's randomised start is drawn from `key`)."""
        if next_level is None:
            obs, env_state, reward, done, info = self.env.step_autoreset(
                key, state.env_state, actions, state.level, state.start_state)
            return obs, state.replace(env_state=env_state), reward, done, info
        next_start = self.env.start_state(jax.random.fold_in(key, 1), next_level)
        obs, env_state, reward, done, info = self.env.step_autoreset(
            key, state.env_state, actions, state.level, next_start, next_level)
        pick = lambda new, old: jax.tree.map(lambda n, o: jnp.where(done, n, o), new, old)
        return obs, AutoResetState(env_state=env_state, level=pick(next_level, state.level),
                                   start_state=pick(next_start, state.start_state)
                                   ), reward, done, info

    def observe(self, state: AutoResetState) -> jax.Array:
        return self.env.observe(state.env_state, state.level)

    def world_state(self, state: AutoResetState) -> jax.Array:
        return self.env.world_state(state.env_state, state.level)

    def action_mask(self, state: AutoResetState) -> jax.Array:
        return self.env.action_mask(state.env_state, state.level)
