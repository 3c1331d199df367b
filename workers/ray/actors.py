"""The Ray actors of a UED run: the local worker classes, built inside each actor's process.

These are plain classes; the Ray driver (`workers.ray.driver`) makes them actors with
`ray.remote(cls).options(...)`, so this module imports nothing of Ray and each actor builds its
own part of the run from the config (no JAX object crosses a process boundary). What crosses:

    levels               numpy pytrees (`to_host`), as arguments or return values
    keys                 JAX key arrays (a few bytes, pickled)
    scores, metrics      numpy arrays and floats
    policy parameters    a `ParamsRef`: the version and a ref to the numpy parameters, fetched
                         from the learner once per version by the driver; an Explorer pulls
                         them only when the version is newer than the one it holds

An actor method that returns levels returns them on the host, so the driver (which owns the
returned object) can hand the ref to any other actor.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

from tabx import xla_flags
from tabx.params import EnvParams
from ued import compile_cache
from ued.config import TrainConfig
from ued.experiment import learner_for
from ued.learners.ppo import PPOLearner
from ued.levels import LevelGenerator
from ued.suites import EvalSuite
from workers.ray.durable_service import DurableLevelService
from workers.roles.evaluator import Evaluator, SuiteResult
from workers.roles.explorer import Explorer
from workers.roles.learner import LearnerWorker
from workers.roles.level_service import to_device, to_host
from workers.ued_step import evaluators_for, generator_for, level_service_for

# An actor's process is started by Ray, not by the `tabx` command: it applies the command's
# XLA settings itself (one CPU device per usable core of its node), when Ray loads the actor
# class, before JAX starts its backend there (no module imported above starts it).
xla_flags.apply()


T = TypeVar("T")
GROUP_LOST_EXIT = 75  # the exit status of a learner group member whose update failed


@dataclass(frozen=True)
class ParamsRef:
    """Policy parameters of one version: `ref` holds one ObjectRef in a list, so that Ray
    passes the ref itself (not its value) and the receiver fetches it only when it must."""

    version: int
    ref: list[Any]


class ActorBase:
    """What every actor of a run shares: the compilation cache switched on as the run asks (so
    a restarted actor reloads its programs rather than compiling them), a readiness call, and
    the node it runs on."""

    def __init__(self, config: TrainConfig):
        compile_cache.enable(config.run.compile_cache)

    def ready(self) -> bool:
        return True

    def pid(self) -> int:
        """The actor's process id (tests kill it with SIGKILL)."""
        import os

        return os.getpid()

    def node(self) -> str:
        import ray

        return ray.get_runtime_context().get_node_id()


class ParamsCache:
    """The parameters an actor plays with: pulled (and put on its device) when newer.
    `fetch` resolves the ref (`ray.get`; a test may hand in its own)."""

    def __init__(self, fetch: Callable[[Any], Any] | None = None) -> None:
        self.version = -1
        self.params: Any = None
        self.fetch = fetch

    def get(self, params: ParamsRef | Any) -> Any:
        if not isinstance(params, ParamsRef):
            return params  # already the parameters (in-process use)
        if params.version != self.version:
            fetch = self.fetch
            if fetch is None:
                import ray

                fetch = ray.get
            self.params = jax.tree.map(jnp.asarray, fetch(params.ref[0]))
            self.version = params.version
        return self.params


class LevelServiceActor(DurableLevelService, ActorBase):
    """The LevelService: the only writer of the buffer. Levels go out on the host. With a
    `folder` (the run's `levels/`) its state-changing calls are logged there, and a restart
    (the constructor again, same arguments) restores them (`workers.ray.durable_service`)."""

    def __init__(self, config: TrainConfig, folder: str | None = None, session: str = ""):
        ActorBase.__init__(self, config)
        built = level_service_for(config, learner_for(config))
        super().__init__(built.generator, built.template, config.ued, seed=config.seed,
                         curriculum=built.curriculum, folder=folder, session=session)

    def fresh(self, key: jax.Array, n: int) -> EnvParams:
        return to_host(super().fresh(key, n))

    def mutate(self, key: jax.Array, levels: EnvParams) -> EnvParams:
        return to_host(super().mutate(key, levels))

    def sample_learnable(self, key: jax.Array, n: int) -> EnvParams:
        return to_host(super().sample_learnable(key, n))

    def buffer_bytes(self) -> bytes | None:
        """The level buffer as it is now, in the level-buffer file format (`tabx runs
        buffer`); None where the method keeps no buffer."""
        return None if self.buffer is None else self.buffer.to_bytes()


class ExplorerActor(ActorBase):
    """Scores levels with the newest policy it was handed (Robust PLR, ACCEL, SFL)."""

    def __init__(self, config: TrainConfig, learner: PPOLearner | None = None):
        super().__init__(config)
        self.learner = learner if learner is not None else learner_for(config)
        self.explorer = Explorer(self.learner, config.ued.score)
        self.cache = ParamsCache()
        self.config = config
        self.generator: LevelGenerator | None = None  # built on the first fresh batch

    def score_levels(self, params: ParamsRef, levels: EnvParams, key: jax.Array, score: str,
                     max_returns: Any = None, num_steps: int | None = None
                     ) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
        metrics, scores, best = self.explorer.score_levels(
            self.cache.get(params), to_device(levels), key, score, max_returns, num_steps)
        return _host_metrics(metrics), scores, best

    def score_fresh(self, params: ParamsRef, levels_key: jax.Array, n: int, key: jax.Array,
                    score: str) -> tuple[dict[str, float], np.ndarray, np.ndarray, EnvParams]:
        """Make `n` fresh levels from `levels_key` (the level service's generator, a pure
        function of its key: the same levels the service would make) and score them; the
        levels come back on the host with the scores, for the service to insert. Keeps the
        generator's CPU off the level service (`ray.schedule: continuous`)."""
        levels = self._fresh(levels_key, n)
        metrics, scores, best = self.explorer.score_levels(
            self.cache.get(params), levels, key, score, None, None)
        return _host_metrics(metrics), scores, best, to_host(levels)

    def learnability_fresh(self, params: ParamsRef, levels_key: jax.Array, n: int,
                           key: jax.Array, num_steps: int | None = None
                           ) -> tuple[dict[str, float], np.ndarray, None, EnvParams]:
        """SFL's batch on the continuous schedule: make `n` fresh levels from `levels_key`
        (as `score_fresh`) and score them by learnability p (1 - p) over `num_steps` steps:
        ({}, scores, None, the levels on the host), shaped as `score_fresh`'s answer."""
        levels = self._fresh(levels_key, n)
        scores = self.explorer.learnability(self.cache.get(params), levels, key, num_steps)
        return {}, scores, None, to_host(levels)

    def _fresh(self, levels_key: jax.Array, n: int) -> EnvParams:
        if self.generator is None:
            self.generator = generator_for(self.config, self.learner)
        return self.generator.sample(levels_key, n)

    def learnability(self, params: ParamsRef, levels: EnvParams, key: jax.Array,
                     num_steps: int | None = None) -> np.ndarray:
        return self.explorer.learnability(self.cache.get(params), to_device(levels), key,
                                          num_steps)


class LearnerActor(ExplorerActor):
    """The one learner: holds the train state and counts policy versions. It can also score
    (`ray.explorers: 0`), with its own parameters. With `group` (coordinator HOST:PORT,
    members, this member's index, its rank among the members on its node, their count) it is
    one member of a learner group (workers/ray/learner_group.py): it takes its share of its node's
    cores (`ray.learner_share_cores`) and joins JAX's multi-process runtime before JAX starts."""

    def __init__(self, config: TrainConfig,
                 group: tuple[str, int, int, int, int] | None = None):
        if group is not None:
            from ued.learners import distributed

            if config.ray.learner_share_cores:
                distributed.share_cores(*group[3:])
                xla_flags.match_devices_to_cores()  # a device per core it keeps
            distributed.join(*group[:3])
        super().__init__(config)
        self.group = group
        self.state: LearnerWorker | None = None

    def _together(self, fn: Callable[[], T]) -> T:
        """`fn()`, an update the group runs together (its results on the host). A member whose
        update fails (a collective that lost a member: gloo's connection closed) ends its
        process: the group cannot go on, and the driver sees a learner lost, not an error of
        the update."""
        if self.group is None:
            return fn()
        try:
            return fn()
        except Exception:
            import os
            import sys
            import traceback

            traceback.print_exc()
            sys.stderr.write(f"learner {self.group[2]} of {self.group[1]}: the group's update "
                             f"failed; this member ends\n")
            sys.stderr.flush()
            os._exit(GROUP_LOST_EXIT)

    def init(self, key: jax.Array) -> None:
        self.state = LearnerWorker(self.learner, self.learner.init(key))

    def _learner(self) -> LearnerWorker:
        if self.state is None:
            raise RuntimeError("the learner actor has no train state: call init first")
        return self.state

    def train(self, levels: EnvParams, key: jax.Array) -> dict[str, float]:
        return self._together(lambda: _host_metrics(
            self._learner().train(to_device(levels), key)[0]))

    def train_scored(self, levels: EnvParams, key: jax.Array, score: str,
                     max_returns: Any = None
                     ) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
        def run() -> tuple[dict[str, float], np.ndarray, np.ndarray]:
            metrics, scores, best = self._learner().train_scored(to_device(levels), key, score,
                                                                 max_returns)
            return _host_metrics(metrics), scores, best

        return self._together(run)

    def train_replay(self, replay: Any, key: jax.Array, score: str
                     ) -> tuple[dict[str, float], np.ndarray, np.ndarray, np.ndarray]:
        """A replay step on a batch the level service drew (`level_buffer.Replay`, handed
        over by ref: it never passes through the driver): (metrics, the replayed ids, their
        new scores, best returns)."""
        metrics, scores, best = self.train_scored(replay.levels, key, score, replay.max_returns)
        return metrics, np.asarray(replay.ids), scores, best

    def params(self) -> Any:
        """The current parameters as numpy (the driver owns the returned object)."""
        return jax.device_get(self._learner().params)

    def version(self) -> int:
        return self._learner().version

    def train_state(self) -> Any:
        return jax.device_get(self._learner().train_state)

    def set_train_state(self, train_state: Any, version: int) -> None:
        self.state = LearnerWorker(self.learner, jax.tree.map(jnp.asarray, train_state), version)


class EvaluatorActor(ActorBase):
    """The zero-shot evaluation suites of the config, one Evaluator each."""

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        self.evaluators = evaluators_for(config, learner_for(config))
        self.cache = ParamsCache()

    def evaluate(self, index: int, params: ParamsRef, key: jax.Array) -> Any:
        return self.evaluators[index].evaluate(self.cache.get(params), key)


class SuiteEvaluatorActor(ActorBase):
    """One suite for one trained policy (`tabx eval RUN_DIR --suite NAME --ray`): built from
    the run's config, it plays the parameters it is handed (numpy) and returns the result."""

    def __init__(self, config: TrainConfig, suite: EvalSuite, episodes: int | None,
                 greedy: bool, profile: str | None = None):
        super().__init__(config)
        self.evaluator = Evaluator(learner_for(config), suite, episodes=episodes, greedy=greedy,
                                   profile=profile or config.env.profile)

    def evaluate(self, params: Any, key: jax.Array) -> SuiteResult:
        return self.evaluator.evaluate(jax.tree.map(jnp.asarray, params), key)


def _host_metrics(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}


__all__ = ["ActorBase", "EvaluatorActor", "ExplorerActor", "LearnerActor", "LevelServiceActor",
           "ParamsCache", "ParamsRef", "SuiteEvaluatorActor"]
