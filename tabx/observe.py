"""Observations, the global state and the action mask.

Per-agent observation, same content and order as the reference (docs/differences.md):
  own unit (14): health, health ratio, x, y, heading, attack range, damage, cooldown elapsed,
      cooldown ratio, radius, mass, sight angle, alive, speed;
  each other unit (16, in viewer-relative cyclic order i+1 .. N-1, 0 .. i-1; zeros where not
      visible): health, health ratio, relative x, y, heading, attack range, damage, cooldown
      elapsed, cooldown ratio, radius, mass, sight angle, alive, is ally, attackable by the
      viewer, speed;
  each zone slot (6; zeros for empty slots): type, relative x, y, semi-axis x, y, effect.
Unlike the reference, features are scaled to order one (the `*_SCALE` constants below; see
docs/observations.md) and every ratio has a safe denominator, so padding never makes NaN.

Global state (for centralised critics): for every unit slot its 14 own features (absolute
position, no masking) plus its team, then every zone slot's 6 features in absolute coordinates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.observe_kernel import assemble_observation
from tabx.params import EnvConfig, EnvParams
from tabx.state import EnvState

HEALTH_SCALE = 200.0  # health / 200: healer 0.125 .. mammoth 3.4
RANGE_SCALE = 40.0  # attack range / 40: cannon 1.0
DAMAGE_SCALE = 50.0  # damage / 50: cannon 1.6, healer -0.14
COOLDOWN_SCALE = 10.0  # seconds / 10
RADIUS_SCALE = 4.25  # radius / 4.25: mammoth 1.0
MASS_LOG_SCALE = 4.0  # log(1 + mass) / 4: farmer 0.17, mammoth 0.98
SPEED_SCALE = 1.4  # speed / 1.4: assassin 1.0
AXES_SCALE = 20.0  # zone semi-axes / 20
LAVA_EFFECT_SCALE = 20.0  # lava health per second / 20 (swamp fractions are already in [0, 1])
ZONE_TYPE_SCALE = 3.0
TWO_PI = 2.0 * jnp.pi


def inverse_half_arena(params: EnvParams) -> jax.Array:
    """(2,) 1 / (arena size / 2): positions are scaled by this product rather than divided by
    half the arena, one rounding rule in every program (XLA:CPU turned such a division into
    this product in some programs and not in others, a last-bit difference)."""
    return 1.0 / (0.5 * params.physics.arena_size)


def unit_features(state: EnvState, params: EnvParams) -> jax.Array:
    """(N, 14) own-style features of every unit, absolute positions, not masked."""
    u = params.units
    alive = state.alive.astype(jnp.float32)
    # The state's clock may run one dt past the cooldown (tabx.env.cooldown_cap); what a unit
    # observes stops at the cooldown in every profile.
    cooldown = jnp.minimum(state.cooldown, u.cooldown)
    return jnp.concatenate([
        (state.health / HEALTH_SCALE)[:, None],
        (state.health / jnp.maximum(u.max_health, 1e-6))[:, None],
        state.position * inverse_half_arena(params),
        (state.heading / TWO_PI)[:, None],
        (u.attack_range / RANGE_SCALE)[:, None],
        (u.damage / DAMAGE_SCALE)[:, None],
        (cooldown / COOLDOWN_SCALE)[:, None],
        (cooldown / jnp.maximum(u.cooldown, 1e-6))[:, None],
        (u.radius / RADIUS_SCALE)[:, None],
        (jnp.log1p(jnp.maximum(u.mass, 0.0)) / MASS_LOG_SCALE)[:, None],
        (u.sight_angle / TWO_PI)[:, None],
        alive[:, None],
        (state.speed / SPEED_SCALE)[:, None],
    ], axis=-1) * u.active[:, None]


def zone_features(params: EnvParams, origin: jax.Array) -> jax.Array:
    """(..., Z, 6) zone features relative to `origin` (..., 2); empty slots are zeros."""
    z = params.zones
    used = (z.zone_type > 0).astype(jnp.float32)
    effect = z.effect / jnp.where(z.zone_type == C.ZONE_LAVA, LAVA_EFFECT_SCALE, 1.0)
    rel = (z.centre - origin[..., None, :]) * inverse_half_arena(params)
    shape = rel.shape[:-1]
    feats = jnp.concatenate([
        jnp.broadcast_to((z.zone_type / ZONE_TYPE_SCALE)[:, None], (*shape, 1)),
        rel,
        jnp.broadcast_to(z.semi_axes / AXES_SCALE, (*shape, 2)),
        jnp.broadcast_to(effect[:, None], (*shape, 1)),
    ], axis=-1)
    return feats * used[:, None]


def observe(config: EnvConfig, state: EnvState, params: EnvParams) -> jax.Array:
    """(N, obs_size) observation of every unit slot (padded slots get zeros).

    Own features, the visibility mask and zone features are computed here; the rows, with the
    other units in each viewer's cyclic order, are assembled by one primitive
    (`tabx.observe_kernel`: a native kernel on the CPU, XLA elsewhere, the same bits).
    tests/tabx/test_observe_fast.py checks against a per-viewer reference.
    """
    n = config.num_units
    u = params.units
    active = u.active.astype(bool)
    own = unit_features(state, params)  # (N, 14)
    # Padded viewers see nothing (their whole observation is zeros).
    seen = state.visible & active[None, :] & active[:, None]
    zones = (zone_features(params, state.position) * u.active[:, None, None]).reshape(n, -1)
    return assemble_observation(own, state.position, inverse_half_arena(params), u.team, seen,
                                state.attackable, zones)


def world_state(config: EnvConfig, state: EnvState, params: EnvParams) -> jax.Array:
    """(state_size,) global state: all units unmasked (+ team), zones in absolute coordinates."""
    own = unit_features(state, params)
    team = (params.units.team.astype(jnp.float32) * params.units.active)[:, None]
    zones = zone_features(params, jnp.zeros(2))
    return jnp.concatenate([jnp.concatenate([own, team], -1).reshape(-1), zones.reshape(-1)])


def cooldown_ready(elapsed: jax.Array, cooldown: jax.Array) -> jax.Array:
    """The attack is ready; the tolerance absorbs float error of summed time steps (0.1 * 25)."""
    return elapsed + 1e-4 >= cooldown


def action_mask(state: EnvState, params: EnvParams) -> jax.Array:
    """(N, 8) bool legal actions. ATTACK needs the cooldown ready; dead or padded units may only
    IDLE (every action is a no-op for them, and a single legal action keeps sampling simple)."""
    able = state.alive
    ready = cooldown_ready(state.cooldown, params.units.cooldown)
    n = state.alive.shape[0]
    mask = jnp.broadcast_to(able[:, None], (n, C.NUM_ACTIONS))
    mask = mask.at[:, C.ATTACK].set(able & ready)
    return mask.at[:, C.IDLE].set(True)


def pick_legal(uniform: jax.Array, mask: jax.Array) -> jax.Array:
    """The legal action of a (..., 8) bool mask picked by `uniform` in [0, 1) (same leading
    shape): uniform over the legal actions. One draw per unit, not one per action: 8 times
    fewer random bits than Gumbel-max sampling, which matters on CPU where threefry dominates
    a random rollout. Every row needs a legal action (IDLE always is).

    The k-th legal action's index is the number of positions whose running count of legal
    actions is at most k: plain sums (no cumsum or argmax, slow on CPU)."""
    count = jnp.sum(mask, axis=-1)
    pick = jnp.minimum(jnp.floor(uniform * count).astype(jnp.int32), count - 1)
    upto = jnp.arange(mask.shape[-1])[:, None] <= jnp.arange(mask.shape[-1])[None, :]
    running = jnp.sum(mask[..., :, None] & upto, axis=-2)  # legal actions at or before j
    return jnp.sum(running <= pick[..., None], axis=-1).astype(jnp.int32)
