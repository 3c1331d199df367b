"""Tier tournaments: stronger heuristic tiers beat weaker ones on a mirror scenario."""

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
    assert np.all(table.win_rate - table.ci95() > 0.75), table.format()
    assert np.all(table.length < config.max_steps)  # they win by elimination, early


def test_random_allies_lose_to_expert_and_table_formats(grid):
    config, level = grid
    table = tier_table(config, level, episodes=256, seed=2, ally_tiers=("random",),
                       enemy_tiers=("expert",))
    assert table.win_rate[0, 0] < 0.1
    text = table.format()
    assert "expert" in text.splitlines()[0] and text.splitlines()[1].startswith("random")


def test_unknown_tier_is_refused(grid):
    config, level = grid
    with pytest.raises(ValueError, match="unknown heuristic tier 'master'"):
        tier_table(config, level, episodes=1, ally_tiers=("master",))


def test_eval_heuristics_cli_prints_the_table_and_writes_json(capsys, tmp_path):
    import json

    from tabx_ued.cli import main

    out_json = tmp_path / "t.json"
    code = main(["eval", "heuristics", "grid", "--episodes", "256", "--tiers", "random,expert",
                 "--json", str(out_json)])
    out = capsys.readouterr().out
    assert code == 0
    assert "ally \\ enemy" in out and out.count("±") == 1 + 4  # the header, 2 x 2 cells
    data = json.loads(out_json.read_text())
    assert data["ally_tiers"] == ["random", "expert"] and data["episodes"] == 256
    assert data["win_rate"][1][0] > 0.9  # expert allies v random enemies


@pytest.mark.parametrize("argv, message", [
    (["eval", "heuristics", "nosuch"], "unknown scenario 'nosuch'"),
    (["eval", "heuristics", "grid", "--tiers", "random,godlike"], "unknown tier(s) godlike"),
    (["eval", "heuristics", "grid", "--episodes", "0"], "--episodes must be >= 1"),
])
def test_eval_heuristics_cli_errors(capsys, argv, message):
    from tabx_ued.cli import main

    assert main(argv) == 2
    assert message in capsys.readouterr().err
