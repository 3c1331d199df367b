"""ACCEL (Parker-Holder et al. 2022): Robust PLR whose replay steps are each followed by a step
that edits the replayed levels and scores the children (no gradient update). The children are
made from the replayed levels as drawn, never looked up by id: a parent may leave the buffer
before its children are made (the Ray driver commits Explorer results in between), so a
snapshot taken between the two steps keeps the parents as levels (`pending_parents`)."""

from __future__ import annotations

from typing import Any

from ued.curricula.base import Branch, ReplayDecider
from ued.curricula.robust_plr import RobustPLR


class ACCEL(RobustPLR):
    """Robust PLR and a mutation step after every replay step."""

    name = "accel"
    branches = (Branch.NEW, Branch.REPLAY, Branch.MUTATE)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        if self.pending_parents():
            return Branch.MUTATE
        return super().next_branch(buffer)

    @classmethod
    def pending_parents_of(cls, state: dict[str, Any]) -> list[int]:
        if state.get("last_branch") != Branch.REPLAY:
            return []
        return [int(i) for i in state.get("last_replay_ids", [])]


__all__ = ["ACCEL"]
