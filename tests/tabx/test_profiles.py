"""Behaviour profiles (tabx.profiles): level data, one compiled step for any mix, selectable per
run, and level files written before profiles existed still load (as the default profile).

What each reference choice changes is tested row by row in tests/tabx/test_differences.py.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from envtools import CONFIG, KEY, level, unit

from tabx import constants as C
from tabx.compile_counter import CompileCounter
from tabx.controllers import Controller, controlled_actions
from tabx.env import TabxEnv
from tabx.params import heuristic_params, index_level, stack_levels
from tabx.profiles import ALL_CHOICES, PROFILES, check_profile, profile_name, with_profile

ENV = TabxEnv(CONFIG)
BOTH = (Controller("heuristic"), Controller("heuristic"))
STEPS = 24


def _battle():
    """A small melee with rangers and random-ish tiers, where the profiles play differently."""
    return level([unit("archer", -6, 0), unit("farmer", -3, 2), unit("assassin", -3, -2)],
                 [unit("farmer", 5, 0, math.pi), unit("healer", 8, 1, math.pi),
                  unit("theking", 6, -3, math.pi)],
                 heuristic=heuristic_params("novice", "medium"))


@jax.jit
def _play(levels, key):
    """STEPS steps of every level of the batch (heuristic on both teams): actions per step."""

    def one(lv, k):
        state = ENV.initial_state(lv)

        def body(state, k):
            actions, state = controlled_actions(k, state, lv, None, BOTH)
            _, state, _, _, _ = ENV.step(k, state, actions, lv)
            return state, actions

        return jax.lax.scan(body, state, jax.random.split(k, STEPS))[1]

    return jax.vmap(one, (0, None))(levels, key)


def test_profiles_mix_in_one_batch_without_recompiling():
    base = _battle()
    ours, reference = with_profile(base, "tabx-ued"), with_profile(base, "reference")
    _play(stack_levels([ours, ours]), KEY).block_until_ready()  # compile on one profile
    with CompileCounter() as cc:
        mixed = np.asarray(_play(stack_levels([ours, reference]), KEY))
        pure = np.asarray(_play(stack_levels([reference, reference]), KEY))
    assert cc.compiles == 0 and cc.traces == 0, cc.traced
    # Each env of the mixed batch plays exactly its own profile ...
    np.testing.assert_array_equal(mixed[1], pure[0])
    # ... and the two profiles do play differently here (random tiers attack only in ours).
    assert not np.array_equal(mixed[0], mixed[1])


def test_with_profile_and_profile_name():
    base = _battle()
    assert profile_name(base) == "tabx-ued"
    ref = with_profile(base, "reference")
    assert int(ref.profile) == ALL_CHOICES and int(ref.reward_mode) == C.REWARD_RATIO_OF_SUMS
    assert profile_name(ref) == "reference"
    assert profile_name(with_profile(ref, "tabx-ued")) == "tabx-ued"
    assert profile_name(ref.replace(profile=jnp.asarray(3, jnp.int32))).startswith("custom")
    batch = with_profile(stack_levels([base, base, base]), "reference")
    assert batch.profile.shape == (3,) and profile_name(index_level(batch, 2)) == "reference"
    assert set(PROFILES) == {"tabx-ued", "reference"}
    with pytest.raises(ValueError, match="unknown profile 'paper'; expected one of"):
        check_profile("paper")


def test_a_buffer_file_written_before_profiles_loads_as_the_default_profile(tmp_path):
    from level_buffer import LevelBuffer
    from level_buffer.tree import named_leaves

    template = _battle()
    # The level as a file written before the `profile` leaf existed stored it.
    old = {k: np.asarray(v) for k, v in named_leaves(template).items() if k != "profile"}
    buf = LevelBuffer(old)
    buf.insert(old, 1.0)
    path = buf.save(tmp_path / "old.msgpack")
    # EnvParams.FILE_DEFAULTS fills the leaf, whatever the template's value.
    loaded = LevelBuffer.load(path, with_profile(template, "reference"))
    level_back = loaded.get_level(int(loaded.ids[0]))
    assert int(np.asarray(level_back.profile)) == 0  # the default, not the template's
    np.testing.assert_array_equal(np.asarray(level_back.units.health),
                                  np.asarray(template.units.health))


def test_config_profile_is_validated_and_applied():
    from ued.config import ConfigError, TrainConfig, load_config
    from ued.experiment import scenario_levels

    config = load_config("configs/marl/mappo_crossfire.yaml", ["env.profile=reference"])
    assert isinstance(config, TrainConfig) and config.env.profile == "reference"
    _, levels = scenario_levels(config)
    assert all(profile_name(lv) == "reference" for lv in levels)
    with pytest.raises(ConfigError, match="env.profile: must be one of tabx-ued, reference"):
        load_config("configs/marl/mappo_crossfire.yaml", ["env.profile=paper"])


def test_rollout_takes_a_profile(capsys):
    from tabx_ued.cli import main

    assert main(["rollout", "cross", "--steps", "4", "--profile", "reference"]) == 0
    assert "profile reference" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["rollout", "cross", "--profile", "paper"])
    assert "invalid choice: 'paper'" in capsys.readouterr().err


def test_eval_takes_a_profile(capsys):
    from tabx_ued.cli import main

    argv = ["eval", "--ally", "heuristic:expert", "--enemy", "heuristic:random", "--scenario",
            "crossfire", "--episodes", "2", "--max-steps", "8"]
    assert main([*argv, "--profile", "reference"]) == 0
    assert "profile reference" in capsys.readouterr().out


@pytest.mark.slow
def test_expert_against_random_kings_on_crossfire_depends_on_the_profile():
    """In the reference the random tier never attacks: expert allies win by the time limit
    almost always.
    In ours random kings attack, and the expert team is wiped out."""
    from tabx.scenarios import config_for, load_named
    from tabx.tournament import tier_table

    scenario = load_named("crossfire")
    config = config_for([scenario])
    tables = {p: tier_table(config, scenario.to_level(config), episodes=8, seed=0,
                            ally_tiers=("expert",), enemy_tiers=("random",), profile=p)
              for p in ("tabx-ued", "reference")}
    reference = tables["reference"]
    assert reference.win_rate[0, 0] >= 0.75 and reference.timeout[0, 0] == 1.0
    assert tables["tabx-ued"].eliminated[0, 0, 0] >= 0.75
