"""Learners with recurrent networks: the PPO learners MAPPO (`ued.learners.mappo`), IPPO
(`ued.learners.ippo`) and MAPPO+RND (`ued.learners.rnd`), built on `ued.learners.ppo`
(rollout, GAE, loss, the jitted update) and `ued.learners.networks` (the GRU trunk); the
Q-learners IQL, VDN and QMIX (`ued.learners.qlearning`, mixers in `ued.learners.mixers`),
which share PPO's rollout and interface.

    learner = make_learner("mappo", env_config, PPOConfig(), team="ally",
                           opponent="heuristic:medium")
    train_state = learner.init(jax.random.key(0))
    train_state, metrics, rollout_stats = learner.update(train_state, levels, key)
"""

from __future__ import annotations

from tabx.controllers import Controller
from tabx.params import EnvConfig
from ued.config import PPOConfig, QLearningConfig
from ued.learners.ippo import IPPO
from ued.learners.mappo import MAPPO
from ued.learners.ppo import PPOLearner, RolloutStats, TrainState, cached_learner
from ued.learners.qlearning import IQL, Q_LEARNERS, QMIX, VDN, QLearner, cached_q_learner
from ued.learners.rnd import MAPPORND

LEARNERS: dict[str, type[PPOLearner]] = {"mappo": MAPPO, "ippo": IPPO, "mappo_rnd": MAPPORND,
                                         **Q_LEARNERS}


def make_learner(algorithm: str, env_config: EnvConfig, ppo: PPOConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium",
                 cached: bool = True, q: QLearningConfig | None = None) -> PPOLearner:
    """A learner of `algorithm` (mappo, ippo, mappo_rnd, iql, vdn, qmix); `q`: the Q-learners'
    own settings (default: the paper's). With `cached` (default) the same arguments give the same
    learner object in a process, so its compiled update is reused."""
    if algorithm not in LEARNERS:
        raise ValueError(f"unknown algorithm {algorithm!r}; expected one of "
                         f"{', '.join(LEARNERS)}")
    ppo = ppo if ppo is not None else PPOConfig()
    if algorithm in Q_LEARNERS:
        q = q if q is not None else QLearningConfig()
        if cached:
            return cached_q_learner(LEARNERS[algorithm], env_config, ppo, team, opponent, q)
        return LEARNERS[algorithm](env_config, ppo, team, opponent, q)
    if q is not None:
        raise ValueError(f"{algorithm} is not a Q-learner: it takes no Q-learning settings")
    if cached:
        return cached_learner(LEARNERS[algorithm], env_config, ppo, team, opponent)
    return LEARNERS[algorithm](env_config, ppo, team, opponent)


__all__ = ["IPPO", "IQL", "LEARNERS", "MAPPO", "MAPPORND", "PPOLearner", "QLearner", "QMIX",
           "RolloutStats", "TrainState", "VDN", "make_learner"]
