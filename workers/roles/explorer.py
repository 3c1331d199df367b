"""Explorer: plays the current policy on new or mutated levels and scores them, no learning.

Robust PLR and ACCEL never train on the levels they discover; SFL scores large batches of
random levels by learnability. Scoring is embarrassingly parallel, which is why it is its own
worker: the Ray version runs many Explorers beside one Learner.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import numpy as np

from tabx.params import EnvParams
from ued.learners.ppo import PPOLearner, RolloutStats
from ued.scores import learnability, level_scores


@partial(jax.jit, static_argnums=1)
def _scores(stats: RolloutStats, score: str, stored_max_returns: jax.Array | None):
    return level_scores(stats, score, stored_max_returns)


def scores_of(stats: RolloutStats, score: str, stored_max_returns: Any = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(scores, max returns) per env as numpy arrays; see `ued.scores.level_scores`."""
    if stored_max_returns is not None:
        stored_max_returns = np.asarray(stored_max_returns, np.float32)
    values, best = _scores(stats, score, stored_max_returns)
    return np.asarray(values, np.float64), np.asarray(best, np.float64)


class Explorer:
    """Scores levels with given policy parameters, without updating them."""

    def __init__(self, learner: PPOLearner, score: str = "max_mc"):
        self.learner = learner
        self.score = score

    def rollout(self, params: Any, levels: EnvParams, key: jax.Array,
                num_steps: int | None = None) -> tuple[dict[str, jax.Array], RolloutStats]:
        """Episode metrics and rollout statistics of the policy on `levels`."""
        return self.learner.score(params, levels, key, num_steps)

    def score_levels(self, params: Any, levels: EnvParams, key: jax.Array,
                     score: str | None = None, max_returns: Any = None,
                     num_steps: int | None = None
                     ) -> tuple[dict[str, jax.Array], np.ndarray, np.ndarray]:
        """(episode metrics, scores, max returns) of `levels` under `params`."""
        metrics, stats = self.rollout(params, levels, key, num_steps)
        values, best = scores_of(stats, score or self.score, max_returns)
        return metrics, values, best

    def learnability(self, params: Any, levels: EnvParams, key: jax.Array,
                     num_steps: int | None = None) -> np.ndarray:
        """SFL's p (1 - p) per level, p the share of finished episodes the team won."""
        _, stats = self.rollout(params, levels, key, num_steps)
        return np.asarray(learnability(stats.wins, stats.dones), np.float64)

    def learnability_batches(self, params: Any, batches: list[tuple[EnvParams, jax.Array]],
                             num_steps: int | None = None) -> list[np.ndarray]:
        """`learnability` of each (levels, key) batch, in order (one after another here; the
        Ray driver's pool spreads them over its Explorers)."""
        return [self.learnability(params, levels, key, num_steps) for levels, key in batches]


__all__ = ["Explorer", "scores_of"]
