"""PPO learners with recurrent policies: MAPPO (`ued.learners.mappo`), IPPO
(`ued.learners.ippo`) and MAPPO+RND (`ued.learners.rnd`), built on `ued.learners.ppo`
(rollout, GAE, loss, the jitted update) and `ued.learners.networks` (the GRU trunk).

    learner = make_learner("mappo", env_config, PPOConfig(), team="ally",
                           opponent="heuristic:medium")
    train_state = learner.init(jax.random.key(0))
    train_state, metrics, rollout_stats = learner.update(train_state, levels, key)
"""

from __future__ import annotations

from tabx.controllers import Controller
from tabx.params import EnvConfig
from ued.config import PPOConfig
from ued.learners.ippo import IPPO
from ued.learners.mappo import MAPPO
from ued.learners.ppo import PPOLearner, RolloutStats, TrainState, cached_learner
from ued.learners.rnd import MAPPORND

LEARNERS: dict[str, type[PPOLearner]] = {"mappo": MAPPO, "ippo": IPPO, "mappo_rnd": MAPPORND}


def make_learner(algorithm: str, env_config: EnvConfig, ppo: PPOConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium",
                 cached: bool = True) -> PPOLearner:
    """A MAPPO, IPPO or MAPPO+RND learner. With `cached` (default) the same arguments give the same
    learner object in a process, so its compiled update is reused."""
    if algorithm not in LEARNERS:
        raise ValueError(f"unknown algorithm {algorithm!r}; expected one of "
                         f"{', '.join(LEARNERS)}")
    ppo = ppo if ppo is not None else PPOConfig()
    if cached:
        return cached_learner(LEARNERS[algorithm], env_config, ppo, team, opponent)
    return LEARNERS[algorithm](env_config, ppo, team, opponent)


__all__ = ["IPPO", "LEARNERS", "MAPPO", "MAPPORND", "PPOLearner", "RolloutStats", "TrainState",
           "make_learner"]
