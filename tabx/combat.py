"""Attacks and heals: who can hit whom, nearest-target choice, and simultaneous resolution.

Every health change of a step (wall, attacks, heals, lava) is summed and clamped once, so the
outcome does not depend on unit index order (the reference clamps sequentially, in index
order, which favours allies).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tabx.geometry import hurtbox_overlap
from tabx.selection import row_argmin


def attack_targets(rel: jax.Array, trig: jax.Array, radius: jax.Array,
                   attack_range: jax.Array, team: jax.Array, heals: jax.Array,
                   alive: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(attackable (N, N), target (N,), has_target (N,)).

    attackable[a, t]: t overlaps a's hurtbox, both are alive, t != a, and t is an enemy of a
    (damage dealers) or an ally of a (healers). The target is the nearest attackable unit by
    centre distance. Dead units are never attackable, so they are never hit, healed or revived.
    """
    attackable = attackable_pairs(rel, trig, radius, attack_range, team, heals, alive)
    # Materialise once: the target choice and has_target would each re-derive it otherwise.
    attackable = jax.lax.optimization_barrier(attackable)
    return (attackable, *nearest_targets(rel, attackable))


def attackable_pairs(rel: jax.Array, trig: jax.Array, radius: jax.Array,
                     attack_range: jax.Array, team: jax.Array, heals: jax.Array,
                     alive: jax.Array) -> jax.Array:
    """attackable (N, N) of `attack_targets`."""
    in_box = hurtbox_overlap(rel, trig, radius, attack_range)
    same_team = team[:, None] == team[None, :]
    role_ok = jnp.where(heals[:, None], same_team, ~same_team)
    not_self = ~jnp.eye(team.shape[0], dtype=bool)
    return in_box & role_ok & not_self & alive[:, None] & alive[None, :]


def nearest_targets(rel: jax.Array, attackable: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(target (N,), has_target (N,)): the nearest attackable unit by centre distance."""
    dist2 = jnp.sum(rel * rel, -1)
    target, _, has_target = row_argmin(dist2, attackable)
    return target, has_target


def resolve_attacks(attacking: jax.Array, has_target: jax.Array, target: jax.Array,
                    damage: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(health_loss (N,), hit (N,), interacted (N, N)) of this step's attacks.

    `attacking[a]`: a chose ATTACK with its cooldown ready. It hits its target (chosen at the
    end of the last step, the one its observation showed) if it had one. Damage and heals of all
    attackers are summed per target; a heal is a negative loss. `interacted` is the symmetric
    attacked-or-was-attacked matrix used by the bush reveal rule.
    """
    hit = attacking & has_target
    n = target.shape[0]
    pair = (target[:, None] == jnp.arange(n)[None, :]) & hit[:, None]  # pair[a, t]
    # A sum over a broadcast product, not a matmul: vmapped tiny matmuls are slow on CPU.
    health_loss = jnp.sum(jnp.where(pair, damage[:, None], 0.0), axis=0)
    return health_loss, hit, pair | pair.T
