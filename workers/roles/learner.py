"""LearnerWorker: the learner's update (`ued.learners`) on whatever batch of levels it is given.

The worker that owns the learner's train state (the learner itself, a `PPOLearner`, is a
static description of the update and holds no state). It counts its gradient updates on the host
(`version`, the policy version stamped on every score), so asking for it never waits for the
device. In local mode the driver calls it directly; a Ray actor wraps the same class.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from tabx.params import EnvParams
from ued.learners.ppo import PPOLearner, RolloutStats, TrainState
from workers.roles.explorer import scores_of


class LearnerWorker:
    """Holds the train state; `train(levels, key)` is one jitted rollout + PPO update."""

    def __init__(self, learner: PPOLearner, train_state: TrainState, version: int = 0):
        self.learner = learner
        self.train_state = train_state
        self.version = int(version)

    @property
    def params(self) -> Any:
        return self.train_state.params

    def train(self, levels: EnvParams, key: jax.Array
              ) -> tuple[dict[str, jax.Array], RolloutStats]:
        """Roll out on `levels` (one env per level) and update the policy; returns the update's
        metrics and the rollout statistics for scoring (both still on the device)."""
        self.train_state, metrics, stats = self.learner.update(self.train_state, levels, key)
        self.version += 1
        return metrics, stats

    def train_scored(self, levels: EnvParams, key: jax.Array, score: str,
                     max_returns: Any = None
                     ) -> tuple[dict[str, jax.Array], np.ndarray, np.ndarray]:
        """`train`, then the levels' scores and best returns under the policy that played them
        (`scores_of`; `max_returns` are the stored R_max of replayed levels)."""
        metrics, stats = self.train(levels, key)
        scores, best = scores_of(stats, score, max_returns)
        return metrics, scores, best


__all__ = ["LearnerWorker"]
