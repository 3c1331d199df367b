"""Recurrent PPO for TABX teams, in three parts (as Brax splits its PPO):

- `ued.learners.ppo.losses`: GAE, the clipped policy loss, the value loss and the masked
  statistics they use, as pure functions of arrays (tests/ued/test_ppo_losses.py);
- `ued.learners.ppo.devices`: the data-parallel placement of an update's envs over devices;
- `ued.learners.ppo.train`: `PPOLearner`, the rollout and the jitted update, on which MAPPO
  (ued.learners.mappo), IPPO (ued.learners.ippo), MAPPO+RND (ued.learners.rnd) and the
  Q-learners (ued.learners.qlearning) are built; the networks are ued.learners.networks.

Everything is importable from here (`from ued.learners.ppo import PPOLearner, gae`).
"""

from __future__ import annotations

from ued.learners.ppo.devices import local_devices, psum_flat
from ued.learners.ppo.losses import (
    MASKED_LOGIT,
    gae,
    masked_logits,
    masked_mean,
    moments,
    normalise,
    policy_terms,
    ppo_policy_loss,
    team_mean,
    valid_count,
    value_loss,
)
from ued.learners.ppo.train import (
    START_KEY_STREAM,
    PPOLearner,
    RolloutStats,
    TrainState,
    Transition,
    cached_learner,
    episode_metrics,
)

__all__ = ["MASKED_LOGIT", "START_KEY_STREAM", "PPOLearner", "RolloutStats", "TrainState",
           "Transition", "cached_learner", "episode_metrics", "gae", "local_devices",
           "masked_logits", "masked_mean", "moments", "normalise", "policy_terms",
           "ppo_policy_loss", "psum_flat", "team_mean", "valid_count", "value_loss"]
