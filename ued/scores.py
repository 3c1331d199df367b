"""Level scores from rollouts, as pure jax functions (jit- and vmap-safe).

Every input is time-major, shape (T, num_envs); `dones[t, e]` is True when the transition at
step t ended an episode of env e, so the steps of an episode are the ones after the previous
done up to and including its own done. The rollout is assumed to start at an episode start
(env reset to the level, auto-reset to the same level on done, as JaxUED's AutoReplayWrapper
does). A trailing episode that has not finished when the rollout ends is ignored. An env with
no completed episode scores -inf, which keeps the level out of a PLR buffer.

These are JaxUED's definitions (src/jaxued/utils.py), built on `episode_stats`:

* positive_value_loss = mean over completed episodes of mean_t max(A_t, 0)   (PVL)
* max_mc             = mean over completed episodes of mean_t (R_max - V_t)  (MaxMC)
* learnability       = p (1 - p), p = fraction of completed episodes won     (SFL)
* max_episode_return = the best undiscounted episodic return in the rollout (to update R_max)

`level_scores` turns a learner's `RolloutStats` into the buffer's per-level scores.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def episode_stats(values: jax.Array, dones: jax.Array, time_average: bool = True
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per env, over completed episodes: (mean, max, count) of each episode's value.

    An episode's value is the mean of `values` over its steps (`time_average=True`) or their
    sum (False). Mean and max are -inf for an env with no completed episode.
    values, dones: (T, num_envs). Returns three (num_envs,) arrays (float32, float32, int32).
    """
    values = jnp.asarray(values, jnp.float32)
    dones = jnp.asarray(dones).astype(bool)
    zeros = jnp.zeros(values.shape[1:], jnp.float32)

    def step(carry, inputs):
        ep_sum, ep_len, total, best, count = carry
        value, done = inputs
        ep_sum, ep_len = ep_sum + value, ep_len + 1.0
        ep_value = ep_sum / ep_len if time_average else ep_sum
        total = total + jnp.where(done, ep_value, 0.0)
        best = jnp.where(done, jnp.maximum(best, ep_value), best)
        count = count + done.astype(jnp.int32)
        # A finished episode restarts the accumulators for the next one.
        return (jnp.where(done, 0.0, ep_sum), jnp.where(done, 0.0, ep_len), total, best,
                count), None

    init = (zeros, zeros, zeros, jnp.full_like(zeros, -jnp.inf), jnp.zeros(zeros.shape,
                                                                           jnp.int32))
    (_, _, total, best, count), _ = lax.scan(step, init, (values, dones))
    mean = jnp.where(count > 0, total / jnp.maximum(count, 1), -jnp.inf)
    return mean, best, count


def positive_value_loss(advantages: jax.Array, dones: jax.Array) -> jax.Array:
    """PVL: mean over completed episodes of the time-mean of max(A_t, 0).

    advantages: (T, num_envs) GAE advantages of the rollout; dones: (T, num_envs).
    Returns (num_envs,) float32, -inf where no episode completed."""
    return episode_stats(jnp.maximum(jnp.asarray(advantages, jnp.float32), 0.0), dones)[0]


def max_mc(values: jax.Array, dones: jax.Array, max_returns: jax.Array) -> jax.Array:
    """MaxMC: mean over completed episodes of the time-mean of (R_max - V(s_t)).

    values: (T, num_envs) value estimates V(s_t); dones: (T, num_envs); max_returns:
    (num_envs,) the best undiscounted return seen on each env's level so far (for a replayed
    level: max(stored max return, `max_episode_return` of this rollout)).
    Returns (num_envs,) float32, -inf where no episode completed."""
    gap = jnp.asarray(max_returns, jnp.float32)[None, :] - jnp.asarray(values, jnp.float32)
    return episode_stats(gap, dones)[0]


def max_episode_return(rewards: jax.Array, dones: jax.Array) -> jax.Array:
    """The best undiscounted return over the completed episodes of each env.

    rewards, dones: (T, num_envs). Returns (num_envs,) float32, -inf where none completed."""
    return episode_stats(rewards, dones, time_average=False)[1]


def learnability(wins: jax.Array, dones: jax.Array) -> jax.Array:
    """SFL learnability p (1 - p), p = the fraction of completed episodes that were won.

    wins: (T, num_envs), the episode outcome (1 won, 0 not), read at the done steps only, so
    either a per-step indicator or a carried "last outcome" works; dones: (T, num_envs).
    Returns (num_envs,) float32, -inf where no episode completed."""
    dones = jnp.asarray(dones).astype(bool)
    won = jnp.where(dones, jnp.asarray(wins, jnp.float32), 0.0).sum(axis=0)
    count = dones.sum(axis=0)
    p = won / jnp.maximum(count, 1)
    return jnp.where(count > 0, p * (1.0 - p), -jnp.inf).astype(jnp.float32)


SCORE_FUNCTIONS = ("max_mc", "pvl", "learnability")


def level_scores(stats, score: str, stored_max_returns: jax.Array | None = None
                 ) -> tuple[jax.Array, jax.Array]:
    """(scores, max returns) per env of a rollout, for the level buffer.

    stats: a `RolloutStats` (values, advantages, dones, rewards, wins, each (T, num_envs));
    score: one of SCORE_FUNCTIONS; stored_max_returns: (num_envs,) the buffer's R_max of
    replayed levels (None for new levels). The max return is the rollout's best episode
    return raised to the stored one; MaxMC uses it as R_max. -inf where no episode ended."""
    best = max_episode_return(stats.rewards, stats.dones)
    if stored_max_returns is not None:
        best = jnp.maximum(best, jnp.asarray(stored_max_returns, jnp.float32))
    if score == "max_mc":
        # R_max from this level's history; a level with no finished episode keeps -inf.
        values = max_mc(stats.values, stats.dones, jnp.where(jnp.isfinite(best), best, 0.0))
    elif score == "pvl":
        values = positive_value_loss(stats.advantages, stats.dones)
    elif score == "learnability":
        values = learnability(stats.wins, stats.dones)
    else:
        raise ValueError(f"unknown score {score!r}; expected one of "
                         f"{', '.join(SCORE_FUNCTIONS)}")
    return values, best
