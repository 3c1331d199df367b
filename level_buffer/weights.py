"""PLR replay weights over the filled slots of a buffer, in plain numpy (host side).

    P_replay = (1 - staleness_coeff) * P_score + staleness_coeff * P_staleness

* rank:  slots sorted by score, best first (ties: lower slot first), h_i = 1 / rank_i,
         P_score ∝ h_i ** (1 / temperature)
* topk:  P_score = softmax of the raw scores of the min(k, size) best slots, 0 elsewhere
* staleness: s_i = clock - timestamp_i, P_staleness = s / sum(s), uniform if all are 0

These are JaxUED's `LevelSampler.level_weights` semantics. Every function takes the arrays of
the filled slots only (length `size`).
"""

from __future__ import annotations

import numpy as np

from level_buffer.config import BufferConfig


def score_order(scores: np.ndarray) -> np.ndarray:
    """Slot indices sorted best score first; a stable sort, so ties keep slot order."""
    return np.argsort(-np.asarray(scores, np.float64), kind="stable")


def rank_profile(n: int, temperature: float) -> np.ndarray:
    """The rank weights in rank order: (1/rank)^(1/temperature), normalised."""
    h = (1.0 / np.arange(1, n + 1, dtype=np.float64)) ** (1.0 / temperature)
    return h / h.sum()


def score_weights(scores: np.ndarray, config: BufferConfig,
                  order: np.ndarray | None = None) -> np.ndarray:
    """P_score over the filled slots; `order` (from `score_order`) may be passed to skip a sort."""
    scores = np.asarray(scores, np.float64)
    n = scores.shape[0]
    if n == 0:
        return np.zeros(0)
    if order is None:
        order = score_order(scores)
    w = np.zeros(n)
    if config.prioritization == "rank":
        w[order] = rank_profile(n, config.temperature)
    else:  # topk
        top = order[: min(n, config.topk_k)]
        s = scores[top]
        if np.isneginf(s).all():  # nothing finished anywhere: no preference among the top
            w[top] = 1.0 / len(top)
        else:
            e = np.exp(s - s.max())
            w[top] = e / e.sum()
    return w


def staleness_weights(timestamps: np.ndarray, clock: int) -> np.ndarray:
    """P_staleness over the filled slots: staleness = clock - timestamp, normalised."""
    stale = (clock - np.asarray(timestamps, np.int64)).astype(np.float64)
    n = stale.shape[0]
    if n == 0:
        return np.zeros(0)
    total = stale.sum()
    if total <= 0:
        return np.full(n, 1.0 / n)
    return stale / total


def replay_weights(scores: np.ndarray, timestamps: np.ndarray, clock: int,
                   config: BufferConfig, order: np.ndarray | None = None) -> np.ndarray:
    """The PLR replay distribution over the filled slots (sums to 1 when size > 0)."""
    rho = config.staleness_coeff
    return ((1.0 - rho) * score_weights(scores, config, order)
            + rho * staleness_weights(timestamps, clock))
