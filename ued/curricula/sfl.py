"""Sampling For Learnability (Rutherford et al. 2024): every step trains on a mix of fresh
levels and levels drawn uniformly from the learnable set, the most learnable levels (p (1 - p),
p the win rate) of `sfl_num_batches` x `sfl_batch_size` random levels, rebuilt every
`sfl_update_freq` steps by the driver (`UEDRun.refresh_learnable`); always a gradient update."""

from __future__ import annotations

from typing import Any

from ued.curricula.base import Branch, Curriculum, ReplayDecider


class SFL(Curriculum):
    """SFL steps only; the learnable set is rebuilt every `update_freq` steps."""

    name = "sfl"
    branches = (Branch.SFL,)

    def __init__(self, update_freq: int):
        super().__init__(True)
        self.update_freq = int(update_freq)

    @classmethod
    def from_config(cls, ued: Any, settings: Any = None) -> Curriculum:
        return cls(ued.sfl_update_freq)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        return Branch.SFL

    def needs_refresh(self, step: int) -> bool:
        return step % self.update_freq == 0

    def score_name(self, ued: Any) -> str:
        return "learnability"


__all__ = ["SFL"]
