"""Prioritisations: how a buffer turns its levels' scores into replay weights (P_score), by name.

    rank     slots sorted by score, best first (ties: lower slot first), h_i = 1 / rank_i,
             P_score ∝ h_i ** (1 / temperature)
    topk     softmax of the raw scores of the min(k, size) best slots, 0 elsewhere
    uniform  every filled slot alike (the score does not matter)

The one place a prioritisation's name is looked up: `BufferConfig` validates against
`PRIORITIZATIONS`, `level_buffer.weights.score_weights` computes with it and `tabx buffer
inspect` describes it. `register_prioritization` adds one (a curriculum with its own replay
distribution, docs/new_method.md); a buffer file names its prioritisation, so a process that
reads such a file imports the module that registers it first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Prioritization:
    """A named score-to-weight rule: `weights(scores, order, config)` gives P_score over the
    filled slots (`order`: their indices best score first); `describe(config)` says it in a few
    words for `tabx buffer inspect`."""

    name: str
    weights: Callable[[np.ndarray, np.ndarray, Any], np.ndarray]
    describe: Callable[[Any], str]


@lru_cache(maxsize=16)
def rank_profile(n: int, temperature: float) -> np.ndarray:
    """The rank weights in rank order: (1/rank)^(1/temperature), normalised (read-only)."""
    h = (1.0 / np.arange(1, n + 1, dtype=np.float64)) ** (1.0 / temperature)
    profile = h / h.sum()
    profile.setflags(write=False)
    return profile


def _rank(scores: np.ndarray, order: np.ndarray, config: Any) -> np.ndarray:
    w = np.zeros(scores.shape[0])
    w[order] = rank_profile(scores.shape[0], float(config.temperature))
    return w


def _topk(scores: np.ndarray, order: np.ndarray, config: Any) -> np.ndarray:
    w = np.zeros(scores.shape[0])
    top = order[: min(scores.shape[0], config.topk_k)]
    s = scores[top]
    if np.isneginf(s).all():  # nothing finished anywhere: no preference among the top
        w[top] = 1.0 / len(top)
    else:
        e = np.exp(s - s.max())
        w[top] = e / e.sum()
    return w


def _uniform(scores: np.ndarray, order: np.ndarray, config: Any) -> np.ndarray:
    return np.full(scores.shape[0], 1.0 / scores.shape[0])


PRIORITIZATIONS: dict[str, Prioritization] = {}


def register_prioritization(rule: Prioritization) -> Prioritization:
    """Add (or replace) the prioritisation `rule.name`."""
    PRIORITIZATIONS[rule.name] = rule
    return rule


for _rule in (Prioritization("rank", _rank, lambda c: f"rank temperature {c.temperature:g}"),
              Prioritization("topk", _topk, lambda c: f"top-{c.topk_k}"),
              Prioritization("uniform", _uniform, lambda c: "uniform")):
    register_prioritization(_rule)
del _rule


__all__ = ["PRIORITIZATIONS", "Prioritization", "rank_profile", "register_prioritization"]
