"""Property tests of the simulator over random levels and random action sequences.

One jitted rollout (reset + lax.scan over `T` steps) is compiled once for a fixed EnvConfig;
hypothesis draws the level (unit types and counts, stats, positions, headings, zones of every
type, physics, arena, reward mode) and the action policy, and every invariant is checked on the
host for every step. TABX_HYPOTHESIS_EXAMPLES raises the number of examples.
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx.env import TabxEnv, cooldown_cap, random_legal_actions
from tabx.params import EnvConfig, heuristic_params, make_level, physics_params
from tabx.profiles import ALL_CHOICES

CONFIG = EnvConfig(max_allies=3, max_enemies=3, max_zones=3, max_steps=24)
N = CONFIG.num_units
T = 30  # > max_steps: every rollout reaches done and then keeps stepping a finished episode
ENV = TabxEnv(CONFIG)
EXAMPLES = int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "25"))
PROPS = settings(max_examples=EXAMPLES, deadline=None,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _rollout(params, key, p_attack, p_illegal):
    """Reset, then T steps of random actions: legal ones, ATTACK with probability p_attack,
    and any action (illegal ones included) with probability p_illegal."""
    obs0, s0 = ENV.reset(key, params)

    def body(state, k):
        k_legal, k_any, k_mix, k_attack, k_step = jax.random.split(k, 5)
        mask = ENV.action_mask(state, params)
        legal = random_legal_actions(k_legal, mask)
        legal = jnp.where(jax.random.uniform(k_attack, (N,)) < p_attack, C.ATTACK, legal)
        anything = jax.random.randint(k_any, (N,), 0, C.NUM_ACTIONS)
        actions = jnp.where(jax.random.uniform(k_mix, (N,)) < p_illegal, anything, legal)
        obs, new_state, reward, done, info = ENV.step(k_step, state, actions, params)
        out = dict(obs=obs, state=new_state, reward=reward, done=done, info=info, mask=mask,
                   actions=actions, world_state=ENV.world_state(new_state, params),
                   next_mask=ENV.action_mask(new_state, params))
        return new_state, out

    _, traj = jax.lax.scan(body, s0, jax.random.split(key, T))
    return obs0, s0, ENV.world_state(s0, params), traj


ROLLOUT = jax.jit(_rollout)


# --- strategies --------------------------------------------------------------------------------


def floats(lo: float, hi: float) -> st.SearchStrategy:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def units(draw, centre, spread, team_size_max):
    count = draw(st.integers(1, team_size_max))
    records = []
    for _ in range(count):
        name = draw(st.sampled_from(C.UNIT_NAMES))
        spec = C.UNIT_SPECS[C.UNIT_TYPE_BY_NAME[name]]
        rec = dict(unit=name,
                   position=(centre[0] + draw(floats(-spread, spread)),
                             centre[1] + draw(floats(-spread, spread))),
                   heading=draw(floats(-4 * math.pi, 4 * math.pi)))
        max_health = spec.health
        if draw(st.booleans()):
            max_health = draw(floats(1.0, 800.0))
            rec["max_health"] = max_health
        rec["health"] = max_health * draw(floats(0.02, 1.0))
        if draw(st.booleans()):
            rec.update(speed=draw(floats(0.0, 5.0)), damage=draw(floats(-30.0, 120.0)),
                       attack_range=draw(floats(0.0, 45.0)), cooldown=draw(floats(0.05, 10.0)),
                       radius=draw(floats(0.3, 5.0)), mass=draw(floats(0.1, 100.0)),
                       sight_angle=draw(floats(0.1, 3.1)))
        records.append(rec)
    return records


@st.composite
def zones(draw, half):
    out = []
    for _ in range(draw(st.integers(0, CONFIG.max_zones))):
        kind = draw(st.sampled_from(["lava", "bush", "swamp"]))
        effect = {"lava": floats(0.0, 40.0), "swamp": floats(0.0, 1.0),
                  "bush": st.just(0.0)}[kind]
        out.append(dict(type=kind,
                        centre=(draw(floats(-half[0], half[0])), draw(floats(-half[1], half[1]))),
                        semi_axes=(draw(floats(0.5, 30.0)), draw(floats(0.5, 30.0))),
                        effect=draw(effect)))
    return out


@st.composite
def levels(draw):
    width, height = draw(floats(20.0, 200.0)), draw(floats(20.0, 150.0))
    half = (0.5 * width, 0.5 * height)
    # Clustered battles (so that units collide, fight and heal) as well as spread-out ones.
    spread = draw(st.sampled_from([4.0, 10.0, 40.0, 120.0]))
    centre = (draw(floats(-half[0], half[0])), draw(floats(-half[1], half[1])))
    physics = physics_params(
        "default", dt=draw(floats(0.05, 1.0)), restitution=draw(floats(0.0, 1.0)),
        slop=draw(floats(0.0, 0.1)), percent=draw(floats(0.0, 1.0)),
        boundary_damage_rate=draw(floats(0.0, 1.0)), turn_rate=draw(floats(0.05, 2 * math.pi)),
        arena_size=(width, height))
    tiers = st.sampled_from(["random", "novice", "medium", "advanced", "expert"])
    level = make_level(
        CONFIG, draw(units(centre, spread, CONFIG.max_allies)),
        draw(units(centre, spread, CONFIG.max_enemies)), draw(zones(half)),
        heuristic=heuristic_params(draw(tiers), draw(tiers)), physics=physics,
        reward_mode=draw(st.sampled_from([C.REWARD_MEAN_OF_RATIOS, C.REWARD_RATIO_OF_SUMS])))
    # Any mix of the reference's choices (tabx.profiles): the invariants hold in every profile.
    return level.replace(profile=jnp.asarray(draw(st.integers(0, ALL_CHOICES)), jnp.int32))


policies = st.tuples(st.sampled_from([0.0, 0.3, 0.8]), st.sampled_from([0.0, 0.2, 1.0]))


def run(level, seed, policy):
    out = ROLLOUT(level, jax.random.PRNGKey(seed), jnp.float32(policy[0]),
                  jnp.float32(policy[1]))
    return jax.tree.map(np.asarray, out)


# --- reference geometry (numpy, float64) ----------------------------------------------------


def np_geometry(pos, heading, u):
    """(box_margin, fov_margin): box_margin < 0 iff t overlaps a's hurtbox (strict);
    fov_margin >= 0 iff t touches v's view wedge. TABX_REFERENCE.md section 4."""
    pos, heading = pos.astype(np.float64), heading.astype(np.float64)
    r = u["radius"].astype(np.float64)
    half = 0.5 * u["sight_angle"].astype(np.float64)
    rel = pos[None, :, :] - pos[:, None, :]
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    lx = c * rel[..., 0] + s * rel[..., 1]
    ly = -s * rel[..., 0] + c * rel[..., 1]
    x0 = (r * np.cos(half))[:, None]
    x1 = x0 + u["attack_range"][:, None]
    hw = (r * np.sin(half))[:, None]
    gx = np.maximum(np.maximum(x0 - lx, lx - x1), 0.0)
    gy = np.maximum(np.abs(ly) - hw, 0.0)
    box_margin = gx * gx + gy * gy - np.square(r)[None, :]
    left, right = heading + half, heading - half
    d1 = -np.sin(left)[:, None] * rel[..., 0] + np.cos(left)[:, None] * rel[..., 1]
    d2 = -np.sin(right)[:, None] * rel[..., 0] + np.cos(right)[:, None] * rel[..., 1]
    fov_margin = np.minimum(r[None, :] - d1, d2 + r[None, :])
    return box_margin, fov_margin


def np_in_bush(pos, z):
    """(inside, ambiguous) of unit centres in bush zones, (N, Z)."""
    axes = np.maximum(z["semi_axes"].astype(np.float64), 1e-6)
    q = np.square((pos[:, None, :] - z["centre"][None]) / axes[None]).sum(-1)
    bush = (z["zone_type"] == C.ZONE_BUSH)[None, :]
    return (q <= 1.0) & bush, (np.abs(q - 1.0) < 1e-3) & bush


def np_hp_ratio(health, u, mode):
    """(2,) team health ratio: mean of health / max health, or sum / sum."""
    out = []
    for team in (C.ALLY, C.ENEMY):
        m = (u["team"] == team) & u["active"]
        if mode == C.REWARD_RATIO_OF_SUMS:
            out.append(health[m].sum() / u["max_health"][m].sum())
        else:
            out.append((health[m] / u["max_health"][m]).mean())
    return np.clip(np.array(out), 0.0, 1.0)


# --- the invariants --------------------------------------------------------------------------


def check_geometry(s, u, z, alive):
    """attackable, target and visible of one state against the numpy reference (pairs within
    float tolerance of a boundary are skipped)."""
    pos, heading = s["position"], s["heading"]
    active = u["active"]
    box_margin, fov_margin = np_geometry(pos, heading, u)
    scale = 1.0 + np.abs(pos).max()
    box_sure = np.abs(box_margin) > 1e-3 * scale * scale
    fov_sure = np.abs(fov_margin) > 1e-3 * scale
    team, heals = u["team"], u["heals"]
    same = team[:, None] == team[None, :]
    role = np.where(heals[:, None], same, ~same)
    expect_att = ((box_margin < 0) & role & ~np.eye(N, dtype=bool) & alive[:, None]
                  & alive[None, :])
    att = s["attackable"]
    sure = box_sure | ~(role & alive[:, None] & alive[None, :])
    np.testing.assert_array_equal(att[sure], expect_att[sure])
    assert not att[~(alive[:, None] & alive[None, :])].any()
    # Target: the nearest attackable unit, and has_target iff there is one.
    np.testing.assert_array_equal(s["has_target"], att.any(-1))
    dist2 = np.square(pos[None, :, :] - pos[:, None, :]).sum(-1)
    for a in np.flatnonzero(s["has_target"]):
        t = s["target"][a]
        assert att[a, t], (a, t)
        assert dist2[a, t] <= dist2[a][att[a]].min() + 1e-4 * scale * scale
    # Visibility: never beyond the field of view; allies always seen within it; opponents not
    # in a bush seen exactly when in the field of view.
    vis = s["visible"]
    rows = active[:, None] & active[None, :]
    fov = fov_margin >= 0
    assert not (vis & rows & ~fov & fov_sure).any(), "visible outside the field of view"
    in_bush, near_edge = np_in_bush(pos, z)
    not_hidden = same | (~in_bush.any(-1) & ~near_edge.any(-1))[None, :]
    check = rows & fov_sure & not_hidden
    np.testing.assert_array_equal(vis[check], fov[check])
    assert not vis[:, ~active].any()


def check_rollout(level, out):
    obs0, s0, ws0, traj = out
    u = jax.tree.map(np.asarray, vars(level.units))
    z = jax.tree.map(np.asarray, vars(level.zones))
    active, max_health, radius = u["active"], u["max_health"], u["radius"]
    cap = np.asarray(cooldown_cap(level))  # the cooldown, one dt more under observed-cooldown
    half = 0.5 * np.asarray(level.physics.arena_size)
    limit = np.maximum(half[None, :] - radius[:, None], 0.0)
    assert obs0.shape == (N, CONFIG.obs_size) and ws0.shape == (CONFIG.state_size,)
    assert np.isfinite(obs0).all() and np.isfinite(ws0).all()

    states = [jax.tree.map(np.asarray, vars(s0))]
    states += [{k: np.asarray(v)[t] for k, v in vars(traj["state"]).items()} for t in range(T)]
    for t, s in enumerate(states):
        health, alive = s["health"], s["alive"]
        assert (health >= 0).all() and (health <= max_health * (1 + 1e-6)).all(), t
        assert not alive[~active].any() and (health[~active] == 0).all(), t
        assert (health[alive] > 0).all(), t
        assert (health[active & ~alive] == 0).all(), "a dead unit has health"
        assert (np.abs(s["position"]) <= limit + 1e-4).all(), f"outside the arena at {t}"
        assert (s["hp_ratio"] >= 0).all() and (s["hp_ratio"] <= 1).all()
        # [0, 2 pi) up to rounding (a tiny negative heading wraps to 2 pi in float32).
        assert (s["heading"] >= -1e-6).all() and (s["heading"] <= 2 * math.pi + 1e-6).all()
        assert np.isfinite(s["position"]).all() and np.isfinite(s["velocity"]).all()
        assert (s["cooldown"] >= 0).all() and (s["cooldown"] <= cap + 1e-6).all()
        check_geometry(s, u, z, alive)
        if t > 0:
            prev = states[t - 1]
            assert not (alive & ~prev["alive"]).any(), f"revived at step {t}"
            assert (health[~prev["alive"]] == prev["health"][~prev["alive"]]).all()

    obs, ws, reward, done = traj["obs"], traj["world_state"], traj["reward"], traj["done"]
    assert obs.shape == (T, N, CONFIG.obs_size) and ws.shape == (T, CONFIG.state_size)
    assert np.isfinite(obs).all() and np.isfinite(ws).all() and np.isfinite(reward).all()
    np.testing.assert_array_equal(obs[:, ~active], 0.0)
    # Zero-sum rewards (win +1, lose -1), bounded.
    np.testing.assert_allclose(reward.sum(-1), 0.0, atol=1e-5)
    assert (np.abs(reward) <= 3.0 + 1e-5).all()
    # Done: reached by max_steps at the latest, then absorbing: no reward, no change.
    first = int(np.argmax(done))
    assert done.any() and first < CONFIG.max_steps
    assert done[first:].all() and not done[:first].any()
    assert np.array_equal(done, traj["state"].done)
    assert int(states[first + 1]["step"]) == first + 1
    won = states[first + 1]["won"]
    assert won.sum() == 1
    # Team ratios from the healths, the dense reward from their change, the terminal reward
    # to the team with the higher rounded ratio (ties to the enemy).
    mode = int(level.reward_mode)
    for t in range(first + 1):
        ratio = np_hp_ratio(states[t + 1]["health"], u, mode)
        np.testing.assert_allclose(states[t + 1]["hp_ratio"], ratio, atol=1e-5)
        delta = states[t + 1]["hp_ratio"] - states[t]["hp_ratio"]
        expected = delta - delta[::-1]
        if t == first:
            assert won[0] == (np.round(ratio[0], 4) > np.round(ratio[1], 4)) or \
                abs(ratio[0] - ratio[1]) < 1e-4
            expected = expected + np.where(won, CONFIG.win_reward, CONFIG.lose_reward)
        np.testing.assert_allclose(reward[t], expected, atol=1e-5)
    np.testing.assert_allclose(states[0]["hp_ratio"], np_hp_ratio(states[0]["health"], u, mode),
                               atol=1e-6)
    for t in range(first + 1, T):
        np.testing.assert_array_equal(reward[t], 0.0)
        for k, v in states[t + 1].items():
            np.testing.assert_array_equal(v, states[first + 1][k], err_msg=f"{k} at {t}")
        np.testing.assert_array_equal(obs[t], obs[first])
    # An attack happens exactly when ATTACK is chosen and the mask allowed it; it hits when the
    # previous step left a target; a hit on a unit lowers (or, healing, raises) its health.
    info = traj["info"]
    for t in range(first + 1):
        attack_ok = (traj["actions"][t] == C.ATTACK) & traj["mask"][t][:, C.ATTACK]
        np.testing.assert_array_equal(info["attacking"][t], attack_ok)
        np.testing.assert_array_equal(info["hit"][t], attack_ok & states[t]["has_target"])
        assert not (info["hit"][t] & ~states[t]["alive"]).any()
        attacked = info["attacking"][t]
        np.testing.assert_allclose(states[t + 1]["cooldown"][attacked & active],
                                   np.minimum(float(level.physics.dt), cap)[
                                       attacked & active], rtol=1e-6)
    # Action masks: IDLE always legal; units that cannot act may only IDLE.
    masks = np.concatenate([traj["mask"], traj["next_mask"][-1:]])
    assert masks[..., C.IDLE].all()
    alive_seq = np.stack([s["alive"] for s in states])
    assert not masks[~alive_seq][:, :C.IDLE].any()


@PROPS
@given(level=levels(), seed=st.integers(0, 2**31 - 1), policy=policies)
def test_random_rollouts_keep_invariants(level, seed, policy):
    check_rollout(level, run(level, seed, policy))


@settings(max_examples=max(5, EXAMPLES // 3), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(level=levels(), seed=st.integers(0, 2**31 - 1), policy=policies)
def test_rollouts_are_deterministic(level, seed, policy):
    a, b = run(level, seed, policy), run(level, seed, policy)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def test_rollout_compiled_once():
    # Hypothesis examples run through one executable (levels are data).
    if ROLLOUT._cache_size() == 0:
        pytest.skip("run together with the property tests")
    assert ROLLOUT._cache_size() == 1
