"""The training loop every run goes through, whatever it trains and wherever its steps run.

`train_loop(runner, run_dir, ...)` owns what all runs share:

    key, k_init = split(key of the seed)       the key chain, and the train state from k_init
    open the checkpoints; with --resume, restore the newest intact step (workers.resume)
    "training ... in RUN_DIR" (or "resuming ..."), the progress line, the TensorBoard writers
    for each step:  key, k = split(key); step(k)
                    log when due (the first step, every run.log_every, the last), timed by a
                        ThroughputClock read after the step's metrics reached the host
                    stop if a logged loss is not finite (TrainingDiverged)
                    evaluate when due (every runner.eval_every, the last)
                    checkpoint when due (every run.checkpoint_every, the last), or after a
                        Ctrl-C (then KeyboardInterrupt: `Interrupt`), unless the parameters
                        are not finite (TrainingDiverged: never saved)
    finally: close the writers and the checkpoints

A `Runner` says what differs: what the train state is and where it lives, what one step does,
what is logged, what is saved beside a checkpoint. The runners are a plain MARL run and a
multi-seed one (`workers.local`), a UED run in this process (`workers.local`) and a UED run
over Ray actors (`workers.ray.driver`). A checkpoint stores the train state and the key after
a step, so a resumed run continues the key chain of an uninterrupted one.
"""

from __future__ import annotations

import abc
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import jax
import jax.numpy as jnp
import numpy as np

from tabx.errors import UserError
from ued.config import TrainConfig
from ued.run_folder import EVENTS_DIR, checkpoint_metadata, open_checkpoints
from ued.tensorboard import SummaryWriter
from workers.driver import Callback
from workers.progress import Played, Progress, ThroughputClock, log_update
from workers.resume import restore_intact


class TrainingDiverged(UserError):
    """A loss or a parameter stopped being finite: the run stops before saving it."""


def nonfinite_losses(metrics: dict[str, Any]) -> list[str]:
    """The logged losses (`loss` in the name) of a step that are not finite (any seed)."""
    bad = []
    for name, value in metrics.items():
        if "loss" not in name:
            continue
        try:
            values = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if not np.isfinite(values).all():
            bad.append(f"{name}={values.ravel()[~np.isfinite(values.ravel())][0]}")
    return bad


def params_finite(train_state: Any) -> bool:
    """Whether every floating array of the parameters (the train state's `params`, else all
    of it) is finite: one reduction per array on its device, one bool to the host."""
    tree = getattr(train_state, "params", train_state)
    checks = [jnp.isfinite(leaf).all() for leaf in jax.tree.leaves(tree)
              if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating)]
    return bool(jnp.stack(checks).all()) if checks else True


def diverged(run_dir: Path, done: int, what: str, last_good: int | None) -> TrainingDiverged:
    """The one line a diverged run stops with: the update, what is not finite, and the
    checkpoint to go back to."""
    back = (f"the last checkpoint, step {last_good} ({run_dir}/checkpoints/{last_good}), holds "
            "finite values" if last_good is not None else "no checkpoint was saved")
    return TrainingDiverged(f"{run_dir}: training diverged at update {done}: {what}; nothing "
                            f"after it is saved, and {back}; lower learner.lr or check the "
                            "config")


@dataclass
class Output:
    """Where a run reports: its TensorBoard writers (one, or one per seed of a multi-seed
    run), the progress line (None: quiet), the caller's callback and the stream for notes
    such as evaluation results (None: quiet)."""

    writers: list[SummaryWriter]
    bar: Progress | None
    callback: Callback | None
    notes: TextIO | None

    @property
    def writer(self) -> SummaryWriter:
        return self.writers[0]


@dataclass(frozen=True)
class Report:
    """A logged step, as the loop hands it to `Runner.log`: the step count, the clock's
    reading (`timing` metrics, env steps/s, the ETA's rate) and where to report."""

    done: int  # steps done
    last: bool  # the last step of this call
    timing: dict[str, float]
    rate: float  # env steps/s since the previous logged step (NaN on the first)
    eta_steps_per_s: float
    total: int  # steps of the whole run
    env_steps: int  # env steps of one step (all seeds)
    output: Output
    played: Played | None = None  # the clock's running totals: the progress line's window

    def show(self, metrics: dict[str, Any], train_state: Any, *, extra: str = "",
             writer: bool = True, callback: bool = True) -> None:
        """Log `metrics` (host values): TensorBoard (unless `writer` is False: the runner
        writes them), the progress line with `extra`, the callback (unless `callback` is
        False: the runner calls it)."""
        out = self.output
        log_update(out.writer if writer else None, out.bar, out.callback if callback else None,
                   self.done, train_state, metrics, self.env_steps, self.rate, self.total,
                   self.last, extra=extra, eta_steps_per_s=self.eta_steps_per_s,
                   played=self.played)


class Runner(abc.ABC):
    """What one kind of run does inside `train_loop` (see the module doc)."""

    snapshots = False  # whether a checkpoint comes with a level snapshot (a UED run)
    explores = False  # whether some steps only score levels: the clock splits the rate

    def __init__(self, config: TrainConfig):
        self.config = config

    @property
    def env_steps(self) -> int:
        """Env steps of one step, as the clock and the progress line count them."""
        return self.config.learner.steps_per_update

    @property
    def eval_every(self) -> int:
        """Steps between evaluations (and after the last); 0: none."""
        return 0

    def first_key(self) -> jax.Array:
        """The start of the key chain."""
        return jax.random.key(self.config.seed)

    def split_key(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(the chain's next key, a key to use now)."""
        key, use = jax.random.split(key)
        return key, use

    def event_dirs(self, run_dir: Path) -> list[Path]:
        """The folders of the TensorBoard writers."""
        return [run_dir / EVENTS_DIR]

    def needs_buffer(self) -> bool:
        """Whether a resumable step needs a level buffer in its snapshot."""
        return False

    @abc.abstractmethod
    def init(self, key: jax.Array) -> None:
        """Initialise the train state from `key`."""

    @abc.abstractmethod
    def template(self) -> Any:
        """A train state shaped as the checkpoints' (to restore into)."""

    @abc.abstractmethod
    def restore(self, run_dir: Path, train_state: Any, start: int) -> str | None:
        """Continue from the checkpoint of step `start`, whose train state is `train_state`;
        returns a note on what had to change to go on (shown to the user), or None."""

    def begin(self, start: int) -> None:
        """Before the first step of this call, restored or not (`start`: the first step)."""
        return None

    @abc.abstractmethod
    def headline(self, run_dir: Path, start: int) -> str:
        """What trains on what, and for how long: the line after "training " or "resuming "."""

    @abc.abstractmethod
    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        """Run step `index` with `key`; whether it trained the policy."""

    def background_steps(self) -> int:
        """Env steps explored beside the steps (levels scored while the learner trains), so
        far this call: the clock counts them as explored."""
        return 0

    @abc.abstractmethod
    def host_metrics(self) -> dict[str, Any]:
        """The newest step's metrics on the host (waits for the step)."""

    @abc.abstractmethod
    def log(self, metrics: dict[str, Any], report: Report) -> None:
        """Log a step: `metrics` from `host_metrics`, timing in `report`."""

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        """After every step: evaluate when `due`; log evaluations that finished."""
        return None

    @abc.abstractmethod
    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        """Before the checkpoint of step `done`: write what it needs beside it; returns the
        train state it stores and the policy version."""

    def finish(self, stop: int, output: Output) -> None:
        """After the last step of this call (not after an error)."""
        return None


class Interrupt:
    """Ctrl-C (SIGINT) during the loop: the step under way finishes, a checkpoint of it is
    written, then KeyboardInterrupt is raised as usual; a second Ctrl-C stops at once,
    without one. Only in the main thread with Python's own SIGINT handler in place (a caller
    with a handler of its own keeps it)."""

    def __init__(self) -> None:
        self.requested = False
        self._old: Any = None

    def __enter__(self) -> Interrupt:
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self._old)  # the second one: at once

    def __exit__(self, *exc: object) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def train_loop(runner: Runner, run_dir: Path, *, resume: bool, max_updates: int | None,
               progress: bool, stream: TextIO, callback: Callback | None) -> Path:
    """Run (or, with `resume`, continue) `runner`'s run in `run_dir`; `max_updates` stops
    after that many steps in this call; `progress` writes the progress line and notes to
    `stream`; `callback(step, train_state, metrics)` runs after every logged step."""
    config = runner.config
    key, k_init = runner.split_key(runner.first_key())
    runner.init(k_init)
    start = 0
    checkpoints = open_checkpoints(run_dir, config)
    restored = (restore_intact(run_dir, checkpoints, runner.template(),
                               snapshots=runner.snapshots, needs_buffer=runner.needs_buffer(),
                               stream=stream, key_template=key)
                if resume else None)
    if restored is not None:
        checkpoints.reload()
        train_state, key, start = restored
        note = runner.restore(run_dir, train_state, start)
        if note is not None and stream is not None:
            stream.write(f"resume: {note}\n")
            stream.flush()
    runner.begin(start)
    total = config.learner.num_updates
    stop = total if max_updates is None else min(total, start + max_updates)
    bar = Progress(total, stream) if progress else None
    if progress:
        stream.write(f"{'resuming' if resume else 'training'} {runner.headline(run_dir, start)}\n")
        stream.flush()

    # A resumed run redoes the steps after its checkpoint: their earlier points are dropped.
    purge = start * config.learner.steps_per_update + 1 if resume else None
    output = Output([SummaryWriter(path, purge_step=purge) for path in runner.event_dirs(run_dir)],
                    bar, callback, stream if progress else None)
    interrupt = Interrupt()
    try:
        interrupt.__enter__()
        clock = ThroughputClock(start, runner.env_steps)
        trained = 0  # steps of this call that trained the policy (the clock's split)
        for index in range(start, stop):
            key, k_step = runner.split_key(key)
            done = index + 1
            last = done == stop
            checkpoint_due = done % config.run.checkpoint_every == 0 or last
            trained += runner.step(index, k_step, last=last, checkpoint_due=checkpoint_due)
            if clock.first_pending or done % config.run.log_every == 0 or last:
                metrics = runner.host_metrics()  # waits for the step: then read the clock
                bad = nonfinite_losses(metrics)
                if bad:
                    raise diverged(run_dir, done, f"{', '.join(bad)} is not finite",
                                   checkpoints.latest())
                timing, rate = clock.read(done, trained if runner.explores else None,
                                          runner.background_steps())
                runner.log(metrics, Report(done, last, timing, rate, clock.eta_steps_per_s,
                                           total, runner.env_steps, output, clock.played))
            every = runner.eval_every
            runner.evaluate(done, bool(every) and (done % every == 0 or last), output)
            if checkpoint_due or interrupt.requested:
                train_state, version = runner.checkpoint(done, run_dir)
                if not params_finite(train_state):
                    raise diverged(run_dir, done, "the parameters are not finite",
                                   checkpoints.latest())
                checkpoints.save(done, train_state, key,
                                 checkpoint_metadata(config, done, version))
            if interrupt.requested:
                stream.write(f"interrupted: checkpoint of step {done} written; continue with: "
                             f"tabx train --resume {run_dir}\n")
                stream.flush()
                raise KeyboardInterrupt
        runner.finish(stop, output)
    finally:
        interrupt.__exit__()
        for writer in output.writers:
            writer.close()
        checkpoints.close()
    return run_dir


__all__ = ["Output", "Report", "Runner", "TrainingDiverged", "nonfinite_losses",
           "params_finite", "train_loop"]
