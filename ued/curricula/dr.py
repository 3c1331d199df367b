"""Domain randomisation (Jakobi 1997): every step trains on fresh random levels."""

from __future__ import annotations

from ued.curricula.base import Branch, Curriculum, ReplayDecider


class DomainRandomization(Curriculum):
    """Fresh random levels at every step, always a gradient update; no level buffer."""

    name = "dr"
    branches = (Branch.NEW,)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        return Branch.NEW

    def learns(self, branch: Branch) -> bool:
        return True  # DR trains on every batch of fresh levels


__all__ = ["DomainRandomization"]
