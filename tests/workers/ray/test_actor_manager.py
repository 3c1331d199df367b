"""The Ray driver's ActorManager against in-process stand-ins for Ray that raise Ray's own error
classes (no cluster): an Explorer killed by Ray's memory monitor (OutOfMemoryError, which is not
a RayActorError) is waited for and its batch re-issued, and the run goes on; a call that keeps
failing spends its budget and stops the run; an evaluation is given up instead; a learner
killed the same way stops the run with the resume command, as `tabx train` prints it.
"""

from __future__ import annotations

import io
import json
from types import SimpleNamespace
from typing import Any

import jax
import pytest
from test_ray_schedule import wire_schedule
from test_ued_train import ued_config

exceptions = pytest.importorskip("ray.exceptions")

from workers.driver import RunStopped  # noqa: E402
from workers.ray.actor_manager import ActorDeaths, ActorManager, Call  # noqa: E402


def oom(actor_id: str) -> Exception:
    """What Ray raises for a call in flight when its memory monitor kills the actor."""
    return exceptions.OutOfMemoryError(
        "Task was killed due to the node running low on memory.\nMemory on the node (IP: "
        f"10.0.0.1, ID: 0a1b) where the task (actor ID: {actor_id}, name=ExplorerActor."
        "__init__, pid=4242, memory used=3.1GB) was running was 7.6GB / 7.8GB (0.97), which "
        "exceeds the memory usage threshold of 0.95.")


class Ref:
    def __init__(self, value: Any = None, error: BaseException | None = None):
        self.value, self.error = value, error


class ActorId:
    def __init__(self, text: str):
        self.text = text

    def hex(self) -> str:
        return self.text


class Handle:
    """An in-process object behind an actor handle: `handle.method.remote(...)` runs now; what
    it raises comes back from `ray.get`, as Ray's errors do."""

    def __init__(self, obj: Any, actor_id: str):
        self._obj, self._actor_id = obj, ActorId(actor_id)

    def __getattr__(self, name: str) -> Any:
        method = getattr(self._obj, name)

        class Method:
            @staticmethod
            def remote(*args: Any, **kwargs: Any) -> Ref:
                args = tuple(a.value if isinstance(a, Ref) else a for a in args)
                try:
                    return Ref(method(*args, **kwargs))
                except Exception as err:
                    return Ref(error=err)

        return Method


class FakeRay:
    """`ray.get`, `ray.wait`, `ray.kill` and Ray's exception classes."""

    exceptions = exceptions

    def get(self, ref: Ref | list[Ref], timeout: float | None = None) -> Any:
        if isinstance(ref, list):
            return [self.get(r) for r in ref]
        if ref.error is not None:
            raise ref.error
        return ref.value

    def wait(self, refs: list[Ref], num_returns: int = 1, timeout: float | None = None):
        return refs[:num_returns], refs[num_returns:]

    def kill(self, actor: Any, no_restart: bool = True) -> None:
        pass

    def get_runtime_context(self) -> Any:
        return SimpleNamespace(gcs_address="127.0.0.1:6379", get_node_id=lambda: "node")


class MemoryKilled:
    """An actor process that Ray's memory monitor kills during the calls numbered `kill_at`
    of `method`: that call fails with OutOfMemoryError, and the actor answers `ready` only
    after one ActorUnavailableError (Ray restarts it)."""

    def __init__(self, obj: Any, method: str, kill_at: set[int] | None, actor_id: str):
        self.obj, self.method, self.kill_at, self.actor_id = obj, method, kill_at, actor_id
        self.calls, self.restarting, self.restarts = 0, False, 0

    def ready(self) -> bool:
        if self.restarting:
            self.restarting = False
            self.restarts += 1
            raise exceptions.ActorUnavailableError("The actor is restarting", None)
        return True

    def __getattr__(self, name: str) -> Any:
        target = getattr(self.obj, name)
        if name != self.method:
            return target

        def call(*args: Any, **kwargs: Any) -> Any:
            self.calls += 1
            if self.kill_at is None or self.calls in self.kill_at:
                self.restarting = True
                raise oom(self.actor_id)
            return target(*args, **kwargs)
        return call


def test_every_error_ray_raises_for_a_lost_actor_or_node_is_a_loss_and_no_other():
    from workers.ray.actor_manager import is_lost

    ray = FakeRay()
    lost = [exceptions.ActorDiedError(), exceptions.ActorUnavailableError("restarting", None),
            oom("e0" * 14), exceptions.NodeDiedError("node 0a1b died"),
            exceptions.ObjectLostError("ab" * 14, None, ""),
            exceptions.OwnerDiedError("ab" * 14, None, "")]
    assert all(is_lost(ray, err) for err in lost)
    bugs = [exceptions.ReferenceCountingAssertionError("ab" * 14, None, ""),
            exceptions.GetTimeoutError("late"), ValueError("the actor's own error")]
    assert not any(is_lost(ray, err) for err in bugs)


def test_an_explorer_killed_by_the_memory_monitor_restarts_and_its_batch_is_reissued():
    from workers.ray.actors import ExplorerActor, LearnerActor, LevelServiceActor
    from workers.ray.async_schedule import AsyncRun
    from workers.ray.start import Workers

    config = ued_config("robust_plr", **{
        "ray.enabled": "true", "ray.explorers": 1, "ray.max_inflight": 2,
        "ued.replay_prob": 0.5, "ued.buffer_size": 32, "ued.min_fill_ratio": 0.25})
    ray = FakeRay()
    learner_actor, explorer_actor = LearnerActor(config), ExplorerActor(config)
    explorer_actor.cache.fetch = ray.get
    explorer = MemoryKilled(explorer_actor, "score_levels", {3}, "e0" * 14)
    workers = Workers(Handle(LevelServiceActor(config), "5e" * 14),
                      Handle(learner_actor, "1e" * 14), [Handle(explorer, "e0" * 14)], None, 0.0)
    learner_actor.init(jax.random.key(0))
    out = io.StringIO()
    schedule, service = wire_schedule(AsyncRun, config, ray, workers, out)
    key = jax.random.key(config.seed)
    branches = []
    for step in range(8):
        key, k_step = jax.random.split(key)
        branches.append(schedule.step(step, k_step)[0])
    schedule.drain()
    assert explorer.calls > 3 and explorer.restarts == 1  # waited for, then sent again
    assert service.actors.deaths.count == {"explorer-0": 1}
    assert ("ray: explorer-0 died (Task was killed due to the node running low on memory.); "
            "its batches are re-issued with the current policy on its restart") in out.getvalue()
    assert schedule.stats.reissued == 1
    assert schedule.ledger == dict.fromkeys(range(8), "committed")  # the run went on
    new = schedule.stats.committed
    assert new >= 3  # the lost batch among them, committed once
    assert workers.service._obj.buffer.stats["insert_attempts"] == 4 * new


def test_calls_in_flight_come_back_as_values_or_errors_and_lost_ones_are_sent_again():
    # The manager keeps submitted calls in flight with their tags (a cap per actor for the
    # caller to keep), sends a lost one again with the arguments of the moment (and its
    # `before_send` hook), and hands back values, or an error for an optional call given up.
    ray = FakeRay()
    actors = ActorManager(ray, ActorDeaths(None), max_failures=2)

    class Work:
        def score(self, x):
            return 10 * x

    flaky = MemoryKilled(Work(), "score", {1}, "e3" * 14)  # its first call is killed
    dead = MemoryKilled(Work(), "score", None, "e4" * 14)  # every call killed
    actors.add("explorer-0", Handle(flaky, "e3" * 14), restarts=True)
    actors.add("evaluator", Handle(dead, "e4" * 14), restarts=True)
    policy = {"version": 1}
    sent_with = []
    batch = Call("explorer-0", "score", lambda: (policy["version"],),
                 before_send=lambda: sent_with.append(policy["version"]))
    actors.submit(batch, tag="batch-0")
    actors.submit(Call.of("explorer-0", "score", 5), tag="batch-1")
    assert actors.tags() == ["batch-0", "batch-1"]
    assert not actors.has_room("explorer-0", 2) and actors.has_room("explorer-0", 3)
    evaluation = Call.of("evaluator", "score", 7)
    evaluation.optional = True
    actors.submit(evaluation, tag="eval")
    policy["version"] = 2  # the learner moved on before the loss was seen
    done = actors.fetch_ready(["explorer-0"])
    assert [(r.tag, r.value, r.error) for r in done] == [("batch-1", 50, None)]
    assert actors.tags(["explorer-0"]) == ["batch-0"] and sent_with == [1, 2]
    assert actors.resent["explorer-0"] == 1  # sent again with the current policy
    assert [(r.tag, r.value) for r in actors.fetch_ready(["explorer-0"], block=True)] == [
        ("batch-0", 20)]
    given_up = []
    while actors.in_flight(["evaluator"]):
        given_up += actors.fetch_ready(["evaluator"])
    assert [(r.tag, type(r.error).__name__) for r in given_up] == [("eval", "OutOfMemoryError")]
    assert not actors.in_flight() and dead.calls == 2


def test_a_call_lost_too_often_stops_the_run_and_an_optional_one_is_given_up():
    ray = FakeRay()
    out = io.StringIO()
    actors = ActorManager(ray, ActorDeaths(out), max_failures=3)

    class Work:
        def score(self, x):
            return x

    explorer = MemoryKilled(Work(), "score", None, "e1" * 14)  # killed on every call
    actors.add("explorer-0", Handle(explorer, "e1" * 14), restarts=True)
    with pytest.raises(RunStopped, match="explorer-0: score was lost 3 times in a row "
                                         r"\(Task was killed"):
        actors.call("explorer-0", "score", 1, then="score runs again on its restart")
    assert actors.deaths.count == {"explorer-0": 3} and explorer.calls == 3
    # The same losses on an optional call: given up, the run goes on.
    call = actors.send(Call.of("explorer-0", "score", 2))
    call.optional = True
    while True:
        with pytest.raises(exceptions.OutOfMemoryError) as lost:
            ray.get(call.ref)
        if not actors.recover(call, lost.value):
            break
        actors.send(call)
    assert call.failures == 3 and actors.available("explorer-0")
    # An error of the actor's own code is no loss: it raises as it is.
    actors.add("worker", Handle(Work(), "e2" * 14), restarts=True)
    with pytest.raises(TypeError):
        actors.call("worker", "score", 1, 2)
    assert actors.deaths.count == {"explorer-0": 6}


def test_a_learner_killed_by_the_memory_monitor_restarts_the_run_then_stops_with_what_resume_does(
        tmp_path, monkeypatch, capsys):
    """A learner the memory monitor kills at its first call, every time (a stand-in): the
    run starts again from step 0 (it has no checkpoint) `ray.learner_restarts` times (2 by
    default), each time saying so, then stops in one line naming the learner, the cause, the
    spent budget and what `--resume` will do."""
    import workers.ray.driver as ray_driver
    from tabx_ued.cli import main
    from ued.run_folder import create_run_dir
    from workers.ray.driver import RAY_RECORD
    from workers.ray.start import Workers

    class Learner:
        def init(self, key):
            raise oom("1e" * 14)

    class Service:
        pass

    ray = FakeRay()
    workers = Workers(Handle(Service(), "5e" * 14), Handle(Learner(), "1e" * 14), [], None, 0.0)
    monkeypatch.setattr(ray_driver, "connect", lambda section, num_cpus=None: (ray, False))
    monkeypatch.setattr(ray_driver, "start_workers", lambda *args: workers)
    config = ued_config("robust_plr", **{"ray.enabled": "true", "ray.explorers": 0})
    run_dir = create_run_dir(config, tmp_path / "run")
    assert main(["train", "--resume", str(run_dir), "--ray", "--quiet"]) == 2
    err = capsys.readouterr().err
    died = ("learner died (Task was killed due to the node running low on memory.) while the "
            "run started")
    for n in (1, 2):
        assert (f"ray: {died}: restart {n} of 2 (ray.learner_restarts): the run has no "
                f"checkpoint yet: it starts again from step 0; 0 steps lost (0 in all)") in err
    assert err.strip().splitlines()[-1] == (
        f"tabx train: error: {run_dir}: {died}; ray.learner_restarts (2) spent; no checkpoint "
        f"yet: tabx train --resume {run_dir} starts it again from step 0")
    assert "Traceback" not in err and "unexpected" not in err
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["status"] == "stopped" and "learner died" in record["error"]


class ServiceKilled:
    """A level service (with its commit log in `folder`) whose process dies during its group
    commits numbered `kill_at`, before logging them; Ray restarts it: its constructor again,
    which restores every logged call."""

    def __init__(self, config: Any, folder: str, kill_at: set[int]):
        from workers.ray.actors import LevelServiceActor

        self.make = lambda: LevelServiceActor(config, folder, "session")
        self.obj, self.kill_at = self.make(), kill_at
        self.groups, self.restarting, self.restarts = 0, False, 0

    def ready(self) -> bool:
        if self.restarting:
            self.restarting = False
            self.restarts += 1
            self.obj = self.make()
            raise exceptions.ActorUnavailableError("The actor is restarting", None)
        return True

    def __getattr__(self, name: str) -> Any:
        if name != "apply_many":
            return getattr(self.obj, name)

        def call(*args: Any) -> Any:
            self.groups += 1
            if self.groups in self.kill_at:
                self.restarting = True
                raise exceptions.ActorDiedError()
            return self.obj.apply_many(*args)
        return call


def continuous_run_with_deaths(config: Any, tmp_path: Any, scoring_call: str,
                               service_deaths: set[int], steps: int, branch: str
                               ) -> tuple[Any, ...]:
    """`steps` steps of the continuous schedule (each a `branch` step), then its drain, over
    stand-in actors whose Explorer is killed during its third `scoring_call` and whose service
    dies in the group commits numbered `service_deaths`: (schedule, Explorer, service actor,
    RemoteService, the deaths' log)."""
    from workers.ray.actors import ExplorerActor, LearnerActor
    from workers.ray.continuous import ContinuousRun
    from workers.ray.start import Workers

    ray = FakeRay()
    learner_actor = LearnerActor(config)
    explorer_actor = ExplorerActor(config, learner_actor.learner)
    explorer_actor.cache.fetch = ray.get
    explorer = MemoryKilled(explorer_actor, scoring_call, {3}, "e0" * 14)
    service_actor = ServiceKilled(config, str(tmp_path / "levels"), service_deaths)
    workers = Workers(Handle(service_actor, "5e" * 14), Handle(learner_actor, "1e" * 14),
                      [Handle(explorer, "e0" * 14)], None, 0.0)
    learner_actor.init(jax.random.key(0))
    out = io.StringIO()
    schedule, service = wire_schedule(ContinuousRun, config, ray, workers, out)
    key = jax.random.key(config.seed)
    for step in range(steps):
        key, k_step = jax.random.split(key)
        assert schedule.step(step, k_step)[0].name == branch
    schedule.drain()
    return schedule, explorer, service_actor, service, out


def test_continuous_scoring_commits_every_batch_once_when_an_explorer_and_the_service_die(
        tmp_path):
    # ACCEL on the continuous schedule; the Explorer is killed during its third batch, the
    # service during its second and fifth group commits: the lost batch is re-issued, the
    # lost group sent again (numbered: nothing applied twice), and every batch is committed
    # once. (With real SIGKILLs: tests/workers/ray/test_ray_driver.py, -m slow.)
    from level_buffer import Source

    config = ued_config("accel", **{
        "ray.enabled": "true", "ray.explorers": 1, "ray.max_inflight": 2,
        "ray.schedule": "continuous", "ued.buffer_size": 32, "ued.min_fill_ratio": 0.25})
    schedule, explorer, service_actor, service, out = continuous_run_with_deaths(
        config, tmp_path, "score_levels", {2, 5}, steps=6, branch="REPLAY")
    assert explorer.restarts == 1 and service_actor.restarts == 2, out.getvalue()
    assert service.actors.deaths.count == {"explorer-0": 1, "service": 2}
    assert schedule.stats.reissued == 1
    committed = schedule.stats.committed
    assert committed >= 6 and schedule.batches == dict.fromkeys(range(schedule.issued),
                                                                "committed")
    buffer = service_actor.obj.buffer
    assert buffer.stats["insert_attempts"] == 4 * committed  # none lost, none twice
    assert int(Source.MUTATION) in set(buffer.column("source").tolist())  # ACCEL's children


def test_continuous_sfl_commits_every_scored_batch_once_when_an_explorer_and_the_service_die(
        tmp_path):
    # SFL on the continuous schedule: the Explorer is killed during its third learnability
    # batch, the service during its second group commit. The commit log holds every scored
    # batch once (the service restarted from it). (Without deaths, and the learnable set's
    # contents: tests/workers/ray/test_ray_schedule.py.)
    from level_buffer.commit_log import read
    from workers.ray.durable_service import LOG_NAME

    config = ued_config("sfl", **{"ray.enabled": "true", "ray.explorers": 1,
                                  "ray.max_inflight": 2, "ray.schedule": "continuous"})
    schedule, explorer, service_actor, _, out = continuous_run_with_deaths(
        config, tmp_path, "learnability_fresh", {2}, steps=4, branch="SFL")
    assert explorer.restarts == 1 and service_actor.restarts == 1, out.getvalue()
    assert schedule.stats.reissued == 1
    committed = schedule.stats.committed
    assert committed >= 4 and schedule.batches == dict.fromkeys(range(schedule.issued),
                                                                "committed")
    records = read(tmp_path / "levels" / LOG_NAME.format(0)).records
    assert [r[1] for r in records] == ["add_learnable"] * committed  # none lost, none twice
    assert [r[0] for r in records] == list(range(1, committed + 1))
    assert service_actor.obj.has_learnable()
