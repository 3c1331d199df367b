"""The local driver: every worker of a run in this process, one step after another.

`LocalDriver.run` trains a plain MARL run (one learner on the config's fixed scenarios) or a
UED run (`ued.method` set). A UED step:

    branch = curriculum.next_branch(buffer)        DR: NEW; PLR/Robust PLR: NEW or REPLAY;
                                                   ACCEL: ... REPLAY then MUTATE; SFL: SFL
    NEW     levels = service.fresh()      -> LearnerWorker.train (PLR, DR) or Explorer (Robust PLR,
                                             ACCEL) -> scores -> service.insert
    REPLAY  replay = service.replay()     -> LearnerWorker.train -> scores -> service.update
    MUTATE  children = mutate(last replay)-> Explorer -> scores -> service.insert (MUTATION)
    SFL     [every sfl_update_freq steps: score sfl_num_batches x sfl_batch_size fresh levels
             by learnability with the Explorer, keep the top sfl_top_k]
            levels = fresh half + learnable half -> LearnerWorker.train

This is sequential PLR / Robust PLR / ACCEL exactly as the papers (and JaxUED) define them.
A UED run folder adds `levels/` to a plain run's (`ued.run_folder`): snapshots, one per
checkpoint, of the level buffer (`tabx buffer inspect RUN_DIR/levels/buffer-N.msgpack`), SFL's
learnable set and the curriculum state. A snapshot is written before the orbax checkpoint of
the same step, so every checkpoint has one, and `--resume` continues exactly: the resumed run's
parameters and buffer equal an uninterrupted run's.

A plain run's loop is `key, k = split(key); train_state, metrics, _ = learner.update(
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
import jax.numpy as jnp
import numpy as np

from level_buffer import Source
from tabx import constants as C
from tabx.params import EnvParams, stack_levels
from ued.config import ConfigError, TrainConfig
from ued.curricula import SFL, Branch, Curriculum
from ued.experiment import learner_for, scenario_levels, seed_keys, split_seed_keys, training_levels
from ued.learners.ppo import PPOLearner
from ued.levels import LevelGenerator
from ued.progress import Progress, ThroughputClock, log_update, logged_scalars
from ued.registry import curriculum_entry, curriculum_for
from ued.run_folder import EVENTS_DIR, LEVELS_DIR, checkpoint_metadata, open_checkpoints, seed_dir
from ued.suites import load_suite
from ued.tensorboard import SummaryWriter
from workers.driver import Callback, Driver
from workers.evaluator import Evaluator
from workers.explorer import Explorer
from workers.learner import LearnerWorker
from workers.level_service import LevelService, to_device, to_host
from workers.resume import restore_intact, state_problem


def level_service_for(config: TrainConfig, learner: PPOLearner) -> LevelService:
    """The LevelService of a UED config: its generator starts from the config's scenarios,
    prepared by `learner` (so the opponent's tier is written into them)."""
    env_config, base_levels = scenario_levels(config)
    # The base levels carry the opponent's tier, so generated levels start from it.
    base = learner.prepare_levels(jax.tree.map(jnp.asarray, stack_levels(base_levels)))
    generator = LevelGenerator(env_config, base, config.levels)
    ued = config.ued
    template = jax.tree.map(lambda x: np.asarray(x)[0], base)
    return LevelService(generator, template, ued, seed=config.seed,
                        use_buffer=curriculum_entry(ued.method).uses_buffer)


def evaluators_for(config: TrainConfig, learner: PPOLearner) -> list[Evaluator]:
    """One Evaluator per zero-shot suite of `ued.eval_suites`."""
    episodes = config.ued.eval_episodes or None
    return [Evaluator(learner, load_suite(name), episodes=episodes, profile=config.env.profile)
            for name in config.ued.eval_suites]


def local_workers(config: TrainConfig) -> tuple[PPOLearner, LevelService, Explorer,
                                               list[Evaluator]]:
    """The learner, LevelService, Explorer and Evaluators of a UED config, built in this
    process."""
    learner = learner_for(config, scenario_levels(config)[0])
    return (learner, level_service_for(config, learner), Explorer(learner, config.ued.score),
            evaluators_for(config, learner))


class UEDRun:
    """One UED run's step logic over its workers: the curriculum decides, the LevelService
    hands out and takes back levels, the LearnerWorker trains, the Explorer scores. The workers are
    the local classes (the local driver) or stand-ins with the same methods that call Ray
    actors (the Ray driver), so both drivers take every decision the same way."""

    def __init__(self, config: TrainConfig, service: Any, explorer: Any,
                 evaluators: list[Any] = ()):
        self.config = config
        ued = config.ued
        self.curriculum: Curriculum = curriculum_for(ued)
        self.service, self.explorer, self.evaluators = service, explorer, list(evaluators)
        self.sfl_scoring_steps = 0
        self.branch_counts = {b: 0 for b in Branch}  # steps of each kind, over the whole run

    @classmethod
    def local(cls, config: TrainConfig) -> tuple[UEDRun, PPOLearner]:
        """A run over workers built in this process, and its learner (to init or restore the
        train state that a `workers.learner.LearnerWorker` holds)."""
        ppo_learner, service, explorer, evaluators = local_workers(config)
        return cls(config, service, explorer, evaluators), ppo_learner

    # --- one step ----------------------------------------------------------------------------

    def step(self, learner: LearnerWorker, step: int, key: jax.Array
             ) -> tuple[Branch, dict[str, Any], EnvParams]:
        """Run one curriculum step; returns its branch, its metrics (device values) and the
        levels it played."""
        keys = jax.random.split(key, 3)  # levels, rollout, edits
        curriculum = self.curriculum
        branch = self.next_branch()
        learns = curriculum.learns(branch)
        replay_ids = None
        if learns:
            metrics, levels, replay_ids = self.learning_step(learner, branch, step, keys)
        else:
            metrics, levels = self.exploring_step(learner, branch, keys)
        curriculum.observe(branch, replay_ids)
        return branch, self.step_metrics(metrics, branch, learns, learner.version), levels

    def next_branch(self) -> Branch:
        return self.curriculum.next_branch(self.service if self.curriculum.uses_buffer
                                           else None)

    @staticmethod
    def step_metrics(metrics: dict[str, Any], branch: Branch, learns: bool, version: int
                     ) -> dict[str, Any]:
        metrics = dict(metrics)
        metrics["ued/branch"] = float(branch)
        metrics["ued/grad_step"] = float(learns)
        metrics["ued/policy_version"] = float(version)
        return metrics

    def learning_step(self, learner: LearnerWorker, branch: Branch, step: int, keys: jax.Array
                      ) -> tuple[dict[str, Any], EnvParams, np.ndarray | None]:
        """A step that trains the policy: (metrics, levels played, replayed ids or None)."""
        k_levels, k_roll, k_edit = keys
        n, score = self.config.learner.num_envs, self.config.ued.score
        service = self.service
        version = learner.version  # the policy that plays (and so scores) this step's levels
        if branch == Branch.REPLAY:
            replay = service.replay(n)
            levels = to_device(replay.levels)
            metrics, scores, best = learner.train_scored(levels, k_roll, score,
                                                         replay.max_returns)
            service.update(replay.ids, scores, best, version)
            return metrics, levels, replay.ids
        if branch == Branch.SFL:
            assert isinstance(self.curriculum, SFL)
            if self.curriculum.needs_refresh(step) or not service.has_learnable():
                self.refresh_learnable(learner, k_edit)
            levels = self.sfl_batch(k_levels, n)
            metrics, _ = learner.train(levels, k_roll)
            return metrics, levels, None
        # NEW (DR; PLR's exploratory gradient updates) or MUTATE with gradient updates.
        levels, source, parent_ids = self.new_levels(branch, k_levels, k_edit)
        if self.curriculum.uses_buffer:
            metrics, scores, best = learner.train_scored(levels, k_roll, score)
            service.insert(levels, scores, best, version, source, parent_ids=parent_ids)
        else:
            metrics, _ = learner.train(levels, k_roll)
        return metrics, levels, None

    def exploring_step(self, learner: LearnerWorker, branch: Branch, keys: jax.Array
                       ) -> tuple[dict[str, Any], EnvParams]:
        """A step that only scores new or mutated levels (Robust PLR, ACCEL) and offers them to
        the buffer: (episode metrics, levels played)."""
        k_levels, k_roll, k_edit = keys
        version = learner.version
        levels, source, parent_ids = self.new_levels(branch, k_levels, k_edit)
        metrics, scores, best = self.explorer.score_levels(learner.params, levels, k_roll,
                                                           self.config.ued.score)
        self.service.insert(levels, scores, best, version, source, parent_ids=parent_ids)
        return metrics, levels

    def new_levels(self, branch: Branch, k_levels: jax.Array, k_edit: jax.Array
                   ) -> tuple[EnvParams, Source, Any]:
        """Fresh levels (NEW) or ACCEL children of the last replay batch (MUTATE), with their
        buffer source and parent ids."""
        if branch == Branch.NEW:
            return self.service.fresh(k_levels, self.config.learner.num_envs), Source.RANDOM, -1
        assert branch == Branch.MUTATE, branch
        parent_ids = np.asarray(self.curriculum.last_replay_ids, np.int64)
        return self.service.mutate_ids(k_edit, parent_ids), Source.MUTATION, parent_ids

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

    def refresh_learnable(self, learner: LearnerWorker, key: jax.Array) -> None:
        """Score sfl_num_batches x sfl_batch_size fresh levels by learnability p (1 - p) under
        the current policy; keep the sfl_top_k most learnable."""
        ued = self.config.ued
        batches = []
        for b in range(ued.sfl_num_batches):
            k_levels, k_roll = jax.random.split(jax.random.fold_in(key, b))
            batches.append((self.service.fresh(k_levels, ued.sfl_batch_size), k_roll))
        scores_all = self.explorer.learnability_batches(learner.params, batches,
                                                        ued.sfl_rollout_steps)
        self.sfl_scoring_steps += ued.sfl_num_batches * ued.sfl_batch_size * ued.sfl_rollout_steps
        levels = jax.tree.map(lambda *xs: np.concatenate(xs),
                              *(to_host(levels) for levels, _ in batches))
        self.service.set_learnable(levels, np.concatenate(scores_all), ued.sfl_top_k)

    # --- evaluation --------------------------------------------------------------------------

    def evaluate(self, learner: LearnerWorker, writer: SummaryWriter, done: int,
                 stream: TextIO | None) -> None:
        """Every evaluation suite on the current policy, logged at step `done`."""
        config = self.config
        key = jax.random.fold_in(jax.random.key(config.seed ^ 0x5EED), done)
        for i, evaluator in enumerate(self.evaluators):
            result = evaluator.evaluate(learner.params, jax.random.fold_in(key, i))
            evaluator.log(writer, done * config.learner.steps_per_update, result)
            if stream is not None:
                stream.write(f"  eval {evaluator.suite.name} after step {done}: mean win rate "
                             f"{result.mean_win_rate:.2f}\n")
                stream.flush()

    # --- state -------------------------------------------------------------------------------

    def state(self, learner: LearnerWorker) -> dict[str, Any]:
        return {"curriculum": self.curriculum.state_dict(), "version": learner.version,
                "sfl_scoring_steps": self.sfl_scoring_steps,
                "branch_counts": {b.name.lower(): n for b, n in self.branch_counts.items()}}

    def load_state(self, state: dict[str, Any]) -> int:
        """Continue from a snapshot's state (`state`); the policy version it was taken at.
        ConfigError when the state does not fit this run (another curriculum's, damaged)."""
        problem = state_problem(state)
        if problem is None and state["curriculum"]["method"] != self.curriculum.name:
            problem = (f"curriculum.method: {state['curriculum']['method']!r:.40}, but this "
                       f"run's is {self.curriculum.name!r}")
        if problem is not None:
            raise ConfigError(f"level snapshot state: {problem}")
        self.curriculum.load_state_dict(state["curriculum"])
        self.sfl_scoring_steps = int(state.get("sfl_scoring_steps", 0))
        counts = state.get("branch_counts", {})  # absent from older snapshots: start at 0
        self.branch_counts = {b: int(counts.get(b.name.lower(), 0)) for b in Branch}
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


def start_marl(config: TrainConfig, run_dir: Path, checkpoints: Any, train_state: Any,
               key: jax.Array, *, resume: bool, max_updates: int | None, progress: bool,
               stream: TextIO) -> tuple[Any, jax.Array, int, int, Progress | None]:
    """Where a plain MARL run starts: with `resume`, the newest intact checkpoint's train
    state and key (shaped as `train_state` and `key`: a multi-seed run's are stacked), else
    those given; and the line saying what trains on what. (train state, key, first update,
    update to stop after, progress bar or None)."""
    start = 0
    restored = (restore_intact(run_dir, checkpoints, train_state, snapshots=False,
                               needs_buffer=False, stream=stream, key_template=key)
                if resume else None)
    if restored is not None:
        checkpoints.reload()
        train_state, key, start = restored
    num_updates = config.learner.num_updates
    stop = num_updates if max_updates is None else min(num_updates, start + max_updates)
    bar = Progress(num_updates, stream) if progress else None
    if progress:
        what = "resuming" if resume else "training"
        seeds = (f", seeds {', '.join(map(str, config.seeds))} in one program" if config.seeds
                 else "")
        stream.write(f"{what} {config.algorithm} on {', '.join(config.env.scenario)} "
                     f"({config.env.team} vs {config.env.opponent}) in {run_dir}; "
                     f"{num_updates} updates of {config.learner.steps_per_update:,} steps"
                     f"{seeds}{f', from update {start}' if start else ''}\n")
        stream.flush()
    return train_state, key, start, stop, bar


def train_marl(config: TrainConfig, run_dir: Path, *, resume: bool = False,
               max_updates: int | None = None, progress: bool = True,
               stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the plain MARL run of `config` in `run_dir` (which holds its
    config.yaml): one learner on the config's scenarios; several seeds in one program when
    the config lists `seeds` (`train_marl_seeds`)."""
    stream = sys.stderr if stream is None else stream
    if config.seeds:
        return train_marl_seeds(config, run_dir, resume=resume, max_updates=max_updates,
                                progress=progress, stream=stream, callback=callback)
    env_config, levels = training_levels(config)
    learner = learner_for(config, env_config)
    ppo = config.learner
    num_updates = ppo.num_updates
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    train_state = learner.init(k_init)
    checkpoints = open_checkpoints(run_dir, config)
    train_state, key, start, stop, bar = start_marl(
        config, run_dir, checkpoints, train_state, key, resume=resume, max_updates=max_updates,
        progress=progress, stream=stream)

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
                           ppo.steps_per_update, rate, num_updates, last,
                           eta_steps_per_s=clock.eta_steps_per_s)
            every = config.run.value_error_every
            if every and (done % every == 0 or last):
                log_value_error(config, learner, train_state.params, writer, done)
            if done % config.run.checkpoint_every == 0 or last:
                checkpoints.save(done, train_state, key,
                                 checkpoint_metadata(config, done, policy_version=done))
    finally:
        writer.close()
        checkpoints.close()
    return run_dir


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
    stream = sys.stderr if stream is None else stream
    seeds = config.seeds
    env_config, levels = training_levels(config)
    learner = learner_for(config, env_config)
    ppo = config.learner
    num_updates = ppo.num_updates
    keys, init_keys = split_seed_keys(seed_keys(seeds))
    train_states = learner.init_seeds(init_keys)
    checkpoints = open_checkpoints(run_dir, config)
    train_states, keys, start, stop, bar = start_marl(
        config, run_dir, checkpoints, train_states, keys, resume=resume,
        max_updates=max_updates, progress=progress, stream=stream)

    writers = [SummaryWriter(seed_dir(run_dir, seed)) for seed in seeds]
    try:
        # Throughput and the progress line count the env steps of all seeds; each seed's
        # events have its own steps on the x axis, as a single-seed run's.
        all_steps = ppo.steps_per_update * len(seeds)
        clock = ThroughputClock(start, all_steps)
        for update in range(start, stop):
            keys, update_keys = split_seed_keys(keys)
            train_states, metrics, _ = learner.update_seeds(train_states, levels, update_keys)
            done = update + 1
            last = done == stop
            if clock.first_pending or done % config.run.log_every == 0 or last:
                per_seed = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
                timing, rate = clock.read(done)
                steps = done * ppo.steps_per_update
                for i, writer in enumerate(writers):
                    writer.scalars(logged_scalars(
                        {**{k: v[i] for k, v in per_seed.items()}, **timing}, rate), step=steps)
                mean = {k: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
                        for k, v in per_seed.items()}
                log_update(None, bar, callback, done, train_states, {**mean, **timing},
                           all_steps, rate, num_updates, last,
                           eta_steps_per_s=clock.eta_steps_per_s)
            every = config.run.value_error_every
            if every and (done % every == 0 or last):
                for i, (seed, writer) in enumerate(zip(seeds, writers, strict=True)):
                    params = jax.tree.map(lambda x, i=i: x[i], train_states.params)
                    log_value_error(config, learner, params, writer, done, seed)
            if done % config.run.checkpoint_every == 0 or last:
                checkpoints.save(done, train_states, keys,
                                 checkpoint_metadata(config, done, policy_version=done))
    finally:
        for writer in writers:
            writer.close()
        checkpoints.close()
    return run_dir


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


def train_ued(config: TrainConfig, run_dir: Path, *, resume: bool = False,
              max_updates: int | None = None, progress: bool = True,
              stream: TextIO | None = None, callback: Callback | None = None) -> Path:
    """Run (or continue) the UED run of `config` in `run_dir` (which holds its config.yaml).
    `max_updates` stops after that many steps in this call; `callback(step, train_state,
    metrics)` runs after every logged step with host metrics."""
    stream = sys.stderr if stream is None else stream
    run, ppo_learner = UEDRun.local(config)
    ppo = config.learner
    total = ppo.num_updates
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    train_state = ppo_learner.init(k_init)
    start, version = 0, 0
    levels_dir = run_dir / LEVELS_DIR
    checkpoints = open_checkpoints(run_dir, config)
    restored = (restore_intact(run_dir, checkpoints, train_state, snapshots=True,
                               needs_buffer=run.service.buffer is not None, stream=stream)
                if resume else None)
    if restored is not None:
        checkpoints.reload()
        train_state, key, start = restored
        try:
            version = run.load_state(run.service.load(levels_dir, start))
        except (FileNotFoundError, ConfigError) as err:
            raise ConfigError(f"{run_dir}: cannot resume from step {start}: {err}") from None
    learner = LearnerWorker(ppo_learner, train_state, version)
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
    counts = run.branch_counts  # restored on resume: the progress line counts the whole run
    try:
        clock = ThroughputClock(start, ppo.steps_per_update)
        trained = 0  # steps of this call that trained the policy (the clock's split)
        for step in range(start, stop):
            key, k_step = jax.random.split(key)
            branch, metrics, levels = run.step(learner, step, k_step)
            counts[branch] += 1
            trained += run.curriculum.learns(branch)
            done = step + 1
            last = done == stop
            if clock.first_pending or done % config.run.log_every == 0 or last:
                metrics = dict(jax.device_get(metrics))  # waits for the step
                timing, rate = clock.read(done, trained)
                metrics.update(timing)
                metrics.update(run.service.stats())
                metrics.update(level_summary(levels))
                if run.sfl_scoring_steps:
                    metrics["sfl/scoring_env_steps"] = float(run.sfl_scoring_steps)
                log_update(writer, bar, callback, done, learner.train_state, metrics,
                           ppo.steps_per_update, rate, total, last,
                           extra=branch_text(counts, run.service.buffer_size()),
                           eta_steps_per_s=clock.eta_steps_per_s)
            if run.evaluators and (done % config.ued.eval_every == 0 or last):
                run.evaluate(learner, writer, done, stream if progress else None)
            if done % config.run.checkpoint_every == 0 or last:
                # The level snapshot first: a checkpoint without one cannot be resumed.
                run.service.save(levels_dir, done, run.state(learner),
                                 keep=config.run.keep_checkpoints)
                checkpoints.save(done, learner.train_state, key,
                                 checkpoint_metadata(config, done, learner.version))
    finally:
        writer.close()
        checkpoints.close()
    return run_dir


def branch_text(counts: dict[Branch, int], buffer_size: int | None) -> str:
    """The progress line's account of a UED run: steps per branch, the buffer's size."""
    parts = [f"{b.name.lower()} {n}" for b, n in counts.items() if n]
    if buffer_size is not None:
        parts.append(f"buffer {buffer_size}")
    return ", ".join(parts)


__all__ = ["LocalDriver", "UEDRun", "branch_text", "evaluators_for", "level_service_for",
           "level_summary", "local_workers",
           "start_marl", "train_marl", "train_marl_seeds", "train_ued"]
