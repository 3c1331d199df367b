"""Randomised starts as level data (`start_noise`, `shuffle_positions`): off, a reset is the
level's own start whatever the key; on, the key draws the start, without recompiling. Scenario
files may set them, and level files written before the fields existed load with them off."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from level_buffer import BufferFileError, LevelBuffer
from level_buffer.tree import named_leaves
from tabx.compile_counter import CompileCounter
from tabx.env import TabxEnv
from tabx.params import level_config, levels_equal
from tabx.scenarios import ScenarioError, load_named
from tabx.scenarios.format import Scenario, level_to_scenario
from tabx.starts import randomise_start

FIXED_STARTS_FILE = Path(__file__).resolve().parents[1] / "data" / "buffer_fixed_starts_v1.msgpack"


@pytest.fixture(scope="module")
def level():
    return load_named("crossfire").to_level()


@pytest.fixture(scope="module")
def reset(level):
    return jax.jit(TabxEnv(level_config(level)).reset)


def positions(reset, key, level) -> np.ndarray:
    return np.asarray(reset(key, level)[1].position)


def test_off_by_default_every_key_gives_the_levels_own_start(level, reset):
    assert float(level.start_noise) == 0.0 and not bool(level.shuffle_positions)
    env = TabxEnv(level_config(level))
    own = jax.tree.map(np.asarray, env.initial_state(level))
    for seed in range(3):
        obs, state = reset(jax.random.key(seed), level)
        assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(state),
                                                        jax.tree.leaves(own), strict=True))
    assert levels_equal(randomise_start(jax.random.key(5), level), level)


def test_noise_and_shuffle_draw_the_start_from_the_key_without_recompiling(level, reset):
    noisy = level.replace(start_noise=jnp.float32(2.0))
    shuffled = level.replace(shuffle_positions=jnp.bool_(True))
    base = positions(reset, jax.random.key(0), level)
    with CompileCounter() as counter:
        a, b = (positions(reset, jax.random.key(s), noisy) for s in (1, 2))
        shuffles = [positions(reset, jax.random.key(s), shuffled) for s in range(6)]
        again = positions(reset, jax.random.key(1), noisy)
    assert counter.compiles == 0, counter.traced
    active = np.asarray(level.units.active)
    team = np.asarray(level.units.team)
    assert not np.array_equal(a[active], b[active]) and np.array_equal(a, again)
    # Within the radius of the level's own start (the wall contact only pulls units inward).
    assert np.all(np.linalg.norm(a - base, axis=-1)[active] <= 2.0 + 1e-5)
    assert np.array_equal(a[~active], base[~active])
    # A shuffle permutes each team's start positions among its own real units.
    for p in shuffles:
        for t in (0, 1):
            mine = active & (team == t)
            assert sorted(map(tuple, p[mine])) == sorted(map(tuple, base[mine]))
    assert any(not np.array_equal(p, base) for p in shuffles)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), noise=st.floats(0.0, 50.0), shuffle=st.booleans())
def test_a_randomised_start_keeps_every_unit_and_only_moves_positions(level, seed, noise,
                                                                      shuffle):
    new = randomise_start(jax.random.key(seed), level.replace(
        start_noise=jnp.float32(noise), shuffle_positions=jnp.bool_(shuffle)))
    moved = np.asarray(new.units.position) != np.asarray(level.units.position)
    assert levels_equal(new.replace(units=new.units.replace(position=level.units.position),
                                    start_noise=level.start_noise,
                                    shuffle_positions=level.shuffle_positions), level)
    assert not moved[~np.asarray(level.units.active)].any()
    if noise == 0.0 and not shuffle:
        assert not moved.any()


def test_scenario_files_may_randomise_starts():
    own = load_named("crossfire")
    assert own.start_noise == 0.0 and not own.shuffle_positions  # the paper's starts are fixed
    data = {**own.to_dict(), "start_noise": 3.5, "shuffle_positions": True}
    scenario = Scenario.from_dict(data, source="s.json")
    level = scenario.to_level()
    assert float(level.start_noise) == 3.5 and bool(level.shuffle_positions)
    back = level_to_scenario(level, name=own.name, category=own.category)
    assert (back.start_noise, back.shuffle_positions) == (3.5, True)
    assert "start_noise" not in own.to_dict()  # written only when on: old files round-trip
    with pytest.raises(ScenarioError, match=r"s.json: start_noise: expected a number in "):
        Scenario.from_dict({**data, "start_noise": -1}, source="s.json")
    with pytest.raises(ScenarioError, match=r"shuffle_positions: expected true or false"):
        Scenario.from_dict({**data, "shuffle_positions": "yes"}, source="s.json")


def test_level_files_written_before_randomised_starts_load_with_them_off(level, tmp_path):
    """The file was saved by the code before `start_noise` / `shuffle_positions` existed."""
    old = LevelBuffer.load(FIXED_STARTS_FILE, level)
    assert len(old) == 3
    levels = old.get(old.ids)
    assert np.all(np.asarray(levels.start_noise) == 0.0)
    assert not np.asarray(levels.shuffle_positions).any()
    assert levels_equal(old.get_level(int(old.ids[0])), level)
    # Saved again, it is a current file and reads back equal.
    again = LevelBuffer.load(old.save(tmp_path / "again.msgpack"), level)
    assert levels_equal(again.get(again.ids), levels)
    # Only a template that names the defaults fills them: for any other, a missing leaf is
    # an error naming it.
    with pytest.raises(BufferFileError, match="template leaves missing from the file: "
                                              r"\['profile', 'shuffle_positions', 'start_noise'\]"):
        LevelBuffer.load(FIXED_STARTS_FILE, named_leaves(level))
