"""Prioritised Level Replay (Jiang et al. 2021a): the buffer's replay decision picks between a
batch of replayed levels and a batch of fresh ones; both are trained on ("exploratory gradient
updates"), and the fresh ones are scored into the buffer."""

from __future__ import annotations

from typing import Any

from ued.curricula.base import Branch, Curriculum, ReplayDecider


class PLR(Curriculum):
    """Replay (by the buffer's prioritisation) or fresh levels, as the buffer decides."""

    name = "plr"
    uses_buffer = True
    branches = (Branch.NEW, Branch.REPLAY)

    @classmethod
    def from_config(cls, ued: Any, settings: Any = None) -> Curriculum:
        return cls(exploratory_grad_updates=ued.exploratory_grad_updates)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        assert buffer is not None
        return Branch.REPLAY if buffer.sample_replay_decision() else Branch.NEW


__all__ = ["PLR"]
