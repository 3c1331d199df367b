"""Learners with recurrent networks: the PPO learners MAPPO (`ued.learners.mappo`), IPPO
(`ued.learners.ippo`) and MAPPO+RND (`ued.learners.rnd`), built on `ued.learners.ppo`
(rollout, GAE, loss, the jitted update) and `ued.learners.networks` (the GRU trunk); the
Q-learners IQL, VDN and QMIX (`ued.learners.qlearning`, mixers in `ued.learners.mixers`),
which share PPO's rollout and interface.

    learner = make_learner("mappo", env_config, LearnerConfig(), team="ally",
                           opponent="heuristic:medium")
    train_state = learner.init(jax.random.key(0))
    train_state, metrics, rollout_stats = learner.update(train_state, levels, key)
"""

from __future__ import annotations

from tabx.controllers import Controller
from tabx.params import EnvConfig
from ued.config import LearnerConfig, QLearningConfig
from ued.learners.ippo import IPPO
from ued.learners.mappo import MAPPO
from ued.learners.ppo import PPOLearner, RolloutStats, TrainState, cached_learner
from ued.learners.qlearning import IQL, QMIX, VDN, QLearner
from ued.learners.rnd import MAPPORND
from ued.registry import learner_entry


def make_learner(algorithm: str, env_config: EnvConfig, ppo: LearnerConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium",
                 cached: bool = True, q: QLearningConfig | None = None) -> PPOLearner:
    """The learner registered as `algorithm` (`ued.registry`: mappo, ippo, mappo_rnd, iql,
    vdn, qmix); `q`: the Q-learners' own settings (default: the paper's). With `cached`
    (default) the same arguments give the same learner object in a process, so its compiled
    update is reused."""
    entry = learner_entry(algorithm)
    ppo = ppo if ppo is not None else LearnerConfig()
    if entry.settings is None and q is not None:
        raise ValueError(f"{algorithm} is not a Q-learner: it takes no Q-learning settings")
    settings = () if entry.settings is None else (q if q is not None else QLearningConfig(),)
    cls = entry.load()
    if cached:
        return cached_learner(cls, env_config, ppo, team, opponent, *settings)
    return cls(env_config, ppo, team, opponent, *settings)


__all__ = ["IPPO", "IQL", "MAPPO", "MAPPORND", "PPOLearner", "QLearner", "QMIX",
           "RolloutStats", "TrainState", "VDN", "make_learner"]
