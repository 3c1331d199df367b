"""Tier tournaments: stronger heuristic tiers beat weaker ones on a mirror scenario; the
per-matchup outcomes (time-outs, health, first death, eliminations) agree with each other."""

from __future__ import annotations

import numpy as np
import pytest

from tabx.scenarios import config_for, load_named
from tabx.tournament import tier_table


@pytest.fixture(scope="module")
def grid():
    scenario = load_named("grid")  # 6 kings v 6 kings
    config = config_for([scenario])
    return config, scenario.to_level(config)


def test_expert_and_medium_beat_random_on_a_mirror_scenario(grid):
    config, level = grid
    table = tier_table(config, level, episodes=256, seed=1, ally_tiers=("medium", "expert"),
                       enemy_tiers=("random",))
    assert table.win_rate.shape == (2, 1)
    # "Clearly more than half": the 95% interval is far above one half.
    assert np.all(table.win_interval()[..., 0] > 0.75), table.format()
    assert np.all(table.length < config.max_steps)  # they win by elimination, early
    # Outcomes agree: no time-outs, so every episode ends with one team wiped out, and the
    # allies' wins are the enemies' eliminations; a wiped-out team has health 0.
    assert np.all(table.timeout == 0.0)
    np.testing.assert_allclose(table.eliminated[..., 1], table.win_rate)
    np.testing.assert_allclose(table.eliminated.sum(-1), 1.0)
    assert np.all(table.hp_ratio[..., 1] < 0.01) and np.all(table.hp_ratio[..., 0] > 0.2)
    # Someone died in every episode, before the end, and mostly the random side first.
    assert np.all(table.first_death >= 1) and np.all(table.first_death < table.length)
    assert np.all(table.first_dead[..., 1] > 0.8)


def test_random_allies_lose_to_expert_and_table_formats(grid):
    config, level = grid
    table = tier_table(config, level, episodes=256, seed=2, ally_tiers=("random",),
                       enemy_tiers=("expert",))
    assert table.win_rate[0, 0] < 0.1
    low, high = table.win_interval()[0, 0]
    assert 0.0 <= low <= table.win_rate[0, 0] <= high < 0.15
    text = table.format().splitlines()
    assert "expert" in text[0] and text[1].startswith("random")
    assert text[3].split()[:2] == ["ally", "enemy"]  # the per-matchup lines
    cells = text[4].split()
    assert cells[:2] == ["random", "expert"] and float(cells[2]) == table.win_rate[0, 0]


def test_random_tier_never_attacks_under_the_reference_profile(grid):
    """The reference draws epsilon actions among moves and turns only: random v random ends
    by the time limit with nobody hurt by an attack (ours: they fight)."""
    config, level = grid
    ours = tier_table(config, level, episodes=16, seed=3, ally_tiers=("random",),
                      enemy_tiers=("random",))
    reference = tier_table(config, level, episodes=16, seed=3, ally_tiers=("random",),
                           enemy_tiers=("random",), profile="reference")
    assert reference.profile == "reference" and np.all(reference.timeout == 1.0)
    assert np.isnan(reference.first_death[0, 0])  # nobody died
    # Ours attack at random: more health lost than to the walls alone.
    assert ours.hp_ratio[0, 0].mean() < reference.hp_ratio[0, 0].mean() - 0.05


def test_unknown_tier_is_refused(grid):
    config, level = grid
    with pytest.raises(ValueError, match="unknown heuristic tier 'master'"):
        tier_table(config, level, episodes=1, ally_tiers=("master",))


def test_eval_heuristics_cli_prints_the_table_and_writes_json(capsys, tmp_path):
    """2 x 2 tiers of 8 episodes: the batch of 16 envs that the random-tier test above compiled
    (the same scenario, so the same EnvConfig and batch runner), so the command only runs it."""
    import json

    from tabx_ued.cli import main

    out_json = tmp_path / "t.json"
    code = main(["eval", "heuristics", "grid", "--episodes", "8", "--tiers", "random,expert",
                 "--json", str(out_json), "--profile", "reference"])
    out = capsys.readouterr().out
    assert code == 0
    assert "ally \\ enemy" in out and out.count("[") == 1 + 4  # the header, 2 x 2 cells
    assert "profile reference" in out
    data = json.loads(out_json.read_text())
    assert data["ally_tiers"] == ["random", "expert"] and data["episodes"] == 8
    assert data["profile"] == "reference"
    assert data["win_rate"][1][0] > 0.9  # expert allies v random enemies
    for name in ("timeout", "length", "hp_ratio", "first_death", "first_dead", "eliminated",
                 "win_interval"):
        assert np.shape(data[name])[:2] == (2, 2), name


@pytest.mark.parametrize("argv, message", [
    (["eval", "heuristics", "nosuch"], "unknown scenario 'nosuch'"),
    (["eval", "heuristics", "grid", "--tiers", "random,godlike"], "unknown tier(s) godlike"),
    (["eval", "heuristics", "grid", "--episodes", "0"], "--episodes must be >= 1"),
])
def test_eval_heuristics_cli_errors(capsys, argv, message):
    from tabx_ued.cli import main

    assert main(argv) == 2
    assert message in capsys.readouterr().err
