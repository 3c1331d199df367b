"""The local driver: every worker of a run in this process, one step after another.

`LocalDriver.run` trains a plain MARL run (one learner on the config's fixed scenarios) or a
UED run (`ued.method` set). A UED step:

    branch = curriculum.next_branch(buffer)        DR: NEW; PLR/Robust PLR: NEW or REPLAY;
                                                   ACCEL: ... REPLAY then MUTATE; SFL: SFL
    NEW     levels = service.fresh()      -> Learner.train (PLR, DR) or Explorer (Robust PLR,
                                             ACCEL) -> scores -> service.insert
    REPLAY  replay = service.replay()     -> Learner.train -> scores -> service.update
    MUTATE  children = mutate(last replay)-> Explorer -> scores -> service.insert (MUTATION)
    SFL     [every sfl_update_freq steps: score sfl_num_batches x sfl_batch_size fresh levels
             by learnability with the Explorer, keep the top sfl_top_k]
            levels = fresh half + learnable half -> Learner.train

This is sequential PLR / Robust PLR / ACCEL exactly as the papers (and JaxUED) define them.
A UED run folder adds `levels/` to a plain run's (`ued.run_folder`): snapshots, one per
checkpoint, of the level buffer (`tabx buffer inspect RUN_DIR/levels/buffer-N.msgpack`), SFL's
learnable set and the curriculum state. A snapshot is written before the orbax checkpoint of
the same step, so every checkpoint has one, and `--resume` continues exactly: the resumed run's
parameters and buffer equal an uninterrupted run's.

A plain run's loop is `key, k = split(key); train_state, metrics, _ = learner.update(
train_state, levels, k)`; a checkpoint stores the train state and the key after an update, so
a resumed run's parameters equal an uninterrupted run's bit for bit. Updates run back to back
on the device; metrics come back to the host only every `run.log_every` updates.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, TextIO

import jax
import jax.numpy as jnp
import numpy as np

from level_buffer import Source
from tabx import constants as C
from tabx.params import EnvParams, stack_levels
from ued.config import ConfigError, TrainConfig
from ued.curricula import SFL, Branch, Curriculum, make_curriculum
from ued.experiment import learner_for, scenario_levels, training_levels
from ued.learners.ppo import PPOLearner
from ued.levels import LevelGenerator
from ued.progress import Progress, ThroughputClock, log_update
from ued.run_folder import EVENTS_DIR, LEVELS_DIR, open_checkpoints
from ued.scores import learnability
from ued.suites import load_suite
from ued.tensorboard import SummaryWriter
from workers.driver import Callback, Driver
from workers.evaluator import Evaluator
from workers.explorer import Explorer, scores_of
from workers.learner import Learner
from workers.level_service import LevelService, to_device, to_host


class UEDRun:
    """The workers of one UED run, wired for local (single-process) use."""

    def __init__(self, config: TrainConfig):
        self.config = config
        env_config, base_levels = scenario_levels(config)
        self.env_config = env_config
        self.learner: PPOLearner = learner_for(config, env_config)
        # The base levels carry the opponent's tier, so generated levels start from it.
        base = self.learner.prepare_levels(jax.tree.map(jnp.asarray, stack_levels(base_levels)))
        self.generator = LevelGenerator(env_config, base, config.levels)
        ued = config.ued
        self.curriculum: Curriculum = make_curriculum(ued.method, ued.exploratory_grad_updates,
                                                      ued.sfl_update_freq)
        template = jax.tree.map(lambda x: np.asarray(x)[0], base)
        self.service = LevelService(self.generator, template, ued, seed=config.seed,
                                    use_buffer=self.curriculum.uses_buffer)
        self.explorer = Explorer(self.learner, ued.score)
        self.evaluators = self._evaluators()
        self.sfl_scoring_steps = 0

    def _evaluators(self) -> list[Evaluator]:
        if not self.config.ued.eval_suites:
            return []
        episodes = self.config.ued.eval_episodes or None
        return [Evaluator(self.learner, load_suite(name), episodes=episodes)
                for name in self.config.ued.eval_suites]

    # --- one step ----------------------------------------------------------------------------

    def step(self, learner: Learner, step: int, key: jax.Array
             ) -> tuple[Branch, dict[str, Any], EnvParams]:
        """Run one curriculum step; returns its branch, its metrics (device values) and the
        levels it played."""
        n = self.config.learner.num_envs
        k_levels, k_roll, k_edit = jax.random.split(key, 3)
        service, curriculum = self.service, self.curriculum
        branch = curriculum.next_branch(service.buffer)
        learns = curriculum.learns(branch)
        version = learner.version  # the policy that plays (and so scores) this step's levels
        replay_ids = None
        if branch == Branch.NEW:
            levels = service.fresh(k_levels, n)
            metrics, stats = self._play(learner, levels, k_roll, learns)
            if service.buffer is not None:
                scores, best = scores_of(stats, self.config.ued.score)
                service.insert(levels, scores, best, version, Source.RANDOM)
        elif branch == Branch.REPLAY:
            replay = service.replay(n)
            levels = to_device(replay.levels)
            metrics, stats = self._play(learner, levels, k_roll, True)
            scores, best = scores_of(stats, self.config.ued.score, replay.max_returns)
            service.update(replay.ids, scores, best, version)
            replay_ids = replay.ids
        elif branch == Branch.MUTATE:
            parent_ids = np.asarray(curriculum.last_replay_ids, np.int64)
            levels = service.mutate(k_edit, service.get(parent_ids))
            metrics, stats = self._play(learner, levels, k_roll, learns)
            scores, best = scores_of(stats, self.config.ued.score)
            service.insert(levels, scores, best, version, Source.MUTATION,
                           parent_ids=parent_ids)
        elif branch == Branch.SFL:
            assert isinstance(curriculum, SFL)
            if curriculum.needs_refresh(step) or service.learnable is None:
                self.refresh_learnable(learner, k_edit)
            levels = self.sfl_batch(k_levels, n)
            metrics, stats = self._play(learner, levels, k_roll, True)
        else:  # pragma: no cover - Branch is closed
            raise AssertionError(branch)
        curriculum.observe(branch, replay_ids)
        metrics = dict(metrics)
        metrics["ued/branch"] = float(branch)
        metrics["ued/grad_step"] = float(learns)
        metrics["ued/policy_version"] = float(learner.version)
        return branch, metrics, levels

    def _play(self, learner: Learner, levels: EnvParams, key: jax.Array, learns: bool):
        if learns:
            return learner.train(levels, key)
        return self.explorer.rollout(learner.params, levels, key)

    def sfl_batch(self, key: jax.Array, n: int) -> EnvParams:
        """SFL's training batch: fresh random levels and levels of the learnable set."""
        k_fresh, k_pick = jax.random.split(key)
        n_fresh = int(round(n * self.config.ued.sfl_fresh_fraction))
        parts = []
        if n_fresh:
            parts.append(to_device(self.service.fresh(k_fresh, n_fresh)))
        if n - n_fresh:
            parts.append(to_device(self.service.sample_learnable(k_pick, n - n_fresh)))
        if len(parts) == 1:
            return parts[0]
        return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), *parts)

    def refresh_learnable(self, learner: Learner, key: jax.Array) -> None:
        """Score sfl_num_batches x sfl_batch_size fresh levels by learnability p (1 - p) under
        the current policy; keep the sfl_top_k most learnable."""
        ued = self.config.ued
        levels_all, scores_all = [], []
        for b in range(ued.sfl_num_batches):
            k_levels, k_roll = jax.random.split(jax.random.fold_in(key, b))
            levels = self.service.fresh(k_levels, ued.sfl_batch_size)
            _, stats = self.explorer.rollout(learner.params, levels, k_roll,
                                             ued.sfl_rollout_steps)
            levels_all.append(to_host(levels))
            scores_all.append(np.asarray(learnability(stats.wins, stats.dones), np.float64))
            self.sfl_scoring_steps += ued.sfl_batch_size * ued.sfl_rollout_steps
        levels = jax.tree.map(lambda *xs: np.concatenate(xs), *levels_all)
        self.service.set_learnable(levels, np.concatenate(scores_all), ued.sfl_top_k)

    # --- state -------------------------------------------------------------------------------

    def state(self, learner: Learner) -> dict[str, Any]:
        return {"curriculum": self.curriculum.state_dict(), "version": learner.version,
                "sfl_scoring_steps": self.sfl_scoring_steps}

    def load_state(self, state: dict[str, Any]) -> int:
        self.curriculum.load_state_dict(state["curriculum"])
        self.sfl_scoring_steps = int(state.get("sfl_scoring_steps", 0))
        return int(state["version"])


def level_summary(levels: EnvParams) -> dict[str, float]:
    """What the curriculum is serving: mean unit stats over real units, zones per level by
    type, the opponent's heuristic parameters (TensorBoard `levels/...`)."""
    u = jax.tree.map(np.asarray, levels.units)
    active = u.active.astype(bool)
    out: dict[str, float] = {}
    if active.any():
        out["levels/unit_max_health"] = float(u.max_health[active].mean())
        out["levels/unit_speed"] = float(u.speed[active].mean())
        out["levels/unit_damage_abs"] = float(np.abs(u.damage[active]).mean())
    zone_type = np.asarray(levels.zones.zone_type)
    for code in (C.ZONE_LAVA, C.ZONE_BUSH, C.ZONE_SWAMP):
        out[f"levels/zones_{C.ZONE_NAMES[code]}"] = float((zone_type == code).sum(-1).mean())
    h = levels.heuristic
    out["levels/enemy_epsilon"] = float(np.asarray(h.epsilon)[..., C.ENEMY].mean())
    out["levels/enemy_aggressive_threshold"] = float(
        np.asarray(h.aggressive_threshold)[..., C.ENEMY].mean())
    return out


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


def train_marl(config: TrainConfig, run_dir: Path, *, resume: bool = False,
               max_updates: int | None = None, progress: bool = True,
               stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the plain MARL run of `config` in `run_dir` (which holds its
    config.yaml): one learner on the config's scenarios."""
    stream = sys.stderr if stream is None else stream
    env_config, levels = training_levels(config)
    learner = learner_for(config, env_config)
    ppo = config.learner
    num_updates = ppo.num_updates
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    train_state = learner.init(k_init)
    start = 0
    checkpoints = open_checkpoints(run_dir, config)
    if resume and checkpoints.latest() is not None:
        train_state, key, start = checkpoints.restore(train_state)
    stop = num_updates if max_updates is None else min(num_updates, start + max_updates)
    bar = Progress(num_updates, stream) if progress else None
    if progress:
        what = "resuming" if resume else "training"
        stream.write(f"{what} {config.algorithm} on {', '.join(config.env.scenario)} "
                     f"({config.env.team} vs {config.env.opponent}) in {run_dir}; "
                     f"{num_updates} updates of {ppo.steps_per_update:,} steps"
                     f"{f', from update {start}' if start else ''}\n")
        stream.flush()

    writer = SummaryWriter(run_dir / EVENTS_DIR)
    try:
        clock = ThroughputClock(start, ppo.steps_per_update)
        for update in range(start, stop):
            key, k_update = jax.random.split(key)
            train_state, metrics, _ = learner.update(train_state, levels, k_update)
            done = update + 1
            last = done == stop
            if clock.first_pending or done % config.run.log_every == 0 or last:
                metrics = dict(jax.device_get(metrics))  # waits for the update
                timing, rate = clock.read(done)
                metrics.update(timing)
                log_update(writer, bar, callback, done, train_state, metrics,
                           ppo.steps_per_update, rate, num_updates, last)
            if done % config.run.checkpoint_every == 0 or last:
                checkpoints.save(done, train_state, key)
    finally:
        writer.close()
        checkpoints.close()
    return run_dir


def train_ued(config: TrainConfig, run_dir: Path, *, resume: bool = False,
              max_updates: int | None = None, progress: bool = True,
              stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the UED run of `config` in `run_dir` (which holds its config.yaml).
    `max_updates` stops after that many steps in this call; `callback(step, train_state,
    metrics)` runs after every logged step with host metrics."""
    stream = sys.stderr if stream is None else stream
    run = UEDRun(config)
    ppo = config.learner
    total = ppo.num_updates
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    train_state = run.learner.init(k_init)
    start, version = 0, 0
    levels_dir = run_dir / LEVELS_DIR
    checkpoints = open_checkpoints(run_dir, config)
    if resume and checkpoints.latest() is not None:
        train_state, key, start = checkpoints.restore(train_state)
        try:
            version = run.load_state(run.service.load(levels_dir, start))
        except FileNotFoundError as err:
            raise ConfigError(f"{run_dir}: cannot resume: {err}") from None
    learner = Learner(run.learner, train_state, version)
    stop = total if max_updates is None else min(total, start + max_updates)
    bar = Progress(total, stream) if progress else None
    if progress:
        what = "resuming" if resume else "training"
        stream.write(f"{what} {config.ued.method} + {config.algorithm} on "
                     f"{', '.join(config.env.scenario)} (free: {', '.join(config.levels.free)}; "
                     f"{config.env.team} vs {config.env.opponent}) in {run_dir}; {total} steps "
                     f"of {ppo.steps_per_update:,} env steps"
                     f"{f', from step {start}' if start else ''}\n")
        stream.flush()

    writer = SummaryWriter(run_dir / EVENTS_DIR)
    counts = {b: 0 for b in Branch}
    try:
        clock = ThroughputClock(start, ppo.steps_per_update)
        for step in range(start, stop):
            key, k_step = jax.random.split(key)
            branch, metrics, levels = run.step(learner, step, k_step)
            counts[branch] += 1
            done = step + 1
            last = done == stop
            if clock.first_pending or done % config.run.log_every == 0 or last:
                metrics = dict(jax.device_get(metrics))  # waits for the step
                timing, rate = clock.read(done)
                metrics.update(timing)
                metrics.update(run.service.stats())
                metrics.update(level_summary(levels))
                if run.sfl_scoring_steps:
                    metrics["sfl/scoring_env_steps"] = float(run.sfl_scoring_steps)
                log_update(writer, bar, callback, done, learner.train_state, metrics,
                           ppo.steps_per_update, rate, total, last,
                           extra=_branch_text(counts, run.service))
            if run.evaluators and (done % config.ued.eval_every == 0 or last):
                _evaluate(run, learner, writer, done, config, stream if progress else None)
            if done % config.run.checkpoint_every == 0 or last:
                # The level snapshot first: a checkpoint without one cannot be resumed.
                run.service.save(levels_dir, done, run.state(learner),
                                 keep=config.run.keep_checkpoints)
                checkpoints.save(done, learner.train_state, key)
    finally:
        writer.close()
        checkpoints.close()
    return run_dir


def _branch_text(counts: dict[Branch, int], service: LevelService) -> str:
    parts = [f"{b.name.lower()} {n}" for b, n in counts.items() if n]
    if service.buffer is not None:
        parts.append(f"buffer {len(service.buffer)}")
    return ", ".join(parts)


def _evaluate(run: UEDRun, learner: Learner, writer: SummaryWriter, done: int,
              config: TrainConfig, stream: TextIO | None) -> None:
    key = jax.random.fold_in(jax.random.key(config.seed ^ 0x5EED), done)
    for i, evaluator in enumerate(run.evaluators):
        result = evaluator.evaluate(learner.params, jax.random.fold_in(key, i))
        evaluator.log(writer, done * config.learner.steps_per_update, result)
        if stream is not None:
            stream.write(f"  eval {evaluator.suite.name} after step {done}: mean win rate "
                         f"{result.mean_win_rate:.2f}\n")
            stream.flush()


__all__ = ["LocalDriver", "UEDRun", "level_summary", "train_marl", "train_ued"]
