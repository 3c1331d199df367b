"""The PPO loss terms and GAE (`ued.learners.ppo.losses`), pure functions tested on their own:
GAE against a hand computation and per-env loops, the clipped policy loss, the value loss and
the masked statistics against numpy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tabx import constants as C
from ued.learners.ppo.losses import (
    gae,
    masked_logits,
    masked_mean,
    moments,
    policy_terms,
    ppo_policy_loss,
    value_loss,
)

# --- GAE -------------------------------------------------------------------------------------


def test_gae_matches_a_hand_computation():
    gamma, lam = 0.9, 0.8
    rewards = np.array([1.0, 0.0, 2.0, -1.0], np.float32)[:, None]
    values = np.array([0.5, 0.2, 0.1, 0.3], np.float32)[:, None]
    dones = np.array([False, True, False, False])[:, None]
    last_value = np.array([0.7], np.float32)
    adv, targets = gae(jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(dones),
                       jnp.asarray(last_value), gamma, lam)
    # By hand, backwards: step 3 bootstraps from last_value; step 1 ends its episode.
    d3 = -1.0 + gamma * 0.7 - 0.3
    a3 = d3
    d2 = 2.0 + gamma * 0.3 - 0.1
    a2 = d2 + gamma * lam * a3
    d1 = 0.0 + 0.0 - 0.2  # done: no bootstrap from the next episode's first state
    a1 = d1
    d0 = 1.0 + gamma * 0.2 - 0.5
    a0 = d0 + gamma * lam * a1
    np.testing.assert_allclose(adv[:, 0], [a0, a1, a2, a3], rtol=1e-6)
    np.testing.assert_allclose(targets[:, 0], np.array([a0, a1, a2, a3]) + values[:, 0],
                               rtol=1e-6, atol=1e-6)


def test_gae_broadcasts_over_envs_and_agents():
    rng = np.random.default_rng(0)
    r = rng.normal(size=(5, 3, 2)).astype(np.float32)
    v = rng.normal(size=(5, 3, 2)).astype(np.float32)
    d = rng.random((5, 3, 1)) < 0.3
    last = rng.normal(size=(3, 2)).astype(np.float32)
    adv, _ = gae(r, v, jnp.asarray(d), last, 0.99, 0.95)
    for e in range(3):
        for a in range(2):
            one, _ = gae(r[:, e, a], v[:, e, a], jnp.asarray(d[:, e, 0]), last[e, a], 0.99, 0.95)
            np.testing.assert_allclose(adv[:, e, a], one, rtol=1e-5, atol=1e-6)


# --- masking and the loss terms --------------------------------------------------------------


def test_illegal_actions_have_zero_probability_and_are_never_sampled():
    logits = jnp.array([[5.0, 1.0, 0.0, 2.0, 9.0, 0.0, 0.0, 3.0]])
    mask = jnp.array([[True, False, True, True, False, False, False, True]])
    probs = jax.nn.softmax(masked_logits(logits, mask))
    assert float(probs[0, 1]) == 0.0 and float(probs[0, 4]) == 0.0
    samples = jax.random.categorical(jax.random.key(0), masked_logits(logits, mask),
                                     shape=(2000, 1))
    assert set(np.unique(np.asarray(samples))) <= {0, 2, 3, 7}
    logp, entropy = policy_terms(logits, mask, jnp.array([3]))
    assert np.isfinite(float(logp[0])) and float(entropy[0]) > 0
    # A unit with IDLE as its only action: log-probability 0, entropy 0.
    only_idle = jnp.zeros((1, 8), bool).at[0, C.IDLE].set(True)
    logp, entropy = policy_terms(logits, only_idle, jnp.array([C.IDLE]))
    assert float(logp[0]) == pytest.approx(0.0) and float(entropy[0]) == pytest.approx(0.0)


def test_loss_terms_ignore_invalid_entries():
    rng = np.random.default_rng(1)
    logp, old, adv = (jnp.asarray(rng.normal(size=6), jnp.float32) for _ in range(3))
    valid = jnp.array([True, True, False, True, False, True])
    loss, _, _ = ppo_policy_loss(logp, old, adv, valid, 0.2)
    changed = jnp.where(valid, logp, 100.0), jnp.where(valid, adv, -50.0)
    loss2, _, _ = ppo_policy_loss(changed[0], old, changed[1], valid, 0.2)
    assert float(loss) == pytest.approx(float(loss2))
    v, ov, tgt = (jnp.asarray(rng.normal(size=6), jnp.float32) for _ in range(3))
    vl = value_loss(v, ov, tgt, valid, 0.05)
    vl2 = value_loss(jnp.where(valid, v, 9.0), ov, tgt, valid, 0.05)
    assert float(vl) == pytest.approx(float(vl2))


def test_value_clipping_keeps_the_larger_loss():
    v, old, target = jnp.array([1.0]), jnp.array([0.0]), jnp.array([2.0])
    clipped = value_loss(v, old, target, jnp.array([True]), 0.1, clip=True)
    unclipped = value_loss(v, old, target, jnp.array([True]), 0.1, clip=False)
    assert float(unclipped) == pytest.approx(0.5)
    assert float(clipped) == pytest.approx(0.5 * 1.9**2)  # clipped V = 0.1


def _numpy_policy_loss(logp, old, adv, valid, clip_eps):
    """The clipped surrogate loss, approx KL and clip fraction over the valid entries, in
    float64 numpy."""
    logp, old, adv = (np.asarray(x, np.float64) for x in (logp, old, adv))
    ratio = np.exp(logp - old)
    surrogate = np.minimum(ratio * adv, np.clip(ratio, 1 - clip_eps, 1 + clip_eps) * adv)
    kl = (ratio - 1) - (logp - old)
    clipped = (np.abs(ratio - 1) > clip_eps).astype(np.float64)
    return (-surrogate[valid].mean(), kl[valid].mean(), clipped[valid].mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_clipped_policy_loss_equals_numpy(seed):
    rng = np.random.default_rng(seed)
    shape = (7, 3, 2)
    old = rng.normal(-1.5, 0.5, shape).astype(np.float32)
    logp = (old + rng.normal(0, 0.2, shape)).astype(np.float32)  # ratios both sides of the clip
    adv = rng.normal(size=shape).astype(np.float32)
    valid = rng.random(shape) < 0.7
    loss, kl, clip_frac = ppo_policy_loss(jnp.asarray(logp), jnp.asarray(old), jnp.asarray(adv),
                                          jnp.asarray(valid), 0.1)
    want = _numpy_policy_loss(logp, old, adv, valid, 0.1)
    assert 0 < want[2] < 1  # some ratios clipped, some not
    np.testing.assert_allclose([float(loss), float(kl), float(clip_frac)], want, rtol=1e-5,
                               atol=1e-6)


def test_a_count_over_all_shards_splits_the_policy_loss_into_summands():
    """With the count of all shards as the divisor, the shards' losses sum to the whole's."""
    rng = np.random.default_rng(3)
    logp, old, adv = (jnp.asarray(rng.normal(size=(4, 6)), jnp.float32) for _ in range(3))
    valid = jnp.asarray(rng.random((4, 6)) < 0.6)
    whole = ppo_policy_loss(logp, old, adv, valid, 0.2)[0]
    count = jnp.sum(valid)
    parts = [ppo_policy_loss(logp[:, i:i + 3], old[:, i:i + 3], adv[:, i:i + 3],
                             valid[:, i:i + 3], 0.2, count)[0] for i in (0, 3)]
    assert float(sum(parts)) == pytest.approx(float(whole), rel=1e-6)


def test_the_value_loss_equals_numpy():
    rng = np.random.default_rng(4)
    v, old, target = (rng.normal(size=(5, 3)).astype(np.float32) for _ in range(3))
    valid = rng.random((5, 3)) < 0.8
    clipped = old + np.clip(v - old, -0.1, 0.1)
    want = 0.5 * np.maximum((v - target) ** 2, (clipped - target) ** 2)[valid].mean()
    got = value_loss(jnp.asarray(v), jnp.asarray(old), jnp.asarray(target), jnp.asarray(valid),
                     0.1)
    assert float(got) == pytest.approx(want, rel=1e-5)
    plain = value_loss(jnp.asarray(v), jnp.asarray(old), jnp.asarray(target),
                       jnp.asarray(valid), 0.1, clip=False)
    assert float(plain) == pytest.approx(0.5 * ((v - target) ** 2)[valid].mean(), rel=1e-5)


def test_masked_statistics_equal_numpy_and_ignore_what_invalid_entries_hold():
    x = np.array([1.0, 2.0, np.nan, 4.0, np.inf, 6.0], np.float32)
    valid = np.array([True, True, False, True, False, True])
    assert float(masked_mean(jnp.asarray(x), jnp.asarray(valid))) == pytest.approx(3.25)
    count, mean, var = moments(jnp.asarray(x), jnp.asarray(valid))
    assert int(count) == 4 and float(mean) == pytest.approx(3.25)
    assert float(var) == pytest.approx(np.var(x[valid]), rel=1e-6)
    assert float(masked_mean(jnp.asarray(x), jnp.zeros(6, bool))) == 0.0  # none valid
