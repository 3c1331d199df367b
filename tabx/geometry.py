"""Pairwise geometry of one battle, as (N, N) matrices: field of view, hurtbox, zone membership.

All functions act on a single environment (vmap them over envs) and never loop over units.
Conventions: `rel[v, t] = p_t - p_v`; angles counter-clockwise from +x, y up.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def pairwise_offsets(position: jax.Array) -> jax.Array:
    """rel[i, j] = position[j] - position[i], shape (N, N, 2)."""
    return position[None, :, :] - position[:, None, :]


def facing(heading: jax.Array, sight_angle: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(facing, half_sight): (N, 2) cos/sin of the heading and of half the sight angle."""
    half = 0.5 * sight_angle
    return (jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1),
            jnp.stack([jnp.cos(half), jnp.sin(half)], -1))


def view_trig(facing: jax.Array, half_sight: jax.Array) -> jax.Array:
    """(N, 8) per-unit trigonometry used by the pairwise tests, from products only:
    cos/sin of the heading, of the two wedge edges (heading +- sight/2), and of sight/2.

    Computed once per step and materialised: XLA would otherwise duplicate it into every
    (N, N) consumer.
    """
    c, s = facing[:, 0], facing[:, 1]
    ch, sh = half_sight[:, 0], half_sight[:, 1]
    trig = jnp.stack([c, s, c * ch - s * sh, s * ch + c * sh, c * ch + s * sh, s * ch - c * sh,
                      ch, sh], axis=-1)
    return jax.lax.optimization_barrier(trig)


def field_of_view(rel: jax.Array, trig: jax.Array, target_radius: jax.Array) -> jax.Array:
    """fov[v, t]: t's body touches v's view wedge (total angle sight_angle < pi, infinite range).

    Each edge of the wedge is pushed outward by the *target's* radius (the reference's test),
    so a target slightly behind the apex is still seen. `trig` comes from `view_trig`.
    """
    # Inward normals of the two edges: n1 = (-sin, cos)(left), n2 = (-sin, cos)(right).
    d1 = -trig[:, None, 3] * rel[..., 0] + trig[:, None, 2] * rel[..., 1]
    d2 = -trig[:, None, 5] * rel[..., 0] + trig[:, None, 4] * rel[..., 1]
    r = target_radius[None, :]
    return (d1 <= r) & (d2 >= -r)


def hurtbox_overlap(rel: jax.Array, trig: jax.Array, radius: jax.Array,
                    attack_range: jax.Array) -> jax.Array:
    """hit[a, t]: t's circle strictly overlaps a's rectangular hurtbox.

    In a's frame (+x = heading) the box spans x in [r_a cos(s/2), r_a cos(s/2) + range] and
    |y| <= r_a sin(s/2), with s a's sight angle (the reference's geometry). `trig` from `view_trig`.
    """
    c, s = trig[:, None, 0], trig[:, None, 1]
    local_x = c * rel[..., 0] + s * rel[..., 1]
    local_y = -s * rel[..., 0] + c * rel[..., 1]
    x0 = (radius * trig[:, 6])[:, None]
    x1 = x0 + attack_range[:, None]
    half_width = (radius * trig[:, 7])[:, None]
    gap_x = jnp.maximum(jnp.maximum(x0 - local_x, local_x - x1), 0.0)
    gap_y = jnp.maximum(jnp.abs(local_y) - half_width, 0.0)
    return gap_x * gap_x + gap_y * gap_y < jnp.square(radius)[None, :]


def in_ellipses(position: jax.Array, centre: jax.Array, semi_axes: jax.Array,
                zone_type: jax.Array) -> jax.Array:
    """inside[i, z]: unit centre i lies in zone z's axis-aligned ellipse (empty slots: never)."""
    axes = jnp.maximum(semi_axes, 1e-6)  # a zero axis would divide by zero: such a zone is empty
    q = jnp.square((position[:, None, :] - centre[None, :, :]) / axes[None, :, :]).sum(-1)
    return (q <= 1.0) & (zone_type > 0)[None, :] & jnp.all(semi_axes > 0, -1)[None, :]
