"""UED curricula as branch logic: which kind of step comes next, and whether it learns.

A UED run is a sequence of steps; every step rolls the policy out on one batch of
`num_envs` levels for `num_steps` steps. What differs between methods is where the batch comes
from and whether the rollout also trains the policy:

    DR          every step: fresh random levels, gradient update                (Jakobi 1997)
    PLR         replay decision: buffer levels (gradient) or fresh levels
                (gradient too: "exploratory gradient updates")                  (Jiang 2021a)
    Robust PLR  as PLR, but fresh levels are only scored, never trained on      (Jiang 2021b)
    ACCEL       as Robust PLR, and after every replay step a step that mutates
                the replayed levels and scores the children (no gradient)       (Parker-Holder 2022)
    SFL         every step: half fresh levels, half drawn uniformly from the
                most learnable levels (p (1 - p)) of a large random batch that is
                rebuilt every `sfl_update_freq` steps; always a gradient update (Rutherford 2024)

The replay decision belongs to the level buffer (`LevelBuffer.sample_replay_decision`: filled to
the minimum fill ratio and a draw below the replay probability), so that its random stream is
saved with the buffer and a resumed run makes the same decisions. The curriculum's own state
(the last branch, ACCEL's last replay batch) is a small dict saved next to each checkpoint;
ACCEL's pending parents (the levels its next step mutates, `pending_parents`) are saved there
too, as levels: a parent may leave the buffer before its children are made.

Each method is registered by name in `ued.registry` (what it needs: a buffer, scores,
Explorers), which builds it with `from_config(ued_section)`.
"""

from __future__ import annotations

import enum
from typing import Any, Protocol


class Branch(enum.IntEnum):
    """The kind of a UED step (logged as `ued/branch`)."""

    NEW = 0  # fresh random levels (DR, and PLR's exploration)
    REPLAY = 1  # levels sampled from the buffer by score and staleness
    MUTATE = 2  # ACCEL children of the last replay batch
    SFL = 3  # SFL's mix of fresh and most-learnable levels


class ReplayDecider(Protocol):
    def sample_replay_decision(self) -> bool: ...


class Curriculum:
    """Base class: `next_branch(buffer)` picks the next step, `learns(branch)` says whether
    it updates the policy, `observe(branch, ids)` records what a step did."""

    name = "curriculum"
    uses_buffer = False
    branches: tuple[Branch, ...] = ()  # every branch `next_branch` can take

    def __init__(self, exploratory_grad_updates: bool | None = None):
        default = self.default_exploratory_grad_updates
        self.exploratory_grad_updates = (default if exploratory_grad_updates is None
                                         else bool(exploratory_grad_updates))
        self.last_branch: Branch | None = None
        self.last_replay_ids: list[int] = []
        # The levels of the last replay batch, as drawn (host arrays; not in `state_dict`).
        self.last_replay_levels: Any = None

    default_exploratory_grad_updates = True

    @classmethod
    def from_config(cls, ued: Any) -> Curriculum:
        """The curriculum a config's `ued:` section (UEDSection) asks for."""
        return cls(ued.exploratory_grad_updates)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        raise NotImplementedError

    def learns(self, branch: Branch) -> bool:
        """Whether a step of this branch applies a gradient update."""
        if branch in (Branch.REPLAY, Branch.SFL):
            return True
        return self.exploratory_grad_updates

    def observe(self, branch: Branch, replay_ids: Any = None, replay_levels: Any = None
                ) -> None:
        """Record a step of `branch`; a replay step's level ids and levels (as drawn)."""
        self.last_branch = branch
        if branch == Branch.REPLAY:
            self.last_replay_ids = [int(i) for i in replay_ids]
            self.last_replay_levels = replay_levels

    def pending_parents(self) -> list[int]:
        """The buffer ids of the levels the next step edits (ACCEL after a replay step), [] for
        none: what a snapshot taken now must hold, as levels, for the run to go on."""
        return []

    def drop_pending(self) -> None:
        """Forget the pending parents (their levels are lost): the next step decides afresh."""
        self.last_branch = None
        self.last_replay_ids = []
        self.last_replay_levels = None

    def state_dict(self) -> dict[str, Any]:
        return {"method": self.name,
                "last_branch": None if self.last_branch is None else int(self.last_branch),
                "last_replay_ids": list(self.last_replay_ids)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("method") != self.name:
            raise ValueError(f"curriculum state of {state.get('method')!r}, expected "
                             f"{self.name!r}")
        last = state.get("last_branch")
        self.last_branch = None if last is None else Branch(int(last))
        self.last_replay_ids = [int(i) for i in state.get("last_replay_ids", [])]
        self.last_replay_levels = None  # restored from the snapshot's parents file, if any


class DomainRandomization(Curriculum):
    name = "dr"
    branches = (Branch.NEW,)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        return Branch.NEW

    def learns(self, branch: Branch) -> bool:
        return True  # DR trains on every batch of fresh levels


class PLR(Curriculum):
    """Prioritised Level Replay; `robust=True` is Robust PLR (PLR-perp): no gradient on new
    levels, which is what makes its regret-based curriculum a minimax-regret strategy."""

    uses_buffer = True
    branches = (Branch.NEW, Branch.REPLAY)

    def __init__(self, robust: bool = False, exploratory_grad_updates: bool | None = None):
        self.name = "robust_plr" if robust else "plr"
        self.default_exploratory_grad_updates = not robust
        super().__init__(exploratory_grad_updates)

    @classmethod
    def from_config(cls, ued: Any) -> Curriculum:
        return cls(exploratory_grad_updates=ued.exploratory_grad_updates)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        assert buffer is not None
        return Branch.REPLAY if buffer.sample_replay_decision() else Branch.NEW


class RobustPLR(PLR):
    """Robust PLR: PLR without gradient updates on new levels (unless asked for)."""

    def __init__(self, exploratory_grad_updates: bool | None = None):
        super().__init__(robust=True, exploratory_grad_updates=exploratory_grad_updates)


class ACCEL(PLR):
    """Robust PLR whose replay steps are each followed by a mutation step: the replayed levels
    are edited and the children scored (and inserted) without a gradient update."""

    branches = (Branch.NEW, Branch.REPLAY, Branch.MUTATE)

    def __init__(self, exploratory_grad_updates: bool | None = None):
        super().__init__(robust=True, exploratory_grad_updates=exploratory_grad_updates)
        self.name = "accel"

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        if self.pending_parents():
            return Branch.MUTATE
        return super().next_branch(buffer)

    def pending_parents(self) -> list[int]:
        return list(self.last_replay_ids) if self.last_branch == Branch.REPLAY else []


class SFL(Curriculum):
    """Sampling For Learnability: every step trains on a mix of fresh levels and levels drawn
    from the learnable set; the driver rebuilds that set every `update_freq` steps."""

    name = "sfl"
    branches = (Branch.SFL,)

    def __init__(self, update_freq: int):
        super().__init__(True)
        self.update_freq = int(update_freq)

    @classmethod
    def from_config(cls, ued: Any) -> Curriculum:
        return cls(ued.sfl_update_freq)

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        return Branch.SFL

    def needs_refresh(self, step: int) -> bool:
        """Whether the learnable set is rebuilt before step `step` (0-based)."""
        return step % self.update_freq == 0


__all__ = ["ACCEL", "PLR", "SFL", "Branch", "Curriculum", "DomainRandomization", "RobustPLR"]
