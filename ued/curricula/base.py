"""The curriculum interface: every decision a UED method makes, as hooks that every driver and
schedule calls (the local driver, the Ray driver's deterministic and asynchronous schedules,
its continuous schedule). No driver, schedule or command looks at a curriculum's class or name.

    next_branch(buffer)          which kind of step comes next (`Branch`)
    learns(branch)               whether a step of that kind applies a gradient update; the
                                 steps that do not are the ones Explorers can take
    level_request(branch, ...)   the new levels of a NEW or MUTATE step: generated or mutated
    scores_new_levels            whether new levels a learning step plays are scored and
                                 offered to the buffer (PLR); else they are only trained on
    buffer_config(ued)           its level buffer: size, replay probability, and how replay
                                 levels are drawn (prioritisation, temperature, staleness)
    score_name(ued)              the score its levels are ranked by (`ued.score`: max_mc, pvl)
    insert_scores(levels, ...)   the scores new levels enter the buffer with (the level service
                                 calls it; default: their regret scores)
    needs_refresh(step)          SFL: whether the learnable set is rebuilt before step `step`
    observe(branch, ...)         what a step did (a replay step: the ids and levels it drew)
    pending_parents()            the buffer ids of the levels the next step edits: a snapshot
                                 keeps them as levels (`parents-<step>.msgpack`)
    state_dict / load_state_dict its state, saved beside every checkpoint

A method with settings of its own beyond the `ued:` section names a new top-level config key
and a dataclass of its fields (`settings_section`, `settings_type`): the config reads and
writes them as it does a built-in section, `validate_settings` refuses bad values, and
`from_config` gets them built.

A method is one subclass in one file (`ued/curricula/<method>.py`, or any importable module:
`ued.method: my_module:MyCurriculum`); docs/new_method.md is the guide. The replay decision
belongs to the level buffer (`LevelBuffer.sample_replay_decision`: filled to the minimum fill
ratio and a draw below the replay probability), so that its random stream is saved with the
buffer and a resumed run makes the same decisions.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace
from typing import Any, ClassVar, Protocol

import numpy as np

from level_buffer import BufferConfig, Source


class Branch(enum.IntEnum):
    """The kind of a UED step (logged as `ued/branch`)."""

    NEW = 0  # fresh random levels (DR, and PLR's exploration)
    REPLAY = 1  # levels sampled from the buffer by the curriculum's replay distribution
    MUTATE = 2  # edits of the last replay batch's levels (ACCEL)
    SFL = 3  # a mix of fresh levels and levels of the learnable set (SFL)


class ReplayDecider(Protocol):
    def sample_replay_decision(self) -> bool: ...


@dataclass(frozen=True, eq=False)
class LevelRequest:
    """New levels a step asks the level service for: the call that makes them (`method` of
    the service with `args`), and how the buffer files them when they are committed."""

    method: str  # "fresh" (NEW), "mutate" (MUTATE), "mutate_replay" (the continuous schedule)
    args: tuple
    source: Source
    parent_ids: np.ndarray | int = -1  # MUTATE: the parents' buffer ids; -1: none

    def make(self, service: Any) -> Any:
        """The levels, made by `service` (a LevelService or a stand-in with its methods)."""
        return getattr(service, self.method)(*self.args)


class Curriculum:
    """The base of every UED method (module doc). Subclasses set `name`, `branches` and, with
    a level buffer, `uses_buffer`, and override the hooks whose default does not fit."""

    name: ClassVar[str] = "curriculum"
    uses_buffer: ClassVar[bool] = False  # keeps a scored level buffer (snapshotted)
    branches: ClassVar[tuple[Branch, ...]] = ()  # every branch `next_branch` can take
    default_exploratory_grad_updates: ClassVar[bool] = True  # train on NEW levels
    # Its own config section (None: the `ued:` section only): a new top-level config key and
    # the (frozen) dataclass of its fields. The config reads it with its field types, keeps
    # it as `TrainConfig.method_settings`, writes it back under that key, and hands the built
    # dataclass to `from_config` (in every process of the run: it travels with the config).
    settings_section: ClassVar[str | None] = None
    settings_type: ClassVar[type | None] = None

    def __init__(self, exploratory_grad_updates: bool | None = None):
        default = self.default_exploratory_grad_updates
        self.exploratory_grad_updates = (default if exploratory_grad_updates is None
                                         else bool(exploratory_grad_updates))
        self.last_branch: Branch | None = None
        self.last_replay_ids: list[int] = []
        # The levels of the last replay batch, as drawn (host arrays; not in `state_dict`).
        self.last_replay_levels: Any = None

    @classmethod
    def from_config(cls, ued: Any, settings: Any = None) -> Curriculum:
        """The curriculum a config's `ued:` section (UEDSection) asks for; `settings`: its own
        section, an instance of `settings_type` (None for a method without one)."""
        return cls(ued.exploratory_grad_updates)

    @classmethod
    def validate_settings(cls, settings: Any, ued: Any) -> None:
        """Refuse values of its own section (`settings_type`) that cannot work, alone or with
        the `ued:` section, by a ConfigError naming the field (`ued.errors.check`); the field
        types are checked when the config is read. Nothing to check here."""

    # --- decisions -----------------------------------------------------------------------------

    def next_branch(self, buffer: ReplayDecider | None) -> Branch:
        """The kind of the next step; `buffer` decides replays (None without a buffer)."""
        raise NotImplementedError

    def learns(self, branch: Branch) -> bool:
        """Whether a step of this branch applies a gradient update."""
        if branch in (Branch.REPLAY, Branch.SFL):
            return True
        return self.exploratory_grad_updates

    def explores_apart(self) -> bool:
        """Whether some of its steps only score levels (so Explorers can take them)."""
        return any(not self.learns(b) for b in self.branches)

    @property
    def scores_new_levels(self) -> bool:
        """Whether new levels a learning step plays are scored and offered to the buffer."""
        return self.uses_buffer

    def needs_refresh(self, step: int) -> bool:
        """Whether the SFL learnable set is rebuilt before step `step` (0-based)."""
        return False

    # --- levels ----------------------------------------------------------------------------

    def level_request(self, branch: Branch, k_levels: Any, k_edit: Any, n: int
                      ) -> LevelRequest:
        """The new levels of a NEW step (`n` generated from `k_levels`) or a MUTATE step (the
        last replay batch's levels, as drawn, edited with `k_edit`)."""
        if branch == Branch.NEW:
            return LevelRequest("fresh", (k_levels, n), Source.RANDOM)
        if branch == Branch.MUTATE:
            parent_ids = np.asarray(self.pending_parents(), np.int64)
            return LevelRequest("mutate", (k_edit, self.last_replay_levels), Source.MUTATION,
                                parent_ids)
        raise ValueError(f"{self.name}: a {branch.name} step makes no new levels")

    def buffer_config(self, ued: Any) -> BufferConfig:
        """Its level buffer, from the config's `ued:` section: the paper's methods draw replay
        levels as the section says (defaults: rank prioritisation, temperature 0.3,
        staleness 0.3); a method with its own replay distribution overrides this."""
        return BufferConfig(capacity=ued.buffer_size, replay_prob=ued.replay_prob,
                            staleness_coeff=ued.staleness_coef,
                            minimum_fill_ratio=ued.min_fill_ratio,
                            prioritization=ued.prioritization, temperature=ued.temperature,
                            topk_k=ued.topk, duplicate_check=ued.duplicate_check)

    @staticmethod
    def with_replay(config: BufferConfig, **changes: Any) -> BufferConfig:
        """`config` with other replay settings (`prioritization="uniform"`, ...)."""
        return replace(config, **changes)

    def insert_scores(self, levels: Any, scores: np.ndarray, buffer: Any) -> np.ndarray:
        """The scores new levels enter the buffer with (run by the level service, before
        `buffer`, a `LevelBuffer`, takes them): their regret scores as they are."""
        return scores

    def score_name(self, ued: Any) -> str:
        """The score its levels are ranked by (`ued.scores`): the config's regret estimate."""
        return ued.score

    # --- what a step did, and state --------------------------------------------------------

    def observe(self, branch: Branch, replay_ids: Any = None, replay_levels: Any = None
                ) -> None:
        """Record a step of `branch`; a replay step's level ids and levels (as drawn)."""
        self.last_branch = branch
        if branch == Branch.REPLAY:
            self.last_replay_ids = [int(i) for i in replay_ids]
            self.last_replay_levels = replay_levels

    @classmethod
    def pending_parents_of(cls, state: dict[str, Any]) -> list[int]:
        """`pending_parents` of a curriculum in `state` (its `state_dict`), without building
        one (`tabx runs check`)."""
        return []

    def pending_parents(self) -> list[int]:
        """The buffer ids of the levels the next step edits ([] for none): what a snapshot
        taken now must hold, as levels, for the run to go on."""
        return self.pending_parents_of(self.state_dict())

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


__all__ = ["Branch", "Curriculum", "LevelRequest", "ReplayDecider"]
