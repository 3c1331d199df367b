"""The PPO loss terms and GAE: pure functions of arrays (no learner, no state), unit-tested
on their own in tests/ued/test_ppo_losses.py.

Masks: an entry is *valid* where its agent's unit is alive at the observation; the means
divide by the number of valid entries, or by a `count` given for all data-parallel shards
(`masked_mean`), so that the shards' values sum to the mean over all of them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MASKED_LOGIT = -1e10


def gae(rewards: jax.Array, values: jax.Array, dones: jax.Array, last_value: jax.Array,
        gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation, time-major: (advantages, value targets).

    rewards, values, dones: (T, ...); dones[t] ends the episode at step t, so V(s_{t+1}) (the
    next episode's first state) is not bootstrapped; last_value: (...) V of the state after the
    last step. delta_t = r_t + gamma V_{t+1} (1 - d_t) - V_t and
    A_t = delta_t + gamma lam (1 - d_t) A_{t+1}."""
    def body(carry, inputs):
        adv_next, value_next = carry
        reward, value, done = inputs
        cont = 1.0 - done.astype(jnp.float32)
        delta = reward + gamma * value_next * cont - value
        adv = delta + gamma * lam * cont * adv_next
        return (adv, value), adv

    init = (jnp.zeros_like(last_value), last_value)
    _, adv = jax.lax.scan(body, init, (rewards, values, dones), reverse=True, unroll=8)
    return adv, adv + values


def masked_logits(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Logits with illegal actions set to -1e10 (probability zero)."""
    return jnp.where(mask, logits, MASKED_LOGIT)


def masked_mean(x: jax.Array, valid: jax.Array, count: jax.Array | None = None) -> jax.Array:
    """Mean of `x` over the entries where `valid` (whatever the others hold, inf or NaN
    included); 0 if there are none. `count` replaces the number of valid entries as the
    divisor: a data-parallel shard passes the count over all shards, so that the shards'
    values sum to the mean over all of them."""
    valid = jnp.broadcast_to(valid, x.shape)
    if count is None:
        count = valid_count(valid)
    return jnp.sum(jnp.where(valid, x, 0.0)) / count.astype(x.dtype)


def valid_count(valid: jax.Array, axis_name: str | None = None) -> jax.Array:
    """The number of valid entries (over all shards of `axis_name`), at least 1: the
    divisor of `masked_mean`."""
    count = jnp.sum(valid)
    if axis_name is not None:
        count = jax.lax.psum(count, axis_name)
    return jnp.maximum(count, 1)


def policy_terms(logits: jax.Array, mask: jax.Array, actions: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
    """(log-probability of `actions`, entropy) of the masked categorical policy."""
    logp_all = jax.nn.log_softmax(masked_logits(logits, mask))
    logp = jnp.take_along_axis(logp_all, actions[..., None].astype(jnp.int32), -1)[..., 0]
    probs = jnp.exp(logp_all)
    entropy = -jnp.sum(jnp.where(mask, probs * logp_all, 0.0), -1)
    return logp, entropy


def ppo_policy_loss(logp: jax.Array, old_logp: jax.Array, advantages: jax.Array,
                    valid: jax.Array, clip_eps: float, count: jax.Array | None = None
                    ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Clipped surrogate loss over valid entries: (loss, approx KL, clip fraction).
    `count`: the divisor of the means (see `masked_mean`)."""
    log_ratio = logp - old_logp
    ratio = jnp.exp(log_ratio)
    surrogate = jnp.minimum(ratio * advantages,
                            jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages)
    loss = -masked_mean(surrogate, valid, count)
    approx_kl = masked_mean((ratio - 1.0) - log_ratio, valid, count)
    clip_frac = masked_mean((jnp.abs(ratio - 1.0) > clip_eps).astype(jnp.float32), valid,
                            count)
    return loss, approx_kl, clip_frac


def value_loss(values: jax.Array, old_values: jax.Array, targets: jax.Array,
               valid: jax.Array, clip_eps: float, clip: bool = True,
               count: jax.Array | None = None) -> jax.Array:
    """0.5 (V - target)^2 over valid entries; with `clip`, the max with the loss of the value
    clipped to within clip_eps of the rollout's value (the reference's value clipping).
    `count`: the divisor of the mean (see `masked_mean`)."""
    loss = jnp.square(values - targets)
    if clip:
        clipped = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        loss = jnp.maximum(loss, jnp.square(clipped - targets))
    return 0.5 * masked_mean(loss, valid, count)


def moments(x: jax.Array, valid: jax.Array, axis_name: str | None = None
            ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(count, mean, variance) of the valid entries of `x` (over all shards of `axis_name`);
    the count as `valid_count` gives it. On shards, one all-reduce carries the count and both
    moments: between processes every all-reduce is a round trip that waits for the slowest
    member, and this one comes before each gradient step's own."""
    valid = jnp.broadcast_to(valid, x.shape)
    if axis_name is None:
        count = valid_count(valid)
        mean = masked_mean(x, valid, count)
        return count, mean, masked_mean(jnp.square(x - mean), valid, count)
    w = valid.astype(x.dtype)
    sums = jax.lax.psum(jnp.stack([jnp.sum(w), jnp.sum(w * x), jnp.sum(w * jnp.square(x))]),
                        axis_name)
    count = jnp.maximum(sums[0], 1.0)
    mean = sums[1] / count
    return count, mean, jnp.maximum(sums[2] / count - jnp.square(mean), 0.0)


def normalise(x: jax.Array, valid: jax.Array, axis_name: str | None = None) -> jax.Array:
    """(x - mean) / (std + 1e-8) over the valid entries (of all shards of `axis_name`)."""
    _, mean, var = moments(x, valid, axis_name)
    return (x - mean) / (jnp.sqrt(var) + 1e-8)


def team_mean(x: jax.Array, valid: jax.Array) -> jax.Array:
    """Mean over the last (agent) axis of the valid entries; the plain mean where none is."""
    v = valid.astype(x.dtype)
    count = jnp.sum(v, -1)
    return jnp.where(count > 0, jnp.sum(x * v, -1) / jnp.maximum(count, 1.0), jnp.mean(x, -1))



__all__ = ["MASKED_LOGIT", "gae", "masked_logits", "masked_mean", "moments", "normalise",
           "policy_terms", "ppo_policy_loss", "team_mean", "valid_count", "value_loss"]
