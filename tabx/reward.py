"""Team health ratios, the dense reward, and the episode outcome.

Dense reward of team k: the change of its health ratio minus the change of the opponent's.
The ratio is the paper's mean over the team's units of health / max health (default), or the
reference code's sum of health / sum of max health (`EnvParams.reward_mode`). On the last step
the winner (higher ratio, rounded to 4 decimals; ties go to the enemy, team 1, as in the paper)
gets `win_reward` and the loser `lose_reward`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tabx import constants as C


def team_hp_ratio(health: jax.Array, max_health: jax.Array, team: jax.Array,
                  active: jax.Array, reward_mode: jax.Array) -> jax.Array:
    """(2,) health ratio per team over its active units (0 for a team without units)."""
    member = (team[None, :] == jnp.arange(C.NUM_TEAMS)[:, None]) & active[None, :]  # (2, N)
    safe_max = jnp.maximum(max_health, 1e-6)
    count = jnp.sum(member, -1)
    mean_of_ratios = jnp.sum(jnp.where(member, health / safe_max, 0.0), -1) / jnp.maximum(count, 1)
    ratio_of_sums = (jnp.sum(jnp.where(member, health, 0.0), -1)
                     / jnp.maximum(jnp.sum(jnp.where(member, safe_max, 0.0), -1), 1e-6))
    ratio = jnp.where(reward_mode == C.REWARD_RATIO_OF_SUMS, ratio_of_sums, mean_of_ratios)
    return jnp.clip(ratio, 0.0, 1.0)


def winner_mask(hp_ratio: jax.Array) -> jax.Array:
    """(2,) bool: the ally team wins only with a strictly higher rounded ratio."""
    rounded = jnp.round(hp_ratio, 4)
    ally_wins = rounded[C.ALLY] > rounded[C.ENEMY]
    return jnp.stack([ally_wins, ~ally_wins])


def dense_reward(new_ratio: jax.Array, old_ratio: jax.Array) -> jax.Array:
    delta = new_ratio - old_ratio
    return delta - delta[::-1]
