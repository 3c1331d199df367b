"""`tabx.observe.observe` (pairwise blocks cut into contiguous pieces, see its docstring) against a
straightforward per-viewer, per-other-unit reference written out here from the documented
layout (docs/environment.md, "Observations"), over random levels and arbitrary states:
random positions, health, cooldowns, dead and padded units, and visibility and attackable
matrices that need not be consistent with the geometry (so every mask is exercised).
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx import observe as O
from tabx.env import TabxEnv
from tabx.params import EnvConfig
from tabx.random_levels import random_level

CONFIGS = (
    EnvConfig(max_allies=1, max_enemies=1, max_zones=0),
    EnvConfig(max_allies=2, max_enemies=3, max_zones=1),
    EnvConfig(max_allies=4, max_enemies=4, max_zones=3),
)
EXAMPLES = int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "25"))
_OBSERVE = {config: jax.jit(lambda s, p, c=config: O.observe(c, s, p)) for config in CONFIGS}
_INITIAL = {config: jax.jit(TabxEnv(config).initial_state) for config in CONFIGS}


def reference_observation(config: EnvConfig, state, params) -> np.ndarray:
    """(N, obs_size) observation, one viewer and one other unit at a time (float64)."""
    s = jax.tree.map(lambda x: np.asarray(x, np.float64), state)
    u = jax.tree.map(lambda x: np.asarray(x, np.float64), params.units)
    z = jax.tree.map(lambda x: np.asarray(x, np.float64), params.zones)
    half = 0.5 * np.asarray(params.physics.arena_size, np.float64)
    n, nz = config.num_units, config.max_zones
    active = u.active > 0

    def own(t):
        if not active[t]:
            return np.zeros(14)
        cooldown = min(s.cooldown[t], u.cooldown[t])  # observed up to the cooldown
        return np.array([
            s.health[t] / O.HEALTH_SCALE, s.health[t] / max(u.max_health[t], 1e-6),
            s.position[t, 0] / half[0], s.position[t, 1] / half[1],
            s.heading[t] / (2 * math.pi), u.attack_range[t] / O.RANGE_SCALE,
            u.damage[t] / O.DAMAGE_SCALE, cooldown / O.COOLDOWN_SCALE,
            cooldown / max(u.cooldown[t], 1e-6), u.radius[t] / O.RADIUS_SCALE,
            math.log1p(max(u.mass[t], 0.0)) / O.MASS_LOG_SCALE,
            u.sight_angle[t] / (2 * math.pi), float(s.alive[t] > 0), s.speed[t] / O.SPEED_SCALE,
        ])

    obs = np.zeros((n, config.obs_size))
    for i in range(n):
        row = [own(i)]
        for k in range(n - 1):
            j = (i + 1 + k) % n  # viewer-relative cyclic order i+1, ..., N-1, 0, ..., i-1
            block = np.zeros(16)
            if active[i] and active[j] and s.visible[i, j] > 0:
                f = own(j)
                block[:2] = f[:2]
                block[2:4] = (s.position[j] - s.position[i]) / half
                block[4:13] = f[4:13]
                block[13] = float(u.team[i] == u.team[j])
                block[14] = float(s.attackable[i, j] > 0)
                block[15] = f[13]
            row.append(block)
        for q in range(nz):
            zone = np.zeros(6)
            if active[i] and z.zone_type[q] > 0:
                lava = z.zone_type[q] == C.ZONE_LAVA
                zone[:] = [z.zone_type[q] / O.ZONE_TYPE_SCALE,
                           *((z.centre[q] - s.position[i]) / half),
                           *(z.semi_axes[q] / O.AXES_SCALE),
                           z.effect[q] / (O.LAVA_EFFECT_SCALE if lava else 1.0)]
            row.append(zone)
        obs[i] = np.concatenate(row)
    return obs


def random_state(config: EnvConfig, rng: np.random.Generator):
    """A random level and an arbitrary state for it (not necessarily reachable)."""
    units = int(rng.integers(1, min(config.max_allies, config.max_enemies) + 1))
    params = random_level(rng, config, min_units=units, max_units=units,
                          max_zones=config.max_zones, validate=False)
    state = _INITIAL[config](params)
    n = config.num_units
    f32 = np.float32
    state = state.replace(
        position=jnp.asarray(rng.uniform(-60, 60, (n, 2)).astype(f32)),
        heading=jnp.asarray(rng.uniform(0, 2 * math.pi, n).astype(f32)),
        health=jnp.asarray((rng.uniform(0, 1, n) * np.asarray(params.units.max_health)
                            ).astype(f32)),
        alive=jnp.asarray(rng.uniform(size=n) < 0.7) & params.units.active.astype(bool),
        cooldown=jnp.asarray(rng.uniform(0, 5, n).astype(f32)),
        speed=jnp.asarray(rng.uniform(0, 1.5, n).astype(f32)),
        visible=jnp.asarray(rng.uniform(size=(n, n)) < 0.6),
        attackable=jnp.asarray(rng.uniform(size=(n, n)) < 0.4),
    )
    return state, params


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.integers(0, len(CONFIGS) - 1), seed=st.integers(0, 2**31 - 1))
def test_observe_matches_reference(which, seed):
    config = CONFIGS[which]
    state, params = random_state(config, np.random.default_rng(seed))
    obs = np.asarray(_OBSERVE[config](state, params))
    ref = reference_observation(config, state, params)
    assert obs.shape == (config.num_units, config.obs_size) and obs.dtype == np.float32
    np.testing.assert_allclose(obs, ref, rtol=2e-6, atol=1e-6)
    np.testing.assert_array_equal(obs[ref == 0.0], 0.0)  # masked and empty slots exactly zero


def test_observe_under_vmap_matches_per_env():
    config = CONFIGS[2]
    rng = np.random.default_rng(7)
    pairs = [random_state(config, rng) for _ in range(4)]
    states = jax.tree.map(lambda *x: jnp.stack(x), *[s for s, _ in pairs])
    levels = jax.tree.map(lambda *x: jnp.stack(x), *[p for _, p in pairs])
    batched = np.asarray(jax.jit(jax.vmap(lambda s, p: O.observe(config, s, p)))(states, levels))
    for b, (state, params) in enumerate(pairs):
        np.testing.assert_array_equal(batched[b], np.asarray(_OBSERVE[config](state, params)))
