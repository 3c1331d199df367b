"""The Ray driver's asynchronous schedule, run in this process over a stand-in for Ray whose
results are late on purpose: a score whose policy moved on by more than `ray.max_policy_lag`
versions is re-scored, never committed; every issued batch is committed exactly once.

The stand-in (`SlowRay`) runs each actor call at once but reports it ready only when the
driver blocks for it, so Explorer batches pile up to `ray.max_inflight` while the learner
trains: the stalest case the real cluster can produce, made deterministic. Ray is not needed.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
import pytest
from test_ued_train import ued_config

from level_buffer import Source
from ued.curricula import Branch
from workers.ray.actor_manager import ActorDeaths, ActorManager
from workers.ray.actors import ExplorerActor, LearnerActor, LevelServiceActor
from workers.ray.async_schedule import AsyncRun
from workers.ray.handles import ExplorerPool, RemoteLearner
from workers.ray.restarts import RemoteService
from workers.ray.start import Workers
from workers.ued_step import UEDRun


class Ref:
    def __init__(self, value: Any):
        self.value = value


class Actor:
    """An in-process object behind an actor handle: `handle.method.remote(...)` runs now."""

    def __init__(self, obj: Any):
        self._obj = obj

    def __getattr__(self, name: str) -> Any:
        method = getattr(self._obj, name)

        class Method:
            @staticmethod
            def remote(*args: Any, **kwargs: Any) -> Ref:
                # Like Ray, a ref passed as an argument arrives as its value.
                args = tuple(a.value if isinstance(a, Ref) else a for a in args)
                return Ref(method(*args, **kwargs))

        return Method


class SlowRay:
    """`ray.get` and `ray.wait`, with nothing ready unless the caller blocks."""

    def get(self, ref: Ref | list[Ref]) -> Any:
        return [r.value for r in ref] if isinstance(ref, list) else ref.value

    def wait(self, refs: list[Ref], num_returns: int = 1, timeout: float | None = None):
        if timeout == 0:
            return [], refs
        return refs[:num_returns], refs[num_returns:]


def wire_schedule(schedule_class: type, config: Any, ray: Any, workers: Workers,
                  deaths: Any = None) -> tuple[Any, RemoteService]:
    """`schedule_class` over `workers` (their learner initialised) as the Ray driver wires it:
    one ActorManager (its deaths written to `deaths`), the level service, the UED run with its
    Explorer pool. Returns (schedule, service)."""
    manager = ActorManager(ray, ActorDeaths(deaths))
    workers.register(manager)
    service = RemoteService(ray, workers.service, manager)
    run = UEDRun(config, service, ExplorerPool(ray, workers.scorers(), workers.scorer_names(),
                                               manager), [])
    schedule = schedule_class(ray, config, run, RemoteLearner(ray, workers.learner, manager),
                              workers, service=service)
    return schedule, service


def run_schedule(schedule_class: type, config: Any, ray: SlowRay, steps: int,
                 before_drain: Any = None, after_step: Any = None):
    """`steps` steps of `schedule_class` over in-process actors (one learner, the config's
    Explorers sharing its programs, the level service), then drained: (schedule, branches,
    the level service). `after_step(schedule)` runs after each step, `before_drain(schedule)`
    between the steps and the drain."""
    learner_actor = LearnerActor(config)
    explorer_actors = [ExplorerActor(config, learner_actor.learner)
                       for _ in range(config.ray.explorers)]
    for actor in explorer_actors:
        actor.cache.fetch = ray.get
    workers = Workers(Actor(LevelServiceActor(config)), Actor(learner_actor),
                      [Actor(a) for a in explorer_actors], None, 0.0)
    learner_actor.init(jax.random.key(0))
    schedule, _ = wire_schedule(schedule_class, config, ray, workers)
    key = jax.random.key(config.seed)
    branches = []
    for step in range(steps):
        key, k_step = jax.random.split(key)
        branches.append(schedule.step(step, k_step)[0])
        assert all(schedule.inflight(i) <= config.ray.max_inflight
                   for i in range(len(schedule.names)))
        if after_step is not None:
            after_step(schedule)
    if before_drain is not None:
        before_drain(schedule)
    schedule.drain()
    return schedule, branches, workers.service._obj


def run_async(max_policy_lag: int, steps: int = 14, method: str = "robust_plr",
              buffer_size: int = 32):
    config = ued_config(method, **{
        "ray.enabled": "true", "ray.explorers": 1, "ray.max_inflight": 2,
        "ray.max_policy_lag": max_policy_lag, "ued.replay_prob": 0.5,
        "ued.buffer_size": buffer_size, "ued.min_fill_ratio": 0.25})
    return run_schedule(AsyncRun, config, SlowRay(), steps)


@pytest.mark.parametrize("max_policy_lag", [0, 100])
def test_stale_scores_are_rescored_and_every_batch_committed_once(max_policy_lag):
    schedule, branches, service = run_async(max_policy_lag)
    new = branches.count(Branch.NEW)
    replay = branches.count(Branch.REPLAY)
    assert new + replay == len(branches) and replay >= 2  # the learner moved on meanwhile
    assert schedule.ledger == dict.fromkeys(range(len(branches)), "committed")
    assert schedule.stats.committed == new
    # Each committed batch offered its 4 levels once: none lost, none counted twice.
    assert service.buffer.stats["insert_attempts"] == 4 * new
    lags = set(schedule.stats.staleness)
    assert max(lags) <= max_policy_lag
    if max_policy_lag == 0:
        assert lags == {0} and schedule.stats.rescored >= 1
    else:  # late results are committed as they are, their lag counted
        assert schedule.stats.rescored == 0 and max(lags) >= 1
    versions = service.buffer.column("policy_version")
    assert np.all(versions <= schedule.learner.version)


def test_accel_children_are_asked_for_before_a_commit_can_evict_their_parents():
    """ACCEL's mutate step names the levels the replay step just drew; the results it commits
    while it waits for a free Explorer insert levels that, in a buffer of one batch, evict
    those parents. The children are asked for first, so every mutate step finds them."""
    schedule, branches, service = run_async(max_policy_lag=100, steps=16, method="accel",
                                            buffer_size=4)
    assert Branch.MUTATE in branches and branches.count(Branch.REPLAY) >= 2
    assert schedule.ledger == dict.fromkeys(range(len(branches)), "committed")
    assert service.buffer.stats["insert_attempts"] == 4 * schedule.stats.committed


class LateRay(SlowRay):
    """A result is ready at the second look that does not wait (or when the caller blocks):
    an Explorer batch issued before an ACCEL replay step arrives at the start of the mutate
    step after it, the order in which its insert can evict the replayed parents."""

    def __init__(self):
        self.looked: set[int] = set()

    def wait(self, refs: list[Ref], num_returns: int = 1, timeout: float | None = None):
        if timeout != 0:
            return refs[:num_returns], refs[num_returns:]
        ready = [r for r in refs if id(r) in self.looked][:num_returns]
        self.looked.update(id(r) for r in refs)
        return ready, [r for r in refs if r not in ready]


def test_accel_mutates_its_replayed_levels_even_when_a_commit_evicted_them():
    """Explorer results that arrive between ACCEL's replay step and its mutate step are
    committed first; in a buffer of one batch their inserts evict replayed parents. The
    mutate step edits the replayed levels themselves, so it never names a level the buffer
    may no longer hold: every step runs, and the children carry their parents' ids."""
    config = ued_config("accel", **{
        "ray.enabled": "true", "ray.explorers": 1, "ray.max_inflight": 2,
        "ray.max_policy_lag": 100, "ued.replay_prob": 0.5, "ued.buffer_size": 4,
        "ued.min_fill_ratio": 0.25})
    evicted_parents = []

    def watch(schedule):
        service = schedule.service.actor._obj
        pending = schedule.run.curriculum.last_replay_ids
        if pending and not set(pending) <= set(service.buffer.ids.tolist()):
            evicted_parents.append(pending)

    schedule, branches, service = run_schedule(AsyncRun, config, LateRay(), 40,
                                               after_step=watch)
    assert branches.count(Branch.MUTATE) >= 5
    assert evicted_parents, "the stand-in never evicted a parent: the test proves nothing"
    assert schedule.ledger == dict.fromkeys(range(len(branches)), "committed")
    assert service.buffer.stats["insert_attempts"] == 4 * schedule.stats.committed


def test_sfl_batches_go_to_every_explorer_before_any_result_is_awaited():
    log = []

    class Recording:
        def __init__(self, name):
            self.name = name

        def learnability(self, params, levels, key, num_steps):
            log.append(("run", self.name))
            return np.full(2, float(levels))

    class Gets(SlowRay):
        def get(self, ref):
            log.append(("get",))
            return super().get(ref)

    pool = ExplorerPool(Gets(), [Actor(Recording("a")), Actor(Recording("b"))], ["a", "b"],
                        ActorManager(Gets()))
    batches = [(level, jax.random.key(i)) for i, level in enumerate((1, 2, 3))]
    scores = pool.learnability_batches(None, batches, 8)
    assert [s[0] for s in scores] == [1.0, 2.0, 3.0]  # in batch order
    assert log[:3] == [("run", "a"), ("run", "b"), ("run", "a")]  # round-robin, all sent
    assert log[3:] == [("get",)] * 3  # before the first result is awaited


class PromptRay(SlowRay):
    """Every result ready at once (Explorers that keep pace with the learner)."""

    def wait(self, refs: list[Ref], num_returns: int = 1, timeout: float | None = None):
        return refs[:num_returns], refs[num_returns:]


def run_continuous(method: str, ray: SlowRay, steps: int = 6, max_policy_lag: int = 1,
                   before_drain: Any = None):
    from workers.ray.continuous import ContinuousRun

    config = ued_config(method, **{
        "ray.enabled": "true", "ray.explorers": 2, "ray.max_inflight": 2,
        "ray.schedule": "continuous", "ray.max_policy_lag": max_policy_lag,
        "ued.buffer_size": 32, "ued.min_fill_ratio": 0.25})
    return run_schedule(ContinuousRun, config, ray, steps, before_drain)


@pytest.mark.parametrize(("method", "ray"), [("robust_plr", SlowRay()),
                                             ("accel", PromptRay())])
def test_continuous_scoring_trains_every_step_and_commits_every_batch_once(method, ray):
    # SlowRay: Explorer results arrive only when the driver blocks (for the buffer's fill), so
    # batches pile up and go stale (re-scored); PromptRay: every result is ready at once, so
    # Explorers are refilled at every step. Every issued batch is committed once.
    schedule, branches, service = run_continuous(method, ray)
    assert branches == [Branch.REPLAY] * len(branches)  # every step trains on a replay batch
    assert schedule.ledger == dict.fromkeys(range(len(branches)), "committed")
    issued = schedule.issued
    assert issued >= (12 if isinstance(ray, PromptRay) else 4)
    assert schedule.batches == dict.fromkeys(range(issued), "committed")
    assert schedule.stats.committed == issued and not service_unanswered(schedule)
    # Each committed batch offered its 4 levels once: none lost, none counted twice.
    assert service.buffer.stats["insert_attempts"] == 4 * issued
    assert service.buffer.stats["updated"] >= 1  # replay scores came back (by id)
    assert max(schedule.stats.staleness) <= 1
    assert schedule.learner.version == len(branches)
    sources = set(service.buffer.column("source").tolist())
    assert (int(Source.MUTATION) in sources) == (method == "accel")
    if isinstance(ray, PromptRay):
        assert schedule.group_commits < issued  # results that arrived together: one commit
    else:
        assert schedule.stats.rescored >= 1  # stale when they arrived: scored again


def service_unanswered(schedule) -> list:
    return [c for c in schedule.service.unanswered if c not in schedule.service.by_ref]


def top_k_of(batches: list, k: int) -> tuple[Any, np.ndarray]:
    """The `k` most learnable levels of `batches` ([levels, scores], oldest first; ties: the
    earlier), and their scores: what SFL's learnable set holds (no episode ended: -1)."""
    levels = jax.tree.map(lambda *xs: np.concatenate(xs), *(b[0] for b in batches))
    scores = np.concatenate([np.asarray(b[1], np.float64) for b in batches])
    scores = np.where(np.isfinite(scores), scores, -1.0)
    order = np.argsort(-scores, kind="stable")[:k]
    return jax.tree.map(lambda x: np.asarray(x)[order], levels), scores[order]


def assert_learnable_is(service: Any, batches: list, config: Any) -> None:
    ued = config.ued
    levels, scores = top_k_of(batches[-ued.sfl_num_batches:], ued.sfl_top_k)
    learnable = service.learnable
    np.testing.assert_array_equal(learnable.scores, scores)
    stored = learnable.get(learnable.ids)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(stored),
                                                    jax.tree.leaves(levels), strict=True))


@pytest.mark.parametrize("ray", [SlowRay(), PromptRay()], ids=["slow", "prompt"])
def test_continuous_sfl_never_blocks_the_learner_and_keeps_the_top_k_committed(
        ray, monkeypatch, tmp_path):
    # SlowRay: Explorer results arrive only when the driver blocks, and an SFL step never
    # blocks on them: the learner trains on fresh levels only, and the drain commits them
    # (late: re-scored). PromptRay: results are committed at every step and the learnable set
    # serves the learner. Either way every scored batch is committed once, and the learnable
    # set is the top sfl_top_k of the newest sfl_num_batches batches committed.
    from workers.roles.level_service import LevelService

    committed, served = [], []
    add, batch = LevelService.add_learnable, LevelService.sfl_batch

    def add_learnable(self, levels, scores):
        committed.append((levels, np.asarray(scores)))
        return add(self, levels, scores)

    def sfl_batch(self, key, n):
        served.append(self.has_learnable())
        return batch(self, key, n)

    monkeypatch.setattr(LevelService, "add_learnable", add_learnable)
    monkeypatch.setattr(LevelService, "sfl_batch", sfl_batch)
    waited: list[float] = []
    schedule, branches, service = run_continuous(
        "sfl", ray, before_drain=lambda s: waited.append(s.stats.wait_for_levels_s))
    config = schedule.config
    assert branches == [Branch.SFL] * 6 and schedule.learner.version == 6
    assert waited == [0.0]  # no step waited for an Explorer
    assert schedule.ledger == dict.fromkeys(range(6), "committed")
    issued = schedule.issued
    assert schedule.batches == dict.fromkeys(range(issued), "committed")
    # Each scored batch applied once, by number: none lost, none twice.
    assert schedule.stats.committed == issued == len(committed) == service.seq
    assert not service_unanswered(schedule)
    scored = config.ued.sfl_batch_size * config.ued.sfl_rollout_steps
    assert schedule.run.sfl_scoring_steps == schedule.stats.explored_steps == issued * scored
    assert_learnable_is(service, committed, config)
    if isinstance(ray, PromptRay):  # the first results were in before the first batch
        assert issued >= 12 and all(served)
    else:  # nothing arrived before the drain: every batch trained on fresh levels only
        assert issued == 4 and not any(served) and schedule.stats.rescored >= 1
    # Distinct scores: the window holds the newest sfl_num_batches batches, an older batch's
    # best levels leave with it; the snapshot holds the window.
    rng = np.random.default_rng(0)
    for levels, _ in committed[:3]:
        service.add_learnable(levels, rng.permutation(config.ued.sfl_batch_size) / 100.0)
    assert_learnable_is(service, committed, config)
    service.save(tmp_path, 1, {})
    window = service.sfl_window.scores
    service.sfl_window = service.learnable = None
    service.load(tmp_path, 1)
    np.testing.assert_array_equal(service.sfl_window.scores, window)
    assert_learnable_is(service, committed, config)
