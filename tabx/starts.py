"""Randomised starts: a level's unit positions drawn from the reset key, as level data.

Two `EnvParams` fields say how (both zero / false by default, and in the paper's scenarios,
whose starts are fixed):

- `shuffle_positions`: each team's real units trade start positions by a random permutation
  (within the team, so the two sides keep their ground; headings stay with the slot);
- `start_noise`: then each real unit moves by a uniform offset in a disc of that radius (world
  units); the wall contact of the start state keeps it in the arena.

Both are arrays, so turning them on, or changing the radius, never recompiles; with both off
`randomise_start` returns the positions bit for bit. `TabxEnv.reset(key, params)` and the
learners' rollouts use it, so a level with randomised starts starts differently per key.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tabx.params import EnvParams
from tabx.rng import random_words, to_unit_float


def randomise_start(key: jax.Array, params: EnvParams) -> EnvParams:
    """`params` with its units' start positions drawn from `key` (one level; vmap for more)."""
    u = params.units
    n = u.active.shape[-1]
    words = random_words(key, (3, n))
    order, angle, radius = (to_unit_float(w) for w in words)
    active = u.active.astype(bool)
    team = u.team.astype(jnp.float32)
    # Within each team, the k-th real slot (in slot order) takes the position of the k-th real
    # slot in a random order: sort keys put team 0 before team 1 and real before padding.
    group = 4.0 * team + 2.0 * (~active)
    by_slot = jnp.argsort(group + jnp.arange(n) / n)
    by_chance = jnp.argsort(group + order)
    shuffled = jnp.zeros_like(u.position).at[by_slot].set(u.position[by_chance])
    position = jnp.where(params.shuffle_positions & active[:, None], shuffled, u.position)
    r = params.start_noise * jnp.sqrt(radius)  # uniform over the disc's area
    theta = 2.0 * jnp.pi * angle
    offset = jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)], axis=-1)
    moved = (params.start_noise > 0) & active[:, None]
    position = jnp.where(moved, position + offset, position)
    return params.replace(units=u.replace(position=position))


__all__ = ["randomise_start"]
