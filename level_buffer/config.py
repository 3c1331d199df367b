"""Configuration of a `LevelBuffer` (`BufferConfig`) and the `Source` of a level.

Defaults are the TABX paper / reference-code PLR settings (capacity 4000, replay probability
0.8, staleness coefficient 0.3, minimum fill 0.5, rank prioritisation with temperature 0.3,
exact duplicate check). JaxUED's library defaults differ (0.95, 0.5, 1.0, temperature 1.0, no
duplicate check); pass them explicitly to reproduce JaxUED runs.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from level_buffer.prioritization import PRIORITIZATIONS


class Source(enum.IntEnum):
    """Where a level in the buffer came from (stored as int8)."""

    RANDOM = 0  # sampled by the level generator (domain randomisation)
    MUTATION = 1  # an ACCEL edit of a buffer level (parent_id names the parent)
    REPLAY = 2  # re-entered from a replay batch (e.g. sent back by a learner)
    LOADED = 3  # read from a scenario file or an older buffer




@dataclass(frozen=True)
class BufferConfig:
    """PLR buffer settings; validated on construction so a bad value fails at the boundary."""

    capacity: int = 4000
    replay_prob: float = 0.8
    staleness_coeff: float = 0.3
    minimum_fill_ratio: float = 0.5
    prioritization: str = "rank"
    temperature: float = 0.3  # rank prioritisation: w ∝ (1/rank)^(1/temperature)
    topk_k: int = 4  # top-k prioritisation: softmax of the raw scores of the k best levels
    duplicate_check: bool = True  # an inserted level equal to a stored one updates it instead
    near_duplicates: bool = False  # also treat float leaves within near_duplicate_atol as equal
    near_duplicate_atol: float = 1e-5

    def __post_init__(self) -> None:
        def bad(name: str, allowed: str) -> ValueError:
            return ValueError(f"BufferConfig.{name} must be {allowed}, got {getattr(self, name)!r}")

        if not isinstance(self.capacity, int) or isinstance(self.capacity, bool) \
                or self.capacity < 1:
            raise bad("capacity", "an integer >= 1")
        for name in ("replay_prob", "staleness_coeff", "minimum_fill_ratio"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise bad(name, "a number in [0, 1]")
        if self.prioritization not in PRIORITIZATIONS:
            raise bad("prioritization", f"one of {tuple(PRIORITIZATIONS)}")
        if not isinstance(self.temperature, (int, float)) or not (
                self.temperature > 0 and math.isfinite(self.temperature)):
            raise bad("temperature", "a finite number > 0")
        if not isinstance(self.topk_k, int) or isinstance(self.topk_k, bool) or self.topk_k < 1:
            raise bad("topk_k", "an integer >= 1")
        if not isinstance(self.near_duplicate_atol, (int, float)) or not (
                0.0 <= self.near_duplicate_atol < math.inf):
            raise bad("near_duplicate_atol", "a finite number >= 0")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BufferConfig:
        """Rebuild from `to_dict` output; unknown keys are an error (a newer file format)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown BufferConfig fields {unknown}")
        return cls(**data)
