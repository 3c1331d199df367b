"""Levels are data: any level of one EnvConfig runs through the same compiled reset and step.

50 random levels (unit counts 1..max per team, zone counts 0..max, unit stats, positions,
physics, arena size, opponent heuristic parameters, reward modes and behaviour profiles all
different) go through one `jax.jit(env.step)` and one `jax.jit(env.reset)`; each must compile
exactly once. The compilations are counted twice: by the jitted functions' executable caches
and by JAX's own trace events (a retrace of anything during the loop would show up there).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tabx import constants as C
from tabx.compile_counter import CompileCounter
from tabx.env import TabxEnv
from tabx.params import EnvConfig, heuristic_params, make_level, physics_params, stack_levels
from tabx.profiles import ALL_CHOICES
from tabx.scenarios import config_for, load_named

CONFIG = EnvConfig(max_allies=4, max_enemies=4, max_zones=3, max_steps=64)
N = CONFIG.num_units
KEY = jax.random.PRNGKey(0)
SCENARIOS = ("crossfire", "elbow", "2F1M2Avs2S1K_2L2B2S")



def random_level(rng: np.random.Generator, i: int):
    width, height = rng.uniform(30, 200), rng.uniform(30, 150)

    def units(count):
        out = []
        for _ in range(count):
            name = str(rng.choice(C.UNIT_NAMES))
            rec = dict(unit=name, position=(rng.uniform(-width / 2, width / 2),
                                            rng.uniform(-height / 2, height / 2)),
                       heading=rng.uniform(-math.pi, 3 * math.pi))
            if rng.random() < 0.5:
                rec.update(health=float(rng.uniform(1, 500)), speed=float(rng.uniform(0, 3)),
                           damage=float(rng.uniform(-20, 100)),
                           attack_range=float(rng.uniform(0, 40)),
                           cooldown=float(rng.uniform(0.1, 10)),
                           radius=float(rng.uniform(0.5, 4)), mass=float(rng.uniform(0.5, 60)),
                           sight_angle=float(rng.uniform(0.3, 3.0)))
                rec["max_health"] = rec["health"] * float(rng.uniform(1, 2))
            out.append(rec)
        return out

    zones = []
    for _ in range(int(rng.integers(0, CONFIG.max_zones + 1))):
        kind = str(rng.choice(["lava", "bush", "swamp"]))
        zones.append(dict(type=kind, centre=(rng.uniform(-40, 40), rng.uniform(-30, 30)),
                          semi_axes=(rng.uniform(1, 20), rng.uniform(1, 20)),
                          effect=float(rng.uniform(0, 1) if kind != "lava" else
                                       rng.uniform(0, 30))))
    tiers = list(("random", "novice", "medium", "advanced", "expert"))
    ally = str(rng.choice(tiers))
    enemy = dict(epsilon=float(rng.random()), aggressive_threshold=float(rng.random()),
                 assassin_speed=float(rng.uniform(0.5, 3)),
                 ranger_attack_range=float(rng.uniform(2, 30)))
    physics = physics_params(
        str(rng.choice(["default", "fast"])), restitution=float(rng.random()),
        slop=float(rng.uniform(0, 0.05)), percent=float(rng.random()),
        boundary_damage_rate=float(rng.uniform(0, 0.5)),
        turn_rate=float(rng.uniform(0.1, 2 * math.pi)), arena_size=(width, height))
    level = make_level(CONFIG, units(1 + i % CONFIG.max_allies),
                       units(1 + (i // CONFIG.max_allies) % CONFIG.max_enemies), zones,
                       heuristic=heuristic_params(ally, enemy), physics=physics,
                       reward_mode=i % 2)
    # A different mix of the reference's behaviours per level (tabx.profiles).
    return level.replace(profile=jnp.asarray((i * 0x9E3779B1) & ALL_CHOICES, jnp.int32))


@pytest.fixture(scope="module")
def random_levels():
    rng = np.random.default_rng(1234)
    levels = [random_level(rng, i) for i in range(50)]
    counts = {(int(np.sum(np.asarray(lv.units.active)[:CONFIG.max_allies])),
               int(np.sum(np.asarray(lv.units.active)[CONFIG.max_allies:])),
               int(np.sum(np.asarray(lv.zones.zone_type) > 0))) for lv in levels}
    assert len(counts) >= 12  # the levels really differ in shape-like ways
    return levels


def _actions(rng: np.random.Generator, steps: int) -> list[jax.Array]:
    return [jnp.asarray(rng.integers(0, C.NUM_ACTIONS, N), jnp.int32) for _ in range(steps)]


def test_one_compilation_for_fifty_levels(random_levels):
    env = TabxEnv(CONFIG)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    actions = _actions(np.random.default_rng(0), 3)
    # Warm up on the first level, then count every trace from here on.
    _, state = reset(KEY, random_levels[0])
    step(KEY, state, actions[0], random_levels[0])
    with CompileCounter() as cc:
        for params in random_levels:
            obs, state = reset(KEY, params)
            for a in actions:
                obs, state, reward, done, _ = step(KEY, state, a, params)
            assert obs.shape == (N, CONFIG.obs_size)
            # numpy checks: an eager jnp op would itself trace and compile.
            assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(reward)).all()
    assert reset._cache_size() == 1
    assert step._cache_size() == 1
    assert cc.traces == 0 and cc.compiles == 0, f"{cc.traces} retraces over 50 levels"


def test_one_compilation_for_batches_of_levels(random_levels):
    env = TabxEnv(CONFIG)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(None, 0)))
    step = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0, 0)))
    a = jnp.asarray(np.random.default_rng(1).integers(0, C.NUM_ACTIONS, (10, N)), jnp.int32)
    for k in range(5):
        batch = stack_levels(random_levels[10 * k: 10 * (k + 1)])
        obs, state = reset(KEY, batch)
        obs, state, reward, done, _ = step(KEY, state, a, batch)
        assert obs.shape == (10, N, CONFIG.obs_size) and reward.shape == (10, 2)
    assert reset._cache_size() == 1 and step._cache_size() == 1


def test_bundled_scenarios_share_one_compiled_step():
    scenarios = [load_named(name) for name in SCENARIOS]
    config = config_for(scenarios)
    env = TabxEnv(config)
    n = config.num_units
    reset, step, mask_fn = jax.jit(env.reset), jax.jit(env.step), jax.jit(env.action_mask)
    rng = np.random.default_rng(0)
    variants = []
    for sc in scenarios:
        variants.append(sc.to_level(config))
        variants.append(sc.to_level(config, physics="fast",
                                    heuristic={"ally": "expert", "enemy": "random"},
                                    reward_mode=C.REWARD_RATIO_OF_SUMS))
    for sc, params in zip([s for s in scenarios for _ in (0, 1)], variants, strict=True):
        active = np.asarray(params.units.active)
        assert active[:config.max_allies].sum() == len(sc.allies)
        assert active[config.max_allies:].sum() == len(sc.enemies)
        obs, state = reset(KEY, params)
        assert obs.shape == (n, config.obs_size)
        for _ in range(5):
            mask = np.asarray(mask_fn(state, params))
            legal = [rng.choice(np.flatnonzero(row)) for row in mask]
            obs, state, reward, done, _ = step(KEY, state, jnp.asarray(legal, jnp.int32), params)
            assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(reward)).all()
        assert np.asarray(env.world_state(state, params)).shape == (config.state_size,)
    assert reset._cache_size() == 1
    assert step._cache_size() == 1
    assert mask_fn._cache_size() == 1
