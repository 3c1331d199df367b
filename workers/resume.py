"""Resume from the newest intact step of a run folder, and report the integrity of all of them.

A step can be resumed when its orbax checkpoint restores and, for a UED run, its level snapshot
reads back: `state-<step>.json` parses, and `buffer-<step>.msgpack`, `learnable-<step>.msgpack`,
`sfl-window-<step>.msgpack` and `parents-<step>.msgpack` (where they exist) pass the
level-buffer format's checks (magic, version, SHA-256, every length, dtype and shape), and the
levels its curriculum state names as the next step's parents (ACCEL after a replay step) are in
the parents file, one per id, or, in a snapshot without one, in its buffer. A snapshot whose
buffer no longer holds them (written by an earlier version) resumes without that mutate step:
`tabx runs check` says so beside the step.
The checkpoint of a step records the SHA-256 of its snapshot's files: one edited since is
damaged too. `restore_intact` tries the steps newest first, says in one line what is wrong with
each step it passes over, and moves the files of every step newer than the one it resumes from
to `RUN_DIR/set-aside/<time>/` (never deletes them), so that the continued run does not mix
with them. `check_run` reports every step without changing anything (`tabx runs check`).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import jax

from level_buffer import LevelBuffer
from level_buffer.fileformat import BufferFileError
from tabx.files import not_a_file
from ued.checkpoint import CheckpointError, Checkpoints
from ued.config import ConfigError, TrainConfig
from ued.errors import gist
from ued.run_folder import CHECKPOINT_DIR, LEVELS_DIR, SET_ASIDE_DIR
from workers.roles.level_service import SNAPSHOT_FILES


@dataclass(frozen=True)
class StepCheck:
    """What is wrong with one step of a run folder (None: intact)."""

    step: int
    checkpoint: str | None  # None: restores
    snapshot: str | None  # None: reads back (or the run keeps none)
    note: str | None = None  # what a resume from it has to change to go on
    checked: bool = True  # the checkpoint's arrays compared with digests recorded at saving

    @property
    def intact(self) -> bool:
        return self.checkpoint is None and self.snapshot is None


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def state_problem(state: Any) -> str | None:
    """What makes a parsed `state-<step>.json` unusable (the curriculum state a UED run writes
    with its snapshot, `UEDRun.state`), or None."""
    if not isinstance(state, dict):
        return f"expected a JSON object, got {type(state).__name__}"
    record = state.get("curriculum")  # its JSON record (a parsed object, not a class)
    if not isinstance(record, dict) or not isinstance(record.get("method"), str):
        return "curriculum: expected an object with the curriculum's method"
    last = record.get("last_branch")
    if last is not None and not _is_int(last):
        return f"curriculum.last_branch: expected a branch number, got {last!r:.40}"
    ids = record.get("last_replay_ids", [])
    if not isinstance(ids, list) or not all(_is_int(i) for i in ids):
        return "curriculum.last_replay_ids: expected a list of level ids"
    if not _is_int(state.get("version")):
        return "version: expected the policy version (an integer)"
    if not _is_int(state.get("sfl_scoring_steps", 0)):
        return "sfl_scoring_steps: expected an integer"
    counts = state.get("branch_counts", {})
    if not isinstance(counts, dict) or not all(_is_int(n) and n >= 0 for n in counts.values()):
        return "branch_counts: expected an object of step counts"
    return None


def snapshot_problem(levels_dir: Path, step: int, needs_buffer: bool,
                     checkpoints: Checkpoints | None = None) -> str | None:
    """What keeps the level snapshot of `step` from reading back, or None; with `checkpoints`,
    also a snapshot file changed since checkpoint `step` recorded its digest."""
    state = levels_dir / f"state-{step}.json"
    kind = not_a_file(state)
    if kind == "missing":
        return f"{state}: missing (the snapshot of step {step} is incomplete)"
    if kind is not None:  # never opened: a device or FIFO could block or never end
        return f"{state}: {kind}"
    try:
        problem = state_problem(json.loads(state.read_text()))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        return f"{state}: unreadable ({gist(err)})"
    if problem is not None:
        return f"{state}: {problem}"
    for name, required in (("buffer", needs_buffer), ("learnable", False),
                           ("sfl-window", False), ("parents", False)):
        path = levels_dir / f"{name}-{step}.msgpack"
        kind = not_a_file(path)
        if kind == "missing":
            if required:
                return f"{path}: missing"
            continue
        if kind is not None:
            return f"{path}: {kind}"
        try:
            LevelBuffer.load(path)
        except (BufferFileError, OSError) as err:
            return str(err).splitlines()[0]
    return checkpoints.file_problem(step) if checkpoints is not None else None


def checkpoint_problem(checkpoints: Checkpoints, template: Any, step: int,
                       key_template: jax.Array | None = None) -> tuple[str | None, Any]:
    """(what keeps checkpoint `step` from restoring or None, the restored (state, key, step)).
    `template` None: read it as saved (`Checkpoints.restore_saved`), with no learner."""
    try:
        if template is None:
            return None, checkpoints.restore_saved(step)
        return None, checkpoints.restore(template, step, key_template)
    except CheckpointError as err:
        return str(err), None


def restore_intact(run_dir: Path, checkpoints: Checkpoints, template: Any, *,
                   snapshots: bool, needs_buffer: bool, stream: TextIO | None,
                   key_template: jax.Array | None = None
                   ) -> tuple[Any, jax.Array, int] | None:
    """The newest step whose checkpoint (and, with `snapshots`, level snapshot) is intact:
    (train state, key, step); None when the run has no checkpoint yet. ConfigError when none
    is intact. Newer steps' files are set aside. `key_template`: the shape of the stored key
    (default one key; `Checkpoints.restore`)."""
    steps = checkpoints.all()
    if not steps:
        # Killed before its first checkpoint (perhaps after that step's snapshot): start over.
        if stream is not None:
            stream.write(f"resume: {run_dir} has no checkpoint yet: the run starts again from "
                         f"step 0\n")
            stream.flush()
        set_aside(run_dir, 0, stream)
        return None
    levels_dir = run_dir / LEVELS_DIR
    problems = []
    for step in reversed(steps):
        problem = (snapshot_problem(levels_dir, step, needs_buffer, checkpoints) if snapshots
                   else None)
        restored = None
        if problem is None:
            problem, restored = checkpoint_problem(checkpoints, template, step, key_template)
        if problem is not None:
            problems.append(problem)
            if stream is not None:
                stream.write(f"resume: step {step} is damaged: {problem}; trying the one "
                             f"before\n")
                stream.flush()
            continue
        set_aside(run_dir, step, stream)
        return restored
    raise ConfigError(f"{run_dir}: no intact checkpoint to resume from (steps "
                      f"{', '.join(map(str, steps))}): {problems[0]}")


def _checkpoint_step(name: str) -> int | None:
    """The step of a checkpoint folder: `<step>`, or orbax's temporary `<step>.orbax-checkpoint-
    tmp-<n>` that a process killed while saving leaves behind."""
    head, _, rest = name.partition(".")
    if head.isdigit() and (not rest or rest.startswith("orbax-checkpoint-tmp")):
        return int(head)
    return None


def set_aside(run_dir: Path, step: int, stream: TextIO | None) -> Path | None:
    """Move the checkpoints and snapshots of steps after `step` to `RUN_DIR/set-aside/<time>/`
    (kept for inspection: a resumed run writes those steps again)."""
    newer = [p for p in sorted((run_dir / CHECKPOINT_DIR).glob("*"))
             if p.is_dir() and _checkpoint_step(p.name) is not None
             and _checkpoint_step(p.name) > step]
    levels_dir = run_dir / LEVELS_DIR
    if levels_dir.is_dir():
        for path in sorted(levels_dir.iterdir()):
            for pattern in SNAPSHOT_FILES:
                prefix, suffix = pattern.split("{}")
                middle = path.name[len(prefix):len(path.name) - len(suffix)]
                if (path.name.startswith(prefix) and path.name.endswith(suffix)
                        and middle.isdigit() and int(middle) > step):
                    newer.append(path)
    if not newer:
        return None
    target = run_dir / SET_ASIDE_DIR / time.strftime("%Y%m%d-%H%M%S")
    for path in newer:
        destination = target / path.relative_to(run_dir)
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(path), str(destination))
    if stream is not None:
        stream.write(f"resume: from step {step}; {len(newer)} newer files moved to {target}\n")
        stream.flush()
    return target


def parents_check(levels_dir: Path, step: int, config: TrainConfig
                  ) -> tuple[str | None, str | None]:
    """(problem, note) of the levels the snapshot of `step` names as the next step's parents
    (the curriculum's `pending_parents`): a problem where the parents file does not match the
    ids, a note where neither it nor the buffer holds them (a resume drops that step)."""
    from ued.registry import curriculum_class

    curriculum = curriculum_class(config.ued.method)  # its class: nothing is built
    try:
        ids = curriculum.pending_parents_of(json.loads(
            (levels_dir / f"state-{step}.json").read_text())["curriculum"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None, None  # the state's own problems are `snapshot_problem`'s
    if not ids:
        return None, None
    path = levels_dir / f"parents-{step}.msgpack"
    try:
        if path.is_file():
            count = len(LevelBuffer.load(path))
            if count != len(ids):
                return (f"{path}: {count} levels, but the curriculum state names {len(ids)} "
                        f"parents"), None
            return None, None
        buffer = levels_dir / f"buffer-{step}.msgpack"
        held = set(LevelBuffer.load(buffer).ids.tolist()) if buffer.is_file() else set()
    except (BufferFileError, OSError) as err:
        return str(err).splitlines()[0], None
    missing = sorted(set(ids) - held)
    if not missing:
        return None, None
    return None, (f"its buffer no longer holds the replayed levels {missing[:8]} that "
                  f"{curriculum.name}'s next step mutates, and it keeps no parents file: a "
                  f"resume drops that mutate step")


def check_run(run_dir: Path, checkpoints: Checkpoints, template: Any = None, *,
              snapshots: bool, needs_buffer: bool, key_template: jax.Array | None = None,
              steps: list[int] | None = None, config: TrainConfig | None = None
              ) -> list[StepCheck]:
    """Every checkpointed step of a run folder (or those of `steps`), oldest first, checked as
    resume would; `template` None reads each checkpoint as it was saved
    (`Checkpoints.restore_saved`). With `config`, a snapshot's pending parents are checked
    too (`parents_check`)."""
    levels_dir = run_dir / LEVELS_DIR
    checks = []
    for step in (checkpoints.all() if steps is None else steps):
        snapshot = (snapshot_problem(levels_dir, step, needs_buffer, checkpoints)
                    if snapshots else None)
        note = None
        if snapshots and snapshot is None and config is not None:
            snapshot, note = parents_check(levels_dir, step, config)
        checks.append(StepCheck(step, checkpoint_problem(checkpoints, template, step,
                                                         key_template)[0], snapshot, note,
                                checkpoints.has_digests(step)))
    return checks


def _keeps_buffer(config: TrainConfig) -> bool:
    """Whether the run's level snapshots hold a level buffer (its curriculum's registry entry)."""
    from ued.registry import curriculum_class

    return config.ued.enabled and curriculum_class(config.ued.method).uses_buffer


def check_run_folder(run_dir: str | Path) -> list[StepCheck]:
    """`check_run` for a run folder as it is on disk: its config says what it keeps (the
    curriculum's registry entry whether it has a level buffer); no learner, train state or
    curriculum is built, and each checkpoint is read as it was saved."""
    from ued.run_folder import open_checkpoints, read_run_config

    run_dir = Path(run_dir)
    config = read_run_config(run_dir)
    with open_checkpoints(run_dir, config, create=False) as checkpoints:
        return check_run(run_dir, checkpoints, snapshots=config.ued.enabled,
                         needs_buffer=_keeps_buffer(config), config=config)


def step_intact(run_dir: Path, checkpoints: Checkpoints, config: TrainConfig, step: int
                ) -> bool:
    """Whether step `step` of a run folder is intact as `tabx runs check` sees it (its
    checkpoint read as saved, and a UED run's level snapshot)."""
    return check_run(run_dir, checkpoints, snapshots=config.ued.enabled,
                     needs_buffer=_keeps_buffer(config), steps=[step], config=config)[0].intact


def resume_point(run_dir: Path, config: TrainConfig) -> tuple[int | None, int]:
    """(the step `tabx train --resume` continues from: the newest intact, as `tabx runs
    check` sees it, None where none is; the number of checkpoints)."""
    from ued.run_folder import open_checkpoints

    with open_checkpoints(run_dir, config, create=False) as checkpoints:
        steps = checkpoints.all()
        for step in reversed(steps):
            if step_intact(run_dir, checkpoints, config, step):
                return step, len(steps)
    return None, len(steps)


def what_resume_does(run_dir: Path, config: TrainConfig) -> str:
    """What `tabx train --resume RUN_DIR` will do, in words (`resume_point`)."""
    step, saved = resume_point(run_dir, config)
    if step is not None:
        return f"tabx train --resume {run_dir} continues it from its checkpoint at step {step}"
    if saved:
        return (f"no checkpoint of it is intact (tabx runs check {run_dir}): tabx train "
                f"--resume {run_dir} cannot continue it")
    return f"no checkpoint yet: tabx train --resume {run_dir} starts it again from step 0"


def format_checks(run_dir: str | Path, checks: list[StepCheck]) -> str:
    """`tabx runs check`: a line per step, then the step `--resume` would continue from."""
    if not checks:
        return f"{run_dir}: no checkpoint yet"
    lines = [f"{run_dir}: {len(checks)} checkpointed steps"]
    for check in checks:
        if check.intact:
            lines.append(f"  step {check.step}: intact" + (
                "" if check.checked else " as far as it was checked: the checkpoint records "
                "no digests (its _CHECKPOINT_METADATA is missing or unreadable), so its array "
                "values are unchecked") + (f" ({check.note})" if check.note else ""))
            continue
        parts = [f"{what}: {problem}" for what, problem in (("checkpoint", check.checkpoint),
                                                            ("snapshot", check.snapshot))
                 if problem]
        lines.append(f"  step {check.step}: damaged: {'; '.join(parts)}")
    intact = [c.step for c in checks if c.intact]
    lines.append(f"newest intact step: {intact[-1]} (tabx train --resume continues from it)"
                 if intact else "no intact step: the run cannot be resumed")
    return "\n".join(lines)


__all__ = ["SET_ASIDE_DIR", "StepCheck", "check_run", "check_run_folder", "format_checks",
           "parents_check", "restore_intact", "resume_point", "set_aside", "state_problem",
           "step_intact", "what_resume_does"]
