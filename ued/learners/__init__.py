"""Learners with recurrent networks: the PPO learners MAPPO (`ued.learners.mappo`), IPPO
(`ued.learners.ippo`) and MAPPO+RND (`ued.learners.rnd`), built on `ued.learners.ppo` (the
loss terms and GAE, the rollout and the jitted update) and `ued.learners.networks` (the GRU
trunk); the Q-learners IQL, VDN and QMIX (`ued.learners.qlearning`, mixers in
`ued.learners.mixers`), which share PPO's rollout and interface.

Every learner is a subclass of `PPOLearner`, whose methods are what the drivers call
(`init`, `update`, `score`, `policy_step`, ...) and whose class attributes say what it reads
and supports. `make_learner` takes a built-in name or a class's import path (docs/new_learner.md).

    learner = make_learner("mappo", env_config, LearnerConfig(), team="ally",
                           opponent="heuristic:medium")
    train_state = learner.init(jax.random.key(0))
    train_state, metrics, rollout_stats = learner.update(train_state, levels, key)
"""

from __future__ import annotations

from typing import Any

from tabx.controllers import Controller
from tabx.params import EnvConfig
from ued.config import LearnerConfig
from ued.learners.ippo import IPPO
from ued.learners.mappo import MAPPO
from ued.learners.ppo import PPOLearner, RolloutStats, TrainState, cached_learner
from ued.learners.qlearning import IQL, QMIX, VDN, MixingQLearner, QLearner
from ued.learners.rnd import MAPPORND
from ued.registry import learner_class


def make_learner(algorithm: str, env_config: EnvConfig, ppo: LearnerConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium",
                 cached: bool = True, settings: Any = None) -> PPOLearner:
    """The learner of `algorithm`: a built-in name (`ued.registry.LEARNERS`: mappo, ippo,
    mappo_rnd, iql, vdn, qmix) or a learner class's path, module:Class. `settings`: the
    learner's own settings section, an instance of its class's `settings_type` (default: that
    type's defaults, the paper's for the Q-learners). With `cached` (default) the same
    arguments give the same learner object in a process, so its compiled update is reused."""
    cls = learner_class(algorithm)
    ppo = ppo if ppo is not None else LearnerConfig()
    if cls.settings_type is None and settings is not None:
        raise ValueError(f"{algorithm} has no settings section of its own: it takes no "
                         f"settings")
    own = () if cls.settings_type is None else (
        settings if settings is not None else cls.settings_type(),)
    if cached:
        return cached_learner(cls, env_config, ppo, team, opponent, *own)
    return cls(env_config, ppo, team, opponent, *own)


__all__ = ["IPPO", "IQL", "MAPPO", "MAPPORND", "MixingQLearner", "PPOLearner", "QLearner", "QMIX",
           "RolloutStats", "TrainState", "VDN", "make_learner"]
