"""The scripted opponent, one behaviour per test, each in a small hand-built situation.

Allies are slots 0-2 and enemies 3-5 (tests/tabx/envtools.py). Unless a test says otherwise the ally
team runs the heuristic with epsilon 0 and the enemies stand still (idle), so every movement
seen is the heuristic's decision.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from envtools import A0, A1, A2, CONFIG, E0, E1, FAR_ENEMY, KEY, N, level, unit, zone
from scipy import stats

from tabx import constants as C
from tabx.controllers import (
    Controller,
    controlled_actions,
    controlled_actions_from_words,
    controller_words,
    with_tiers,
)
from tabx.env import TabxEnv
from tabx.heuristic import heuristic_actions, unit_roles
from tabx.params import EnvParams, heuristic_params
from tabx.profiles import PROFILE_NAMES, with_profile
from tabx.rng import random_words

ENV = TabxEnv(CONFIG)
# An enemy nobody can see: in a bush that no ally enters (a team needs one living unit).
HIDING_BUSH = zone("bush", -50, -30, 3, 3)
HIDDEN_ENEMY = unit("farmer", -50, -30, math.pi)
MOVES = {C.UP, C.DOWN, C.LEFT, C.RIGHT}
TURNS = {C.TURN_LEFT, C.TURN_RIGHT}


def greedy(ally: dict | str = "expert", enemy: dict | str = "expert", **overrides):
    """Heuristic parameters with epsilon 0 on both teams (other values from the tiers)."""
    a = {**({"epsilon": 0.0} if isinstance(ally, dict) else {}), **(ally if isinstance(ally, dict)
                                                                    else {})}
    e = enemy if isinstance(enemy, dict) else {}
    tier_a = ally if isinstance(ally, str) else "expert"
    tier_e = enemy if isinstance(enemy, str) else "expert"
    from tabx.params import HEURISTIC_TIERS

    a = {**HEURISTIC_TIERS[tier_a], "epsilon": 0.0, **a, **overrides}
    e = {**HEURISTIC_TIERS[tier_e], "epsilon": 0.0, **e}
    return heuristic_params(a, e)


def play(params: EnvParams, key: jax.Array, steps: int,
         controllers: tuple[Controller, Controller] = (Controller("heuristic"), Controller("idle")),
         state=None):
    """Run `steps` steps; returns per-step (actions, state before the step) and the final state."""
    if state is None:
        state = ENV.initial_state(params)
    actions, before, final = _play(params, key, state, steps, controllers)
    return np.asarray(actions), before, final


@partial(jax.jit, static_argnames=("steps", "controllers"))
def _play(params, key, state, steps, controllers):

    def body(state, k):
        actions, state = controlled_actions(k, state, params, None, controllers)
        _, new_state, _, _, _ = ENV.step(k, state, actions, params)
        return new_state, (actions, state)

    final, (actions, before) = jax.lax.scan(body, state, jax.random.split(key, steps))
    return actions, before, final


decide = jax.jit(heuristic_actions)


def test_roles_from_stats_and_team_thresholds():
    params = level([unit("assassin", 0, 0), unit("archer", 5, 0), unit("healer", 10, 0)],
                   [unit("assassin", 0, 20), unit("archer", 5, 20)],
                   heuristic=heuristic_params({"assassin_speed": 1.5}, "medium"))
    assassin, ranger, healer = (np.asarray(r) for r in unit_roles(params))
    # The ally team's assassin threshold 1.5 is above the assassin's speed 1.4: no assassin.
    assert assassin[A0] == False and assassin[E0] == True  # noqa: E712
    assert ranger[A1] and ranger[A2] and not ranger[A0]  # healer range 10 counts as ranger
    assert healer[A2] and not healer[A1]


def test_assassin_goes_behind_its_target_and_a_farmer_stays_in_front():
    # Faces the attacker, so its back is at x > 10; tough enough to survive the test.
    target = unit("farmer", 10, 0, math.pi, health=1000.0)
    for name, behind in (("assassin", True), ("farmer", False)):
        params = level([unit(name, 0, 3)], [target, FAR_ENEMY], heuristic=greedy())
        _, before, final = play(params, KEY, 60)
        # The target faces -x: the attacker is behind it where its x is larger.
        x = np.asarray(before.position[:, A0, 0] - before.position[:, E0, 0])
        if behind:
            assert x.max() > 1.0, f"assassin never got behind the target: max dx {x.max():.2f}"
        else:
            assert x.max() < 0.0, f"a farmer went behind the target: max dx {x.max():.2f}"


def test_assassin_targets_lowest_max_health_others_the_nearest():
    # A king (346 hp) near, a farmer (60 hp) farther; both in view.
    enemies = [unit("theking", 6, 1, math.pi), unit("farmer", 12, -2, math.pi)]
    for name, expected in (("assassin", E1), ("farmer", E0)):
        params = level([unit(name, 0, 0)], enemies, heuristic=greedy())
        _, state = ENV.reset(KEY, params)
        _, after = decide(KEY, state, params)
        np.testing.assert_allclose(after.memory_position[A0], state.position[expected])


def test_ranger_retreats_inside_threshold_and_holds_outside():
    enemy = unit("farmer", 10, 0, math.pi, health=1000.0)  # survives the test
    # Expert threshold 0.7 x range 27 = 18.9 > 10: retreat (left, away from the farmer).
    params = level([unit("archer", 0, 0)], [enemy, FAR_ENEMY], heuristic=greedy("expert"))
    actions, before, _ = play(params, KEY, 60)
    assert actions[0, A0] == C.LEFT
    gap = np.linalg.norm(np.asarray(before.position[:, E0] - before.position[:, A0]), axis=-1)
    # It backs off to the threshold and then keeps that distance (attacking when ready).
    assert 0.7 * 27 - 1.5 < gap[-20:].min() and gap[-20:].max() < 0.7 * 27 + 1.5
    assert np.any(actions[:, A0] == C.ATTACK)
    # Novice threshold 0.1 x 27 = 2.7 < 10: no retreat, it closes in.
    params = level([unit("archer", 0, 0)], [enemy, FAR_ENEMY], heuristic=greedy("novice"))
    actions, before, _ = play(params, KEY, 60)
    assert C.LEFT not in actions[:10, A0]
    assert before.position[10, A0, 0] > 4.0


def test_healer_heads_for_the_injured_ally_not_the_healthy_one():
    healthy = unit("farmer", 12, 9)
    injured = unit("farmer", 12, -9, health=20.0, max_health=60.0)
    params = level([unit("healer", 0, 0), healthy, injured], [FAR_ENEMY], heuristic=greedy())
    _, before, final = play(params, KEY, 60)
    pos = np.asarray(before.position)
    to_injured = np.linalg.norm(pos[:, A2] - pos[:, A0], axis=-1)
    to_healthy = np.linalg.norm(pos[:, A1] - pos[:, A0], axis=-1)
    assert to_injured[-1] < to_healthy[-1] - 5.0
    assert float(final.health[A2]) > 20.0  # and it healed it
    assert float(final.health[A1]) == 60.0


def test_lost_target_goes_to_last_seen_position_then_searches():
    params = level([unit("farmer", 0, 0)], [unit("farmer", 12, 0, math.pi), HIDDEN_ENEMY],
                   [HIDING_BUSH], heuristic=greedy())
    _, state = ENV.reset(KEY, params)
    actions, state = decide(KEY, state, params)
    assert bool(state.memory_valid[A0])
    np.testing.assert_allclose(state.memory_position[A0], [12.0, 0.0])
    # The target vanishes from view (into the bush).
    position = state.position.at[E0].set(jnp.asarray([-49.0, -30.0]))
    inside = jnp.zeros((N, CONFIG.max_zones), bool).at[E0, 0].set(True).at[E1, 0].set(True)
    state = ENV._refresh_geometry(state.replace(position=position), params,
                                  jnp.zeros((N, N), bool), inside)
    assert not bool(state.visible[A0, E0])
    actions, before, final = play(params, KEY, 60, state=state)
    a = actions[:, A0]
    valid = np.asarray(before.memory_valid[:, A0])
    first_search = int(np.argmin(valid))  # first step without memory
    assert first_search > 5, "it should pursue for several steps first"
    assert set(a[:first_search]) <= {C.RIGHT}
    assert abs(float(before.position[first_search, A0, 0]) - 12.0) < 1.2
    assert set(a[first_search:]) <= TURNS


def test_a_corpse_on_the_remembered_spot_ends_the_pursuit_at_once():
    # The remembered spot is where an enemy now lies dead, in view: the unit searches on this
    # very step in both profiles (the reference forgets a spot it reaches only a step later).
    params = level([unit("farmer", 0, 0)], [unit("farmer", 8, 0, math.pi), HIDDEN_ENEMY],
                   [HIDING_BUSH], heuristic=greedy())
    _, state = ENV.reset(KEY, params)
    state = state.replace(alive=state.alive.at[E0].set(False),
                          health=state.health.at[E0].set(0.0),
                          memory_position=state.memory_position.at[A0].set(jnp.asarray([8.5, 0])),
                          memory_valid=state.memory_valid.at[A0].set(True))
    assert bool(state.visible[A0, E0])
    for profile in PROFILE_NAMES:
        actions, after = decide(KEY, state, with_profile(params, profile))
        assert int(actions[A0]) in TURNS, profile
        assert not bool(after.memory_valid[A0])


def test_ranger_with_nothing_in_sight_heads_for_the_nearest_bush():
    bushes = [zone("bush", 20, 10, 4, 3), HIDING_BUSH]
    for name in ("archer", "farmer"):
        params = level([unit(name, 0, 0, math.pi)], [HIDDEN_ENEMY], bushes, heuristic=greedy())
        actions, before, final = play(params, KEY, 60)
        inside = ((final.position[A0] - jnp.asarray([20.0, 10.0])) / jnp.asarray([4.0, 3.0]))
        if name == "archer":
            assert float(jnp.sum(inside**2)) <= 1.0, "the archer did not reach the bush"
            assert set(actions[-5:, A0]) <= TURNS  # then it searches from the bush
        else:
            assert set(actions[:, A0]) <= TURNS  # a non-ranger just searches


def test_turns_toward_a_target_when_the_turn_would_make_it_attackable():
    for sign, turn in ((1, C.TURN_LEFT), (-1, C.TURN_RIGHT)):
        angle = sign * 40 * math.pi / 180
        enemy = unit("farmer", 4 * math.cos(angle), 4 * math.sin(angle))
        params = level([unit("farmer", 0, 0)], [enemy, FAR_ENEMY], heuristic=greedy())
        _, state = ENV.reset(KEY, params)
        assert not bool(state.attackable[A0, E0]) and bool(state.visible[A0, E0])
        actions, _ = decide(KEY, state, params)
        assert int(actions[A0]) == turn
        # Far away the turn would not bring it in reach: it walks instead.
        far = unit("farmer", 20 * math.cos(angle), 20 * math.sin(angle))
        params = level([unit("farmer", 0, 0)], [far, FAR_ENEMY], heuristic=greedy())
        _, state = ENV.reset(KEY, params)
        actions, _ = decide(KEY, state, params)
        assert int(actions[A0]) in MOVES


def test_attacks_when_attackable_and_ready_only():
    params = level([unit("farmer", 0, 0)], [unit("farmer", 2.5, 0, math.pi), FAR_ENEMY],
                   heuristic=greedy())
    _, state = ENV.reset(KEY, params)
    assert bool(state.attackable[A0, E0])
    actions, _ = decide(KEY, state.replace(cooldown=state.cooldown.at[A0].set(0.0)), params)
    assert int(actions[A0]) != C.ATTACK
    actions, _ = decide(KEY, state.replace(cooldown=state.cooldown.at[A0].set(10.0)), params)
    assert int(actions[A0]) == C.ATTACK


def test_epsilon_one_is_uniform_over_legal_actions():
    params = level([unit("farmer", 0, 0)], [unit("farmer", 12, 0, math.pi), FAR_ENEMY],
                   heuristic=heuristic_params("random", "random"))
    _, state = ENV.reset(KEY, params)
    state = state.replace(cooldown=state.cooldown.at[A0].set(10.0))  # all 8 actions legal
    keys = jax.random.split(jax.random.PRNGKey(3), 8000)
    actions = np.asarray(jax.vmap(decide, (0, None, None))(keys, state, params)[0][:, A0])
    counts = np.bincount(actions, minlength=C.NUM_ACTIONS)
    assert stats.chisquare(counts).pvalue > 1e-3, counts
    # With the attack not ready, ATTACK is never drawn and the other 7 stay uniform.
    state = state.replace(cooldown=state.cooldown.at[A0].set(0.0))
    actions = np.asarray(jax.vmap(decide, (0, None, None))(keys, state, params)[0][:, A0])
    counts = np.bincount(actions, minlength=C.NUM_ACTIONS)
    assert counts[C.ATTACK] == 0
    assert stats.chisquare(np.delete(counts, C.ATTACK)).pvalue > 1e-3, counts


def test_epsilon_zero_is_deterministic_while_a_target_or_memory_exists():
    params = level([unit("archer", 0, 0), unit("assassin", 0, 5), unit("healer", -3, 0)],
                   [unit("farmer", 12, 0, math.pi), unit("theking", 10, 6, math.pi)],
                   heuristic=greedy())
    keys = jax.random.split(jax.random.PRNGKey(5), 16)
    runs = [play(params, k, 60, (Controller("heuristic"), Controller("heuristic")))
            for k in keys[:4]]
    # Only a unit with neither target nor memory acts at random (its search rotation): compare
    # up to the first step where a living unit has neither.
    before = runs[0][1]
    undecided = np.any(np.asarray(before.alive & ~before.memory_valid), axis=-1)
    until = int(np.argmax(undecided)) if undecided.any() else len(undecided)
    assert until >= 20
    for other in runs[1:]:
        np.testing.assert_array_equal(runs[0][0][:until], other[0][:until])


def test_search_rotation_is_stochastic_and_reverses():
    params = level([unit("farmer", 0, 0, math.pi)], [HIDDEN_ENEMY], [HIDING_BUSH],
                   heuristic=greedy())
    actions, _, _ = play(params, KEY, 200)
    a = actions[:, A0]
    assert set(a) == TURNS, "both search directions appear"
    # Runs are long (a sweep), not a coin flip per step.
    switches = np.count_nonzero(a[1:] != a[:-1])
    assert 1 <= switches < 40
    other, _, _ = play(params, jax.random.PRNGKey(99), 200)
    assert not np.array_equal(a, other[:, A0])


def test_never_reads_hidden_units():
    """Moving or wounding a unit that nobody on the ally team sees changes no ally action."""
    params = level([unit("archer", 0, 0), unit("farmer", 0, 6)],
                   [unit("farmer", 14, 2, math.pi), unit("theking", -40, 20, 0.0)],
                   heuristic=heuristic_params("medium", "medium"))
    _, state = ENV.reset(KEY, params)
    assert not bool(jnp.any(state.visible[:2, E1]))
    base, _ = decide(KEY, state, params)
    moved = state.replace(position=state.position.at[E1].set(jnp.asarray([-45.0, -25.0])),
                          health=state.health.at[E1].set(10.0))
    moved_actions, _ = decide(KEY, moved, params)
    np.testing.assert_array_equal(np.asarray(base)[:2], np.asarray(moved_actions)[:2])


def test_memory_is_cleared_on_reset_and_autoreset():
    params = level([unit("farmer", 0, 0)], [unit("farmer", 12, 0, math.pi), FAR_ENEMY],
                   heuristic=greedy())
    _, state = ENV.reset(KEY, params)
    assert not bool(jnp.any(state.memory_valid))
    _, state = decide(KEY, state, params)
    assert bool(state.memory_valid[A0])
    done = state.replace(step=jnp.asarray(CONFIG.max_steps - 1, jnp.int32))
    start = ENV.initial_state(params)
    _, after, _, d, _ = jax.jit(ENV.step_autoreset)(KEY, done, jnp.full((N,), C.IDLE), params,
                                                    start)
    assert bool(d) and not bool(jnp.any(after.memory_valid))


def test_controllers_mix_external_heuristic_random():
    params = level([unit("farmer", 0, 0), unit("farmer", 0, 5)],
                   [unit("farmer", 12, 0, math.pi), unit("farmer", 12, 5, math.pi)],
                   heuristic=greedy())
    _, state = ENV.reset(KEY, params)
    external = jnp.full((N,), C.DOWN, jnp.int32)
    ctrl = (Controller("external"), Controller("heuristic"))
    actions, _ = controlled_actions(KEY, state, params, external, ctrl)
    heur, _ = decide(jax.random.split(KEY)[0], state, params)
    a = np.asarray(actions)
    assert list(a[[A0, A1]]) == [C.DOWN, C.DOWN]
    np.testing.assert_array_equal(a[[E0, E1]], np.asarray(heur)[[E0, E1]])
    actions, _ = controlled_actions(KEY, state, params, None, (Controller("idle"),
                                                               Controller("random")))
    assert set(np.asarray(actions)[[A0, A1]]) == {C.IDLE}
    with pytest.raises(ValueError, match="no actions were given"):
        controlled_actions(KEY, state, params, None, ctrl)


def test_batch_words_drive_each_env_like_its_own_words():
    """`controller_words` draws a whole batch's randomness from one key (no threefry per env):
    every env gets its own words, and an env driven by its row of the batch decides exactly as
    `controlled_actions_from_words` does for it alone."""
    params = level([unit("archer", 0, 0), unit("farmer", 0, 5)],
                   [unit("farmer", 12, 0, math.pi), unit("archer", 12, 5, math.pi)],
                   heuristic=heuristic_params("random", "novice"))
    _, state = ENV.reset(KEY, params)
    envs = 16
    words = controller_words(KEY, envs, N)
    assert words.shape == (envs, 2, N) and words.dtype == jnp.uint32
    assert len({bytes(np.asarray(w)) for w in words}) == envs  # no two envs share their draw
    np.testing.assert_array_equal(words, controller_words(KEY, envs, N))
    ctrl = (Controller("random"), Controller("heuristic"))
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (envs, *jnp.shape(x))), (state, params))
    actions, after = jax.vmap(lambda w, s, p: controlled_actions_from_words(w, s, p, None, ctrl))(
        words, *batch)
    for e in (0, 7, 15):
        alone, alone_state = controlled_actions_from_words(words[e], state, params, None, ctrl)
        np.testing.assert_array_equal(actions[e], alone)
        np.testing.assert_array_equal(after.search_turn[e], alone_state.search_turn)
    # Random allies and epsilon-random enemies differ between envs: the rows are used.
    assert len({tuple(np.asarray(a)) for a in actions}) > 1
    # The per-env entry point is the same policy on the words drawn from its key.
    n = params.units.team.shape[0]
    direct, _ = controlled_actions(KEY, state, params, None, ctrl)
    from_words, _ = controlled_actions_from_words(
        random_words(KEY, (2, n)), state, params, None, ctrl)
    np.testing.assert_array_equal(direct, from_words)


def test_controller_parsing_and_tiers():
    assert Controller.parse("heuristic:expert") == Controller("heuristic", "expert")
    assert str(Controller.parse("random")) == "random"
    for bad, match in (("heuristic:godlike", "unknown heuristic tier"),
                       ("robot", "unknown controller"), ("random:expert", "only goes with")):
        with pytest.raises(ValueError, match=match):
            Controller.parse(bad)
    assert Controller.parse_scripted("heuristic:novice") == Controller("heuristic", "novice")
    with pytest.raises(ValueError, match="'external' is not an opponent: .* no learner plays"):
        Controller.parse_scripted("external", "an opponent")
    params = level([unit("farmer", 0, 0)], [unit("farmer", 12, 0)],
                   heuristic=heuristic_params("medium", "medium"))
    tiered = with_tiers(params, (Controller("heuristic"), Controller("heuristic", "expert")))
    np.testing.assert_allclose(tiered.heuristic.epsilon, [0.2, 0.01])
    np.testing.assert_allclose(tiered.heuristic.aggressive_threshold, [0.3, 0.7])


def test_changing_tier_never_recompiles():
    params = level([unit("archer", 0, 0)], [unit("farmer", 12, 0, math.pi)])
    ctrl = (Controller("heuristic"), Controller("heuristic"))
    fn = jax.jit(lambda k, s, p: controlled_actions(k, s, p, None, ctrl))
    _, state = ENV.reset(KEY, params)
    from tabx.params import HEURISTIC_TIERS

    for ally in HEURISTIC_TIERS:
        for enemy in HEURISTIC_TIERS:
            fn(KEY, state, params.replace(heuristic=heuristic_params(ally, enemy)))
    assert fn._cache_size() == 1
