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
