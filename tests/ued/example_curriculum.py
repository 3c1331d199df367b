"""A curriculum registered by name: the method's class and its registry entry.

`AlternatingReplay` alternates between training on fresh random levels and, once the level
buffer has decided to replay, training on replayed ones: PLR with its replay decision taken
at most every other step. It is a `ued.curricula.Curriculum` (which branch comes next, whether
it trains) registered by name; after `import example_curriculum`, `ued.method:
alternating_replay` is a valid config and `tabx train` runs it like any built-in method (a
method used by import path needs no entry: examples/uniform_replay.py). tests/ued/test_registry.py
imports it.
"""

from __future__ import annotations

from ued.curricula import Branch, Curriculum, ReplayDecider
from ued.registry import CurriculumEntry, register_curriculum


class AlternatingReplay(Curriculum):
    """Fresh levels, then a replay decision by the buffer, in turn; every step trains."""

    name = "alternating_replay"
    uses_buffer = True
    branches = (Branch.NEW, Branch.REPLAY)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        assert buffer is not None
        if self.last_branch == Branch.NEW and buffer.sample_replay_decision():
            return Branch.REPLAY
        return Branch.NEW


# Its name in configs; the class says what it needs (a level buffer, its branches).
ENTRY = register_curriculum(CurriculumEntry("alternating_replay", AlternatingReplay))
