"""Terrain zones: lava damage, swamp slow-down and bush concealment.

Membership is the unit centre inside a zone's axis-aligned ellipse (reference behaviour). All
zones act at once through (N, Z) matrices: no branch per zone type, no per-zone loop and no
(N, N, N) tensor (the reference's bush rule builds one).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tabx import constants as C


def lava_damage(inside: jax.Array, zone_type: jax.Array, effect: jax.Array,
                dt: jax.Array) -> jax.Array:
    """Health lost in lava this step: effect * dt per lava zone containing the unit."""
    lava = (zone_type == C.ZONE_LAVA)[None, :] & inside
    return jnp.sum(jnp.where(lava, effect[None, :], 0.0), -1) * dt


def swamp_speed(inside: jax.Array, zone_type: jax.Array, effect: jax.Array,
                base_speed: jax.Array) -> jax.Array:
    """Speed for the next move: base speed times (1 - effect) per swamp containing the unit."""
    swamp = (zone_type == C.ZONE_SWAMP)[None, :] & inside
    factor = jnp.prod(jnp.where(swamp, 1.0 - jnp.clip(effect, 0.0, 1.0)[None, :], 1.0), -1)
    return jnp.clip(base_speed * factor, 0.0, base_speed)


def bush_visibility(fov: jax.Array, inside: jax.Array, zone_type: jax.Array, team: jax.Array,
                    alive: jax.Array, interacted: jax.Array) -> jax.Array:
    """visible[v, t] from the field of view and the bush rules, with team-shared vision.

    An opponent t whose centre is in a bush is hidden from viewer v unless some living member
    of v's team (v included) is in that same bush, or attacked or was attacked by t this step
    (the one-step reveal). Team sharing can only undo bush hiding, never widen the field of
    view: the result is always within `fov`.
    """
    return apply_bush_hiding(fov, team, bush_hidden(inside, zone_type, team, alive, interacted))


def bush_hidden(inside: jax.Array, zone_type: jax.Array, team: jax.Array, alive: jax.Array,
                interacted: jax.Array) -> jax.Array:
    """hidden[T, t] (2, N): t is hidden by a bush from team T (see `bush_visibility`)."""
    # Team reductions are written as broadcast-and-reduce, not matmuls: vmapped tiny matmuls
    # are slow on CPU, and these fuse with their neighbours.
    members = team[None, :] == jnp.arange(C.NUM_TEAMS)[:, None]  # (2, N)
    in_bush = inside & (zone_type == C.ZONE_BUSH)[None, :]  # (N, Z)
    seeing = members & alive[None, :]
    team_in_bush = jnp.any(seeing[:, :, None] & in_bush[None, :, :], axis=1)  # (2, Z)
    # hidden[T, t]: t sits in a bush that no living member of team T is in ...
    hidden = jnp.any(in_bush[None, :, :] & ~team_in_bush[:, None, :], axis=-1)  # (2, N)
    # ... and no member of T attacked t or was attacked by it this step.
    revealed = jnp.any(members[:, :, None] & interacted[None, :, :], axis=1)  # (2, N)
    return hidden & ~revealed


def apply_bush_hiding(fov: jax.Array, team: jax.Array, hidden: jax.Array) -> jax.Array:
    """visible[v, t] = fov[v, t] unless t is an opponent hidden from v's team (`bush_hidden`).
    The row of v's team is picked by a select (a gather is slow under vmap)."""
    same_team = team[:, None] == team[None, :]
    hidden_from = jnp.where((team == C.ALLY)[:, None], hidden[C.ALLY][None, :],
                            hidden[C.ENEMY][None, :])
    return fov & (same_team | ~hidden_from)
