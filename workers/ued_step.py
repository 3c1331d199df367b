"""One UED curriculum step, the same on every driver: the curriculum's branch, what to ask the
level service for, what to play, what to commit.

    branch = curriculum.next_branch(buffer)        DR: NEW; PLR/Robust PLR: NEW or REPLAY;
                                                   ACCEL: ... REPLAY then MUTATE; SFL: SFL
    NEW     levels = service.fresh()      -> LearnerWorker.train (PLR, DR) or Explorer (Robust PLR,
                                             ACCEL) -> scores -> service.insert
    REPLAY  replay = service.replay()     -> LearnerWorker.train -> scores -> service.update
    MUTATE  children = service.mutate(the last replay batch's levels, as drawn)
                                          -> Explorer -> scores -> service.insert (MUTATION)
    SFL     [every sfl_update_freq steps: score sfl_num_batches x sfl_batch_size fresh levels
             by learnability with the Explorer, keep the top sfl_top_k]
            levels = fresh half + learnable half -> LearnerWorker.train

This is sequential PLR / Robust PLR / ACCEL exactly as the papers (and JaxUED) define them.
`UEDRun.step` runs them; every decision is the curriculum's, through its hooks
(`ued.curricula.base`): which branch, whether it learns, what new levels to ask for, how the
buffer draws replays and whether new levels it trains on are scored. Where and when the parts
run is its `Schedule`: by default all of it here and now (the local driver, and the Ray
driver's deterministic mode, whose workers are stand-ins that call Ray actors); the Ray
driver's asynchronous schedule hands the steps that only score levels to Explorers and commits
their results when they arrive. Its
continuous schedule (`workers.ray.continuous`) departs from these steps for Robust PLR, ACCEL and
SFL: Explorers score without pause (SFL: the learnable set is refreshed as scored batches come
in, not every sfl_update_freq steps).

A step that scores new or mutated levels asks the level service for them with the
curriculum's `LevelRequest`: the service call that makes them, and the source and parents the
buffer files them under when they are committed. ACCEL's children are made from the replayed levels
themselves, never looked up by id: on the asynchronous schedule Explorer results committed
between the replay step and the mutate step may evict a parent from the buffer. For the same
reason a snapshot taken between the two steps holds the parents as levels
(`parents-<step>.msgpack`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TextIO, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

from level_buffer import Replay
from level_buffer.fileformat import BufferFileError
from tabx import constants as C
from tabx.params import EnvParams, stack_levels
from ued.config import ConfigError, TrainConfig
from ued.curricula import Branch, Curriculum, LevelRequest
from ued.experiment import learner_for, scenario_levels
from ued.learners.ppo import PPOLearner
from ued.levels import LevelGenerator
from ued.registry import curriculum_for
from ued.run_folder import LEVELS_DIR
from ued.suites import load_suite
from ued.tensorboard import SummaryWriter
from workers.resume import state_problem
from workers.roles.evaluator import Evaluator
from workers.roles.explorer import Explorer
from workers.roles.learner import LearnerWorker
from workers.roles.level_service import LevelService, sfl_split, to_device, to_host

T = TypeVar("T")


def generator_for(config: TrainConfig, learner: PPOLearner) -> LevelGenerator:
    """The level generator of a UED config: it starts from the config's scenarios, prepared
    by `learner` (so the opponent's tier is written into them). A pure function of its key:
    the level service and an Explorer make the same levels from the same key."""
    env_config, base_levels = scenario_levels(config)
    # The base levels carry the opponent's tier, so generated levels start from it.
    base = learner.prepare_levels(jax.tree.map(jnp.asarray, stack_levels(base_levels)))
    return LevelGenerator(env_config, base, config.levels)


def level_service_for(config: TrainConfig, learner: PPOLearner) -> LevelService:
    """The LevelService of a UED config, with `generator_for`'s generator and the level buffer
    its curriculum asks for (`Curriculum.buffer_config`; none where it keeps none)."""
    generator = generator_for(config, learner)
    ued = config.ued
    template = jax.tree.map(lambda x: np.asarray(x)[0], generator.base_levels)
    return LevelService(generator, template, ued, seed=config.seed,
                        curriculum=curriculum_for(ued, config.curriculum_settings()))


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


class Schedule(Protocol):
    """Where and when the parts of a UED step run (`UEDRun.step`)."""

    def learn(self, step: int, train: Callable[[], T]) -> T:
        """Run step `step`'s learner part, `train()`, and return its result."""

    def explore(self, learner: Any, step: int, request: LevelRequest, key: jax.Array
                ) -> tuple[dict[str, Any] | None, EnvParams | None]:
        """Score `request`'s levels with the current policy (rollout key `key`) and commit
        them (`UEDRun.commit`): (episode metrics, levels played), or (None, None) when the
        result is committed later."""


class UEDRun:
    """One UED run's step logic over its workers: the curriculum decides, the LevelService
    hands out and takes back levels, the LearnerWorker trains, the Explorer scores. The workers are
    the local classes (the local driver) or stand-ins with the same methods that call Ray
    actors (the Ray driver), so both drivers take every decision the same way. A UEDRun is
    also the schedule that runs every part of a step here and now."""

    def __init__(self, config: TrainConfig, service: Any, explorer: Any,
                 evaluators: list[Any] = ()):
        self.config = config
        ued = config.ued
        self.curriculum: Curriculum = curriculum_for(ued, config.curriculum_settings())
        self.score = self.curriculum.score_name(ued)  # the score levels are ranked by
        self.service, self.explorer, self.evaluators = service, explorer, list(evaluators)
        self.sfl_scoring_steps = 0
        self.branch_counts = {b: 0 for b in Branch}  # steps of each kind, over the whole run

    @classmethod
    def local(cls, config: TrainConfig) -> tuple[UEDRun, PPOLearner]:
        """A run over workers built in this process, and its learner (to init or restore the
        train state that a `workers.roles.learner.LearnerWorker` holds)."""
        ppo_learner, service, explorer, evaluators = local_workers(config)
        return cls(config, service, explorer, evaluators), ppo_learner

    # --- one step ----------------------------------------------------------------------------

    def step(self, learner: LearnerWorker, step: int, key: jax.Array,
             schedule: Schedule | None = None
             ) -> tuple[Branch, dict[str, Any] | None, EnvParams | None]:
        """Run one curriculum step; returns its branch, its metrics (device values) and the
        levels it played; both None for a step whose result `schedule` commits later.
        `schedule`: where and when its parts run (default: all of it here and now)."""
        schedule = self if schedule is None else schedule
        keys = jax.random.split(key, 3)  # levels, rollout, edits
        k_levels, k_roll, k_edit = keys
        curriculum = self.curriculum
        branch = self.next_branch()
        learns = curriculum.learns(branch)
        replay = None
        if learns:
            metrics, levels, replay = schedule.learn(
                step, lambda: self.learning_step(learner, branch, step, keys))
        else:
            metrics, levels = schedule.explore(learner, step,
                                               self.level_request(branch, k_levels, k_edit),
                                               k_roll)
        if replay is None:
            curriculum.observe(branch)
        else:
            curriculum.observe(branch, replay.ids, replay.levels)
        if metrics is not None:
            metrics = self.step_metrics(metrics, branch, learns, learner.version)
        return branch, metrics, levels

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

    def level_request(self, branch: Branch, k_levels: jax.Array, k_edit: jax.Array
                      ) -> LevelRequest:
        """The new levels of a NEW or MUTATE step, as the curriculum asks for them."""
        return self.curriculum.level_request(branch, k_levels, k_edit,
                                             self.config.learner.num_envs)

    def commit(self, request: LevelRequest, levels: Any, scores: Any, best: Any,
               version: int) -> None:
        """Offer scored new levels to the buffer, filed as `request` says; `version`: the
        policy that scored them."""
        self.service.insert(levels, scores, best, version, request.source,
                                   parent_ids=request.parent_ids)

    # The schedule that runs every part of a step here and now.

    def learn(self, step: int, train: Callable[[], T]) -> T:
        return train()

    def explore(self, learner: LearnerWorker, step: int, request: LevelRequest, key: jax.Array
                ) -> tuple[dict[str, Any], EnvParams]:
        """A step that only scores new or mutated levels (Robust PLR, ACCEL) and offers them to
        the buffer: (episode metrics, levels played)."""
        version = learner.version
        levels = request.make(self.service)
        metrics, scores, best = self.explorer.score_levels(learner.params, levels, key,
                                                           self.score)
        self.commit(request, levels, scores, best, version)
        return metrics, levels

    def learning_step(self, learner: LearnerWorker, branch: Branch, step: int, keys: jax.Array
                      ) -> tuple[dict[str, Any], EnvParams, Replay | None]:
        """A step that trains the policy: (metrics, levels played, the replay batch or
        None)."""
        k_levels, k_roll, k_edit = keys
        n, score = self.config.learner.num_envs, self.score
        service = self.service
        version = learner.version  # the policy that plays (and so scores) this step's levels
        if branch == Branch.REPLAY:
            replay = service.replay(n)
            levels = to_device(replay.levels)
            metrics, scores, best = learner.train_scored(levels, k_roll, score,
                                                         replay.max_returns)
            service.update(replay.ids, scores, best, version)
            return metrics, levels, replay
        if branch == Branch.SFL:
            if self.curriculum.needs_refresh(step) or not service.has_learnable():
                self.refresh_learnable(learner, k_edit)
            levels = self.sfl_batch(k_levels, n)
            metrics, _ = learner.train(levels, k_roll)
            return metrics, levels, None
        # NEW (DR; PLR's exploratory gradient updates) or MUTATE with gradient updates.
        request = self.level_request(branch, k_levels, k_edit)
        levels = request.make(service)
        if self.curriculum.scores_new_levels:
            metrics, scores, best = learner.train_scored(levels, k_roll, score)
            self.commit(request, levels, scores, best, version)
        else:
            metrics, _ = learner.train(levels, k_roll)
        return metrics, levels, None

    def sfl_batch(self, key: jax.Array, n: int) -> EnvParams:
        """SFL's training batch: fresh random levels and levels of the learnable set."""
        k_fresh, n_fresh, k_pick, n_pick = sfl_split(key, n, self.config.ued.sfl_fresh_fraction)
        parts = []
        if n_fresh:
            parts.append(to_device(self.service.fresh(k_fresh, n_fresh)))
        if n_pick:
            parts.append(to_device(self.service.sample_learnable(k_pick, n_pick)))
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

    # --- evaluation and logging --------------------------------------------------------------

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

    def logged_metrics(self, levels: EnvParams | None,
                       stats: dict[str, float] | None = None) -> dict[str, float]:
        """What a logged step adds to its metrics: the buffer's statistics (`stats`: as the
        caller has them, else asked for now), what the curriculum is serving (`levels`: the
        step's, None if it played none here), SFL's scoring."""
        out = dict(self.service.stats() if stats is None else stats)
        if levels is not None:
            out.update(level_summary(levels))
        if self.sfl_scoring_steps:
            out["sfl/scoring_env_steps"] = float(self.sfl_scoring_steps)
        return out

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

    def save(self, run_dir: Path, done: int, learner: LearnerWorker) -> None:
        """The level snapshot of step `done` in `RUN_DIR/levels/`, with the levels the next
        step edits (ACCEL after a replay step). Written before the checkpoint of the same
        step: a checkpoint without one cannot be resumed."""
        curriculum = self.curriculum
        parents = curriculum.last_replay_levels if curriculum.pending_parents() else None
        self.service.save(str(run_dir / LEVELS_DIR), done, self.state(learner),
                          keep=self.config.run.keep_checkpoints, parents=parents)

    def resume(self, run_dir: Path, start: int) -> tuple[int, str | None]:
        """Continue from the level snapshot of step `start`: (the policy version it was taken
        at, a note on what had to change to go on, or None). ConfigError when it is missing or
        does not fit this run."""
        folder = str(run_dir / LEVELS_DIR)
        try:
            version = self.load_state(self.service.load(folder, start))
            return version, self.restore_parents(folder, start)
        except (FileNotFoundError, ConfigError, BufferFileError) as err:
            raise ConfigError(f"{run_dir}: cannot resume from step {start}: {err}") from None

    def restore_parents(self, folder: str, start: int) -> str | None:
        """The levels the next step edits, from the snapshot's parents file or, in a snapshot
        that has none, from its buffer. When the buffer no longer holds them (a snapshot that
        an earlier version took between an ACCEL replay step and its mutate step) the mutate
        step is dropped: the note says so."""
        curriculum = self.curriculum
        ids = curriculum.pending_parents()
        if not ids:
            return None
        levels = self.service.load_parents(folder, start)
        if levels is not None:
            count = jax.tree.leaves(levels)[0].shape[0]
            if count != len(ids):
                raise ConfigError(f"{folder}/parents-{start}.msgpack: {count} levels, but the "
                                  f"curriculum state names {len(ids)} parents")
        else:
            levels = self.service.stored_levels(ids)
        if levels is None:
            curriculum.drop_pending()
            return (f"the level snapshot of step {start} names replayed levels (ids "
                    f"{sorted(set(ids))[:8]}) that its buffer no longer holds and keeps no "
                    f"parents file: {curriculum.name}'s mutation step after that replay is "
                    f"dropped and the run goes on with the next step's own decision")
        curriculum.last_replay_levels = levels
        return None


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


def branch_text(counts: dict[Branch, int], buffer_size: int | None) -> str:
    """The progress line's account of a UED run: steps per branch, the buffer's size."""
    parts = [f"{b.name.lower()} {n}" for b, n in counts.items() if n]
    if buffer_size is not None:
        parts.append(f"buffer {buffer_size}")
    return ", ".join(parts)


__all__ = ["Schedule", "UEDRun", "branch_text", "evaluators_for",
           "generator_for", "level_service_for", "level_summary", "local_workers"]
