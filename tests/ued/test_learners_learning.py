"""Learning test: MAPPO (and, with -m slow, IPPO) with the paper's PPO settings learns to win a
small battle.

Two archers face +x; a farmer (driven by the random controller) stands above them, outside
their field of view, so an untrained policy rarely turns and shoots and mostly loses on
health at the time limit (ties go to the enemy). With a learning-rate schedule of 40 updates of
64 envs x 64 steps, the policy wins nearly every episode after 35 (the mean of the last 5 is
0.97 here, as after all 40: the last 5 add no margin to the check). Runs in about 30-45 s on
2 CPU cores.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest
from test_learners_helpers import learning_duel

from tabx.params import repeat_level
from ued.config import LearnerConfig
from ued.learners import make_learner


@pytest.mark.parametrize("algorithm", ["mappo", pytest.param("ippo", marks=pytest.mark.slow)])
def test_learns_two_archers_against_a_farmer(algorithm, optimizing_compiler):
    config, level = learning_duel()
    num_envs, num_steps, updates, schedule = 64, 64, 35, 40
    levels = jax.tree.map(jnp.asarray, repeat_level(level, num_envs))
    ppo = LearnerConfig(num_envs=num_envs, num_steps=num_steps, hidden_dim=64,
                    total_timesteps=num_envs * num_steps * schedule)
    learner = make_learner(algorithm, config, ppo, team="ally", opponent="random")
    state = learner.init(jax.random.key(0))
    key = jax.random.key(1)
    win_rates = []
    for _ in range(updates):
        key, k = jax.random.split(key)
        state, metrics, _ = learner.update(state, levels, k)
        win_rates.append(float(metrics["episode/win_rate"]))
    untrained = win_rates[0]  # the rollout of the first update: the initial policy
    trained = sum(win_rates[-5:]) / 5
    assert untrained < 0.4, win_rates
    assert trained > 0.85, win_rates
    assert trained - untrained > 0.5, win_rates
