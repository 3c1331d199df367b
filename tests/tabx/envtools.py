"""Small shared builders for the environment tests (hand-built levels, one compiled step).

Slot layout of `CONFIG` (3 v 3, 2 zone slots): allies in slots 0, 1, 2, enemies in 3, 4, 5.
Tests that need a "bystander" on a team put it far away in a corner, facing the wall, so it
neither sees, hits nor touches anything.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.env import TabxEnv
from tabx.params import EnvConfig, EnvParams, make_level
from tabx.state import EnvState

CONFIG = EnvConfig(max_allies=3, max_enemies=3, max_zones=2)
N = CONFIG.num_units
A0, A1, A2, E0, E1, E2 = range(N)
KEY = jax.random.PRNGKey(0)
DEG = math.pi / 180.0

# Bystanders: far from everything, facing away from the arena centre.
FAR_ALLY = dict(unit="farmer", position=(-50.0, -30.0), heading=math.pi)
FAR_ENEMY = dict(unit="farmer", position=(50.0, 30.0), heading=0.0)


def unit(name: str, x: float, y: float, heading: float = 0.0, **stats: Any) -> dict[str, Any]:
    """A make_level unit record."""
    return dict(unit=name, position=(float(x), float(y)), heading=float(heading), **stats)


def zone(kind: str, x: float, y: float, ax: float, ay: float, effect: float = 0.0
         ) -> dict[str, Any]:
    """A make_level zone record (axis-aligned ellipse)."""
    return dict(type=kind, centre=(float(x), float(y)), semi_axes=(float(ax), float(ay)),
                effect=float(effect))


def level(allies: Sequence[dict], enemies: Sequence[dict], zones: Sequence[dict] = (),
          config: EnvConfig = CONFIG, **kw: Any) -> EnvParams:
    return make_level(config, list(allies), list(enemies), list(zones), **kw)


def acts(mapping: Mapping[int, int] | None = None, n: int = N, default: int = C.IDLE
         ) -> jax.Array:
    """An int32 (n,) action vector: `default` everywhere except the slots in `mapping`."""
    a = np.full(n, default, np.int32)
    for slot, action in (mapping or {}).items():
        a[slot] = action
    return jnp.asarray(a)


def kill(state: EnvState, *slots: int) -> EnvState:
    """The state with the given units dead (health 0), as if killed in the previous step."""
    alive, health = state.alive, state.health
    for s in slots:
        alive = alive.at[s].set(False)
        health = health.at[s].set(0.0)
    return state.replace(alive=alive, health=health)


class Sim:
    """Jitted reset / step / mask / world_state of one config, compiled once and reused."""

    def __init__(self, config: EnvConfig = CONFIG):
        self.config = config
        self.env = TabxEnv(config)
        self.reset_fn = jax.jit(self.env.reset)
        self.step_fn = jax.jit(self.env.step)
        self.autoreset_fn = jax.jit(self.env.step_autoreset)
        self.mask_fn = jax.jit(self.env.action_mask)
        self.world_state_fn = jax.jit(self.env.world_state)

    def reset(self, params: EnvParams) -> tuple[jax.Array, EnvState]:
        return self.reset_fn(KEY, params)

    def step(self, state: EnvState, actions: Mapping[int, int] | jax.Array | None,
             params: EnvParams):
        if actions is None or isinstance(actions, Mapping):
            actions = acts(actions, self.config.num_units)
        return self.step_fn(KEY, state, actions, params)

    def mask(self, state: EnvState, params: EnvParams) -> np.ndarray:
        return np.asarray(self.mask_fn(state, params))

    def run(self, params: EnvParams, actions: Sequence[Mapping[int, int] | None],
            state: EnvState | None = None) -> list[tuple]:
        """Step through a list of per-step action maps; returns every step's
        (obs, state, reward, done, info), starting from reset unless `state` is given."""
        if state is None:
            state = self.reset(params)[1]
        out = []
        for a in actions:
            res = self.step(state, a, params)
            state = res[1]
            out.append(res)
        return out


def np_state(state: EnvState) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in vars(state).items()}
