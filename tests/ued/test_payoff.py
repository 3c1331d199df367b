"""Policy-vs-policy payoff tables (`ued.payoff`, `tabx eval payoff`) and the team swap of
`ued.evaluate.play`: a policy trained as the allies plays the enemy team.

The runs are a tiny MAPPO policy on a mirrored 2 archers v 2 archers duel, saved untrained
(update 0): playing needs no training, and the untrained policy fights often enough (the archers
start in range, facing each other) for its win rates to sit well inside (0, 1).
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import jax
import numpy as np
import pytest
from test_learners_helpers import tiny_config
from test_train_cli import run_cli

from tabx.params import EnvConfig, make_level
from ued.checkpoint import Checkpoints
from ued.config import ConfigError
from ued.evaluate import play
from ued.experiment import learner_for
from ued.payoff import payoff_table
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE, load_policy

MIRROR = EnvConfig(max_allies=2, max_enemies=2, max_zones=0, max_steps=24)
# One episode count and one scripted side (random) for every table and game here: the compiled
# episodes depend on the learners, the controllers' kinds and the episode count, so the tests
# share their few compilations.
EPISODES = 256


def mirror_level():
    return make_level(
        MIRROR,
        [dict(unit="archer", position=(-7.0, -4.0), heading=0.0),
         dict(unit="archer", position=(-7.0, 4.0), heading=0.0)],
        [dict(unit="archer", position=(7.0, -4.0), heading=math.pi),
         dict(unit="archer", position=(7.0, 4.0), heading=math.pi)])


@pytest.fixture(scope="module")
def mirror_file() -> str:
    from tabx.scenarios import level_to_scenario, save_scenario

    path = Path(tempfile.mkdtemp(prefix="tabx-payoff-tests-")) / "mirror2a2a.json"
    save_scenario(path, level_to_scenario(mirror_level(), name="mirror2a2a"))
    return str(path)


def saved_run(folder: Path, scenario: str, team: str = "ally", seed: int = 1) -> Path:
    """A run folder holding an untrained policy (checkpoint 0)."""
    config = tiny_config(**{"env.scenario": scenario, "env.max_steps": MIRROR.max_steps,
                            "env.team": team})
    folder.mkdir(parents=True)
    (folder / CONFIG_FILE).write_text(config.to_yaml())
    with Checkpoints(folder / CHECKPOINT_DIR) as ck:
        ck.save(0, learner_for(config).init(jax.random.key(seed)), jax.random.key(0))
    return folder


@pytest.fixture(scope="module")
def ally_run(tmp_path_factory, mirror_file) -> Path:
    return saved_run(tmp_path_factory.mktemp("runs") / "ally", mirror_file)


def test_a_policy_plays_the_other_team_as_a_policy_trained_there(tmp_path, ally_run,
                                                                 mirror_file):
    """The team swap: the ally-trained policy on the enemy slots plays exactly as a run trained
    on the enemy team with the same parameters."""
    enemy_run = saved_run(tmp_path / "enemy", mirror_file, team="enemy")
    ally, enemy = load_policy(ally_run), load_policy(enemy_run)
    enemy = type(enemy)(enemy.run_dir, enemy.config, enemy.learner, ally.params, enemy.update)
    level = mirror_level()
    swapped = play(MIRROR, level, ally, ally, EPISODES, seed=5)
    native = play(MIRROR, level, ally, enemy, EPISODES, seed=5)
    np.testing.assert_array_equal(swapped.won, native.won)
    np.testing.assert_array_equal(swapped.returns, native.returns)
    assert 0 < swapped.won[:, 1].mean() < 1  # both teams win some episodes


def test_two_copies_of_one_policy_give_a_symmetric_table(capsys, tmp_path, ally_run,
                                                         mirror_file):
    out = tmp_path / "tables" / "mirror"
    code, text, err = run_cli(capsys, "eval", "payoff", str(ally_run), str(ally_run),
                              "--tiers", "random", "--scenario", mirror_file,
                              "--episodes", str(EPISODES), "--out", str(out))
    assert code == 0, err
    assert "ally \\ enemy" in text and "ally#2" in text
    data = json.loads(out.with_name("mirror.json").read_text())
    assert data["allies"] == data["enemies"] == ["ally", "ally#2", "random"]
    assert data["episodes"] == EPISODES
    cells = data["scenarios"]["mirror2a2a"]
    rate = np.array(cells["win_rate"])
    assert rate.shape == (3, 3) and data["mean"]["win_rate"] == rate.tolist()
    assert np.all((np.array(cells["low"]) <= rate) & (rate <= np.array(cells["high"])))
    assert out.with_name("mirror.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    policy = rate[:2, :2]
    # The untrained policy does fight: a win rate away from 0 and 1 makes the check mean
    # something.
    p = policy.mean()
    assert 0.1 < p < 0.9, policy
    # Every policy-vs-policy cell estimates the same rate (one policy on both sides, on a
    # mirrored scenario): the table is symmetric, each cell within 4 standard errors.
    tolerance = 4 * math.sqrt(2 * p * (1 - p) / EPISODES)
    assert np.abs(policy - policy.T).max() < tolerance
    assert np.abs(policy - p).max() < tolerance
    # Each cell is its own sample (seeds differ), not one game copied.
    assert len({float(v) for v in rate.ravel()}) > 1


def test_payoff_bad_inputs_are_one_line_errors(capsys, tmp_path, ally_run, mirror_file):
    def error(*argv: str) -> str:
        code, _, err = run_cli(capsys, "eval", "payoff", *argv)
        assert code == 2, err
        assert len(err.strip().splitlines()) == 1
        return err

    assert "give one of --scenario" in error(str(ally_run))
    assert "give one of --scenario" in error(str(ally_run), "--scenario", mirror_file,
                                             "--suite", "units-2F1M2Avs2S1K")
    assert "not a run folder" in error(str(tmp_path / "nothing"), "--scenario", mirror_file)
    assert "unknown heuristic tier" in error("--tiers", "heuristic:godlike", "--scenario",
                                             mirror_file)
    assert "not a tier of the table" in error("--tiers", "external", "--scenario",
                                              mirror_file)
    assert "at least one side" in error("--scenario", mirror_file)
    assert "unknown scenario" in error("--tiers", "idle", "--scenario", "no-such-scenario")
    assert "episodes must be >= 1" in error("--tiers", "idle", "--scenario", mirror_file,
                                            "--episodes", "0")
    # Policies of another EnvConfig cannot share a table.
    lopsided = tmp_path / "lopsided"
    lopsided.mkdir()
    config = tiny_config()
    (lopsided / CONFIG_FILE).write_text(config.to_yaml())
    with Checkpoints(lopsided / CHECKPOINT_DIR) as ck:
        ck.save(0, learner_for(config).init(jax.random.key(0)), jax.random.key(0))
    with pytest.raises(ConfigError, match="trained with"):
        payoff_table([str(ally_run), str(lopsided)], [], [mirror_file], episodes=2)
    # On unequal teams (2 v 1), a policy trained on the allies plays only the allies: with no
    # tier and no enemy-trained run, nobody plays the enemies.
    assert "no side can play the enemy team" in error(str(lopsided), "--scenario",
                                                      config.env.scenario[0])


def test_on_unequal_teams_rows_and_columns_are_the_sides_that_fit(tmp_path, mirror_file):
    from tabx.controllers import Controller
    from ued.payoff import payoff_axes

    config = tiny_config()  # 2 archers v 1 farmer
    ally_policy = load_policy(saved_run(tmp_path / "a", config.env.scenario[0]))
    enemy_policy = load_policy(saved_run(tmp_path / "e", config.env.scenario[0], team="enemy"))
    env_config = ally_policy.learner.env_config
    sides = [ally_policy, enemy_policy, Controller("heuristic", "medium")]
    assert payoff_axes(sides, env_config) == ([0, 2], [1, 2])
    # On equal teams every policy plays both.
    mirror = load_policy(saved_run(tmp_path / "m", mirror_file))
    assert payoff_axes([mirror, Controller("idle")], MIRROR) == ([0, 1], [0, 1])
