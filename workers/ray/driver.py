"""The Ray driver: a UED run's workers as Ray actors, on this machine or a cluster.

    tabx train CONFIG --ray                  start Ray on this machine
    tabx train CONFIG --ray --address auto   join a running cluster (or HOST:PORT)

The driver process coordinates. It runs the curriculum, owns the JAX key chain and every object
ref that matters, and decides every batch: batch `s` is curriculum step `s`, played with the
key the chain gives that step, so any batch can be recomputed from the ledger. The actors wrap
the local classes (`workers.ray.actors`):

    LevelService  one, CPU: generator, ACCEL mutator, level buffer (the buffer's only writer)
    Learner       one, on a GPU where the cluster has one (`ray.learner_gpus`): the jitted
                  rollout + PPO update on the levels it is given
    Explorer      `ray.explorers` of them, CPU: score new and mutated levels (Robust PLR,
                  ACCEL), rank SFL's random batches by learnability, with the newest policy
                  the learner published
    Evaluator     one, CPU: the zero-shot suites, on its own schedule (`ued.eval_every`)

Levels and scores cross as numpy pytrees and come back as return values (owned by the driver);
policy parameters are fetched from the learner once per version and handed to Explorers as a
ref they pull only when it is newer than the one they hold. Every score carries the policy
version that produced it and its batch id; the buffer keeps the version.

Two modes (`ray.deterministic`):

- **asynchronous** (default): batches the learner does not train on go to Explorers and run
  beside the learner, each Explorer at most `ray.max_inflight` batches ahead. A result is
  committed when it arrives; one whose policy is more than `ray.max_policy_lag` versions older
  than the learner's is re-scored with the current policy instead (counted, `ray/rescored`).
- **deterministic**: every batch in step order, each committed before the next is decided,
  exactly the local driver's schedule: parameters and buffer equal the local driver's.

`ray.schedule: continuous` replaces the asynchronous mode's steps with continuous scoring
(`workers.ray.continuous`, handed to `RayDriver` by `workers.train.driver_for`).
"""

from __future__ import annotations

import os
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, TextIO

import jax

from tabx.files import atomic_write_json
from ued.config import ConfigError, TrainConfig
from ued.curricula import Branch
from ued.run_folder import LEVELS_DIR
from workers.driver import Callback, Driver, RunStopped
from workers.ray.actor_manager import (
    ActorDeaths,
    ActorManager,
    Call,
    death_cause,
    is_lost,
    names_actor,
)
from workers.ray.async_schedule import AsyncRun
from workers.ray.handles import ExplorerPool, RemoteEvaluator, RemoteLearner
from workers.ray.learner_group import LearnerGroup, Restarts
from workers.ray.restarts import SERVICE, Chaos, RemoteService
from workers.ray.start import (
    RAY_NAMESPACE,
    Workers,
    address_setting,
    check_reachable,
    connect,
    import_ray,
    join_address,
    keep_driver_off_accelerators,
    local_plan,
    local_resources,
    start_workers,
)
from workers.ray.stats import RateWindow, live_actors
from workers.resume import resume_point, what_resume_does
from workers.training_loop import Output, Report, Runner, train_loop
from workers.ued_step import UEDRun, branch_text

RAY_RECORD = "ray.json"  # in the run folder: where the actors run, what was committed


def driver_refs(ray: Any) -> int:
    """Object refs this process holds (`ray/driver_refs`): flat over a healthy run, whatever
    its length; a count that grows with the steps is a leak (objects pinned in the store)."""
    return len(ray._private.worker.global_worker.core_worker.get_all_reference_counts())


def lost_learner(ray: Any, err: BaseException, workers: Workers | None) -> bool:
    """Whether `err` stops the run for its lost learner (or a member of its learner group):
    the one loss `ray.learner_restarts` answers. The other actors restart in place
    (`ActorManager`); a stop after their restart budget, a call lost again and again, or the
    driver's own node is not cured by starting everything again."""
    if isinstance(err, RunStopped):
        return err.lost == "learner"
    if workers is None or not is_lost(ray, err):
        return False  # lost before the learner was there: nothing says it was the learner
    learner = workers.learner
    members = learner.members if isinstance(learner, LearnerGroup) else [learner]
    return any(names_actor(err, member._actor_id.hex()) for member in members)


def stop_reason(ray: Any, err: BaseException, workers: Workers | None) -> str | None:
    """Why the run stops where `err` means it cannot go on but can be resumed: a RunStopped
    (a learner lost, a call's failure budget spent, an actor not back) or a loss the
    ActorManager did not see (an actor or node lost at start-up, the driver's own raylet);
    None for any other error. A lost actor is named: `NAME died (CAUSE)`."""
    if isinstance(err, RunStopped):
        cause = err.__cause__
        if err.lost and cause is not None and is_lost(ray, cause):
            return f"{err.lost} died ({death_cause(cause)})"
        return str(err)
    if lost_learner(ray, err, workers):
        return f"learner died ({death_cause(err)})"
    if is_lost(ray, err) or isinstance(err, ray.exceptions.LocalRayletDiedError):
        return f"an actor of the run died ({death_cause(err)})"
    return None


def restarts_the_run(stopped: RunStopped, session: tuple[int, int] | None) -> bool:
    """Whether starting the run's actors again (`ray.learner_restarts`) answers `stopped`:
    the learner (or a learner-group member) lost, the one actor Ray does not restart in
    place, or any actor lost while the actors started (`session` None: before the first
    step), which nothing restarted. Another actor's stop mid-run came after Ray restarted it
    in place until its budget was spent: starting every actor again would meet the same
    fault."""
    return stopped.lost == "learner" or (bool(stopped.lost) and session is None)


def need_ued(config: TrainConfig) -> None:
    if not config.ued.enabled:
        raise ConfigError("ray.enabled: the Ray driver runs UED runs (ued.method); a plain "
                          "MARL run trains in one process: drop ray.enabled")


class RunRecord:
    """`RUN_DIR/ray.json`: written when the actors are up (`status: running`, the cluster's
    address and the actors' names, so that `tabx runs status` and `tabx runs buffer` can find
    the run), refreshed at every logged step, and final when the run ends or stops. A logged
    step's refresh (`background=True`) is written by a thread, off the step path; every other
    update waits until the file holds it."""

    def __init__(self, path: Path):
        self.path = path
        self.data: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._writer: threading.Thread | None = None

    def update(self, background: bool = False, **fields: Any) -> None:
        self.data.update(fields, updated=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        snapshot = dict(self.data)  # the values are replaced, never changed in place
        if self._writer is not None and self._writer.is_alive():
            if background:
                return  # the next refresh writes it; a logged step never waits for a write
            self._writer.join()
        if background:
            self._writer = threading.Thread(target=self._write, args=(snapshot,), daemon=True)
            self._writer.start()
        else:
            self._write(snapshot)

    def _write(self, snapshot: dict[str, Any]) -> None:
        with self._lock:
            atomic_write_json(self.path, snapshot)


class RayDriver(Driver):
    """Runs a UED run's workers as Ray actors (see the module doc). `schedules`: the
    asynchronous schedules other than the sequential `AsyncRun`, by `ray.schedule` name
    (`workers.train.driver_for` adds `workers.ray.continuous`'s)."""

    name = "ray"

    def __init__(self, schedules: dict[str, type[AsyncRun]] | None = None):
        self.schedules = dict(schedules or {})

    def check(self, config: TrainConfig) -> None:
        """Every refusal that needs no Ray: made before the run folder exists."""
        keep_driver_off_accelerators()
        need_ued(config)
        ray = import_ray()
        address, setting = address_setting(config.ray)
        if address:
            check_reachable(address, setting)
        elif not ray.is_initialized():
            local_plan(config.ray, *local_resources())

    def run(self, config: TrainConfig, run_dir: Path, *, resume: bool = False,
            max_updates: int | None = None, progress: bool = True,
            stream: TextIO | None = None, callback: Callback | None = None) -> Path:
        """The run, started again from its newest intact checkpoint (from step 0 before the
        first) after each stop for its lost learner (or a member of its learner group), or
        for an actor lost while the actors started, up to `ray.learner_restarts` times
        (`restarts_the_run`, `workers.ray.learner_group.Restarts`): the path `tabx train
        --resume` takes. A stop for another actor (restarted in place by Ray until its own
        budget was spent), or one with the budget spent, ends the run in one line naming
        what died and what `--resume` will do."""
        need_ued(config)
        keep_driver_off_accelerators()
        stream = sys.stderr if stream is None else stream
        restarts = Restarts(config.ray.learner_restarts)
        while True:
            self.runner: RayRunner | None = None
            try:
                return self.session(config, run_dir, resume=resume, max_updates=max_updates,
                                    progress=progress, stream=stream, callback=callback,
                                    restarts=restarts)
            except RunStopped as stopped:
                runner = self.runner
                session = (None if runner is None or runner.reached is None
                           else (runner.start, runner.reached))
                restart = restarts_the_run(stopped, session)
                reason = f"{stopped}{' while the run started' if session is None else ''}"
                latest, saved = resume_point(run_dir, config)
                if restart and restarts.left() and (latest is not None or not saved):
                    max_updates = restarts.restart(reason, latest, session, max_updates,
                                                   stream)
                    resume = True
                    continue
                spent = (f"; ray.learner_restarts ({restarts.limit}) spent"
                         if restart and not restarts.left() else "")
                text = f"{reason}{spent}; {what_resume_does(run_dir, config)}"
                stream.write(f"ray: the run stops: {text}\n")
                stream.flush()
                raise RunStopped(f"{run_dir}: {text}", lost=stopped.lost) from stopped

    def session(self, config: TrainConfig, run_dir: Path, *, resume: bool,
                max_updates: int | None, progress: bool, stream: TextIO,
                callback: Callback | None, restarts: Restarts) -> Path:
        """One start of the run's actors and `train_loop` over them."""
        ray = import_ray()
        plan = (None if join_address(config.ray) or ray.is_initialized()
                else local_plan(config.ray, *local_resources()))
        if plan is not None and plan.note:
            stream.write(plan.note + "\n")
            stream.flush()
        ray, started = connect(config.ray, None if plan is None else plan.cpus)
        workers = None
        record = RunRecord(run_dir / RAY_RECORD)
        run_name = f"{run_dir.name}-{uuid.uuid4().hex[:8]}"
        try:
            workers = start_workers(ray, config, stream, run_name, run_dir / LEVELS_DIR,
                                    None if plan is None else plan.explorer_cpus)
            record.update(status="running", driver_pid=os.getpid(),
                          address=ray.get_runtime_context().gcs_address,
                          namespace=RAY_NAMESPACE,
                          actors={name: f"{run_name}/{name}" for name in workers.names()},
                          **restarts.fields())
            self.runner = RayRunner(ray, workers, config, record, stream, self.schedules)
            run_dir = train_loop(self.runner, run_dir, resume=resume, max_updates=max_updates,
                                 progress=progress, stream=stream, callback=callback)
            record.update(status="finished")
            return run_dir
        except BaseException as err:
            reason = stop_reason(ray, err, workers)
            if reason is None:  # an error or Ctrl-C: the record says the run is over
                if record.data:
                    record.update(status="stopped", error=f"{type(err).__name__}: {err}")
                raise
            record.update(status="stopped", error=reason)
            lost = ("learner" if lost_learner(ray, err, workers) else
                    err.lost if isinstance(err, RunStopped) else "")
            raise RunStopped(reason, lost=lost) from err
        finally:
            if workers is not None:
                for actor in workers.all():
                    actor.kill(ray) if isinstance(actor, LearnerGroup) else ray.kill(actor)
            if started:
                ray.shutdown()


class RayRunner(Runner):
    """A UED run over the actors of `workers`, in `train_loop`: the deterministic mode plays
    each step as the local driver does (`UEDRun.step` over blocking calls), the asynchronous
    one on `AsyncRun`'s schedule."""

    snapshots = True
    explores = True

    def __init__(self, ray: Any, workers: Workers, config: TrainConfig, record: RunRecord,
                 stream: TextIO, schedules: dict[str, type[AsyncRun]] | None = None):
        super().__init__(config)
        self.schedules = {"sequential": AsyncRun, **(schedules or {})}
        self.ray, self.workers, self.record, self.stream = ray, workers, record, stream
        self.deaths = ActorDeaths(stream)  # logged even when quiet: a death is news
        # Every call to the run's actors goes through one manager (restarts, re-issue).
        self.actors = ActorManager(ray, self.deaths)
        workers.register(self.actors)
        self.service = RemoteService(ray, workers.service, self.actors)
        evaluators = [RemoteEvaluator(ray, workers.evaluator, i, name, self.actors)
                      for i, name in enumerate(config.ued.eval_suites)]
        pool = ExplorerPool(ray, workers.scorers(), workers.scorer_names(), self.actors)
        self.run = UEDRun(config, self.service, pool, evaluators)
        self.deterministic = config.ray.deterministic
        self.version, self.start = 0, 0
        self.counts = {b: 0 for b in Branch}  # this session's steps per branch
        self.metrics: dict[str, Any] = {}  # of the newest step that trained
        self.levels: Any = None  # played by the newest step, None if it went to an Explorer
        self.learner: RemoteLearner | None = None
        self.asynchronous: AsyncRun | None = None
        self.chaos: Chaos | None = None
        self._asked: tuple[Call, Call] | None = None  # the service's statistics, asked for
        # Steps done (a restart after a loss counts those since the checkpoint); None until
        # `begin`: a loss before it stopped the session before its first step.
        self.reached: int | None = None
        # trained and explored env steps/s in ray.json, over RATE_WINDOW_S
        self.rate = RateWindow()
        self.learner_first_s: float | None = None  # the learner's first update, compile included
        self.first_said = False

    @property
    def eval_every(self) -> int:
        return self.config.ued.eval_every if self.run.evaluators else 0

    def needs_buffer(self) -> bool:
        return self.service.buffer_size() is not None

    def init(self, key: jax.Array) -> None:
        self.actors.call("learner", "init", key)

    def template(self) -> Any:
        return self.actors.call("learner", "train_state")

    def restore(self, run_dir: Path, train_state: Any, start: int) -> str | None:
        self.version, note = self.run.resume(run_dir, start)
        self.actors.call("learner", "set_train_state", train_state, self.version)
        return note

    def begin(self, start: int) -> None:
        ray, workers, config = self.ray, self.workers, self.config
        self.start = self.reached = start
        self.rate = RateWindow()
        self.learner = RemoteLearner(ray, workers.learner, self.actors, self.version)
        placement = workers.placement(ray)
        group = workers.learner if isinstance(workers.learner, LearnerGroup) else None
        self.record.update(mode=self.mode, learner_gpus=workers.gpus,
                           learners=config.ray.learners, placement=placement, steps=[start, start],
                           **({"learner_nodes": group.nodes(ray)} if group else {}),
                           total_steps=config.learner.num_updates)
        if self.deterministic:
            self.asynchronous = None
        else:
            schedule = self.schedules.get(config.ray.schedule)
            if schedule is None:
                raise ConfigError(f"ray.schedule: {config.ray.schedule!r} is not among this "
                                  f"driver's schedules ({', '.join(self.schedules)})")
            self.asynchronous = schedule(ray, config, self.run, self.learner, workers,
                                         self.service, start=start)
        self.chaos = Chaos(ray, config.ray, list(zip(workers.names(), workers.all(),
                                                     strict=True)), self.stream)

    @property
    def mode(self) -> str:
        """deterministic, asynchronous (the sequential schedule) or continuous."""
        if self.deterministic:
            return "deterministic"
        return "continuous" if self.config.ray.schedule == "continuous" else "asynchronous"

    def headline(self, run_dir: Path, start: int) -> str:
        config, workers = self.config, self.workers
        mode = self.mode
        return (f"{config.ued.method} + {config.algorithm} on Ray ({mode}, "
                f"{len(workers.explorers)} explorers, learner "
                f"{'GPU' if workers.gpus else 'CPU'}) in {run_dir}; "
                f"{config.learner.num_updates} steps of {config.learner.steps_per_update:,} "
                f"env steps{f', from step {start}' if start else ''}")

    def schedule_fields(self) -> dict[str, Any]:
        """What `ray.json` says of the schedule so far (this session's branches)."""
        fields = {"branches": {b.name.lower(): n for b, n in self.counts.items()},
                  "restarts": dict(sorted(self.deaths.count.items()))}
        return {**fields, **(self.asynchronous.record() if self.asynchronous else {})}

    def background_steps(self) -> int:
        return self.asynchronous.background_steps() if self.asynchronous else 0

    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        asynchronous = self.asynchronous
        t0 = time.perf_counter()
        if asynchronous is None:
            branch, metrics, self.levels = self.run.step(self.learner, index, key)
        else:
            branch, metrics, self.levels = asynchronous.step(index, key)
        self.counts[branch] += 1
        self.run.branch_counts[branch] += 1
        self.chaos.after_step(index + 1, last)
        if metrics is not None:
            self.metrics = metrics
            if self.learner_first_s is None:  # the first step the learner trained on
                self.learner_first_s = time.perf_counter() - t0
        if asynchronous is not None and checkpoint_due:
            asynchronous.drain()  # a snapshot holds every issued batch's result
        self.reached = index + 1
        return self.run.curriculum.learns(branch)

    def host_metrics(self) -> dict[str, Any]:
        return dict(jax.device_get(self.metrics))

    def buffer_view(self, last: bool) -> tuple[dict[str, float], int | None]:
        """The level service's statistics and buffer size, off the step path: asked for at a
        logged step, read at the next one (so a logged step does not wait behind the
        service's queue); the first and the last logged step wait for them."""
        def ask() -> tuple[Call, Call]:
            return (self.actors.send(Call.of(SERVICE, "stats")),
                    self.actors.send(Call.of(SERVICE, "buffer_size")))

        asked = ask() if self._asked is None or last else self._asked
        view = self.actors.get(asked[0]), self.actors.get(asked[1])
        self._asked = None if last else ask()
        return view

    def log(self, values: dict[str, Any], report: Report) -> None:
        run, asynchronous = self.run, self.asynchronous
        values.update(report.timing)
        stats, buffer_size = self.buffer_view(report.last)
        values.update(run.logged_metrics(self.levels, stats))
        extra = branch_text(run.branch_counts, buffer_size)
        values["ray/driver_refs"] = float(driver_refs(self.ray))
        if asynchronous is not None:
            live = live_actors(self.ray, self.actors, self.workers.scorer_names()
                               if self.workers.explorers else [])
            values.update(asynchronous.stats.scalars(live, len(asynchronous.pending)))
            extra = asynchronous.stats.text(live, buffer_size)
        if self.learner_first_s is not None and not self.first_said:
            # The learner compiles at its first update, which may come steps after the first
            # logged one (new levels first): say so when it happens.
            self.first_said = True
            values["time/learner_first_update_s"] = self.learner_first_s
            if report.output.notes is not None:
                report.output.notes.write(f"  learner's first update: {self.learner_first_s:.1f}"
                                          f" s (compilation included)\n")
                report.output.notes.flush()
        report.show(values, None, extra=extra, callback=False)
        played = report.played  # the loop's trained and explored env steps (Explorers' too)
        rates = {}
        if played is not None and played.explored is not None:
            trained, explored = self.rate.add(played.trained, played.explored)
            rates = {"trained_steps_per_s": trained, "explored_steps_per_s": explored,
                     "rate_window_s": round(self.rate.span_s, 1)}
        self.record.update(background=True, steps=[self.start, report.done], **rates,
                           buffer_size=buffer_size, **self.schedule_fields())
        callback = report.output.callback
        if callback is not None:
            callback(report.done, self.learner.train_state,
                     {k: float(v) for k, v in values.items()})

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if due:
            if self.asynchronous is None:
                self.run.evaluate(self.learner, output.writer, done, output.notes)
            else:
                self.asynchronous.submit_evaluation(done)
        if self.asynchronous is not None:
            self.asynchronous.log_evaluations(output.writer, output.notes)

    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        if self.asynchronous is not None:  # a snapshot holds every issued batch's result
            self.asynchronous.drain()  # (done already at a due checkpoint; one after Ctrl-C)
        self.run.save(run_dir, done, self.learner)
        return self.learner.train_state, self.learner.version

    def finish(self, stop: int, output: Output) -> None:
        ray, workers = self.ray, self.workers
        if self.asynchronous is not None:
            self.asynchronous.drain()
            self.asynchronous.log_evaluations(output.writer, output.notes, block=True)
        try:  # where the actors ended (a restarted one may have moved)
            for name in workers.names():
                restarts = name.startswith("explorer") or name == "evaluator"
                if restarts and self.actors.available(name):
                    self.actors.wait_back(name, timeout_s=60)
            placement_end = workers.placement(ray)
        except Exception as err:
            if not (isinstance(err, RunStopped) or is_lost(ray, err)):
                raise
            placement_end = None
        self.record.update(placement_end=placement_end, steps=[self.start, stop],
                           chaos_kills=self.chaos.kills, **self.schedule_fields())


__all__ = ["RAY_NAMESPACE", "RAY_RECORD", "RayDriver", "RayRunner", "RunRecord", "connect",
           "import_ray"]
