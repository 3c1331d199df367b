"""The local driver: every worker of a run in this process, one step after another.

`LocalDriver.run` trains a plain MARL run (one learner on the config's fixed scenarios) or a
UED run (`ued.method` set), each through the one training loop (`workers.training_loop`) with
a runner of this module. A UED step is `workers.ued_step.UEDRun.step`, all of it here and now:
sequential PLR / Robust PLR / ACCEL / SFL exactly as the papers (and JaxUED) define them.

A UED run folder adds `levels/` to a plain run's (`ued.run_folder`): snapshots, one per
checkpoint, of the level buffer (`tabx buffer inspect RUN_DIR/levels/buffer-N.msgpack`), SFL's
learnable set and the curriculum state. A snapshot is written before the orbax checkpoint of
the same step, so every checkpoint has one, and `--resume` continues exactly: the resumed run's
parameters and buffer equal an uninterrupted run's.

A plain run's step is `key, k = split(key); train_state, metrics, _ = learner.update(
train_state, levels, k)`; a checkpoint stores the train state and the key after an update, so
a resumed run's parameters equal an uninterrupted run's bit for bit. Updates run back to back
on the device; metrics come back to the host only every `run.log_every` updates. A config with
`seeds` runs that loop for every seed at once, vmapped in one program (`train_marl_seeds`).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, TextIO

import jax
import numpy as np

from ued.config import TrainConfig
from ued.experiment import learner_for, scenario_levels, seed_keys, split_seed_keys, training_levels
from ued.learners.ppo import PPOLearner
from ued.run_folder import seed_dir
from ued.tensorboard import SummaryWriter
from workers.driver import Callback, Driver
from workers.progress import logged_scalars
from workers.roles.learner import LearnerWorker
from workers.training_loop import Output, Report, Runner, train_loop
from workers.ued_step import UEDRun, branch_text


class LocalDriver(Driver):
    """Runs every worker in this process (the default; no Ray needed)."""

    name = "local"

    def run(self, config: TrainConfig, run_dir: Path, *, resume: bool = False,
            max_updates: int | None = None, progress: bool = True,
            stream: TextIO | None = None, callback: Callback | None = None) -> Path:
        stream = sys.stderr if stream is None else stream
        train = train_ued if config.ued.enabled else train_marl
        return train(config, run_dir, resume=resume, max_updates=max_updates,
                     progress=progress, stream=stream, callback=callback)


class MARLRunner(Runner):
    """A plain MARL run: one learner on the config's scenarios, its train state here."""

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        env_config, self.levels = training_levels(config)
        self.learner = learner_for(config, env_config)
        self.train_state: Any = None
        self.metrics: dict[str, Any] = {}

    def init(self, key: jax.Array) -> None:
        self.train_state = self.learner.init(key)

    def template(self) -> Any:
        return self.train_state

    def restore(self, run_dir: Path, train_state: Any, start: int) -> None:
        self.train_state = train_state
        return None

    def headline(self, run_dir: Path, start: int) -> str:
        config = self.config
        seeds = (f", seeds {', '.join(map(str, config.seeds))} in one program" if config.seeds
                 else "")
        return (f"{config.algorithm} on {', '.join(config.env.scenario)} "
                f"({config.env.team} vs {config.env.opponent}) in {run_dir}; "
                f"{config.learner.num_updates} updates of {config.learner.steps_per_update:,} "
                f"steps{seeds}{f', from update {start}' if start else ''}")

    @property
    def eval_every(self) -> int:
        return self.config.run.value_error_every

    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        self.train_state, self.metrics, _ = self.learner.update(self.train_state, self.levels,
                                                                key)
        return True

    def host_metrics(self) -> dict[str, Any]:
        return dict(jax.device_get(self.metrics))

    def log(self, metrics: dict[str, Any], report: Report) -> None:
        metrics.update(report.timing)
        report.show(metrics, self.train_state)

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if due:
            log_value_error(self.config, self.learner, self.train_state.params, output.writer,
                            done)

    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        return self.train_state, done


class SeedsRunner(MARLRunner):
    """A plain MARL run of a config with `seeds`: every seed's learner in one compiled program
    (`PPOLearner.update_seeds`, the update vmapped over seeds), on the same levels. The train
    states and the key chains are stacked on a leading seed axis; each seed logs to its own
    `RUN_DIR/seed-<s>/`."""

    @property
    def env_steps(self) -> int:
        # Throughput and the progress line count the env steps of all seeds; each seed's
        # events have its own steps on the x axis, as a single-seed run's.
        return self.config.learner.steps_per_update * len(self.config.seeds)

    def first_key(self) -> jax.Array:
        return seed_keys(self.config.seeds)

    def split_key(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        return split_seed_keys(key)

    def event_dirs(self, run_dir: Path) -> list[Path]:
        return [seed_dir(run_dir, seed) for seed in self.config.seeds]

    def init(self, key: jax.Array) -> None:
        self.train_state = self.learner.init_seeds(key)

    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        self.train_state, self.metrics, _ = self.learner.update_seeds(self.train_state,
                                                                      self.levels, key)
        return True

    def host_metrics(self) -> dict[str, Any]:
        return {k: np.asarray(v) for k, v in jax.device_get(self.metrics).items()}

    def log(self, per_seed: dict[str, Any], report: Report) -> None:
        steps = report.done * self.config.learner.steps_per_update
        for i, writer in enumerate(report.output.writers):
            writer.scalars(logged_scalars(
                {**{k: v[i] for k, v in per_seed.items()}, **report.timing}, report.rate),
                step=steps)
        mean = {k: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
                for k, v in per_seed.items()}
        report.show({**mean, **report.timing}, self.train_state, writer=False)

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if not due:
            return
        for i, (seed, writer) in enumerate(zip(self.config.seeds, output.writers,
                                               strict=True)):
            params = jax.tree.map(lambda x, i=i: x[i], self.train_state.params)
            log_value_error(self.config, self.learner, params, writer, done, seed)


def train_marl(config: TrainConfig, run_dir: Path, *, resume: bool = False,
               max_updates: int | None = None, progress: bool = True,
               stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the plain MARL run of `config` in `run_dir` (which holds its
    config.yaml): one learner on the config's scenarios; several seeds in one program when
    the config lists `seeds` (`train_marl_seeds`)."""
    if config.seeds:
        return train_marl_seeds(config, run_dir, resume=resume, max_updates=max_updates,
                                progress=progress, stream=stream, callback=callback)
    return train_loop(MARLRunner(config), run_dir, resume=resume, max_updates=max_updates,
                      progress=progress, stream=sys.stderr if stream is None else stream,
                      callback=callback)


def train_marl_seeds(config: TrainConfig, run_dir: Path, *, resume: bool = False,
                     max_updates: int | None = None, progress: bool = True,
                     stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """`train_marl` of a config with `seeds`: every seed's learner trains in one compiled
    program (`PPOLearner.update_seeds`, the update vmapped over seeds), on the same levels.

    The train states and the key chains are stacked on a leading seed axis; seed i's chain
    is a single-seed run's, from `jax.random.key(seeds[i])`, so seed s of a multi-seed run
    trains as a run with `seed: s` does (to float rounding: batched matrix products may sum
    in another order). A checkpoint holds the stacked state and keys: `--resume` continues
    every seed. Each seed logs to its own `RUN_DIR/seed-<s>/` (TensorBoard events, the same
    tags as a single-seed run); the progress line and `callback` see the mean over seeds
    (`callback` gets the stacked train states)."""
    return train_loop(SeedsRunner(config), run_dir, resume=resume, max_updates=max_updates,
                      progress=progress, stream=sys.stderr if stream is None else stream,
                      callback=callback)


def log_value_error(config: TrainConfig, learner: PPOLearner, params: Any,
                    writer: SummaryWriter, done: int, seed: int | None = None) -> None:
    """`value_error/<scenario>/{mean_abs_error,ci95,mc_stderr}` of every scenario of the
    config after update `done` (`run.value_error_*`; rollouts of `learner.num_steps`). Its
    keys derive from the seed (`seed`, default the config's) and the update, never from the
    training key chain, so logging it does not change the run."""
    from ued.value_error import value_error

    _, levels = scenario_levels(config)
    seed = config.seed if seed is None else seed
    base = jax.random.fold_in(jax.random.key(seed), done)
    for index, (name, level) in enumerate(zip(config.env.scenario, levels, strict=True)):
        result = value_error(learner, params, learner.prepare_levels(level),
                             jax.random.fold_in(base, index), config.run.value_error_states,
                             config.run.value_error_rollouts, config.learner.num_steps,
                             scenario=name).summary()
        tag = f"value_error/{Path(name).stem}"
        writer.scalars({f"{tag}/mean_abs_error": result["mean_abs_error"],
                        f"{tag}/ci95": result["ci95"],
                        f"{tag}/mc_stderr": result["mean_mc_stderr"]},
                       step=done * config.learner.steps_per_update)


class UEDRunner(Runner):
    """A UED run with every worker in this process (`UEDRun.local`)."""

    snapshots = True
    explores = True

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        self.run, self.ppo = UEDRun.local(config)
        self.learner: LearnerWorker | None = None
        self.train_state: Any = None
        self.version = 0
        self.metrics: dict[str, Any] = {}
        self.levels: Any = None

    @property
    def eval_every(self) -> int:
        return self.config.ued.eval_every if self.run.evaluators else 0

    def needs_buffer(self) -> bool:
        return self.run.service.buffer is not None

    def init(self, key: jax.Array) -> None:
        self.train_state = self.ppo.init(key)

    def template(self) -> Any:
        return self.train_state

    def restore(self, run_dir: Path, train_state: Any, start: int) -> str | None:
        self.train_state = train_state
        self.version, note = self.run.resume(run_dir, start)
        return note

    def begin(self, start: int) -> None:
        self.learner = LearnerWorker(self.ppo, self.train_state, self.version)

    def headline(self, run_dir: Path, start: int) -> str:
        config = self.config
        return (f"{config.ued.method} + {config.algorithm} on "
                f"{', '.join(config.env.scenario)} (free: {', '.join(config.levels.free)}; "
                f"{config.env.team} vs {config.env.opponent}) in {run_dir}; "
                f"{config.learner.num_updates} steps of {config.learner.steps_per_update:,} "
                f"env steps{f', from step {start}' if start else ''}")

    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        branch, self.metrics, self.levels = self.run.step(self.learner, index, key)
        # Restored on resume: the progress line counts the whole run.
        self.run.branch_counts[branch] += 1
        return self.run.curriculum.learns(branch)

    def host_metrics(self) -> dict[str, Any]:
        return dict(jax.device_get(self.metrics))

    def log(self, metrics: dict[str, Any], report: Report) -> None:
        run = self.run
        metrics.update(report.timing)
        metrics.update(run.logged_metrics(self.levels))
        report.show(metrics, self.learner.train_state,
                    extra=branch_text(run.branch_counts, run.service.buffer_size()))

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if due:
            self.run.evaluate(self.learner, output.writer, done, output.notes)

    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        self.run.save(run_dir, done, self.learner)
        return self.learner.train_state, self.learner.version


def train_ued(config: TrainConfig, run_dir: Path, *, resume: bool = False,
              max_updates: int | None = None, progress: bool = True,
              stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the UED run of `config` in `run_dir` (which holds its config.yaml).
    `max_updates` stops after that many steps in this call; `callback(step, train_state,
    metrics)` runs after every logged step with host metrics."""
    return train_loop(UEDRunner(config), run_dir, resume=resume, max_updates=max_updates,
                      progress=progress, stream=sys.stderr if stream is None else stream,
                      callback=callback)


__all__ = ["LocalDriver", "MARLRunner", "SeedsRunner", "UEDRunner", "train_marl",
           "train_marl_seeds", "train_ued"]
