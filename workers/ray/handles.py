"""The driver's handles on a Ray run's actors: the learner (policy versions counted here,
parameters fetched once per version), the Explorer pool and the evaluator, and the records of
the batches and evaluations in flight."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import jax
import numpy as np

from ued.curricula import LevelRequest
from ued.tensorboard import SummaryWriter
from workers.ray.actor_manager import ActorManager, Call
from workers.ray.actors import (
    ParamsRef,
)

# --- the deterministic mode: the local step logic over blocking calls -------------------------


class RemoteLearner:
    """The learner actor behind `workers.roles.learner.LearnerWorker`'s interface, with the policy
    version counted here and the parameters fetched once per version (a ref owned by the driver)."""

    def __init__(self, ray: Any, actor: Any, actors: ActorManager, version: int = 0):
        self._actors = actors
        self._actors.add("learner", actor, restarts=False)
        self._actor = actor
        self.version = int(version)
        self._params: ParamsRef | None = None

    def train(self, levels: Any, key: jax.Array) -> tuple[dict[str, Any], None]:
        metrics = self._actors.call("learner", "train", levels, key)
        self.version += 1
        return metrics, None

    def train_scored(self, levels: Any, key: jax.Array, score: str,
                     max_returns: Any = None) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
        out = self._actors.call("learner", "train_scored", levels, key, score, max_returns)
        self.version += 1
        return out

    @property
    def params(self) -> ParamsRef:
        if self._params is None or self._params.version != self.version:
            self._params = ParamsRef(self.version, [self._actor.params.remote()])
        return self._params

    @property
    def train_state(self) -> Any:
        return self._actors.call("learner", "train_state")


class ExplorerPool:
    """Explorer actors behind `workers.roles.explorer.Explorer`'s interface: calls go round-robin
    and wait (the deterministic mode). A call whose Explorer dies runs again on its restart with the
    same arguments: in this mode they are what the schedule asks for. `manager`: the run's
    ActorManager (where the Explorers restart), `names` theirs in it."""

    def __init__(self, ray: Any, actors: list[Any], names: list[str], manager: ActorManager):
        self._manager = manager
        self._names = names
        for name, actor in zip(self._names, actors, strict=True):
            self._manager.add(name, actor, restarts=False)
        self._next = 0

    def _send(self, method: str, *args: Any, then: str) -> Call:
        name = self._names[self._next % len(self._names)]
        self._next += 1
        return self._manager.send(Call.of(name, method, *args, then=then))

    def _call(self, method: str, *args: Any) -> Any:
        return self._manager.get(self._send(method, *args,
                                            then=f"{method} runs again on its restart"))

    def score_levels(self, params: ParamsRef, levels: Any, key: jax.Array, score: str,
                     max_returns: Any = None, num_steps: int | None = None) -> Any:
        return self._call("score_levels", params, levels, key, score, max_returns, num_steps)

    def learnability(self, params: ParamsRef, levels: Any, key: jax.Array,
                     num_steps: int | None = None) -> np.ndarray:
        return self._call("learnability", params, levels, key, num_steps)

    def learnability_batches(self, params: ParamsRef, batches: list[tuple[Any, jax.Array]],
                             num_steps: int | None = None) -> list[np.ndarray]:
        """SFL's batches spread over the Explorers at once, results in batch order (so the
        same as one after another); a batch whose Explorer died runs again on its restart."""
        then = "its learnability batches run again on its restart"
        calls = [self._send("learnability", params, levels, key, num_steps, then=then)
                 for levels, key in batches]
        return [self._manager.get(call) for call in calls]


class RemoteEvaluator:
    """The evaluator actor behind `workers.roles.evaluator.Evaluator`'s interface (one per suite).
    An evaluation whose actor dies runs again on its restart (same parameters and key)."""

    def __init__(self, ray: Any, actor: Any, index: int, suite_name: str,
                 actors: ActorManager):
        self._actors = actors
        self._actors.add("evaluator", actor, restarts=False)
        self.index = index
        self.suite = _SuiteName(suite_name)

    def evaluate(self, params: ParamsRef, key: jax.Array) -> Any:
        return self._actors.call("evaluator", "evaluate", self.index, params, key,
                                 then="evaluate runs again on its restart")

    def log(self, writer: SummaryWriter, step: int, result: Any) -> None:
        from workers.roles.evaluator import log

        log(writer, step, result)


@dataclass(frozen=True)
class _SuiteName:
    name: str


# --- the asynchronous mode ------------------------------------------------------------------


@dataclass
class Batch:
    """One curriculum step handed to an Explorer: what is needed to commit or re-issue it."""

    step: int
    request: LevelRequest  # the service call that made the levels, how they are filed
    key: jax.Array
    version: int  # of the policy it was (last) sent with
    explorer: int
    levels: Call | None  # to the service: its ref is the numpy levels (None: the Explorer
    # makes them from the key, `ExplorerActor.score_fresh`)
    score: Call | None = None  # to the Explorer (its arguments: the current policy)
    issued_s: float = field(default_factory=time.perf_counter)
    rescored: int = 0
    made: Any = None  # the levels an Explorer made (`levels` None), once its result is in


@dataclass
class Evaluation:
    """One suite's evaluation at one step, on the Evaluator (its call runs it again)."""

    step: int
    suite: str
    call: Call


