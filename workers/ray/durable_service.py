"""The level service of a Ray run: a `LevelService` that makes every acknowledged commit durable
between snapshots, so that a restart of its process loses none and applies none twice.

Every call that changes the service's state (`insert`, `update`, `replay`,
`sample_replay_decision`, `set_learnable`, `add_learnable`) is applied, then appended to a
commit log in the run's `levels/` folder, fsynced, and only then acknowledged. The calls are
deterministic given the state (the buffer's own random state included), so a snapshot plus the
log after it reproduces the state exactly:

    levels/commits-<step>.log    the calls since the snapshot of <step> (0: since the start of
                                 the session, from the state the constructor builds), one
                                 record each: [sequence number, method, args, kwargs]

A snapshot (`save`) starts a new log based on it and removes the older one; `load` (a resumed
run) does the same. Each log's header names its base step and the session (the driver's run
name) that wrote it. Ray restarts a dead actor by running its constructor again with the same
arguments: the constructor finds this session's newest log, loads its base snapshot and
replays the records. Logs of another session (a run that stopped and is being resumed) are not
replayed: they are moved to `RUN_DIR/set-aside/` when they hold records (the resumed run redoes
those steps), removed when empty.

The driver numbers its state-changing calls (`apply(seq, method, ...)`); a call it sends again
after a death is answered from the result of the first application when the log already holds
it, never applied twice. `apply_many` is a group commit: several numbered calls applied in
order, one fsync for all of their records, then one answer; a crash before the fsync loses
only calls that were never acknowledged (the driver sends them again).
"""

from __future__ import annotations

import shutil
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from level_buffer.commit_log import CommitLog, CommitLogError, read
from tabx.params import EnvParams
from ued.config import UEDSection
from ued.curricula import Curriculum
from ued.levels import LevelGenerator
from ued.run_folder import SET_ASIDE_DIR
from workers.roles.level_service import LevelService

LOG_NAME = "commits-{}.log"
MUTATING = ("insert", "update", "replay", "sample_replay_decision", "set_learnable",
            "add_learnable")
KEEP_RESULTS = 256  # results of the newest calls, for calls sent again after a restart


@dataclass(frozen=True)
class Slot:
    """In a group commit's call (`apply_many`): the argument passed flat at `index`."""

    index: int


class DurableLevelService(LevelService):
    """A LevelService with a commit log in `folder` (None: none, as the local one)."""

    def __init__(self, generator: LevelGenerator, template_level: EnvParams, ued: UEDSection,
                 seed: int = 0, curriculum: Curriculum | None = None,
                 folder: str | Path | None = None,
                 session: str = "") -> None:
        super().__init__(generator, template_level, ued, seed=seed, curriculum=curriculum)
        self.folder = None if folder is None else Path(folder)
        self.session = session
        self.seq = 0  # the newest applied call's sequence number
        self.results: OrderedDict[int, tuple[str, Any]] = OrderedDict()  # seq -> (method,
        # result) of the newest calls
        self.log: CommitLog | None = None
        self.restored: tuple[int, int] | None = None  # (base step, records) after a restart
        self._treedef = jax.tree.structure(self.template)
        if self.folder is not None and not self._recover():
            self._start(0)

    # --- state-changing calls ----------------------------------------------------------------

    def apply(self, seq: int, method: str, *args: Any, **kwargs: Any) -> Any:
        """Apply state-changing call number `seq`, `method(*args, **kwargs)`, once: a number
        already applied returns that call's result again. (The arguments are passed flat, so
        that Ray resolves an ObjectRef among them.)"""
        return self._apply(seq, method, args, kwargs, sync=True)

    def apply_many(self, calls: list[tuple[int, str, tuple, dict]], *values: Any) -> list[Any]:
        """Group commit: apply the numbered calls `calls` ([seq, method, args, kwargs], in
        order) each as `apply` does, then make their log records durable with one fsync, and
        only then answer (their results, in order). An argument `Slot(i)` stands for
        `values[i]`: passed flat, so that Ray resolves the ObjectRefs among them (levels made
        by this service and scored elsewhere)."""
        def fill(arg: Any) -> Any:
            return values[arg.index] if isinstance(arg, Slot) else arg

        results = [self._apply(seq, method, tuple(fill(a) for a in args),
                               {k: fill(v) for k, v in kwargs.items()}, sync=False)
                   for seq, method, args, kwargs in calls]
        if self.log is not None:
            self.log.sync()
        return results

    def _apply(self, seq: int, method: str, args: tuple, kwargs: dict, sync: bool) -> Any:
        if method not in MUTATING:
            raise ValueError(f"{method!r} is not a state-changing call of the level service")
        if seq <= self.seq:
            if seq not in self.results:
                raise RuntimeError(f"level service: call {seq} ({method}) was applied long "
                                   f"ago; its result is no longer kept")
            applied, result = self.results[seq]
            if applied != method:  # two callers numbering calls: a bug, never a silent skip
                raise RuntimeError(f"level service: call {seq} is {method}, but the call "
                                   f"applied as {seq} was {applied}")
            return result
        if seq != self.seq + 1:
            raise RuntimeError(f"level service: call {seq} ({method}) arrived after call "
                               f"{self.seq}: calls {self.seq + 1}..{seq - 1} are missing")
        result = getattr(LevelService, method)(self, *args, **kwargs)
        if self.log is not None:
            self.log.append([seq, method, self._encode(list(args)), self._encode(kwargs)],
                            sync=sync)
        self._applied(seq, method, result)
        return result

    def _applied(self, seq: int, method: str, result: Any) -> None:
        self.seq = seq
        self.results[seq] = (method, result)
        while len(self.results) > KEEP_RESULTS:
            self.results.popitem(last=False)

    # Direct calls go through the log too (numbered after the newest).
    def insert(self, *args: Any, **kwargs: Any) -> Any:
        return self.apply(self.seq + 1, "insert", *args, **kwargs)

    def update(self, *args: Any, **kwargs: Any) -> Any:
        return self.apply(self.seq + 1, "update", *args, **kwargs)

    def replay(self, *args: Any, **kwargs: Any) -> Any:
        return self.apply(self.seq + 1, "replay", *args, **kwargs)

    def sample_replay_decision(self) -> bool:
        return self.apply(self.seq + 1, "sample_replay_decision")

    def set_learnable(self, *args: Any, **kwargs: Any) -> Any:
        return self.apply(self.seq + 1, "set_learnable", *args, **kwargs)

    def add_learnable(self, *args: Any, **kwargs: Any) -> Any:
        return self.apply(self.seq + 1, "add_learnable", *args, **kwargs)

    # --- snapshots ---------------------------------------------------------------------------

    def save(self, folder: str | Path, step: int, state: dict[str, Any],
             keep: int | None = None, parents: EnvParams | None = None) -> None:
        super().save(folder, step, state, keep, parents)
        if self.folder is not None and Path(folder).resolve() == self.folder.resolve():
            self._start(step)

    def load(self, folder: str | Path, step: int) -> dict[str, Any]:
        state = super().load(folder, step)
        if self.folder is not None and Path(folder).resolve() == self.folder.resolve():
            self._start(step)
        return state

    # --- the log -----------------------------------------------------------------------------

    def _logs(self) -> list[tuple[Path, dict[str, Any] | None]]:
        """Every commit log in the folder with its header (None: unreadable)."""
        out = []
        for path in sorted(self.folder.glob(LOG_NAME.format("*"))):
            try:
                out.append((path, read(path).header))
            except CommitLogError:
                out.append((path, None))
        return out

    def _start(self, base: int) -> None:
        """A new log based on the snapshot of `base` (0: the session's initial state); older
        logs of this session are removed, other sessions' set aside or removed."""
        if self.log is not None:
            self.log.close()
        path = self.folder / LOG_NAME.format(base)
        for old, header in self._logs():
            if header is not None and header.get("session") == self.session:
                if old != path:
                    old.unlink(missing_ok=True)
            else:
                self._set_aside(old)
        self.log = CommitLog.create(path, base=int(base), seq=int(self.seq),
                                    session=self.session)

    def _set_aside(self, path: Path) -> None:
        """Move another session's log away (removed when it holds no record)."""
        try:
            contents = read(path)
            empty = not contents.records and not contents.torn
        except CommitLogError:
            empty = False
        if empty:
            path.unlink(missing_ok=True)
            return
        target = self.folder.parent / SET_ASIDE_DIR / time.strftime("%Y%m%d-%H%M%S")
        target = target / self.folder.name
        target.mkdir(parents=True, exist_ok=True)
        shutil.move(str(path), str(target / path.name))

    def _recover(self) -> bool:
        """Restore this session's state from its newest log (after a restart). False where the
        session has none (a first start)."""
        mine = [(int(header.get("base", 0)), path) for path, header in self._logs()
                if header is not None and header.get("session") == self.session]
        if not mine:
            return False
        base, path = max(mine)
        log, contents = CommitLog.reopen(path)
        if base > 0:
            LevelService.load(self, self.folder, base)
        self.seq = int(contents.header.get("seq", 0))
        for seq, method, args, kwargs in contents.records:
            result = getattr(LevelService, method)(self, *self._decode(args),
                                                   **self._decode(kwargs))
            self._applied(int(seq), method, result)
        self.log = log
        self.restored = (base, len(contents.records))
        print(f"level service: restarted from the snapshot of step {base} and "
              f"{len(contents.records)} logged commits ({path})"
              f"{'; a torn last record was cut off' if contents.torn else ''}",
              file=sys.stderr, flush=True)
        for path_, header in self._logs():  # an older log of this session left by a crash
            if header is not None and header.get("session") == self.session and path_ != path:
                path_.unlink(missing_ok=True)
        return True

    # --- encoding ----------------------------------------------------------------------------

    def _encode(self, value: Any) -> Any:
        if isinstance(value, EnvParams):
            return {"__levels__": [np.asarray(x) for x in jax.tree.leaves(value)]}
        if isinstance(value, dict):
            return {k: self._encode(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [self._encode(v) for v in value]
        if isinstance(value, bool | float | str) or value is None:
            return value
        if isinstance(value, int):
            return int(value)  # an IntEnum (Source) as its number
        return np.asarray(value)  # numpy and jax arrays, numpy scalars

    def _decode(self, value: Any) -> Any:
        if isinstance(value, dict):
            if set(value) == {"__levels__"}:
                return jax.tree.unflatten(self._treedef, value["__levels__"])
            return {k: self._decode(v) for k, v in value.items()}
        if isinstance(value, list):
            return [self._decode(v) for v in value]
        return value


__all__ = ["LOG_NAME", "MUTATING", "DurableLevelService", "Slot"]
