"""The Ray driver's continuous schedule (`ray.schedule: continuous`): Explorers score new levels
without pause while the learner takes a gradient step at every curriculum step.

For the curricula that score levels they do not train on (Robust PLR, ACCEL):

    Explorers   each keeps `ray.max_inflight` batches of fresh levels (ACCEL: the children of
                the newest replay batches first) in flight, scored with the newest policy the
                learner has published; a result is committed as it arrives, unless its policy
                is more than `ray.max_policy_lag` versions old (then it is scored again). An
                Explorer makes a batch's fresh levels itself from the key the driver gave the
                batch (the generator is a pure function of its key: the levels the service
                would make); they come back with the scores and the service only inserts them
    learner     every step is a replay step: it trains on a batch the level service drew,
                handed to it by ref (the levels never pass through the driver); the step
                waits until the buffer holds `ued.min_fill_ratio` of its capacity
    driver      while the learner trains it commits Explorer results and refills Explorers;
                the next replay batch is drawn while the current one trains; the results that
                arrived together are committed in one call and one fsync (a group commit,
                `DurableLevelService.apply_many`); replay scores are sent without waiting,
                and every numbered call is acknowledged before a snapshot

What differs from the papers' sequential algorithm (and `ray.schedule: sequential`): no coin
decides between a new and a replay step (`ued.replay_prob` is not used): the learner replays
at every step and the ratio of scored new levels to replayed ones is the Explorers' throughput
over the learner's; a replay batch is drawn one update ahead, so it does not see the scores of
the batch being trained; new levels are scored by a policy up to `ray.max_policy_lag` versions
old; ACCEL mutates each replay batch as it was drawn (a parent evicted since still has its
children).

SFL, on the same machinery (the same batches in flight, lag check, re-issue and group commit):

    Explorers   each keeps `ray.max_inflight` learnability batches in flight: `ued.sfl_batch_size`
                fresh levels it makes from the batch's key, each played `ued.sfl_rollout_steps`
                steps with the newest policy and scored p (1 - p) (`learnability_fresh`)
    service     each committed batch goes into the window of the newest `ued.sfl_num_batches`
                committed batches (`LevelService.add_learnable`, numbered, group-committed);
                the learnable set is then the `ued.sfl_top_k` most learnable levels of the
                window (ties: the earlier batch, then the earlier level), replaced at every
                committed batch
    learner     every step trains on its SFL batch (`LevelService.sfl_batch`, by ref):
                round(n x `ued.sfl_fresh_fraction`) fresh levels and the rest drawn uniformly
                from the learnable set as it stands when the batch is drawn (one update ahead,
                while the previous step trains); while the set is still empty (before the
                first scored batch is committed) the whole batch is fresh levels. It never
                waits for an Explorer

What differs from the paper's SFL (and `ray.schedule: sequential`): the learnable set is not
rebuilt every `ued.sfl_update_freq` steps from `ued.sfl_num_batches` batches scored while the
learner waits (that setting is not used); it follows the Explorers' throughput, a batch at a
time, as a sliding window; its batches are scored by policies up to `ray.max_policy_lag`
versions old, not all by the same one; the first steps train on fresh levels only; the fresh
levels of a training batch come from this schedule's own key chain (by step), not the step's.
`sfl/scoring_env_steps` counts the committed batches' steps.

DR and PLR train on every batch and score nothing apart from training: they keep the
sequential schedule's steps.

Every Explorer batch is committed exactly once: numbered like every state-changing call
(`workers.ray.restarts.RemoteService`), re-issued with the current policy when its Explorer
dies, its levels asked for again when the service dies (`AsyncRun`'s restart hooks).
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from typing import Any

import jax

from level_buffer import Source
from ued.config import TrainConfig
from ued.curricula import Branch, LevelRequest
from workers.ray.actor_manager import Call
from workers.ray.async_schedule import AsyncRun
from workers.ray.durable_service import Slot
from workers.ray.handles import Batch, RemoteLearner
from workers.ray.restarts import SERVICE, RemoteService
from workers.ray.start import Workers
from workers.ued_step import UEDRun

BACKGROUND_KEY = 0xC0471  # folded into the seed: the key chain of the Explorers' batches
SFL_BATCH_KEY = 0x5F1B  # folded into the seed: the keys of SFL's training batches, by step
KEY_BLOCK = 256  # Explorer batches whose keys one JAX call makes


class ContinuousRun(AsyncRun):
    """The continuous schedule over the actors of one run (module doc); `start`: the first
    step of this session (it seeds the key chain of the Explorers' batches)."""

    def __init__(self, ray: Any, config: TrainConfig, run: UEDRun, learner: RemoteLearner,
                 workers: Workers, service: RemoteService, start: int = 0):
        super().__init__(ray, config, run, learner, workers, service, start)
        curriculum = run.curriculum
        # What the curriculum's branches and hooks say, never its class: one whose steps
        # only score new levels (Robust PLR, ACCEL) has them scored without pause; one that
        # trains on every batch (DR, PLR) keeps the sequential steps.
        self.scores_apart = curriculum.explores_apart()
        # SFL steps: Explorers score learnability batches without pause; the learner trains on
        # SFL batches drawn from the learnable set as it stands.
        self.learnability = Branch.SFL in curriculum.branches
        self.explores = self.scores_apart or self.learnability
        # A MUTATE branch: each replay batch's children are scored next (ACCEL).
        self.mutates = Branch.MUTATE in curriculum.branches
        self.requests: deque[tuple[LevelRequest, Call]] = deque()  # ACCEL children waiting
        self.key = jax.random.fold_in(jax.random.key(config.seed ^ BACKGROUND_KEY), start)
        self.issued = 0  # Explorer batches issued this session
        self.batches: dict[int, str] = {}  # Explorer batch -> "issued" | "committed"
        self.next_replay: Call | None = None  # drawn while the learner trains
        self.next_sfl: tuple[int, Call] | None = None  # (step, its SFL batch), the same
        self.sfl_key = jax.random.key(config.seed ^ SFL_BATCH_KEY)
        self.filled = False  # the buffer reached its minimum fill ratio (it never shrinks)
        self.group_commits = 0
        self.paused = False  # no new Explorer batches (while draining)
        self._key_block: tuple[int, list[jax.Array]] = (-1, [])

    # Explorers: kept busy -------------------------------------------------------------------

    def top_up(self) -> None:
        """Give every Explorer with room a batch: ACCEL's children first, else fresh levels."""
        if self.paused:
            return
        limit = self.config.ray.max_inflight
        for i in sorted(range(len(self.scorers)), key=self.inflight):
            if not self.actors.available(self.names[i]):
                continue
            while self.actors.has_room(self.names[i], limit):
                self.issue(i)

    def batch_keys(self, batch: int) -> tuple[jax.Array, jax.Array]:
        """(levels key, rollout key) of Explorer batch number `batch`: split by blocks of
        KEY_BLOCK batches (one JAX call per block, not per batch: the driver's CPU)."""
        block, index = divmod(batch, KEY_BLOCK)
        if self._key_block[0] != block:
            keys = jax.random.split(jax.random.fold_in(self.key, block), 2 * KEY_BLOCK)
            self._key_block = (block, list(keys))
        keys = self._key_block[1]
        return keys[2 * index], keys[2 * index + 1]

    def issue(self, i: int) -> None:
        """Explorer `i`'s next batch: ACCEL's children (made by the service), else fresh
        levels the Explorer makes itself from the batch's key (`score_fresh`: the generator
        is a pure function of its key, so the levels are the ones the service would make,
        and the service only inserts)."""
        n = self.config.learner.num_envs
        k_levels, key = self.batch_keys(self.issued)
        score = self.run.score
        then = "its batches are re-issued with the current policy on its restart"
        if self.learnability:  # SFL: fresh levels the Explorer makes, scored by learnability
            ued = self.config.ued
            size, steps = ued.sfl_batch_size, ued.sfl_rollout_steps
            request = LevelRequest("fresh", (k_levels, size), Source.RANDOM)
            batch = Batch(self.issued, request, key, self.learner.version, i, None)
            batch.score = Call(self.names[i], "learnability_fresh",
                               lambda: (self.learner.params, k_levels, size, key, steps),
                               then=then)
        elif self.requests:
            request, levels = self.requests.popleft()
            batch = Batch(self.issued, request, key, self.learner.version, i, levels)
            batch.score = Call(self.names[i], "score_levels",
                               lambda: (self.learner.params, levels.ref, key, score, None,
                                        None), then=then, after=(levels,))
        else:
            request = LevelRequest("fresh", (k_levels, n), Source.RANDOM)
            batch = Batch(self.issued, request, key, self.learner.version, i, None)
            batch.score = Call(self.names[i], "score_fresh",
                               lambda: (self.learner.params, k_levels, n, key, score),
                               then=then)
        self.batches[self.issued] = "issued"
        self.issued += 1
        self._submit(batch)

    def collect(self, block: bool) -> None:
        """Commit every Explorer result that is ready (waiting for one if `block`), in one
        group commit; refill the Explorers; take the service's acknowledgements."""
        if self.pending:
            group = []
            for batch, result in self.finished(block):
                accepted = self.accept(batch, result)
                if accepted is not None:
                    group.append(accepted)
            if group:
                self.commit_group(group)
        if self.explores:
            self.top_up()
        self.service.settle(block=False)

    def accept(self, batch: Batch, result: Any) -> tuple[Batch, Any, Any, int] | None:
        """`AsyncRun.accept`; a `score_fresh` result also brings its levels: kept on the
        batch (`made`) for its insert."""
        if batch.levels is None:
            batch.made = result[3]
            result = result[:3]
        return super().accept(batch, result)

    def commit_group(self, group: list[tuple[Batch, Any, Any, int]]) -> None:
        """Offer the scored batches of `group` to the buffer in one call (one fsync)."""
        calls = []
        ued = self.config.ued
        for j, (batch, scores, best, lag) in enumerate(group):
            request = batch.request
            if self.learnability:  # into the window of SFL's learnable set
                calls.append(("add_learnable", (Slot(j), scores), {}))
                explored = ued.sfl_batch_size * ued.sfl_rollout_steps
                self.run.sfl_scoring_steps += explored
            else:
                calls.append(("insert", (Slot(j), scores, best, batch.version, request.source),
                              {"parent_ids": request.parent_ids}))
                explored = self.config.learner.steps_per_update
            self.batches[batch.step] = "committed"
            self.stats.committed += 1
            self.stats.staleness[lag] += 1
            self.recent_lags.append(lag)
            self.stats.explored_steps += explored
        levels = tuple(batch.made if batch.levels is None else batch.levels
                       for batch, *_ in group)
        self.service.send_group(calls, levels)
        for batch, *_ in group:
            batch.made = None  # held by the group's call until it is acknowledged
        self.group_commits += 1

    def drain(self) -> None:
        """Wait for every batch in flight and every acknowledgement (before a snapshot)."""
        self.paused = True
        try:
            while self.pending:
                self.collect(block=True)
            self.service.settle(block=True)
        finally:
            self.paused = False

    def background_steps(self) -> int:
        """Env steps of the Explorer batches committed this session: every one was scored
        beside the learner's steps."""
        return self.stats.explored_steps

    def record(self) -> dict[str, Any]:
        return {**super().record(), "schedule": "continuous",
                "explorer_batches": dict(Counter(self.batches.values())),
                "group_commits": self.group_commits}

    # The learner: a replay step at every step -----------------------------------------------

    def wait_until_filled(self) -> None:
        """Commit Explorer results until the buffer holds its minimum fill ratio."""
        ued = self.config.ued
        need = max(1, math.ceil(ued.min_fill_ratio * ued.buffer_size))
        while not self.filled:
            self.service.settle(block=True)
            if (self.service.buffer_size() or 0) >= need:
                self.filled = True
                return
            self.top_up()
            self.collect(block=True)

    def serve_until(self, call: Call) -> None:
        """Commit Explorer results and refill the Explorers until `call` is answered."""
        while True:
            self.top_up()
            refs = [call.ref, *(c.ref for c in self.actors.in_flight(self.names))]
            ready, _ = self.ray.wait(refs, num_returns=1)
            if ready and ready[0] == call.ref:
                return
            if self.ray.wait([call.ref], timeout=0)[0]:
                return
            self.collect(block=False)

    def trained(self, step: int, train: Call) -> Any:
        """The answer of step `step`'s learner call `train`, serving the Explorers (commits,
        refills) while it runs; counts the step as trained and committed."""
        t0 = time.perf_counter()
        self.serve_until(train)
        answer = self.actors.get(train)
        self.stats.learner_busy_s += time.perf_counter() - t0
        self.stats.trained_steps += self.config.learner.steps_per_update
        self.learner.version += 1
        self.ledger[step] = "committed"
        return answer

    def step(self, step: int, key: jax.Array) -> tuple[Branch, dict[str, Any] | None, Any]:
        """Curriculum step `step`: a replay step on the learner, with the Explorers kept busy
        meanwhile (SFL: `sfl_step`; DR and PLR, which train on every batch: the sequential
        steps)."""
        if self.learnability:
            return self.sfl_step(step, key)
        if not self.scores_apart:
            return super().step(step, key)
        self.top_up()
        self.collect(block=False)
        self.wait_until_filled()
        n, score = self.config.learner.num_envs, self.run.score
        k_roll, k_edit = jax.random.split(key)
        replay = self.next_replay or self.service.send("replay", n, by_ref=True)
        version = self.learner.version
        train = self.actors.send(Call("learner", "train_replay",
                                      lambda: (replay.ref, k_roll, score), after=(replay,)))
        # The next batch is drawn while this one trains (it does not see this one's scores).
        self.next_replay = self.service.send("replay", n, by_ref=True)
        metrics, ids, scores, best = self.trained(step, train)
        self.service.forget(replay)  # answered: the learner trained on its result
        self.service.send("update", ids, scores, best, version)
        self.run.curriculum.observe(Branch.REPLAY, ids)
        if self.mutates:  # the children of this batch, next in line for an Explorer
            levels = self.actors.send(Call(SERVICE, "mutate_replay",
                                           lambda: (k_edit, replay.ref), after=(replay,)))
            self.requests.append((LevelRequest("mutate_replay", (k_edit,), Source.MUTATION,
                                               ids), levels))
            # Its children are asked for: nothing is pending for a snapshot to keep.
            self.run.curriculum.observe(Branch.MUTATE)
        metrics = UEDRun.step_metrics(metrics, Branch.REPLAY, True, self.learner.version)
        return Branch.REPLAY, metrics, None

    # SFL: a step on the learnable set as it stands ------------------------------------------

    def sfl_levels(self, step: int) -> Call:
        """Step `step`'s SFL batch (`LevelService.sfl_batch`), asked of the service (or already
        drawn, while the previous step trained); it goes to the learner by ref."""
        if self.next_sfl is not None and self.next_sfl[0] == step:
            return self.next_sfl[1]
        key = jax.random.fold_in(self.sfl_key, step)
        return self.actors.send(Call.of(SERVICE, "sfl_batch", key,
                                        self.config.learner.num_envs))

    def sfl_step(self, step: int, key: jax.Array) -> tuple[Branch, dict[str, Any], None]:
        """An SFL step: the learner trains on its SFL batch (fresh levels and the learnable
        set's) while the Explorers score learnability batches; it never waits for them."""
        self.top_up()
        self.collect(block=False)
        k_roll = jax.random.split(key, 3)[1]  # UEDRun.step's rollout key
        levels = self.sfl_levels(step)
        train = self.actors.send(Call("learner", "train", lambda: (levels.ref, k_roll),
                                      after=(levels,)))
        # The next batch is drawn while this one trains (it does not see the Explorer
        # results committed meanwhile).
        self.next_sfl = (step + 1, self.sfl_levels(step + 1))
        metrics = self.trained(step, train)
        self.run.curriculum.observe(Branch.SFL)
        metrics = UEDRun.step_metrics(metrics, Branch.SFL, True, self.learner.version)
        return Branch.SFL, metrics, None


__all__ = ["ContinuousRun"]
