"""95 % confidence intervals of evaluation results: Wilson for rates, normal for means."""

from __future__ import annotations

import math

import numpy as np


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float, float]:
    """(rate, low, high): the 95 % Wilson score interval of a binomial rate."""
    if n == 0:
        return math.nan, math.nan, math.nan
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return p, max(0.0, centre - half), min(1.0, centre + half)


def mean_ci(x: np.ndarray, z: float = 1.96) -> tuple[float, float]:
    """(mean, half width of the 95 % normal interval)."""
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return math.nan, math.nan
    half = z * x.std(ddof=1) / math.sqrt(x.size) if x.size > 1 else math.nan
    return float(x.mean()), float(half)


__all__ = ["mean_ci", "wilson"]
