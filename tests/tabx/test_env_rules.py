"""Behaviour tests of the simulator, one small hand-built situation per rule.

Numbers marked [ref] are the reference implementation's verified numbers
(TABX_REFERENCE.md section 4); the others follow from the rules in tabx/env.py's docstring.
All tests share one EnvConfig (3 v 3, 2 zones) and one compiled step (module fixture).
"""

from __future__ import annotations

import inspect
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from envtools import (
    A0,
    A1,
    A2,
    CONFIG,
    DEG,
    E0,
    E1,
    E2,
    FAR_ALLY,
    FAR_ENEMY,
    KEY,
    N,
    Sim,
    kill,
    level,
    unit,
    zone,
)

from tabx import constants as C
from tabx.physics import resolve_collisions

UP, DOWN, LEFT, RIGHT = C.UP, C.DOWN, C.LEFT, C.RIGHT
ATTACK, TURN_RIGHT, TURN_LEFT, IDLE = C.ATTACK, C.TURN_RIGHT, C.TURN_LEFT, C.IDLE


@pytest.fixture(scope="module")
def sim() -> Sim:
    return Sim(CONFIG)


def np_(x) -> np.ndarray:
    return np.asarray(x)


def lone_farmer(x: float = 0.0, y: float = 0.0, heading: float = 0.0, **stats):
    """One ally farmer in slot 0, bystanders elsewhere."""
    return level([unit("farmer", x, y, heading, **stats)], [FAR_ENEMY])


# --- API shapes ------------------------------------------------------------------------------


def test_step_signature_and_shapes(sim):
    params = level([unit("farmer", 0, 0)], [unit("archer", 10, 0, math.pi)])
    obs, state = sim.reset(params)
    assert obs.shape == (N, CONFIG.obs_size)
    assert CONFIG.obs_size == 14 + 16 * (N - 1) + 6 * CONFIG.max_zones
    obs, state, reward, done, info = sim.step(state, None, params)
    assert obs.shape == (N, CONFIG.obs_size)
    assert reward.shape == (2,) and jnp.issubdtype(reward.dtype, jnp.floating)
    assert done.shape == () and done.dtype == jnp.bool_
    assert isinstance(info, dict)
    assert sim.world_state_fn(state, params).shape == (CONFIG.state_size,)
    assert sim.mask(state, params).shape == (N, C.NUM_ACTIONS)
    assert int(state.step) == 1


# --- movement and turning --------------------------------------------------------------------


@pytest.mark.parametrize("action, direction", [(UP, (0, 1)), (DOWN, (0, -1)), (LEFT, (-1, 0)),
                                               (RIGHT, (1, 0))])
def test_move_lags_its_action_by_one_step(sim, action, direction):
    # Heading 60 degrees: moves are in the world frame, whatever the heading.
    params = lone_farmer(heading=60 * DEG)
    _, s0 = sim.reset(params)
    (_, s1, *_), (_, s2, *_), (_, s3, *_) = sim.run(params, [{A0: action}, None, None])
    step = 1.1 * 0.5  # speed * dt
    np.testing.assert_allclose(np_(s1.position[A0]), [0, 0], atol=1e-6)  # not yet moved
    np.testing.assert_allclose(np_(s1.velocity[A0]), np.multiply(direction, 1.1), atol=1e-6)
    np.testing.assert_allclose(np_(s2.position[A0]), np.multiply(direction, step), atol=1e-6)
    np.testing.assert_allclose(np_(s2.velocity[A0]), [0, 0], atol=1e-6)  # IDLE stops
    np.testing.assert_allclose(np_(s3.position[A0]), np_(s2.position[A0]), atol=1e-6)
    np.testing.assert_allclose(np_(s1.heading[A0]), np_(s0.heading[A0]), atol=1e-6)


@pytest.mark.parametrize("action, sign", [(TURN_LEFT, 1), (TURN_RIGHT, -1)])
def test_turn_takes_effect_in_the_same_step(sim, action, sign):
    params = lone_farmer(heading=90 * DEG)
    (_, s1, *_), (_, s2, *_) = sim.run(params, [{A0: action}, {A0: action}])
    # pi/6 rad/s * 0.5 s = 15 degrees per turn, applied at once; no motion.
    np.testing.assert_allclose(np_(s1.heading[A0]), (90 + sign * 15) * DEG, atol=1e-5)
    np.testing.assert_allclose(np_(s2.heading[A0]), (90 + sign * 30) * DEG, atol=1e-5)
    np.testing.assert_allclose(np_(s2.position[A0]), [0, 0], atol=1e-6)


def test_turning_rotates_hurtbox_and_view(sim):
    # After six left turns (90 degrees) the farmer hits and sees up, no longer to the right;
    # turning on round the full circle brings it back (accumulated rounding included).
    params = level([unit("farmer", 0, 0, 0.0), FAR_ALLY],
                   [unit("farmer", 4.2, 0, 0.0), unit("farmer", 0, 4.2, 0.0), FAR_ENEMY])
    _, s = sim.reset(params)
    assert bool(s.attackable[A0, E0]) and not bool(s.attackable[A0, E1])
    res = sim.run(params, [{A0: TURN_LEFT}] * 6, state=s)
    s6 = res[-1][1]
    np.testing.assert_allclose(float(s6.heading[A0]), math.pi / 2, atol=1e-5)
    assert bool(s6.attackable[A0, E1]) and not bool(s6.attackable[A0, E0])
    assert bool(s6.visible[A0, E1]) and not bool(s6.visible[A0, E0])
    # 30 right turns (450 degrees) from 90 degrees: back to heading 0, modulo 2 pi.
    res = sim.run(params, [{A0: TURN_RIGHT}] * 30, state=s6)
    s_back = res[-1][1]
    h = float(s_back.heading[A0])
    assert 0.0 <= h < 2 * math.pi
    assert min(h, 2 * math.pi - h) < 1e-4
    assert bool(s_back.attackable[A0, E0]) and bool(s_back.visible[A0, E0])
    assert not bool(s_back.attackable[A0, E1])


def test_many_turns_keep_heading_and_geometry_consistent(sim):
    # 200 left turns = 3000 degrees = 120 degrees (mod 360): the hurtbox and the view follow the
    # stored heading after a long episode of turning.
    d = (math.cos(120 * DEG), math.sin(120 * DEG))
    params = level([unit("farmer", 0, 0, 0.0), FAR_ALLY],
                   [unit("farmer", 4.2 * d[0], 4.2 * d[1], 0.0),
                    unit("farmer", 30 * d[1], -30 * d[0], 0.0), FAR_ENEMY])
    res = sim.run(params, [{A0: TURN_LEFT}] * 200)
    s = res[-1][1]
    np.testing.assert_allclose(float(s.heading[A0]), 120 * DEG, atol=1e-3)
    assert bool(s.attackable[A0, E0]) and bool(s.visible[A0, E0])
    assert not bool(s.visible[A0, E1])  # 90 degrees to the right of the heading


def test_heading_wraps_into_zero_two_pi(sim):
    params = lone_farmer(heading=0.0)
    (_, s1, *_), = sim.run(params, [{A0: TURN_RIGHT}])
    np.testing.assert_allclose(np_(s1.heading[A0]), 2 * math.pi - 15 * DEG, atol=1e-5)


def test_move_cancelled_by_non_move_action(sim):
    params = lone_farmer()
    for stop in (ATTACK, TURN_LEFT, TURN_RIGHT, IDLE):
        (_, s1, *_), (_, s2, *_) = sim.run(params, [{A0: RIGHT}, {A0: stop}])
        np.testing.assert_allclose(np_(s2.velocity[A0]), [0, 0], atol=1e-6)
        np.testing.assert_allclose(np_(s2.position[A0]), [0.55, 0], atol=1e-6)


# --- arena wall ------------------------------------------------------------------------------


def test_wall_damage_and_clipping(sim):
    # Farmer (r 1): bound x = 60.5 - 1 = 59.5. Moving right from 59.0 lands at 59.55: clipped.
    params = lone_farmer(59.0, 0.0)
    res = sim.run(params, [{A0: RIGHT}, {A0: RIGHT}, {A0: IDLE}, None])
    healths = [float(r[1].health[A0]) for r in res]
    xs = [float(r[1].position[A0, 0]) for r in res]
    # Step 1: not yet moved (59.0 < 59.5), no damage; then 60 -> 57 -> 54 [ref] while resting
    # at the wall (inclusive test), 5 % of max health per step.
    np.testing.assert_allclose(healths, [60, 57, 54, 51], atol=1e-4)
    np.testing.assert_allclose(xs, [59.0, 59.5, 59.5, 59.5], atol=1e-5)


@pytest.mark.parametrize("x, y", [(0.0, 38.0), (0.0, -38.0), (-59.5, 0.0), (59.5, 37.9)])
def test_wall_touching_on_every_side(sim, x, y):
    params = lone_farmer(x, y)
    (_, s1, *_), = sim.run(params, [None])
    np.testing.assert_allclose(float(s1.health[A0]), 57.0, atol=1e-4)


def test_no_wall_damage_just_inside(sim):
    params = lone_farmer(59.4, 37.9)
    (_, s1, *_), = sim.run(params, [None])
    assert float(s1.health[A0]) == 60.0


def test_position_outside_the_arena_is_clipped_at_reset(sim):
    params = lone_farmer(80.0, -50.0)
    _, s0 = sim.reset(params)
    np.testing.assert_allclose(np_(s0.position[A0]), [59.5, -38.0], atol=1e-6)


# --- collisions ------------------------------------------------------------------------------


def test_two_farmers_overlapping_by_one(sim):
    params = level([unit("farmer", 0, 0, math.pi)], [unit("farmer", 1, 0, 0.0)])
    (_, s1, *_), = sim.run(params, [None])
    # [ref] each moves (1 - slop) * percent / 2 = 0.2475.
    np.testing.assert_allclose(np_(s1.position[A0]), [-0.2475, 0], atol=1e-5)
    np.testing.assert_allclose(np_(s1.position[E0]), [1.2475, 0], atol=1e-5)


def test_mammoth_and_farmer_split_by_inverse_mass(sim):
    # Mammoth r 4.25 (mass 50) and farmer r 1 at distance 4: overlap 1.25.
    params = level([unit("mammoth", 0, 0, math.pi)], [unit("farmer", 0, 4.0, math.pi / 2)])
    (_, s1, *_), = sim.run(params, [None])
    moved_m = float(jnp.linalg.norm(s1.position[A0] - jnp.asarray([0.0, 0.0])))
    moved_f = float(jnp.linalg.norm(s1.position[E0] - jnp.asarray([0.0, 4.0])))
    np.testing.assert_allclose(moved_m, 0.0122, atol=5e-5)  # [ref]
    np.testing.assert_allclose(moved_f, 0.608, atol=5e-4)  # [ref]
    assert float(s1.position[A0, 1]) < 0 < float(s1.position[E0, 1]) - 4.0  # pushed apart


def test_coincident_units_are_separated(sim):
    params = level([unit("farmer", 5, 5, math.pi)], [unit("farmer", 5, 5, 0.0)])
    (obs, s1, *_), = sim.run(params, [None])
    p = np_(s1.position)
    assert np.isfinite(p).all() and np.isfinite(np_(obs)).all()
    np.testing.assert_allclose(p[A0] + p[E0], [10, 10], atol=1e-5)  # symmetric split
    np.testing.assert_allclose(np.linalg.norm(p[A0] - p[E0]), 0.995, atol=1e-5)


def test_dead_units_still_collide(sim):
    params = level([unit("farmer", 0, 0, math.pi), FAR_ALLY],
                   [unit("farmer", 1, 0, 0.0), FAR_ENEMY])
    _, s0 = sim.reset(params)
    s0 = kill(s0, E0)
    _, s1, _, done, _ = sim.step(s0, None, params)
    assert not bool(done)
    np.testing.assert_allclose(np_(s1.position[A0]), [-0.2475, 0], atol=1e-5)
    np.testing.assert_allclose(np_(s1.position[E0]), [1.2475, 0], atol=1e-5)


def test_padded_slots_do_not_collide(sim):
    # Padded slots sit at the origin with radius 1: a real unit there must not be pushed.
    params = level([unit("farmer", 0, 0)], [FAR_ENEMY])
    (_, s1, *_), = sim.run(params, [None])
    np.testing.assert_allclose(np_(s1.position[A0]), [0, 0], atol=1e-7)


def _collide(p, v, r, m, e=0.8, slop=0.01, percent=0.5):
    f = lambda x: jnp.asarray(x, jnp.float32)
    return resolve_collisions(f(p), f(v), f(r), f(m), jnp.ones(len(r), bool), f(e), f(slop),
                              f(percent))


@pytest.mark.parametrize("e", [0.0, 0.5, 0.8, 1.0])
def test_head_on_impulse_conserves_momentum_with_restitution(e):
    p = [[0.0, 0.0], [1.5, 0.0]]
    v = [[1.0, 0.0], [-2.0, 0.0]]
    m = np.array([2.0, 3.0])
    _, v_new = _collide(p, v, [1.0, 1.0], m, e=e)
    v_new = np_(v_new)
    np.testing.assert_allclose((m[:, None] * v_new).sum(0), (m[:, None] * np.array(v)).sum(0),
                               atol=1e-5)
    rel_before = v[1][0] - v[0][0]
    rel_after = v_new[1, 0] - v_new[0, 0]
    np.testing.assert_allclose(rel_after, -e * rel_before, atol=1e-5)
    np.testing.assert_allclose(v_new[:, 1], 0.0, atol=1e-6)


def test_simultaneous_collisions_conserve_momentum():
    rng = np.random.default_rng(0)
    for _ in range(20):
        k = 6
        p = rng.uniform(-2, 2, (k, 2))
        v = rng.uniform(-1, 1, (k, 2))
        m = rng.uniform(0.5, 50, k)
        r = rng.uniform(0.5, 1.5, k)
        _, v_new = _collide(p, v, r, m)
        np.testing.assert_allclose((m[:, None] * np_(v_new)).sum(0), (m[:, None] * v).sum(0),
                                   atol=1e-3)


def test_separating_pair_gets_no_impulse():
    p = [[0.0, 0.0], [1.5, 0.0]]
    v = [[-1.0, 0.0], [1.0, 0.0]]
    p_new, v_new = _collide(p, v, [1.0, 1.0], [1.0, 1.0])
    np.testing.assert_allclose(np_(v_new), v, atol=1e-6)
    # Separating: correction depth * percent without slop, split evenly.
    np.testing.assert_allclose(np_(p_new)[:, 0], [-0.125, 1.625], atol=1e-5)


# --- hurtbox and field of view ----------------------------------------------------------------


# Hurtbox and field of view are read from the env's own state at reset (no motion yet), so
# the tests do not depend on how geometry.py factors its trigonometry.


def _pair_state(sim, target_xy, heading=0.0, **viewer_stats):
    params = level([unit("farmer", 0, 0, heading, **viewer_stats)],
                   [unit("farmer", *target_xy, 0.0)])
    return sim.reset(params)[1]


def hurtbox_hits(sim, target_xy, heading=0.0) -> bool:
    return bool(_pair_state(sim, target_xy, heading).attackable[A0, E0])


def fov_sees(sim, target_xy, heading=0.0) -> bool:
    return bool(_pair_state(sim, target_xy, heading).visible[A0, E0])


@pytest.mark.parametrize("xy, hit", [((4.2, 0.0), True), ((1.0, 1.6), True), ((2.0, 1.8), False),
                                     ((-2.0, 0.0), False), ((0.0, 2.5), False)])
def test_hurtbox_reference_numbers(sim, xy, hit):
    assert hurtbox_hits(sim, xy) is hit  # [ref] first three


def test_hurtbox_edges(sim):
    x0 = math.cos(math.pi / 4)  # box x in [0.7071, 3.2071], |y| <= 0.7071
    x1 = x0 + 2.5
    assert hurtbox_hits(sim, (x1 + 1 - 1e-3, 0.0))
    assert not hurtbox_hits(sim, (x1 + 1 + 1e-3, 0.0))
    assert hurtbox_hits(sim, (2.0, x0 + 1 - 1e-3))
    assert not hurtbox_hits(sim, (2.0, x0 + 1 + 1e-3))
    assert not hurtbox_hits(sim, (2.0, -(x0 + 1 + 1e-3)))
    # The box turns with the heading.
    assert hurtbox_hits(sim, (0.0, 4.2), heading=math.pi / 2)
    assert not hurtbox_hits(sim, (4.2, 0.0), heading=math.pi / 2)
    assert hurtbox_hits(sim, (-4.2, 0.0), heading=math.pi)


@pytest.mark.parametrize("xy, seen", [((-1.3, 0.0), True), ((-1.5, 0.0), False),
                                      ((55.0, 0.0), True), ((10.0, 11.4), True),
                                      ((10.0, 11.45), False), ((10.0, -11.4), True),
                                      ((10.0, -11.45), False), ((0.0, 5.0), False)])
def test_field_of_view(sim, xy, seen):
    # [ref] (-1.3, 0) seen behind the apex, (-1.5, 0) not. Edge at 45 deg pushed out by r = 1:
    # (10, y) seen iff y <= 10 + sqrt(2) = 11.414. Infinite range.
    assert fov_sees(sim, xy) is seen


def test_env_geometry_matches_reference_numbers(sim):
    # The same numbers through the env's own state (attackable, visible) at reset, where no
    # collision has moved anything yet.
    params = level([unit("farmer", 0, 0, 0.0)],
                   [unit("farmer", 4.2, 0, math.pi), unit("farmer", 1.0, 1.6, math.pi),
                    unit("farmer", -1.3, 0.0, 0.0)])
    _, s = sim.reset(params)
    assert bool(s.attackable[A0, E0]) and bool(s.attackable[A0, E1])
    assert not bool(s.attackable[A0, E2])
    assert bool(s.visible[A0, E2])  # behind the apex, inside the pushed-out edges
    params = level([unit("farmer", 0, 0, 0.0)],
                   [unit("farmer", 2.0, 1.8, math.pi), unit("farmer", -1.5, 0.0, 0.0)])
    _, s = sim.reset(params)
    assert bool(s.visible[A0, E0]) and not bool(s.attackable[A0, E0])
    assert not bool(s.visible[A0, E1])


# --- attacks ---------------------------------------------------------------------------------


def duel(ally_stats=None, enemy_stats=None, gap=3.0):
    """Ally farmer at the origin facing an enemy farmer `gap` to the right, both in range."""
    return level([unit("farmer", 0, 0, 0.0, **(ally_stats or {})), FAR_ALLY],
                 [unit("farmer", gap, 0, math.pi, **(enemy_stats or {})), FAR_ENEMY])


def test_attack_hits_the_target_and_mask_follows_cooldown(sim):
    params = duel()
    _, s = sim.reset(params)
    assert bool(s.has_target[A0]) and int(s.target[A0]) == E0
    # Farmer cooldown 2.5 s at dt 0.5: the 5th step is the first ready one.
    healths = []
    for k in range(1, 7):
        mask = sim.mask(s, params)
        assert bool(mask[A0, ATTACK]) is (k == 5), k
        _, s, _, _, info = sim.step(s, {A0: ATTACK}, params)
        assert bool(info["attacking"][A0]) is (k == 5)
        healths.append(float(s.health[E0]))
    np.testing.assert_allclose(healths, [60, 60, 60, 60, 46, 46])
    assert float(s.health[A0]) == 60.0  # the enemy idled
    assert not sim.mask(s, params)[A0, ATTACK]  # cooldown spent


def test_archer_first_shot_at_step_16(sim):
    params = level([unit("archer", 0, 0, 0.0)], [unit("farmer", 20, 0, 0.0)])
    _, s = sim.reset(params)
    for k in range(1, 18):
        ready = bool(sim.mask(s, params)[A0, ATTACK])
        assert ready is (k == 16), k
        _, s, *_ = sim.step(s, {A0: ATTACK}, params)
        assert float(s.health[E0]) == (60.0 if k < 16 else 32.0), k


def test_attack_uses_target_from_previous_step(sim):
    # The enemy sprints out of the hurtbox during step 2 (speed 10 -> 5 units): the ally's
    # attack in step 2 still hits, as its observation after step 1 said.
    params = duel(ally_stats=dict(cooldown=0.5), enemy_stats=dict(speed=10.0))
    res = sim.run(params, [{E0: UP}, {A0: ATTACK}])
    (obs1, s1, *_), (_, s2, _, _, info2) = res
    assert bool(s1.has_target[A0]) and int(s1.target[A0]) == E0
    np.testing.assert_allclose(np_(s2.position[E0]), [3.0, 5.0], atol=1e-5)
    assert float(s2.health[E0]) == 46.0
    assert bool(info2["hit"][A0])
    assert not bool(s2.has_target[A0])


def test_unit_entering_the_box_this_step_is_not_hit(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=1.0), FAR_ALLY],
                   [unit("farmer", 3, 5, math.pi, speed=10.0), FAR_ENEMY])
    # Step 1: the enemy starts moving down. Step 2: it arrives in the box, but the target the
    # ally saw after step 1 was nothing: a whiff, which still spends the cooldown.
    res = sim.run(params, [{E0: DOWN}, {A0: ATTACK}])
    (_, s1, *_), (_, s2, _, _, info2) = res
    assert not bool(s1.has_target[A0])
    np.testing.assert_allclose(np_(s2.position[E0]), [3.0, 0.0], atol=1e-5)
    assert float(s2.health[E0]) == 60.0
    assert bool(info2["attacking"][A0]) and not bool(info2["hit"][A0])
    assert bool(s2.has_target[A0])
    np.testing.assert_allclose(float(s2.cooldown[A0]), 0.5, atol=1e-6)
    assert not sim.mask(s2, params)[A0, ATTACK]


def test_attack_without_ready_cooldown_does_nothing_and_keeps_counting(sim):
    params = duel()
    _, s0 = sim.reset(params)
    _, s1, _, _, info = sim.step(s0, {A0: ATTACK}, params)
    assert not bool(info["attacking"][A0])
    np.testing.assert_allclose(float(s1.cooldown[A0]), float(s0.cooldown[A0]) + 0.5, atol=1e-6)
    assert float(s1.health[E0]) == 60.0


def test_nearest_attackable_is_the_target(sim):
    # Both enemies in the box; the nearer one is in the later slot.
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)],
                   [unit("farmer", 3.9, -0.6, math.pi), unit("farmer", 2.0, 0.6, math.pi)])
    _, s0 = sim.reset(params)
    assert bool(s0.attackable[A0, E0]) and bool(s0.attackable[A0, E1])
    assert int(s0.target[A0]) == E1
    (_, s1, *_), = sim.run(params, [{A0: ATTACK}])
    assert float(s1.health[E1]) == 46.0 and float(s1.health[E0]) == 60.0


def test_damage_dealers_never_target_allies_or_self(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5), unit("farmer", 3, 0, 0.0)],
                   [FAR_ENEMY])
    _, s0 = sim.reset(params)
    assert not bool(s0.attackable[A0, A1]) and not bool(s0.has_target[A0])
    assert not np_(s0.attackable).diagonal().any()
    (_, s1, *_), = sim.run(params, [{A0: ATTACK}])
    assert float(s1.health[A1]) == 60.0


def test_healer_heals_allies_only_and_clamps(sim):
    # Healer (range 10) with a wounded ally and an enemy both in its box; enemy nearer.
    params = level([unit("healer", 0, 0, 0.0, cooldown=0.5),
                    unit("farmer", 5, 0, 0.0, health=30.0, max_health=60.0),
                    unit("farmer", 8, 0.3, 0.0, health=58.0, max_health=60.0)],
                   [unit("farmer", 2, 0, 0.0)])
    _, s0 = sim.reset(params)
    assert bool(s0.attackable[A0, A1]) and bool(s0.attackable[A0, A2])
    assert not bool(s0.attackable[A0, E0])
    assert int(s0.target[A0]) == A1
    (_, s1, *_), = sim.run(params, [{A0: ATTACK}])
    assert float(s1.health[A1]) == 37.0  # 30 + 7
    assert float(s1.health[E0]) == 60.0
    # Second heal on the 58/60 unit once the nearer one is gone: clamped at max health.
    params = level([unit("healer", 0, 0, 0.0, cooldown=0.5),
                    unit("farmer", 8, 0.3, 0.0, health=58.0, max_health=60.0)], [FAR_ENEMY])
    (_, s1, *_), = sim.run(params, [{A0: ATTACK}])
    assert float(s1.health[A1]) == 60.0


def test_damage_clamped_at_zero(sim):
    params = duel(ally_stats=dict(cooldown=0.5), enemy_stats=dict(health=5.0, max_health=60.0))
    (_, s1, *_), = sim.run(params, [{A0: ATTACK}])
    assert float(s1.health[E0]) == 0.0 and not bool(s1.alive[E0])


def test_simultaneous_kills(sim):
    # Both farmers at 10/60 hit each other in the same step: both die, and the episode ends
    # at once with both teams wiped out; the tie goes to the enemy team.
    params = level([unit("farmer", 0, 0, 0.0, health=10.0, max_health=60.0, cooldown=0.5)],
                   [unit("farmer", 3, 0, math.pi, health=10.0, max_health=60.0, cooldown=0.5)])
    (_, s1, reward, done, info), = sim.run(params, [{A0: ATTACK, E0: ATTACK}])
    assert not bool(s1.alive[A0]) and not bool(s1.alive[E0])
    assert float(s1.health[A0]) == 0.0 and float(s1.health[E0]) == 0.0
    assert bool(done) and bool(info["terminated"])
    assert np_(s1.won).tolist() == [False, True]
    np.testing.assert_allclose(np_(reward), [-1.0, 1.0], atol=1e-6)


def test_heal_and_damage_on_one_unit_are_summed(sim):
    # Healer (slot 0) heals a full-health farmer while an enemy hits it in the same step:
    # 60 + 7 - 14 = 53 (the reference clamps the heal first and ends at 46).
    params = level([unit("healer", -3, 0, 0.0, cooldown=0.5), unit("farmer", 0, 0, 0.0)],
                   [unit("farmer", 3, 0, math.pi, cooldown=0.5)])
    (_, s1, *_), = sim.run(params, [{A0: ATTACK, E0: ATTACK}])
    assert float(s1.health[A1]) == 53.0


def _slot_order_outcome(sim, allies, enemies, ally_acts, enemy_acts, steps):
    params = level(allies, enemies)
    actions = {i: a for i, a in enumerate(ally_acts)}
    actions.update({3 + i: a for i, a in enumerate(enemy_acts)})
    res = sim.run(params, [actions] * steps)
    return res[-1][1], res


def test_no_index_order_bias(sim):
    # Two healers-and-hitters fights; permuting the slots within each team permutes the outcome.
    allies = [unit("healer", -3, 0.5, 0.0, cooldown=0.5), unit("farmer", 0, 0, 0.0, cooldown=0.5),
              unit("assassin", 0, 3.5, 0.0)]
    enemies = [unit("farmer", 3, 0, math.pi, cooldown=0.5), unit("theking", 2.8, 3.4, math.pi),
               unit("healer", 7, 0.5, math.pi, cooldown=0.5)]
    ally_acts = [ATTACK, ATTACK, ATTACK]
    enemy_acts = [ATTACK, ATTACK, ATTACK]
    base, _ = _slot_order_outcome(sim, allies, enemies, ally_acts, enemy_acts, 6)
    assert float(base.health.sum()) < 25 + 60 + 70 + 60 + 346 + 25 - 50  # a real fight
    pa, pe = [2, 0, 1], [1, 2, 0]
    swapped, _ = _slot_order_outcome(sim, [allies[i] for i in pa], [enemies[i] for i in pe],
                                     [ally_acts[i] for i in pa], [enemy_acts[i] for i in pe], 6)
    perm = pa + [3 + i for i in pe]  # new slot k holds old slot perm[k]
    np.testing.assert_allclose(np_(swapped.health), np_(base.health)[perm], atol=1e-4)
    np.testing.assert_allclose(np_(swapped.position), np_(base.position)[perm], atol=1e-4)
    np.testing.assert_array_equal(np_(swapped.alive), np_(base.alive)[perm])
    np.testing.assert_allclose(np_(swapped.hp_ratio), np_(base.hp_ratio), atol=1e-6)


def test_symmetric_overlaps_no_index_order_bias(sim):
    # Three farmers overlapping in a row: the middle one is pushed equally from both sides.
    params = level([unit("farmer", -1.5, 0), unit("farmer", 0, 0), unit("farmer", 1.5, 0)],
                   [FAR_ENEMY])
    (_, s1, *_), = sim.run(params, [None])
    p = np_(s1.position)
    np.testing.assert_allclose(p[A1], [0, 0], atol=1e-6)
    np.testing.assert_allclose(p[A0, 0], -p[A2, 0], atol=1e-6)


# --- death -----------------------------------------------------------------------------------


def test_dead_units_are_never_targeted_nor_revived(sim):
    # The ally kills the 10-HP enemy in step 1; an enemy healer right behind it tries to heal
    # it in steps 2.. (the reference's stale matrix would resurrect it).
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5), FAR_ALLY],
                   [unit("farmer", 3, 0, math.pi, health=10.0, max_health=60.0),
                    unit("healer", 6, 0, math.pi, cooldown=0.5)])
    _, s0 = sim.reset(params)
    assert int(s0.target[E1]) == E0
    res = sim.run(params, [{A0: ATTACK}] + [{E1: ATTACK, A0: ATTACK}] * 5)
    _, s1, _, done1, _ = res[0]
    assert not bool(s1.alive[E0]) and not bool(done1)
    assert not np_(s1.attackable)[:, E0].any()
    assert not bool(s1.has_target[E1]) and not bool(s1.has_target[A0])
    for _, s, _, _, info in res[1:]:
        assert not bool(s.alive[E0]) and float(s.health[E0]) == 0.0
        assert not bool(info["hit"][E1])


def test_healer_cannot_revive_a_lava_death(sim):
    # [ref staleness bug] A farmer dies in lava; its healer tries to heal it on the next step.
    params = level([unit("farmer", 0, 0, 0.0, health=10.0, max_health=60.0),
                    unit("healer", -3, 0, 0.0, cooldown=1.5)],
                   [FAR_ENEMY], zones=[zone("lava", 0, 0, 1.5, 1.5, 10.0)])
    res = sim.run(params, [None, None, {A1: ATTACK}, {A1: ATTACK}, None])
    healths = [float(r[1].health[A0]) for r in res]
    np.testing.assert_allclose(healths, [5, 0, 0, 0, 0])
    assert not any(bool(r[1].alive[A0]) for r in res[1:])
    assert bool(res[2][4]["attacking"][A1]) and not bool(res[2][4]["hit"][A1])


def test_dead_units_do_not_act(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5), FAR_ALLY],
                   [unit("farmer", 3, 0, 0.0), FAR_ENEMY])
    _, s0 = sim.reset(params)
    s0 = kill(s0, A0)
    res = sim.run(params, [{A0: RIGHT}, {A0: TURN_LEFT}, {A0: ATTACK}], state=s0)
    for _, s, _, _, info in res:
        np.testing.assert_allclose(np_(s.position[A0]), [0, 0], atol=1e-6)
        assert float(s.heading[A0]) == 0.0
        assert float(s.health[E0]) == 60.0 and not bool(info["attacking"][A0])
        assert not bool(s.alive[A0])


def test_a_unit_killed_while_moving_does_not_drift(sim):
    # The enemy walks UP in the step it is killed by the ally's hit: its corpse stays put.
    params = level([unit("farmer", 0, 0, 0.0, damage=100.0), FAR_ALLY],
                   [unit("farmer", 3, 0, math.pi), FAR_ENEMY])
    _, s0 = sim.reset(params)
    s0 = s0.replace(cooldown=s0.cooldown.at[A0].set(2.5))  # attack ready now
    assert bool(s0.has_target[A0]) and int(s0.target[A0]) == E0
    res = sim.run(params, [{A0: ATTACK, E0: UP}, None, None], state=s0)
    assert not bool(res[0][1].alive[E0])
    for _, s, _, _, _ in res:
        np.testing.assert_allclose(np_(s.position[E0]), [3, 0], atol=1e-6)


def test_action_mask_dead_and_padded_only_idle(sim):
    params = level([unit("farmer", 0, 0), FAR_ALLY], [FAR_ENEMY])
    _, s0 = sim.reset(params)
    s0 = kill(s0, A1)
    mask = sim.mask(s0, params)
    only_idle = np.eye(C.NUM_ACTIONS, dtype=bool)[IDLE]
    for slot in (A1, A2, E1, E2):  # dead, padded
        np.testing.assert_array_equal(mask[slot], only_idle)
    expected = np.ones(C.NUM_ACTIONS, bool)
    expected[ATTACK] = False  # cooldown not ready at reset
    np.testing.assert_array_equal(mask[A0], expected)


# --- zones -----------------------------------------------------------------------------------


def test_lava_burns_effect_times_dt(sim):
    params = level([unit("farmer", 0, 0), unit("farmer", 5, 0)], [FAR_ENEMY],
                   zones=[zone("lava", 0, 0, 2, 2, 10.0)])
    res = sim.run(params, [None] * 3)
    np.testing.assert_allclose([float(r[1].health[A0]) for r in res], [55, 50, 45])
    assert all(float(r[1].health[A1]) == 60.0 for r in res)


def test_lava_membership_is_the_centre(sim):
    # Body overlaps the lava ellipse but the centre is outside: no damage.
    params = level([unit("farmer", 2.5, 0)], [FAR_ENEMY], zones=[zone("lava", 0, 0, 2, 2, 10.0)])
    (_, s1, *_), = sim.run(params, [None])
    assert float(s1.health[A0]) == 60.0


def test_swamp_slows_the_next_move(sim):
    # Swamp of radius 1 at the origin halves the speed while the centre is inside.
    params = level([unit("farmer", 0, 0)], [FAR_ENEMY], zones=[zone("swamp", 0, 0, 1, 1, 0.5)])
    _, s0 = sim.reset(params)
    np.testing.assert_allclose(float(s0.speed[A0]), 0.55, atol=1e-6)
    res = sim.run(params, [{A0: RIGHT}] * 8)
    xs = [float(r[1].position[A0, 0]) for r in res]
    # Slowed steps of 0.275 until the centre leaves (x 1.1 > 1); the full speed is read by the
    # action of the step after that and moves the unit one step later still.
    np.testing.assert_allclose(xs, [0, 0.275, 0.55, 0.825, 1.1, 1.375, 1.925, 2.475], atol=1e-5)
    np.testing.assert_allclose(float(res[4][1].speed[A0]), 1.1, atol=1e-6)


def test_overlapping_swamps_multiply(sim):
    params = level([unit("farmer", 0, 0)], [FAR_ENEMY],
                   zones=[zone("swamp", 0, 0, 3, 3, 0.5), zone("swamp", 1, 0, 3, 3, 0.5)])
    _, s0 = sim.reset(params)
    np.testing.assert_allclose(float(s0.speed[A0]), 1.1 * 0.25, atol=1e-6)


# --- bushes ------------------------------------------------------------------------------------


BUSH = zone("bush", 0, 0, 3, 3)


def test_bush_hides_an_opponent(sim):
    # Enemy in the bush at the origin, the ally outside facing it; the enemy sees the ally.
    params = level([unit("farmer", -10, 0, 0.0)], [unit("farmer", 0, 0, math.pi)], zones=[BUSH])
    _, s = sim.reset(params)
    assert not bool(s.visible[A0, E0])
    assert bool(s.visible[E0, A0])
    # Without the bush it is seen.
    params = level([unit("farmer", -10, 0, 0.0)], [unit("farmer", 0, 0, math.pi)])
    _, s = sim.reset(params)
    assert bool(s.visible[A0, E0])


def test_bush_teammate_in_the_same_bush_shares_vision(sim):
    bushes = [BUSH, zone("bush", 0, 20, 3, 3)]
    # Slot A1 is in the same bush as the enemy (facing down at it); A0 watches from outside.
    params = level([unit("farmer", -10, 0, 0.0), unit("farmer", 0, 2.5, -math.pi / 2)],
                   [unit("farmer", 0, 0, math.pi)], zones=bushes)
    _, s = sim.reset(params)
    assert bool(s.visible[A1, E0]) and bool(s.visible[A0, E0])
    # A teammate in another bush does not help.
    params = level([unit("farmer", -10, 0, 0.0), unit("farmer", 0, 20, -math.pi / 2)],
                   [unit("farmer", 0, 0, math.pi)], zones=bushes)
    _, s = sim.reset(params)
    assert not bool(s.visible[A0, E0]) and not bool(s.visible[A1, E0])
    # The viewer itself in the bush sees the enemy there.
    params = level([unit("farmer", -2.5, 0, 0.0)], [unit("farmer", 0, 0.0, math.pi)],
                   zones=bushes)
    _, s = sim.reset(params)
    assert bool(s.visible[A0, E0])


def test_bush_shared_vision_never_exceeds_own_fov(sim):
    # A0 faces away from the enemy; its teammate in the bush sees it, A0 must not.
    params = level([unit("farmer", -10, 0, math.pi), unit("farmer", 0, 2.5, -math.pi / 2)],
                   [unit("farmer", 0, 0, math.pi)], zones=[BUSH])
    _, s = sim.reset(params)
    assert bool(s.visible[A1, E0])
    assert not bool(s.visible[A0, E0])


def test_bush_dead_teammate_does_not_share(sim):
    params = level([unit("farmer", -10, 0, 0.0), unit("farmer", 0, 2.5, -math.pi / 2), FAR_ALLY],
                   [unit("farmer", 0, 0, math.pi)], zones=[BUSH])
    _, s0 = sim.reset(params)
    assert bool(s0.visible[A0, E0])
    _, s1, *_ = sim.step(kill(s0, A1), None, params)
    assert not bool(s1.visible[A0, E0])


def test_bush_same_team_always_visible_in_fov(sim):
    params = level([unit("farmer", -10, 0, 0.0), unit("farmer", 0, 0, 0.0)], [FAR_ENEMY],
                   zones=[BUSH])
    _, s = sim.reset(params)
    assert bool(s.visible[A0, A1])


def test_bush_reveal_lasts_one_step_after_attacking(sim):
    # The hidden enemy hits A0 in step 1: A0's team sees it after step 1 only.
    bush = zone("bush", 0, 0, 1.5, 1.5)
    params = level([unit("farmer", -3, 0, 0.0), unit("farmer", -12, 4, 0.0)],
                   [unit("farmer", 0, 0, math.pi, cooldown=0.5)], zones=[bush])
    _, s0 = sim.reset(params)
    assert not bool(s0.visible[A0, E0]) and not bool(s0.visible[A1, E0])
    res = sim.run(params, [{E0: ATTACK}, None, None])
    (_, s1, *_), (_, s2, *_), (_, s3, *_) = res
    assert float(s1.health[A0]) == 46.0
    assert bool(s1.visible[A0, E0]) and bool(s1.visible[A1, E0])  # team-wide reveal
    assert not bool(s2.visible[A0, E0]) and not bool(s2.visible[A1, E0])
    assert not bool(s3.visible[A0, E0])


def test_bush_reveal_after_being_attacked(sim):
    # A0 can hit the hidden enemy (attacks don't need sight), which reveals it for one step.
    bush = zone("bush", 0, 0, 1.5, 1.5)
    params = level([unit("farmer", -3, 0, 0.0, cooldown=0.5)], [unit("farmer", 0, 0, 0.0)],
                   zones=[bush])
    _, s0 = sim.reset(params)
    assert not bool(s0.visible[A0, E0]) and bool(s0.attackable[A0, E0])
    res = sim.run(params, [{A0: ATTACK}, None])
    (_, s1, *_), (_, s2, *_) = res
    assert float(s1.health[E0]) == 46.0
    assert bool(s1.visible[A0, E0])
    assert not bool(s2.visible[A0, E0])


# --- reward and termination --------------------------------------------------------------------


@pytest.mark.parametrize("mode", [C.REWARD_MEAN_OF_RATIOS, C.REWARD_RATIO_OF_SUMS])
def test_dense_reward(sim, mode):
    # The ally farmer hits the enemy farmer (14 HP) in a team with a mammoth (685 HP).
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)],
                   [unit("farmer", 3, 0, math.pi), unit("mammoth", 30, 20, 0.0)], reward_mode=mode)
    (_, s1, reward, _, _), = sim.run(params, [{A0: ATTACK}])
    loss = 14 / 60 / 2 if mode == C.REWARD_MEAN_OF_RATIOS else 14 / (60 + 685)
    np.testing.assert_allclose(np_(reward), [loss, -loss], atol=1e-6)
    expected_ratio = 1 - loss
    np.testing.assert_allclose(np_(s1.hp_ratio), [1.0, expected_ratio], atol=1e-6)


def test_reference_reward_example_ratio_of_sums(sim):
    # [ref] a 3-HP farmer loss (wall) in a team of 885 max HP: -3/885 = -0.00339.
    params = level([unit("farmer", 59.5, 0, 0.0), unit("theking", 0, 0), unit("mammoth", 0, 20)],
                   [FAR_ENEMY], reward_mode=C.REWARD_RATIO_OF_SUMS)
    (_, _, reward, _, _), = sim.run(params, [None])
    np.testing.assert_allclose(np_(reward), [-3 / 1091, 3 / 1091], atol=1e-6)
    # [ref] the 2F1M2A team (885 max HP) with an archer at 140/140 standing in for 2 archers
    # and a farmer: -3/885 = -0.00339.
    params = level([unit("farmer", 59.5, 0, 0.0), unit("archer", 0, 0, health=140.0),
                    unit("mammoth", 0, 20)], [FAR_ENEMY], reward_mode=C.REWARD_RATIO_OF_SUMS)
    (_, _, reward, _, _), = sim.run(params, [None])
    np.testing.assert_allclose(float(reward[0]), -0.00339, atol=1e-5)
    # The paper's mean of ratios: one of three units loses 5 % of its health.
    params = params.replace(reward_mode=jnp.asarray(C.REWARD_MEAN_OF_RATIOS, jnp.int32))
    (_, _, reward, _, _), = sim.run(params, [None])
    np.testing.assert_allclose(float(reward[0]), -0.05 / 3, atol=1e-6)


def test_first_reward_starts_from_real_health(sim):
    # A wounded unit (30/60) and a unit standing in lava: the first reward has no jump from an
    # assumed full health; only the lava damage of step 1 counts.
    params = level([unit("farmer", 0, 0, 0.0, health=30.0, max_health=60.0)], [FAR_ENEMY])
    obs, s0 = sim.reset(params)
    np.testing.assert_allclose(np_(s0.hp_ratio), [0.5, 1.0], atol=1e-6)
    (_, _, reward, _, _), = sim.run(params, [None])
    np.testing.assert_allclose(np_(reward), [0.0, 0.0], atol=1e-7)
    params = level([unit("farmer", 0, 0)], [FAR_ENEMY], zones=[zone("lava", 0, 0, 2, 2, 10.0)])
    _, s0 = sim.reset(params)
    np.testing.assert_allclose(np_(s0.hp_ratio), [1.0, 1.0], atol=1e-6)
    assert float(s0.health[A0]) == 60.0  # reset deals no damage
    (_, _, reward, _, _), = sim.run(params, [None])
    np.testing.assert_allclose(np_(reward), [-5 / 60, 5 / 60], atol=1e-6)


def test_idle_symmetric_level_times_out_and_tie_goes_to_enemy(sim):
    # [ref] 512 idle steps end in done at step 512 with reward (-1, +1).
    params = level([unit("farmer", -20, 0, math.pi)], [unit("farmer", 20, 0, 0.0)])
    _, s = sim.reset(params)
    idle = jnp.full(N, IDLE, jnp.int32)
    for k in range(1, CONFIG.max_steps + 1):
        _, s, reward, done, info = sim.step(s, idle, params)
        if k < CONFIG.max_steps:
            assert not bool(done), k
    assert int(s.step) == 512 and bool(done)
    np.testing.assert_allclose(np_(reward), [-1.0, 1.0])
    assert np_(s.won).tolist() == [False, True]
    assert bool(info["truncated"]) and not bool(info["terminated"])


def test_elimination_ends_the_episode_on_the_killing_step(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)],
                   [unit("farmer", 3, 0, math.pi, health=10.0, max_health=60.0)])
    (_, s1, reward, done, info), = sim.run(params, [{A0: ATTACK}])
    assert bool(done) and bool(s1.done) and int(s1.step) == 1
    assert bool(info["terminated"])
    assert np_(s1.won).tolist() == [True, False]
    np.testing.assert_allclose(np_(reward), [10 / 60 + 1.0, -10 / 60 - 1.0], atol=1e-6)
    np.testing.assert_array_equal(np_(info["dead_units"]), [0, 1])


def test_finished_episode_does_not_keep_paying(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)],
                   [unit("farmer", 3, 0, math.pi, health=10.0, max_health=60.0)])
    res = sim.run(params, [{A0: ATTACK}, {A0: RIGHT}, {A0: TURN_LEFT}, None])
    _, s_done, _, _, _ = res[0]
    for obs, s, reward, done, _ in res[1:]:
        assert bool(done)
        np.testing.assert_array_equal(np_(reward), [0.0, 0.0])
        for a, b in zip(vars(s).values(), vars(s_done).values(), strict=True):
            np.testing.assert_array_equal(np_(a), np_(b))
        np.testing.assert_array_equal(np_(obs), np_(res[0][0]))


def _autoreset(sim, state, actions, params):
    # The lead's API passes the start state in (reset_state) in newer versions.
    if "reset_state" in inspect.signature(sim.env.step_autoreset).parameters:
        return sim.autoreset_fn(KEY, state, actions, params, sim.env.initial_state(params))
    return sim.autoreset_fn(KEY, state, actions, params)


def test_step_autoreset(sim):
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)],
                   [unit("farmer", 3, 0, math.pi, health=10.0, max_health=60.0)])
    obs0, s0 = sim.reset(params)
    obs, s, reward, done, info = _autoreset(
        sim, s0, jnp.asarray([ATTACK] + [IDLE] * 5, jnp.int32), params)
    assert bool(done) and bool(info["terminated"])
    np.testing.assert_allclose(np_(reward), [10 / 60 + 1.0, -10 / 60 - 1.0], atol=1e-6)
    assert int(s.step) == 0 and not bool(s.done)
    for a, b in zip(jax_leaves(s), jax_leaves(s0), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(np_(obs), np_(obs0), atol=1e-6)
    # Not done: the autoreset step is the plain step.
    params2 = duel()
    _, t0 = sim.reset(params2)
    a = jnp.asarray([RIGHT, IDLE, IDLE, TURN_LEFT, IDLE, IDLE], jnp.int32)
    plain = sim.step_fn(KEY, t0, a, params2)
    auto = _autoreset(sim, t0, a, params2)
    for x, y in zip(jax_leaves(plain[:4]), jax_leaves(auto[:4]), strict=True):
        np.testing.assert_allclose(x, y, atol=1e-6)


def jax_leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


# --- observations ------------------------------------------------------------------------------


def test_observation_layout_cyclic_order_and_masking(sim):
    # Six units with distinct health, headings chosen so some pairs see each other and some
    # don't; every other-unit block must match the unit's own features (scale-free check).
    allies = [unit("farmer", -10, 0, 0.0, health=50.0, max_health=60.0),
              unit("archer", -12, 6, -0.3, health=33.0, max_health=40.0),
              unit("healer", -14, -6, math.pi)]
    enemies = [unit("assassin", 10, 0, math.pi, health=69.0, max_health=70.0),
               unit("theking", 12, 5, math.pi / 2),
               unit("cannon", 14, -7, 0.9 * math.pi, health=91.0, max_health=100.0)]
    params = level(allies, enemies, zones=[zone("swamp", 10, 0, 2, 2, 0.3)])
    obs, s = sim.reset(params)
    obs, s, *_ = sim.step(s, {A0: RIGHT, E1: TURN_LEFT}, params)  # some cooldown/speed state
    obs, vis, att = np_(obs), np_(s.visible), np_(s.attackable)
    assert vis.any() and not vis.all()
    team = np.array([0, 0, 0, 1, 1, 1])
    own_idx = [0, 1, *range(4, 13), 13]
    blk_idx = [0, 1, *range(4, 13), 15]
    n_seen = 0
    for i in range(N):
        for k in range(N - 1):
            j = (i + 1 + k) % N
            block = obs[i, 14 + 16 * k: 14 + 16 * (k + 1)]
            if not vis[i, j]:
                np.testing.assert_array_equal(block, 0.0)
                continue
            n_seen += 1
            np.testing.assert_allclose(block[blk_idx], obs[j, own_idx], atol=1e-6)
            np.testing.assert_allclose(block[2:4], obs[j, 2:4] - obs[i, 2:4], atol=1e-5)
            assert block[13] == float(team[i] == team[j])
            assert block[14] == float(att[i, j])
    assert n_seen >= 4


def test_observation_zone_slots_and_padding(sim):
    params = level([unit("farmer", 0, 0)], [FAR_ENEMY], zones=[zone("lava", 5, 5, 2, 3, 10.0)])
    obs, s = sim.reset(params)
    obs = np_(obs)
    zone_part = obs[:, 14 + 16 * (N - 1):]
    assert zone_part.shape == (N, 12)
    assert np.abs(zone_part[A0, :6]).sum() > 0
    np.testing.assert_array_equal(zone_part[:, 6:], 0.0)  # empty zone slot
    for slot in (A1, A2, E1, E2):  # padded slots observe nothing
        np.testing.assert_array_equal(obs[slot], 0.0)
    ws = np_(sim.world_state_fn(s, params))
    assert ws.shape == (CONFIG.state_size,)
    np.testing.assert_array_equal(ws[-6:], 0.0)
    assert np.abs(ws[-12:-6]).sum() > 0


def test_no_nan_with_degenerate_padding(sim):
    # Padded slots with zero max health, cooldown, radius, mass and sight angle.
    params = level([unit("farmer", 0, 0, 0.0, cooldown=0.5)], [unit("farmer", 3, 0, math.pi)])
    pad = ~np_(params.units.active)
    zero = lambda x: jnp.where(jnp.asarray(pad), 0.0, x)
    params = params.replace(units=params.units.replace(
        max_health=zero(params.units.max_health), cooldown=zero(params.units.cooldown),
        radius=zero(params.units.radius), mass=zero(params.units.mass),
        sight_angle=zero(params.units.sight_angle)),
        zones=params.zones.replace(semi_axes=jnp.zeros_like(params.zones.semi_axes)))
    obs, s = sim.reset(params)
    assert np.isfinite(np_(obs)).all()
    for _ in range(3):
        obs, s, reward, _, _ = sim.step(s, {A0: ATTACK, E0: ATTACK}, params)
        assert np.isfinite(np_(obs)).all() and np.isfinite(np_(reward)).all()
        assert np.isfinite(np_(sim.world_state_fn(s, params))).all()
    assert float(s.health[E0]) < 60.0  # the level still plays
