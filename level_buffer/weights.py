"""PLR replay weights over the filled slots of a buffer, in plain numpy (host side).

    P_replay = (1 - staleness_coeff) * P_score + staleness_coeff * P_staleness

* P_score: the config's prioritisation (`level_buffer.prioritization`: rank, topk, uniform)
* staleness: s_i = clock - timestamp_i, P_staleness = s / sum(s), uniform if all are 0

These are JaxUED's `LevelSampler.level_weights` semantics. Every function takes the arrays of
the filled slots only (length `size`).
"""

from __future__ import annotations

import numpy as np

from level_buffer.config import BufferConfig
from level_buffer.prioritization import PRIORITIZATIONS


def score_order(scores: np.ndarray) -> np.ndarray:
    """Slot indices sorted best score first; a stable sort, so ties keep slot order."""
    return np.argsort(-np.asarray(scores, np.float64), kind="stable")


def score_weights(scores: np.ndarray, config: BufferConfig,
                  order: np.ndarray | None = None) -> np.ndarray:
    """P_score over the filled slots; `order` (from `score_order`) may be passed to skip a sort."""
    scores = np.asarray(scores, np.float64)
    n = scores.shape[0]
    if n == 0:
        return np.zeros(0)
    if order is None:
        order = score_order(scores)
    return PRIORITIZATIONS[config.prioritization].weights(scores, order, config)


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
