"""NoveltyPVL: Robust PLR whose levels are ranked by positive value loss (PVL) plus a bonus for
novelty: a new level enters the buffer with its PVL plus `novelty.bonus_weight` times its
distance to the nearest level the buffer holds, in the units' stats (max health, speed,
damage, each over its range in the buffer). A replay rescores a level by PVL alone, so the
bonus lasts until then. It shows the scoring hooks, `score_name` (the regret estimate) and
`insert_scores` (run by the level service, on every driver, before the buffer takes new
levels), and a settings section of its own (`novelty:`). From this folder:

    tabx train quickstart ued.method=novelty_pvl:NoveltyPVL 'levels.free=[unit_spec]' \
        novelty.bonus_weight=1.0
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ued.curricula.robust_plr import RobustPLR
from ued.errors import check

STATS = ("units.max_health", "units.speed", "units.damage")


def unit_stats(levels: dict[str, np.ndarray] | Any) -> np.ndarray:
    """(levels, features): every unit slot's stats, one row per level."""
    get = levels.__getitem__ if isinstance(levels, dict) else (
        lambda path: getattr(levels.units, path.split(".")[1]))
    return np.concatenate([np.asarray(get(p), np.float64).reshape(-1, np.asarray(
        get(p)).shape[-1]) for p in STATS], axis=1)


@dataclass(frozen=True)
class Novelty:
    """The `novelty:` section of a config."""

    bonus_weight: float = 0.5  # weight of the novelty (a distance of 1: a range in one stat)


class NoveltyPVL(RobustPLR):
    """Robust PLR ranked by PVL plus a novelty bonus at insertion."""

    name = "novelty_pvl"
    settings_section = "novelty"  # the config's top-level key of its settings
    settings_type = Novelty

    def __init__(self, exploratory_grad_updates: bool | None = None,
                 settings: Novelty | None = None):
        super().__init__(exploratory_grad_updates)
        self.settings = settings if settings is not None else Novelty()

    @classmethod
    def from_config(cls, ued: Any, settings: Novelty | None = None) -> NoveltyPVL:
        return cls(ued.exploratory_grad_updates, settings)

    @classmethod
    def validate_settings(cls, settings: Novelty, ued: Any) -> None:
        check(settings.bonus_weight >= 0, "novelty.bonus_weight",
              f"must be >= 0, got {settings.bonus_weight}")

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
        return scores + self.settings.bonus_weight * np.where(np.isfinite(scores), novelty, 0.0)
