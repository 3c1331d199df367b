"""Observations, the global state and the action mask.

Per-agent observation, same content and order as the reference (TABX_REFERENCE.md section 3):
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

import functools

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
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


def unit_features(state: EnvState, params: EnvParams) -> jax.Array:
    """(N, 14) own-style features of every unit, absolute positions, not masked."""
    u = params.units
    half = 0.5 * params.physics.arena_size
    alive = state.alive.astype(jnp.float32)
    return jnp.concatenate([
        (state.health / HEALTH_SCALE)[:, None],
        (state.health / jnp.maximum(u.max_health, 1e-6))[:, None],
        state.position / half,
        (state.heading / TWO_PI)[:, None],
        (u.attack_range / RANGE_SCALE)[:, None],
        (u.damage / DAMAGE_SCALE)[:, None],
        (state.cooldown / COOLDOWN_SCALE)[:, None],
        (state.cooldown / jnp.maximum(u.cooldown, 1e-6))[:, None],
        (u.radius / RADIUS_SCALE)[:, None],
        (jnp.log1p(jnp.maximum(u.mass, 0.0)) / MASS_LOG_SCALE)[:, None],
        (u.sight_angle / TWO_PI)[:, None],
        alive[:, None],
        (state.speed / SPEED_SCALE)[:, None],
    ], axis=-1) * u.active[:, None]


def zone_features(params: EnvParams, origin: jax.Array) -> jax.Array:
    """(..., Z, 6) zone features relative to `origin` (..., 2); empty slots are zeros."""
    z = params.zones
    half = 0.5 * params.physics.arena_size
    used = (z.zone_type > 0).astype(jnp.float32)
    effect = z.effect / jnp.where(z.zone_type == C.ZONE_LAVA, LAVA_EFFECT_SCALE, 1.0)
    rel = (z.centre - origin[..., None, :]) / half
    shape = rel.shape[:-1]
    feats = jnp.concatenate([
        jnp.broadcast_to((z.zone_type / ZONE_TYPE_SCALE)[:, None], (*shape, 1)),
        rel,
        jnp.broadcast_to(z.semi_axes / AXES_SCALE, (*shape, 2)),
        jnp.broadcast_to(effect[:, None], (*shape, 1)),
    ], axis=-1)
    return feats * used[:, None]


@functools.cache
def _observation_layout(n: int, z: int) -> tuple[np.ndarray, np.ndarray]:
    """Where every element of the (N, obs_size) observation comes from, as constant indices.

    `observe` lays the distinct values of one env out in a flat source vector, `[own (N, 14) |
    per-unit (N, 16) | relative positions (N, N, 2) | is ally (N, N) | attackable (N, N) |
    zones (N, Z, 6)]`, and its visibility in a flat mask `[visible (N, N) | True]`. Returns
    (value index, mask index), both (N, obs_size) int32: element [i, p] of the observation is
    `source[value[i, p]]` where `mask[mask_index[i, p]]`, else 0.
    """
    own, per_unit = 0, 14 * n
    rel = per_unit + 16 * n
    ally = rel + 2 * n * n
    attackable = ally + n * n
    zones = attackable + n * n
    i = np.arange(n)[:, None]
    j = cyclic_order(n)  # (N, N-1) the other units in each viewer's order
    block = np.broadcast_to(per_unit + 16 * j[..., None] + np.arange(16), (n, n - 1, 16)).copy()
    pair = n * i + j  # (N, N-1) index of (viewer, other) in an (N, N) matrix
    block[..., 2] = rel + 2 * pair
    block[..., 3] = rel + 2 * pair + 1
    block[..., 13] = ally + pair
    block[..., 14] = attackable + pair
    value = np.concatenate([
        own + 14 * i + np.arange(14),
        block.reshape(n, -1),
        zones + 6 * z * i + np.arange(6 * z),
    ], axis=1)
    always = n * n  # the mask's last entry, True
    mask = np.concatenate([
        np.full((n, 14), always),
        np.broadcast_to(pair[..., None], (n, n - 1, 16)).reshape(n, -1),
        np.full((n, 6 * z), always),
    ], axis=1)
    value, mask = value.astype(np.int32), mask.astype(np.int32)
    value.flags.writeable = mask.flags.writeable = False  # cached: shared by every caller
    return value, mask


def cyclic_order(n: int) -> np.ndarray:
    """(N, N-1) indices of the other units in each viewer's cyclic order i+1, ..., i-1."""
    return (np.arange(n)[:, None] + 1 + np.arange(n - 1)[None, :]) % n


def cyclic_others(n: int) -> jax.Array:
    """`cyclic_order` as a jax array."""
    return jnp.asarray(cyclic_order(n))


def observe(config: EnvConfig, state: EnvState, params: EnvParams) -> jax.Array:
    """(N, obs_size) observation of every unit slot (padded slots get zeros).

    Written as one gather: every distinct value (own features, per-unit features, pairwise
    relative positions, is-ally and attackable flags, zone features) is computed once into a
    flat source vector, and the whole observation, in viewer-relative cyclic order, is read
    from it at constant indices (`_observation_layout`), masked by visibility. XLA:CPU emits
    that as one loop that writes the observation once, in place of per-viewer gathers with
    transposes, basis-vector sums and a final concatenate (docs/benchmarks.md, "Observation
    speed-up (session 3)"). Same values as the straightforward construction, bit for bit.
    """
    n = config.num_units
    u = params.units
    active = u.active.astype(bool)
    own = unit_features(state, params)  # (N, 14)
    half = 0.5 * params.physics.arena_size
    zeros = jnp.zeros((n, 2), jnp.float32)
    # Own-style features in the other-unit layout (pairwise slots 2, 3, 13, 14 unused).
    per_unit = jnp.concatenate([own[:, :2], zeros, own[:, 4:13], zeros, own[:, 13:]], -1)
    rel = (state.position[None, :, :] - state.position[:, None, :]) / half  # (N, N, 2)
    is_ally = (u.team[None, :] == u.team[:, None]).astype(jnp.float32)
    attackable = state.attackable.astype(jnp.float32)
    # Padded viewers see nothing (their whole observation is zeros).
    visible = state.visible & active[None, :] & active[:, None]
    zones = zone_features(params, state.position) * u.active[:, None, None]  # (N, Z, 6)
    source = jnp.concatenate([own.reshape(-1), per_unit.reshape(-1), rel.reshape(-1),
                              is_ally.reshape(-1), attackable.reshape(-1), zones.reshape(-1)])
    shown = jnp.concatenate([visible.reshape(-1), jnp.ones(1, bool)])
    value, mask = _observation_layout(n, config.max_zones)
    # Flat indices, reshaped at the end: with (N, obs_size) indices XLA laid the vmapped result
    # out env-minor inside a scan (strided reads of the source), 1.2x slower at 10v10.
    obs = jnp.where(shown.at[mask.reshape(-1)].get(mode="promise_in_bounds"),
                    source.at[value.reshape(-1)].get(mode="promise_in_bounds"), 0.0)
    return obs.reshape(value.shape)


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
