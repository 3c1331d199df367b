"""NoveltyPVL: Robust PLR whose levels are ranked by positive value loss (PVL) plus a bonus for
novelty: a new level enters the buffer with its PVL plus `bonus` times its distance to the
nearest level the buffer holds, in the units' stats (max health, speed, damage, each over its
range in the buffer). A replay rescores a level by PVL alone, so the bonus lasts until then.
It shows the scoring hooks: `score_name` (the regret estimate) and `insert_scores` (run by the
level service, on every driver, before the buffer takes new levels). From this folder:

    tabx train quickstart ued.method=novelty_pvl:NoveltyPVL 'levels.free=[unit_spec]'
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ued.curricula.robust_plr import RobustPLR

STATS = ("units.max_health", "units.speed", "units.damage")


def unit_stats(levels: dict[str, np.ndarray] | Any) -> np.ndarray:
    """(levels, features): every unit slot's stats, one row per level."""
    get = levels.__getitem__ if isinstance(levels, dict) else (
        lambda path: getattr(levels.units, path.split(".")[1]))
    return np.concatenate([np.asarray(get(p), np.float64).reshape(-1, np.asarray(
        get(p)).shape[-1]) for p in STATS], axis=1)


class NoveltyPVL(RobustPLR):
    """Robust PLR ranked by PVL plus a novelty bonus at insertion."""

    name = "novelty_pvl"
    bonus = 0.5  # weight of the novelty (a distance of 1: a whole range away in one stat)

    def score_name(self, ued: Any) -> str:
        return "pvl"

    def insert_scores(self, levels: Any, scores: np.ndarray, buffer: Any) -> np.ndarray:
        if len(buffer) == 0:
            return scores
        new = unit_stats(levels)
        stored = unit_stats({p: buffer.leaf(p) for p in STATS})
        span = np.maximum(stored.max(0) - stored.min(0), 1e-6)
        gaps = np.abs(new[:, None, :] - stored[None, :, :]) / span
        novelty = np.sqrt((gaps ** 2).sum(-1)).min(1)
        return scores + self.bonus * np.where(np.isfinite(scores), novelty, 0.0)
