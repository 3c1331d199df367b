"""Motion of unit bodies: explicit Euler, the arena wall, and circle collisions.

Collisions are resolved in one simultaneous (Jacobi) pass over all pairs, vectorised as (N, N)
matrices, instead of the reference's sequential pass in unit-index order. For a single pair the
two are identical (same impulse, same mass-split positional correction); with several
overlapping pairs ours has no index-order bias (docs/differences.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def integrate(position: jax.Array, velocity: jax.Array, dt: jax.Array) -> jax.Array:
    """Explicit Euler step (accelerations are always zero: actions set velocities)."""
    return position + velocity * dt


def wall_contact(position: jax.Array, radius: jax.Array, arena_size: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
    """Clip bodies into the arena; `touching[i]` if unit i is at or beyond the wall.

    The test is inclusive like the reference's, so a unit resting against the wall keeps taking
    boundary damage.
    """
    limit = jnp.maximum(0.5 * arena_size[None, :] - radius[:, None], 0.0)
    touching = jnp.any((position <= -limit) | (position >= limit), axis=-1)
    return jnp.clip(position, -limit, limit), touching


def resolve_collisions(position: jax.Array, velocity: jax.Array, radius: jax.Array,
                       mass: jax.Array, solid: jax.Array, restitution: jax.Array,
                       slop: jax.Array, percent: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One simultaneous pass of mass-aware impulses and positional correction.

    For each overlapping pair (i, j) with normal n from i to j and depth d:
    approaching or resting (v_rel . n <= 0): impulse j = -(1+e) v_rel.n / (1/m_i + 1/m_j) and
    correction max(d - slop, 0) * percent; separating: correction d * percent, no impulse.
    Corrections and impulses are split by inverse mass. `solid` masks bodies that collide
    (active units, dead or alive: corpses still collide, as in the reference).
    """
    n_units = position.shape[0]
    rel = position[None, :, :] - position[:, None, :]  # p_j - p_i
    dist2 = jnp.sum(rel * rel, -1)
    dist = jnp.sqrt(jnp.maximum(dist2, 1e-16))
    idx = jnp.arange(n_units)
    # Coincident centres: separate along +x for the lower index (antisymmetric, so pairs split).
    fallback = jnp.where(idx[:, None] < idx[None, :], 1.0, -1.0)
    coincident = dist2 < 1e-16
    normal = jnp.where(coincident[..., None],
                       jnp.stack([fallback, jnp.zeros_like(fallback)], -1),
                       rel / dist[..., None])
    depth = radius[:, None] + radius[None, :] - jnp.where(coincident, 0.0, dist)
    pair = solid[:, None] & solid[None, :] & (idx[:, None] != idx[None, :]) & (depth > 0)

    inv_mass = 1.0 / jnp.maximum(mass, 1e-6)
    inv_sum = inv_mass[:, None] + inv_mass[None, :]
    rel_v = velocity[None, :, :] - velocity[:, None, :]
    v_normal = jnp.sum(rel_v * normal, -1)
    approaching = v_normal <= 0
    correction = jnp.where(approaching, jnp.maximum(depth - slop, 0.0), depth) * percent
    correction = jnp.where(pair, correction, 0.0)
    impulse = jnp.where(pair & approaching, -(1.0 + restitution) * v_normal / inv_sum, 0.0)

    # Unit i moves against the normal of each of its pairs, by its inverse-mass share.
    share = inv_mass[:, None] / inv_sum
    new_position = position - jnp.sum((correction * share)[..., None] * normal, axis=1)
    new_velocity = velocity - inv_mass[:, None] * jnp.sum(impulse[..., None] * normal, axis=1)
    return new_position, new_velocity
