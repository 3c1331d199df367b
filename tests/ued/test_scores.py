"""ued.scores against hand-computed examples and a plain-loop reference; jit-safe."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ued.scores import (
    episode_stats,
    learnability,
    max_episode_return,
    max_mc,
    positive_value_loss,
)

NEG_INF = -np.inf


def cols(*columns):
    """(T, num_envs) from per-env columns."""
    return jnp.asarray(np.stack(columns, axis=1), jnp.float32)


DONES = cols([0, 1, 0, 0, 1], [0, 0, 0, 0, 0], [1, 0, 0, 0, 0]).astype(bool)


def test_positive_value_loss_hand_computed():
    adv = cols([1, -1, 2, 4, -3], [5, 5, 5, 5, 5], [2, 9, 9, 9, 9])
    # env 0: episodes [1, 0] -> 0.5 and [2, 4, 0] -> 2, mean 1.25
    # env 1: no episode ends -> -inf; env 2: [2] -> 2, the unfinished tail is ignored
    np.testing.assert_allclose(positive_value_loss(adv, DONES), [1.25, NEG_INF, 2.0])


def test_max_mc_hand_computed():
    values = cols([0.5, 1.0, 0.0, 0.25, 1.0], [0, 0, 0, 0, 0], [3, 0, 0, 0, 0])
    r_max = jnp.asarray([1.0, 1.0, 2.0])
    # env 0: gaps [0.5, 0] -> 0.25 and [1, 0.75, 0] -> 7/12; mean 5/12
    # env 2: gap [2 - 3] = -1 (a value above the best return)
    np.testing.assert_allclose(max_mc(values, DONES, r_max), [5 / 12, NEG_INF, -1.0],
                               rtol=1e-6)


def test_max_episode_return_hand_computed():
    rewards = cols([0, 1, 0, 0, 3], [1, 1, 1, 1, 1], [-2, 9, 9, 9, 9])
    np.testing.assert_allclose(max_episode_return(rewards, DONES), [3.0, NEG_INF, -2.0])


def test_learnability_hand_computed():
    dones = cols([0, 1, 0, 0, 1], [0, 0, 0, 0, 0], [1, 1, 1, 1, 0], [1, 0, 1, 0, 1])
    wins = cols([0, 1, 0, 0, 0], [1, 1, 1, 1, 1], [1, 1, 1, 0, 1], [1, 1, 1, 1, 1])
    # env 0: 1 of 2 won -> 0.25; env 1: none -> -inf; env 2: 3 of 4 (the last win is not at
    # a done) -> 3/16; env 3: all won -> 0; wins between dones are ignored
    np.testing.assert_allclose(learnability(wins, dones), [0.25, NEG_INF, 3 / 16, 0.0])


def test_episode_stats_counts_and_sum_mode():
    x = cols([1, 2, 3, 4, 5], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1])
    mean, best, count = episode_stats(x, DONES, time_average=False)
    np.testing.assert_allclose(mean, [(3 + 12) / 2, NEG_INF, 1.0])
    np.testing.assert_allclose(best, [12, NEG_INF, 1.0])
    np.testing.assert_array_equal(count, [2, 0, 1])


def reference(values: np.ndarray, dones: np.ndarray) -> np.ndarray:
    """Mean over completed episodes of the per-episode time-mean, with Python loops."""
    out = []
    for e in range(values.shape[1]):
        episodes, current = [], []
        for t in range(values.shape[0]):
            current.append(values[t, e])
            if dones[t, e]:
                episodes.append(np.mean(current))
                current = []
        out.append(np.mean(episodes) if episodes else -np.inf)
    return np.array(out)


def test_random_rollouts_match_loop_reference_under_jit():
    rng = np.random.default_rng(0)
    adv = rng.normal(size=(64, 16)).astype(np.float32)
    dones = rng.random((64, 16)) < 0.1
    dones[:, 0] = False  # one env with no finished episode
    got = jax.jit(positive_value_loss)(adv, dones)
    np.testing.assert_allclose(got, reference(np.maximum(adv, 0), dones), rtol=1e-5)
    values = rng.normal(size=(64, 16)).astype(np.float32)
    r_max = rng.normal(size=16).astype(np.float32)
    got = jax.jit(max_mc)(values, dones, r_max)
    np.testing.assert_allclose(got, reference(r_max[None] - values, dones), rtol=1e-5,
                               atol=1e-6)
    assert got.dtype == jnp.float32 and got.shape == (16,)


def test_vmap_over_a_leading_axis():
    adv = jnp.ones((3, 5, 2))
    dones = jnp.zeros((3, 5, 2), bool).at[:, -1, :].set(True)
    out = jax.vmap(positive_value_loss)(adv, dones)
    assert out.shape == (3, 2)
    np.testing.assert_allclose(out, 1.0)


@pytest.mark.parametrize("fn", [positive_value_loss, learnability])
def test_no_finished_episode_is_neg_inf(fn):
    out = fn(jnp.ones((4, 3)), jnp.zeros((4, 3), bool))
    assert np.isneginf(np.asarray(out)).all()
