"""The asynchronous (sequential) schedule of a Ray run: batches the learner does not train on go
to Explorers and run beside the learner, each Explorer at most `ray.max_inflight` batches
ahead; a result is committed when it arrives, and one more than `ray.max_policy_lag` versions
stale is scored again with the current policy. `workers.continuous` builds on it."""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any, TextIO, TypeVar

import jax
import numpy as np

from ued.config import TrainConfig
from ued.curricula import Branch
from ued.tensorboard import SummaryWriter
from workers.actor_manager import Call
from workers.ray_handles import Batch, Evaluation, RemoteLearner
from workers.ray_restarts import SERVICE, RemoteService
from workers.ray_start import Workers
from workers.ray_stats import RayStats
from workers.ued_step import LevelRequest, UEDRun

T = TypeVar("T")


class AsyncRun:
    """The asynchronous schedule over the actors of one run (see the module doc). Its calls go
    through the run's ActorManager (`service.actors`): a batch or an evaluation lost with its
    actor is sent again on the restart. `start`: the session's first step (a schedule of its
    own key chain uses it; this one takes its keys from the steps)."""

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
        self.pending: dict[Any, Batch] = {}
        self.inflight = [0] * len(self.scorers)
        self.stats = RayStats()
        self.ledger: dict[int, str] = {}  # step -> "issued" | "committed"
        self.recent_lags: deque[int] = deque(maxlen=1000)
        self.evaluations: list[Evaluation] = []  # running

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
            self.evaluations.append(Evaluation(done, name, self.actors.send(call)))

    def log_evaluations(self, writer: SummaryWriter, stream: TextIO | None,
                        block: bool = False) -> None:
        """Log the evaluations that are done. One whose Evaluator died runs again, with the
        same parameters and key, once the Evaluator is back; one the ActorManager gives up
        is counted (`evaluations_lost`) and training goes on."""
        from workers.evaluator import log

        waiting, self.evaluations = self.evaluations, []
        for evaluation in waiting:
            ready, _ = self.ray.wait([evaluation.call.ref], timeout=None if block else 0)
            if not ready:
                self.evaluations.append(evaluation)
                continue
            try:
                result = self.ray.get(evaluation.call.ref)
            except Exception as err:
                if self.actors.recover(evaluation.call, err):
                    self.stats.evaluations_rerun += 1
                    self.actors.send(evaluation.call)
                    self.evaluations.append(evaluation)
                else:
                    self.stats.evaluations_lost += 1
                continue
            log(writer, evaluation.step * self.config.learner.steps_per_update, result)
            if stream is not None:
                stream.write(f"  eval {evaluation.suite} after step {evaluation.step}: mean "
                             f"win rate {result.mean_win_rate:.2f}\n")
                stream.flush()
        if block and self.evaluations:  # re-run ones: wait for them too
            self.log_evaluations(writer, stream, block=True)

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
            free = [i for i, n in enumerate(self.inflight) if n < limit]
            if free:
                return min(free, key=lambda i: self.inflight[i])
            self.collect(block=True)

    def _submit(self, batch: Batch) -> None:
        """Send (again) `batch`'s scoring to its Explorer, with the current policy."""
        batch.version = self.learner.version
        ref = self.actors.send(batch.score).ref
        self.pending[ref] = batch
        self.inflight[batch.explorer] += 1

    def explore(self, learner: RemoteLearner, step: int, request: LevelRequest,
                key: jax.Array) -> tuple[None, None]:
        """Issue step `step` (the schedule's `explore`): the service makes its levels
        (`request`), an Explorer scores them; the driver holds only the refs. Committed when
        the result arrives (`collect`)."""
        # The levels are asked for before waiting for an Explorer: waiting commits finished
        # batches, and an insert sent before an ACCEL `mutate_ids` could evict the replayed
        # parents it names (the service answers one caller's calls in the order sent).
        levels = self.actors.send(Call.of(SERVICE, request.method, *request.args))
        i = self._free_explorer()
        batch = Batch(step, request, key, learner.version, i, levels)
        score = self.config.ued.score
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
        service makes the same levels (an ACCEL parent is still in the buffer, since the
        inserts after it run after it, as before)."""
        for batch in sorted(self.pending.values(), key=lambda b: b.step):
            if batch.levels is not None and self.actors.lost_with_restart(batch.levels):
                self.actors.send(batch.levels)

    def collect(self, block: bool) -> None:
        """Commit the explorer results that are ready (wait for one if `block`)."""
        if not self.pending:
            return
        t0 = time.perf_counter()
        ready, _ = self.ray.wait(list(self.pending), num_returns=1,
                                 timeout=None if block else 0)
        if block:
            self.stats.wait_for_levels_s += time.perf_counter() - t0
        for ref in ready:
            accepted = self.accept(ref)
            if accepted is not None:
                self.commit(*accepted)

    def accept(self, ref: Any, result: Any = None) -> tuple[Batch, Any, Any, int] | None:
        """Take the finished Explorer call `ref` (its `result` when already fetched) off the
        pending ones: (batch, scores, best, policy lag) to commit, or None when the call
        failed (re-issued) or its policy is too old (scored again)."""
        batch = self.pending.pop(ref)
        self.inflight[batch.explorer] -= 1
        try:
            _, scores, best = self.ray.get(ref) if result is None else result
        except Exception as err:
            self.reissue(batch, err)
            return None
        batch.score.failures = 0
        lag = self.learner.version - batch.version
        if lag > self.config.ray.max_policy_lag:
            # Too old to trust: score the same levels again with the current policy.
            self.stats.rescored += 1
            batch.rescored += 1
            self._submit(batch)
            return None
        return batch, scores, best, lag

    def reissue(self, batch: Batch, err: Exception) -> None:
        """`batch` was lost (its Explorer died, or the service before it made the levels): once
        the ActorManager has the actor back, submit it again with the current parameters (Ray's
        own retry would reuse the old ones); levels lost with the service are asked for
        again first (`ActorManager.send`)."""
        t0 = time.perf_counter()
        self.actors.recover(batch.score, err)  # raises where the run stops
        self.stats.wait_for_levels_s += time.perf_counter() - t0
        self.stats.reissued += 1
        self._submit(batch)

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


