"""The asynchronous (sequential) schedule of a Ray run: batches the learner does not train on go
to Explorers and run beside the learner, each Explorer at most `ray.max_inflight` batches
ahead; a result is committed when it arrives, and one more than `ray.max_policy_lag` versions
stale is scored again with the current policy. `workers.ray.continuous` builds on it."""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any, TextIO, TypeVar

import jax
import numpy as np

from ued.config import TrainConfig
from ued.curricula import Branch, LevelRequest
from ued.tensorboard import SummaryWriter
from workers.ray.actor_manager import Call
from workers.ray.handles import Batch, Evaluation, RemoteLearner
from workers.ray.restarts import SERVICE, RemoteService
from workers.ray.start import Workers
from workers.ray.stats import RayStats
from workers.ued_step import UEDRun

T = TypeVar("T")


class AsyncRun:
    """The asynchronous schedule over the actors of one run (see the module doc). Its calls go
    through the run's ActorManager (`service.actors`), which keeps them in flight and sends a
    batch or an evaluation lost with its actor again on the restart (with the current policy).
    `start`: the session's first step (a schedule of its own key chain uses it; this one takes
    its keys from the steps)."""

    def __init__(self, ray: Any, config: TrainConfig, run: UEDRun, learner: RemoteLearner,
                 workers: Workers, service: RemoteService, start: int = 0):
        self.ray, self.config, self.run, self.learner, self.workers = (ray, config, run,
                                                                       learner, workers)
        self.scorers = workers.scorers()
        self.names = workers.scorer_names()
        # The run's service too: one numbering of the state-changing calls per actor.
        self.service = service
        self.actors = service.actors
        workers.register(self.actors)
        self.service.on_restart.append(self.ask_again_for_lost_levels)
        self.stats = RayStats()
        self.ledger: dict[int, str] = {}  # step -> "issued" | "committed"
        self.recent_lags: deque[int] = deque(maxlen=1000)

    @property
    def pending(self) -> list[Batch]:
        """The Explorer batches in flight, oldest first (the ActorManager keeps them)."""
        return self.actors.tags(self.names)

    def inflight(self, i: int) -> int:
        """Batches in flight to Explorer `i`."""
        return len(self.actors.in_flight([self.names[i]]))

    # Evaluation runs beside training: submitted at its steps, logged when it is done -------

    def submit_evaluation(self, done: int) -> None:
        if self.workers.evaluator is None or not self.actors.available("evaluator"):
            return
        key = jax.random.fold_in(jax.random.key(self.config.seed ^ 0x5EED), done)
        params = self.learner.params
        for i, name in enumerate(self.config.ued.eval_suites):
            # The same parameters and key on a re-run; given up rather than stopping the run.
            call = Call.of("evaluator", "evaluate", i, params, jax.random.fold_in(key, i),
                           then=f"its evaluation of {name} after step {done} runs again on "
                                f"its restart")
            call.optional = True
            self.actors.submit(call, Evaluation(done, name, call))

    @property
    def evaluations(self) -> list[Evaluation]:
        """The evaluations running, oldest first."""
        return self.actors.tags(["evaluator"])

    def log_evaluations(self, writer: SummaryWriter, stream: TextIO | None,
                        block: bool = False) -> None:
        """Log the evaluations that are done (with `block`: all of them, waiting). One whose
        Evaluator died runs again, with the same parameters and key, once the Evaluator is
        back (the ActorManager sends it again); one the ActorManager gives up is counted
        (`evaluations_lost`) and training goes on."""
        from workers.roles.evaluator import log

        while True:
            for done in self.actors.fetch_ready(["evaluator"], block=block):
                evaluation = done.tag
                if done.error is not None:
                    self.stats.evaluations_lost += 1
                    continue
                log(writer, evaluation.step * self.config.learner.steps_per_update, done.value)
                if stream is not None:
                    stream.write(f"  eval {evaluation.suite} after step {evaluation.step}: "
                                 f"mean win rate {done.value.mean_win_rate:.2f}\n")
                    stream.flush()
            self.stats.evaluations_rerun = self.actors.resent["evaluator"]
            if not (block and self.evaluations):
                return

    def background_steps(self) -> int:
        """Env steps explored beside the steps this session (none: every batch this schedule
        scores is a step of its own)."""
        return 0

    def record(self) -> dict[str, Any]:
        """What `ray.json` keeps of the schedule: batches, re-scores, the staleness histogram."""
        states = Counter(self.ledger.values())
        return {"committed_batches": self.stats.committed, "rescored": self.stats.rescored,
                "staleness": {str(k): v for k, v in sorted(self.stats.staleness.items())},
                "ledger": dict(states), "trained_steps": self.stats.trained_steps,
                "reissued": self.stats.reissued,
                "evaluations_rerun": self.stats.evaluations_rerun,
                "evaluations_lost": self.stats.evaluations_lost,
                "explored_steps": self.stats.explored_steps,
                "learner_busy_s": self.stats.learner_busy_s,
                "wait_for_levels_s": self.stats.wait_for_levels_s}

    # Explorer work ------------------------------------------------------------------------

    def _free_explorer(self) -> int:
        """An explorer with room, waiting for results (and committing them) until one has."""
        limit = self.config.ray.max_inflight
        while True:
            free = [i for i, name in enumerate(self.names) if self.actors.has_room(name, limit)]
            if free:
                return min(free, key=self.inflight)
            self.collect(block=True)

    def _submit(self, batch: Batch) -> None:
        """Send `batch`'s scoring to its Explorer, with the current policy (at every sending:
        the ActorManager sends it again after its Explorer's death)."""
        def current_policy() -> None:
            batch.version = self.learner.version

        batch.score.before_send = current_policy
        self.actors.submit(batch.score, batch)

    def explore(self, learner: RemoteLearner, step: int, request: LevelRequest,
                key: jax.Array) -> tuple[None, None]:
        """Issue step `step` (the schedule's `explore`): the service makes its levels
        (`request`), an Explorer scores them; the driver holds only the refs. Committed when
        the result arrives (`collect`)."""
        # The levels are asked for before waiting for an Explorer, which commits finished
        # batches meanwhile (ACCEL's children are made from the replayed levels themselves,
        # so an insert that evicts a parent changes nothing).
        levels = self.actors.send(Call.of(SERVICE, request.method, *request.args))
        i = self._free_explorer()
        batch = Batch(step, request, key, learner.version, i, levels)
        score = self.run.score
        # Rebuilt at every sending: the current policy, the levels as asked for last (the
        # closure holds the levels' call, not the batch: no cycle keeps refs alive).
        batch.score = Call(self.names[i], "score_levels",
                           lambda: (self.learner.params, levels.ref, key, score, None, None),
                           then="its batches are re-issued with the current policy on its "
                                "restart", after=(levels,))
        self.ledger[step] = "issued"
        self._submit(batch)
        return None, None

    def learn(self, step: int, train: Callable[[], T]) -> T:
        """Step `step`'s learner part (the schedule's `learn`): now, committed when done."""
        t0 = time.perf_counter()
        out = train()
        self.stats.learner_busy_s += time.perf_counter() - t0
        self.stats.trained_steps += self.config.learner.steps_per_update
        self.ledger[step] = "committed"
        return out

    def ask_again_for_lost_levels(self) -> None:
        """After a restart of the service: ask again, in step order and before anything else,
        for the levels of every batch that died with it. Same calls, same keys: the restored
        service makes the same levels."""
        self.actors.send_lost_again([batch.levels for batch in
                                     sorted(self.pending, key=lambda b: b.step)
                                     if batch.levels is not None])

    def finished(self, block: bool) -> list[tuple[Batch, Any]]:
        """The Explorer batches that are done, with their results (waiting for one if
        `block`); a batch lost with its Explorer (or with the service before it made its
        levels) is sent again by the ActorManager with the current policy and stays in
        flight."""
        t0 = time.perf_counter()
        done = self.actors.fetch_ready(self.names, block=block)
        self.stats.wait_for_levels_s += time.perf_counter() - t0 if block else 0.0
        self.stats.reissued = sum(self.actors.resent[name] for name in self.names)
        return [(result.tag, result.value) for result in done]

    def collect(self, block: bool) -> None:
        """Commit the explorer results that are ready (wait for one if `block`)."""
        if not self.pending:
            return
        for batch, result in self.finished(block):
            accepted = self.accept(batch, result)
            if accepted is not None:
                self.commit(*accepted)

    def accept(self, batch: Batch, result: Any) -> tuple[Batch, Any, Any, int] | None:
        """A finished Explorer batch and its result: (batch, scores, best, policy lag) to
        commit, or None when its policy is too old (scored again)."""
        _, scores, best = result
        lag = self.learner.version - batch.version
        if lag > self.config.ray.max_policy_lag:
            # Too old to trust: score the same levels again with the current policy.
            self.stats.rescored += 1
            batch.rescored += 1
            self._submit(batch)
            return None
        return batch, scores, best, lag

    def commit(self, batch: Batch, scores: np.ndarray, best: np.ndarray, lag: int) -> None:
        self.run.commit(batch.request, batch.levels.ref, scores, best, batch.version)
        self.ledger[batch.step] = "committed"
        self.stats.committed += 1
        self.stats.staleness[lag] += 1
        self.recent_lags.append(lag)
        self.stats.explored_steps += self.config.learner.steps_per_update

    def drain(self) -> None:
        while self.pending:
            self.collect(block=True)

    # One step -----------------------------------------------------------------------------

    def step(self, step: int, key: jax.Array) -> tuple[Branch, dict[str, Any] | None, Any]:
        """Decide and issue curriculum step `step` (`UEDRun.step` on this schedule): Explorer
        batches return at once (metrics and levels None); learner batches wait for the
        update. Results that arrived meanwhile are committed first."""
        self.collect(block=False)
        return self.run.step(self.learner, step, key, schedule=self)


