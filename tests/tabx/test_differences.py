"""docs/differences.md, walked row by row: every `choice` row names a reference behaviour that
the `reference` profile restores; here each one gets a small scenario where the choice
matters, played with the choice off (ours) and on (the reference's), and asserted both ways.

All scenarios run in ONE compiled call: a batch of (case, off/on) levels, each playing
`STEPS` steps with the scripted policy on the allies while the enemies stand still (idle).
Slots: allies 0-2, enemies 3-5 (tests/tabx/envtools.py).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from envtools import A0, A1, CONFIG, E0, KEY, N, level, unit, zone

from tabx import constants as C
from tabx import profiles as P
from tabx.controllers import Controller, controlled_actions
from tabx.env import TabxEnv
from tabx.params import EnvParams, heuristic_params, stack_levels
from tabx.state import EnvState

DOC = Path(__file__).resolve().parents[2] / "docs" / "differences.md"
ENV = TabxEnv(CONFIG)
STEPS = 32
CONTROLLERS = (Controller("heuristic"), Controller("external"))
MOVES = {C.UP, C.DOWN, C.LEFT, C.RIGHT}
TURNS = {C.TURN_LEFT, C.TURN_RIGHT}
# Out of every ally's sight: in a bush no ally enters (a team needs one living unit).
HIDING_BUSH = zone("bush", -50, -30, 3, 3)
HIDDEN_ENEMY = unit("farmer", -50, -30, math.pi)


def greedy(**ally: float):
    """Expert parameters with epsilon 0 for both teams, `ally` overriding the allies'."""
    from tabx.params import HEURISTIC_TIERS

    return heuristic_params({**HEURISTIC_TIERS["expert"], "epsilon": 0.0, **ally},
                            {**HEURISTIC_TIERS["expert"], "epsilon": 0.0})


@dataclass
class Trace:
    """One played scenario: per step the actions, the state after the heuristic decided
    (its memory) and the state after the step; the final state."""

    actions: np.ndarray  # (STEPS, N)
    decided: EnvState  # leaves (STEPS, ...)
    after: EnvState  # leaves (STEPS, ...)


@dataclass
class Case:
    """A scenario where one choice matters. `toggle` is the profile bit switched between the
    two runs (None: the reward mode), `base` bits are set in both."""

    level: EnvParams
    check: Callable[[Trace, Trace], None]  # (ours, reference)
    toggle: int | None
    base: int = 0
    prepare: Callable[[EnvState], EnvState] | None = None


def _epsilon_moves() -> Case:
    # Two random-tier farmers next to an enemy they could hit.
    lv = level([unit("farmer", 0, 0), unit("farmer", 0, -3)],
               [unit("farmer", 2.5, 0, math.pi, health=1e4)],
               heuristic=heuristic_params("random", "expert"))

    def check(ours, ref):
        a = ours.actions[:, [A0, A1]]
        assert np.isin(a, [C.ATTACK, C.IDLE]).any()  # any legal action
        r = ref.actions[:, [A0, A1]]
        assert set(np.unique(r)) <= MOVES | TURNS  # never ATTACK or IDLE
    return Case(lv, check, P.EPSILON_MOVES)


def _kite_move_point() -> Case:
    # An expert archer (kites under 0.7 x 27 = 18.9) and a farmer 20 away facing it: its move
    # point (in front of the farmer) is 18 away.
    lv = level([unit("archer", 0, 0)], [unit("farmer", 20, 0, math.pi, health=1e4)],
               heuristic=greedy())

    def check(ours, ref):
        assert ours.actions[0, A0] == C.RIGHT  # 20 > 18.9: no threat, close in
        assert ref.actions[0, A0] == C.LEFT  # 18 < 18.9: retreat
    return Case(lv, check, P.KITE_MOVE_POINT)


def _search_right() -> Case:
    lv = level([unit("farmer", 0, 0), unit("farmer", 0, 10), unit("farmer", 0, -10)],
               [HIDDEN_ENEMY], [HIDING_BUSH], heuristic=greedy())

    def check(ours, ref):
        assert set(np.unique(ours.actions[:, :3])) == TURNS  # reverses at random
        assert set(np.unique(ref.actions[:, :3])) == {C.TURN_RIGHT}
    return Case(lv, check, P.SEARCH_RIGHT)


def _turn_prediction() -> Case:
    # A farmer 4 away at 40 degrees: three turn steps (45 degrees) bring it into the real
    # hurtbox, not into the reference's narrow predicted one.
    angle = math.radians(40)
    lv = level([unit("farmer", 0, 0)],
               [unit("farmer", 4 * math.cos(angle), 4 * math.sin(angle), health=1e4)],
               heuristic=greedy())

    def check(ours, ref):
        assert ours.actions[0, A0] == C.TURN_LEFT
        assert ref.actions[0, A0] in MOVES
    return Case(lv, check, P.TURN_PREDICTION)


def _turn_in_place() -> Case:
    # A mammoth with a farmer straight ahead, just out of reach: the reference's prediction
    # says a hit (no turn step needed), so the reference turns anyway; ours walks.
    lv = level([unit("mammoth", 0, 0)], [unit("farmer", 8.4, 0, math.pi, health=1e4)],
               heuristic=greedy())

    def check(ours, ref):
        assert ours.actions[0, A0] == C.RIGHT
        assert ref.actions[0, A0] == C.TURN_RIGHT
    return Case(lv, check, P.TURN_IN_PLACE, base=P.TURN_PREDICTION)


def _memory_reach() -> Case:
    # A farmer (speed 1.1: 0.55 per step, a move lands one step after its decision) remembers
    # a spot 2.95 ahead. Deciding at 2.2 (0.75 from it), ours (radius 0.78) forgets and stops;
    # the reference (radius sqrt(2) dt = 0.71) walks on, and once more on the arrival step.
    lv = level([unit("farmer", 0, 0)], [HIDDEN_ENEMY], [HIDING_BUSH], heuristic=greedy())

    def remember(state):
        return state.replace(memory_position=state.memory_position.at[A0].set(
            jnp.asarray([2.95, 0.0])), memory_valid=state.memory_valid.at[A0].set(True))

    def check(ours, ref):
        assert float(ours.after.position[-1, A0, 0]) == pytest.approx(2.75, abs=1e-4)
        assert float(ref.after.position[-1, A0, 0]) == pytest.approx(2.75 + 2 * 0.55, abs=1e-4)
        assert not ours.decided.memory_valid[-1, A0] and not ref.decided.memory_valid[-1, A0]
    return Case(lv, check, P.MEMORY_REACH, prepare=remember)


def _bush_box() -> Case:
    # An archer in the bush's bounding box but outside its ellipse.
    lv = level([unit("archer", 23.5, 12.5)], [HIDDEN_ENEMY],
               [zone("bush", 20, 10, 4, 3), HIDING_BUSH], heuristic=greedy())

    def check(ours, ref):
        assert ours.actions[0, A0] == C.LEFT  # toward the bush's centre
        assert ref.actions[0, A0] in TURNS  # "in the bush": it searches
    return Case(lv, check, P.BUSH_BOX)


def _assassin_current_speed() -> Case:
    # An assassin slowed by a swamp, a king (max health 346) near, a farmer (60) farther.
    enemies = [unit("theking", 6, 1, math.pi, health=1e4), unit("farmer", 12, -2, math.pi)]
    lv = level([unit("assassin", 0, 0)], enemies, [zone("swamp", 0, 0, 3, 3, 0.5)],
               heuristic=greedy())

    def check(ours, ref):
        # Its target (remembered position) after the first decision.
        np.testing.assert_allclose(ours.decided.memory_position[0, A0], [12.0, -2.0])
        np.testing.assert_allclose(ref.decided.memory_position[0, A0], [6.0, 1.0])
    return Case(lv, check, P.ASSASSIN_CURRENT_SPEED)


def _corpse_drift() -> Case:
    # A farmer with 1 health walks toward an enemy from inside lava and dies on that step.
    lv = level([unit("farmer", 0, 0, health=1.0), unit("farmer", -40, -30, math.pi)],
               [unit("farmer", 20, 0, math.pi)], [zone("lava", 0, 0, 2, 2, 10.0)],
               heuristic=greedy())

    def check(ours, ref):
        assert ours.actions[0, A0] == C.RIGHT and ref.actions[0, A0] == C.RIGHT
        assert not ours.after.alive[0, A0] and not ref.after.alive[0, A0]
        assert float(ours.after.position[-1, A0, 0]) == pytest.approx(0.0)
        assert float(ref.after.position[-1, A0, 0]) == pytest.approx(0.55)  # one more move
    return Case(lv, check, P.CORPSE_DRIFT)


def _corpse_vision() -> Case:
    # An ally dies (lava) inside a bush that hides an enemy; a teammate outside looks on.
    lv = level([unit("farmer", -1, 0, health=1.0), unit("farmer", -10, 0)],
               [unit("farmer", 1.5, 0, math.pi, health=1e4)],
               [zone("bush", 0, 0, 3, 3), zone("lava", -1, 0, 0.5, 0.5, 10.0)],
               heuristic=greedy())

    def check(ours, ref):
        assert not ours.after.alive[0, A0] and not ref.after.alive[0, A0]
        assert not ours.after.visible[0, A1, E0]
        assert ref.after.visible[0, A1, E0]
    return Case(lv, check, P.CORPSE_VISION)


def _observed_cooldown() -> Case:
    # A farmer (cooldown 2.5 s, 5 steps at dt 0.5) with an enemy in reach from the start.
    lv = level([unit("farmer", 0, 0)], [unit("farmer", 2.5, 0, math.pi, health=1e4)],
               heuristic=greedy())

    def check(ours, ref):
        # Ours attacks on the first ready step, every 5 steps; the reference one step later.
        assert list(np.flatnonzero(ours.actions[:, A0] == C.ATTACK)[:3]) == [4, 9, 14]
        assert list(np.flatnonzero(ref.actions[:, A0] == C.ATTACK)[:3]) == [5, 11, 17]
    return Case(lv, check, P.OBSERVED_COOLDOWN)


def _team_health() -> Case:
    # At the time limit: allies a full king and a farmer at 6/60 (mean of ratios 0.55, ratio
    # of sums 0.87), enemies two farmers at 42/60 (0.7 either way). Far apart, facing away.
    lv = level([unit("theking", -50, 30, math.pi), unit("farmer", -50, 20, math.pi, health=6.0,
                                                         max_health=60.0)],
               [unit("farmer", 50, 30, health=42.0, max_health=60.0),
                unit("farmer", 50, 20, health=42.0, max_health=60.0)],
               heuristic=greedy())

    def near_the_limit(state):
        return state.replace(step=jnp.asarray(CONFIG.max_steps - 2, jnp.int32))

    def check(ours, ref):
        assert ours.after.done[1] and ref.after.done[1]
        assert list(ours.after.won[1]) == [False, True]
        assert list(ref.after.won[1]) == [True, False]
    return Case(lv, check, None, prepare=near_the_limit)


CASES: dict[str, Callable[[], Case]] = {
    "epsilon-moves": _epsilon_moves,
    "kite-move-point": _kite_move_point,
    "search-right": _search_right,
    "turn-prediction": _turn_prediction,
    "turn-in-place": _turn_in_place,
    "memory-reach": _memory_reach,
    "bush-box": _bush_box,
    "assassin-current-speed": _assassin_current_speed,
    "corpse-drift": _corpse_drift,
    "corpse-vision": _corpse_vision,
    "observed-cooldown": _observed_cooldown,
    "team-health": _team_health,
}


def doc_rows() -> dict[str, str]:
    """{row id: profile column} of the table in docs/differences.md."""
    rows = {}
    for line in DOC.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        match = re.fullmatch(r"`([a-z0-9-]+)`", cells[0]) if line.startswith("|") else None
        if match:
            rows[match.group(1)] = cells[-1]
    return rows


@jax.jit
def _play(levels: EnvParams, states: EnvState, key: jax.Array):
    idle = jnp.full(N, C.IDLE, jnp.int32)

    def one(lv, state):
        def body(state, k):
            actions, decided = controlled_actions(k, state, lv, idle, CONTROLLERS)
            _, after, _, _, _ = ENV.step(k, decided, actions, lv)
            return after, (actions, decided, after)

        return jax.lax.scan(body, state, jax.random.split(key, STEPS))[1]

    return jax.vmap(one)(levels, states)


@pytest.fixture(scope="module")
def traces() -> dict[str, tuple[Trace, Trace]]:
    cases = {name: make() for name, make in CASES.items()}
    levels, states = [], []
    initial = jax.jit(ENV.initial_state)
    for case in cases.values():
        for on in (False, True):
            lv = case.level.replace(profile=jnp.asarray(
                case.base | (case.toggle if on and case.toggle is not None else 0), jnp.int32))
            if case.toggle is None:
                lv = lv.replace(reward_mode=jnp.asarray(
                    C.REWARD_RATIO_OF_SUMS if on else C.REWARD_MEAN_OF_RATIOS, jnp.int32))
            state = initial(lv)
            states.append(case.prepare(state) if case.prepare else state)
            levels.append(lv)
    out = jax.device_get(_play(stack_levels(levels), stack_levels(states), KEY))
    result = {}
    for i, name in enumerate(cases):
        pair = [Trace(*(jax.tree.map(lambda x, j=2 * i + k: np.asarray(x[j]), part)
                        for part in out)) for k in (0, 1)]
        result[name] = (pair[0], pair[1])
    return result


def test_every_difference_row_says_which_profile():
    rows = doc_rows()
    assert len(rows) >= 30, "the table of differences is missing or unparsed"
    assert set(rows.values()) <= {"fix", "choice", "interface", "option"}, rows


def test_every_choice_row_has_a_scenario_and_a_profile_bit():
    choices = {k for k, v in doc_rows().items() if v == "choice"}
    assert choices == set(CASES)
    assert set(P.CHOICES) | {"team-health"} == choices
    # The reference profile restores all of them.
    assert P.PROFILES["reference"] == (P.ALL_CHOICES, C.REWARD_RATIO_OF_SUMS)


@pytest.mark.parametrize("name", list(CASES))
def test_choice_changes_what_the_row_claims(traces, name):
    ours, reference = traces[name]
    CASES[name]().check(ours, reference)

