"""What a level buffer is made of, as data: the per-slot fields and `BufferState`, the snapshot
that `LevelBuffer.state()` produces and the file format (`level_buffer.fileformat`) writes and
reads. Both modules build on this one, so neither needs the other's internals."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from level_buffer.config import BufferConfig, Source
from level_buffer.tree import LevelSpec

# Per-slot fields: dtype and the value of an unfilled slot.
SLOT_FIELDS: dict[str, tuple[np.dtype, Any]] = {
    "score": (np.dtype(np.float64), -np.inf),
    "timestamp": (np.dtype(np.int64), 0),
    "max_return": (np.dtype(np.float64), -np.inf),
    "replay_count": (np.dtype(np.int64), 0),
    "source": (np.dtype(np.int8), int(Source.RANDOM)),
    "parent_id": (np.dtype(np.int64), -1),
    "level_id": (np.dtype(np.int64), -1),
    "policy_version": (np.dtype(np.int64), -1),
    "depth": (np.dtype(np.int64), 0),
}
STAT_NAMES = ("insert_attempts", "inserted", "rejected", "duplicates", "evicted", "sampled",
              "updated")


@dataclasses.dataclass
class BufferState:
    """Everything a buffer file holds; arrays cover the filled slots only."""

    spec: LevelSpec
    config: BufferConfig
    size: int
    clock: int
    next_id: int
    stats: dict[str, int]
    rng_state: dict[str, Any]
    levels: list[np.ndarray]
    slots: dict[str, np.ndarray]


__all__ = ["SLOT_FIELDS", "STAT_NAMES", "BufferState"]
