"""`tabx bench ued`: a UED run's throughput on the local driver and on Ray, by Explorer count.

Protocol (docs/benchmarks_distributed.md, "Distributed UED"): one UED config (default
configs/ued/quickstart.yaml, evaluation off) runs `--warmup` curriculum steps (actor start-up
and compilation), then `--steps` timed steps, on

- the local driver: every worker in this process, one after another;
- the Ray driver's deterministic schedule with 0 Explorers: the local driver's very steps over
  actors. The two are timed in turn, step by step (step `i` of one, then of the other), so
  the machine's slow minutes fall on both; the median of their per-step ratios is the Ray
  path's overhead;
- the Ray driver's asynchronous schedule with each `--explorers` count (0: the learner actor
  scores the new levels too), its actors started afresh for each count.

Warm-up lasts until every branch of the curriculum has run once, so that no timed step
compiles.

Per setting it reports trained env steps/s (steps the learner trained on) and explored env
steps/s (steps spent scoring levels that were not trained on: Robust PLR's and ACCEL's new and
mutated batches, SFL's learnability rollouts), the learner's busy fraction, the driver's time
waiting for Explorer results, and the staleness histogram (policy versions between a score's
policy and the learner's at commit).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import jax
import numpy as np

from tabx.errors import UserError
from tabx.files import atomic_write_text
from tabx_bench.arguments import int_at_least, int_list, seconds_up_to
from ued.config import ConfigError, TrainConfig, load_config
from ued.experiment import learner_for
from workers.roles.learner import LearnerWorker
from workers.ued_step import UEDRun

DEFAULT_CONFIG = "ued/quickstart"  # a shipped config (ued.config_files)
# --simulate's bounds: stand-in Explorers (each a slot of an actor; 4096 is 64 times the
# largest count docs/benchmarks_distributed.md measures), the seconds a stand-in batch or
# learner step sleeps, and the timed seconds per count.
MAX_SIMULATED = 4096
MAX_SIM_STEP_S = 3600.0
MAX_SIM_SECONDS = 86400.0


@dataclass
class UEDBenchResult:
    driver: str  # "local" | "ray" (asynchronous) | "ray-deterministic" (the local schedule)
    # | "ray-continuous" (continuous scoring)
    explorers: int  # Explorer actors (0 on the local driver and for the learner-scores case)
    method: str
    steps: int  # timed curriculum steps
    seconds: float
    trained_steps: int  # env steps trained on
    explored_steps: int  # env steps spent scoring levels not trained on
    learner_busy_fraction: float
    wait_for_levels_s: float
    staleness: dict[str, int] = field(default_factory=dict)
    rescored: int = 0
    branches: dict[str, int] = field(default_factory=dict)
    step_seconds: list[float] = field(default_factory=list)  # per timed step (not async)
    learners: int = 1  # learner actors of the group (`ray.learners`)

    @property
    def trained_per_s(self) -> float:
        return self.trained_steps / self.seconds

    @property
    def explored_per_s(self) -> float:
        return self.explored_steps / self.seconds

    @property
    def label(self) -> str:
        if self.driver == "local":
            return "local"
        explorers = f"{self.explorers} explorer{'' if self.explorers == 1 else 's'}"
        if self.driver == "ray-deterministic":
            return f"ray, {explorers}, deterministic"
        group = f", {self.learners} learners" if self.learners > 1 else ""
        if self.driver == "ray-continuous":
            return f"ray, {explorers}, continuous{group}"
        return f"ray, {explorers}{group}"

    def to_json(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out.update(trained_per_s=self.trained_per_s, explored_per_s=self.explored_per_s)
        return out


def _steps_of(run: UEDRun, config: TrainConfig, branches: Counter) -> tuple[int, int]:
    """(trained, explored) env steps of the branches counted, SFL's scoring included."""
    per = config.learner.steps_per_update
    trained = sum(n for b, n in branches.items() if run.curriculum.learns(b)) * per
    explored = sum(n for b, n in branches.items() if not run.curriculum.learns(b)) * per
    return trained, explored + run.sfl_scoring_steps


class Warmup:
    """Untimed steps: at least `steps`, and until every branch of the curriculum has run once
    (so that each of its programs is compiled), at most `patience` times `steps`."""

    def __init__(self, run: UEDRun, steps: int, patience: int = 10,
                 branches: Any = None):
        self.expected = set(run.curriculum.branches if branches is None else branches)
        self.seen: set = set()
        self.steps, self.limit, self.count = steps, steps * patience, 0

    def saw(self, branch: Any) -> None:
        self.seen.add(branch)
        self.count += 1

    @property
    def done(self) -> bool:
        return self.count >= self.limit or (self.count >= self.steps
                                            and self.seen >= self.expected)


class LocalStepper:
    """The local driver's step loop, in this process, one step per call."""

    driver = "local"

    def __init__(self, config: TrainConfig):
        self.config = config
        self.run, ppo = UEDRun.local(config)
        self.key, k_init = jax.random.split(jax.random.key(config.seed))
        self.learner = LearnerWorker(ppo, ppo.init(k_init))
        self.index = 0

    def step(self) -> Any:
        self.key, k_step = jax.random.split(self.key)
        branch = self.run.step(self.learner, self.index, k_step)[0]
        jax.block_until_ready(self.learner.train_state)
        self.index += 1
        return branch

    def close(self) -> None:
        pass


class RayStepper:
    """The Ray driver on fresh actors, one step per call: its asynchronous schedule, or with
    `ray.deterministic` the local driver's schedule over the actors (the local work)."""

    def __init__(self, ray: Any, config: TrainConfig, stream: TextIO):
        from workers.ray.actor_manager import ActorDeaths, ActorManager
        from workers.ray.async_schedule import AsyncRun
        from workers.ray.handles import ExplorerPool, RemoteLearner
        from workers.ray.restarts import RemoteService
        from workers.ray.start import start_workers

        self.ray, self.config = ray, config
        self.workers = start_workers(ray, config, stream)
        continuous = config.ray.schedule == "continuous"
        self.driver = ("ray-deterministic" if config.ray.deterministic else
                       "ray-continuous" if continuous else "ray")
        # One RemoteService for the run and the schedule: it numbers the state-changing calls.
        actors = ActorManager(ray, ActorDeaths(None))
        self.workers.register(actors)
        service = RemoteService(ray, self.workers.service, actors)
        self.run = UEDRun(config, service, ExplorerPool(ray, self.workers.scorers(),
                                                        self.workers.scorer_names(), actors))
        self.key, k_init = jax.random.split(jax.random.key(config.seed))
        ray.get(self.workers.learner.init.remote(k_init))
        self.learner = RemoteLearner(ray, self.workers.learner, actors)
        if continuous:
            from workers.ray.continuous import ContinuousRun

            self.schedule = ContinuousRun(ray, config, self.run, self.learner, self.workers,
                                          service)
        else:
            self.schedule = AsyncRun(ray, config, self.run, self.learner, self.workers, service)
        self.index = 0

    @property
    def branches(self) -> Any:
        """The branches its steps take (continuous scoring: replay steps only)."""
        if getattr(self.schedule, "scores_apart", False):
            from ued.curricula import Branch

            return {Branch.REPLAY}
        return None

    def step(self) -> Any:
        self.key, k_step = jax.random.split(self.key)
        if self.config.ray.deterministic:
            branch = self.run.step(self.learner, self.index, k_step)[0]
        else:
            branch = self.schedule.step(self.index, k_step)[0]
        self.index += 1
        return branch

    def settle(self) -> None:
        """Wait for the batches in flight and the learner."""
        self.schedule.drain()
        self.ray.get(self.workers.learner.version.remote())

    def close(self) -> None:
        from workers.ray.learner_group import LearnerGroup

        for actor in self.workers.all():
            actor.kill(self.ray) if isinstance(actor, LearnerGroup) else self.ray.kill(actor)


def _warm_up(stepper: LocalStepper | RayStepper, warmup: int) -> None:
    warm = Warmup(stepper.run, warmup, branches=getattr(stepper, "branches", None))
    while not warm.done:
        warm.saw(stepper.step())
    if isinstance(stepper, RayStepper):
        stepper.settle()
    stepper.run.sfl_scoring_steps = 0


def _result(stepper: LocalStepper | RayStepper, branches: Counter,
            step_seconds: list[float], seconds: float) -> UEDBenchResult:
    config = stepper.config
    steps = sum(branches.values())
    counts = {b.name.lower(): n for b, n in branches.items()}
    explorers = len(stepper.workers.explorers) if isinstance(stepper, RayStepper) else 0
    if stepper.driver not in ("ray", "ray-continuous"):  # every step waited: the local
        # accounting
        trained, explored = _steps_of(stepper.run, config, branches)
        busy = 1.0 if stepper.driver == "local" else float("nan")
        return UEDBenchResult(stepper.driver, explorers, config.ued.method, steps, seconds,
                              trained, explored, learner_busy_fraction=busy,
                              wait_for_levels_s=0.0, branches=counts, step_seconds=step_seconds)
    stats = stepper.schedule.stats
    # SFL's scoring: on the learner's steps (sequential), or among the Explorers' batches
    # (continuous, already in `explored_steps`).
    sfl = 0 if getattr(stepper.schedule, "learnability", False) else stepper.run.sfl_scoring_steps
    return UEDBenchResult(
        stepper.driver, explorers, config.ued.method, steps, seconds, stats.trained_steps,
        stats.explored_steps + sfl,
        learner_busy_fraction=stats.learner_busy_s / seconds,
        wait_for_levels_s=stats.wait_for_levels_s,
        staleness={str(k): v for k, v in sorted(stats.staleness.items())},
        rescored=stats.rescored, branches=counts, learners=config.ray.learners)


def bench_interleaved(steppers: list[LocalStepper | RayStepper], warmup: int,
                      steps: int) -> list[UEDBenchResult]:
    """Warm every stepper up, then time them step by step in turn (step `i` of each, then
    step `i + 1`), so that a slow minute of the machine slows all of them alike."""
    for stepper in steppers:
        _warm_up(stepper, warmup)
    branches = [Counter() for _ in steppers]
    step_seconds: list[list[float]] = [[] for _ in steppers]
    for _ in range(steps):
        for i, stepper in enumerate(steppers):
            started = time.perf_counter()
            branches[i][stepper.step()] += 1
            step_seconds[i].append(time.perf_counter() - started)
    return [_result(s, b, t, sum(t)) for s, b, t in zip(steppers, branches, step_seconds,
                                                          strict=True)]


def bench_async(ray: Any, config: TrainConfig, warmup: int, steps: int,
                stream: TextIO) -> UEDBenchResult:
    """The asynchronous schedule on fresh actors, timed from the first timed step until every
    batch it issued is committed."""
    from workers.ray.stats import RayStats

    stepper = RayStepper(ray, config, stream)
    try:
        _warm_up(stepper, warmup)
        stepper.schedule.stats = RayStats()
        branches: Counter = Counter()
        for _ in range(steps):
            branches[stepper.step()] += 1
        stepper.settle()
        seconds = time.perf_counter() - stepper.schedule.stats.t0
        return _result(stepper, branches, [], seconds)
    finally:
        stepper.close()


def run_ued_bench(config: TrainConfig, explorers: list[int], warmup: int, steps: int,
                  local: bool = True, stream: TextIO | None = None,
                  restarts: list[RestartResult] | None = None,
                  learners: tuple[int, ...] = (1,)) -> list[UEDBenchResult]:
    """Every setting in turn (see the module doc); a line per setting on `stream`. With a
    `restarts` list, an Explorer's restart is timed too (compilation cache off, then on) and
    appended to it. `learners`: the asynchronous settings run with each learner-group size
    (`ray.learners`)."""
    from workers.ray.start import connect

    stream = sys.stderr if stream is None else stream
    results: list[UEDBenchResult] = []

    def report(result: UEDBenchResult, started: float) -> None:
        stream.write(f"  {result.label}: {result.trained_per_s:,.0f} trained + "
                     f"{result.explored_per_s:,.0f} explored env steps/s, learner busy "
                     f"{_percent(result.learner_busy_fraction)}, waited "
                     f"{result.wait_for_levels_s:.1f} s for levels "
                     f"({time.perf_counter() - started:.0f} s)\n")
        stream.flush()

    def label(driver: str, n: int) -> str:
        return UEDBenchResult(driver, n, "", 1, 1, 0, 0, 0, 0).label

    labels = ([label("local", 0), label("ray-deterministic", 0)] if local else []) + [
        label("ray-continuous" if config.ray.schedule == "continuous" else "ray", n)
        + (f", {g} learners" if g > 1 else "") for g in learners
        for n in explorers]
    stream.write(f"bench ued: {config.ued.method}, at least {warmup} warm-up + {steps} timed "
                 f"steps of {config.learner.steps_per_update:,} env steps; settings: "
                 f"{'; '.join(labels)}\n")
    stream.flush()
    if not config.ray.address and not config.ray.num_cpus:
        # A Ray started here gets a logical CPU per actor that reserves one (a learner and
        # the most Explorers asked for), whatever the core count: the bench measures sharing.
        config = dataclasses.replace(config, ray=dataclasses.replace(
            config.ray, num_cpus=max([0, *explorers]) + max(learners)))

    def setting(n: int, deterministic: bool, group: int = 1) -> TrainConfig:
        # The deterministic schedule is the sequential one (whatever ray.schedule says).
        schedule = "sequential" if deterministic else config.ray.schedule
        return dataclasses.replace(config, ray=dataclasses.replace(
            config.ray, enabled=True, explorers=n, deterministic=deterministic,
            schedule=schedule, learners=group)).validate()

    ray, connected_here = connect(config.ray)
    try:
        if local:
            # The local driver and the Ray driver's deterministic schedule with 0 Explorers
            # play the same steps; interleaved, their ratio is the Ray path's overhead.
            started = time.perf_counter()
            steppers: list[LocalStepper | RayStepper] = [LocalStepper(config)]
            try:
                steppers.append(RayStepper(ray, setting(0, True), stream))
                results += bench_interleaved(steppers, warmup, steps)
            finally:
                for stepper in steppers:
                    stepper.close()
            for result in results:
                report(result, started)
        for group in learners:
            for n in explorers:
                started = time.perf_counter()
                results.append(bench_async(ray, setting(n, False, group), warmup, steps,
                                           stream))
                report(results[-1], started)
        if restarts is not None:
            restarts += [bench_restart(ray, config, cache, stream) for cache in (False, True)]
    finally:
        if connected_here:
            ray.shutdown()
    return results


@dataclass
class RestartResult:
    """An Explorer killed and restarted: seconds from the kill until it answers again, and
    until its first scored batch (compiled again, or loaded from the compilation cache)."""

    compile_cache: bool
    first_score_s: float  # of the fresh actor: start-up and compilation
    ready_s: float
    restarted_score_s: float
    service_commits: int = 0  # logged commits the LevelService replayed on its restart
    service_ready_s: float = 0.0  # from its kill until it answers with them restored


def bench_restart(ray: Any, config: TrainConfig, compile_cache: bool,
                  stream: TextIO, cache_dir: str | None = None) -> RestartResult:
    """Start an Explorer, score a batch, kill its process (`ray.kill`, restart allowed), and
    time its return. With `compile_cache` the actor reads and writes a fresh persistent
    compilation cache (so the restart finds what the first life compiled), else none;
    `cache_dir` names the cache folder instead of a fresh one (the tests pass their
    session's, whose programs are compiled already: the same steps, without the compile)."""
    import tempfile

    from workers.ray.actors import ExplorerActor, LevelServiceActor, ParamsRef
    from workers.ray.start import actor_env

    with tempfile.TemporaryDirectory(prefix="tabx-restart-cache-") as cache:
        env = actor_env(False)
        env["TABX_COMPILE_CACHE_DIR"] = (cache_dir or cache) if compile_cache else "off"
        setting = dataclasses.replace(config, run=dataclasses.replace(
            config.run, compile_cache=compile_cache))

        def spawn(cls: type, **options: Any) -> Any:
            return ray.remote(cls).options(runtime_env={"env_vars": env}, **options
                                           ).remote(setting)

        folder = tempfile.mkdtemp(prefix="tabx-restart-levels-", dir=cache)
        service = ray.remote(LevelServiceActor).options(
            runtime_env={"env_vars": env}, num_cpus=0, max_restarts=-1, max_task_retries=0
        ).remote(setting, folder, "bench")
        explorer = spawn(ExplorerActor, num_cpus=1, max_restarts=-1, max_task_retries=0)
        try:
            ppo = learner_for(setting)
            params = ParamsRef(0, [ray.put(jax.device_get(ppo.init(jax.random.key(0)).params))])
            levels = service.fresh.remote(jax.random.key(1), config.learner.num_envs)

            def score() -> float:
                started = time.perf_counter()
                ray.get(explorer.score_levels.remote(params, levels, jax.random.key(2),
                                                     config.ued.score))
                return time.perf_counter() - started

            ray.get(explorer.ready.remote())
            first = score()
            ready, restarted = _time_restart(ray, explorer, score)
            # The service: a snapshot interval's worth of commits in its log, then a kill.
            n = config.learner.num_envs
            commits = 50
            for i in range(commits):
                batch = service.fresh.remote(jax.random.key(100 + i), n)
                ray.get(service.apply.remote(i + 1, "insert", batch, np.arange(n, dtype=float),
                                             np.ones(n), 0))
            size = ray.get(service.buffer_size.remote())
            service_ready, _ = _time_restart(ray, service, lambda: None)
            if ray.get(service.buffer_size.remote()) != size:
                raise RuntimeError("the restarted level service lost commits")
        finally:
            for actor in (service, explorer):
                ray.kill(actor)
    stream.write(f"  restart, compilation cache {'on' if compile_cache else 'off'}: Explorer "
                 f"back in {ready:.1f} s, first batch scored {restarted:.1f} s after the kill "
                 f"(a fresh actor's first batch: {first:.1f} s); LevelService back with "
                 f"{commits} commits replayed in {service_ready:.1f} s\n")
    stream.flush()
    return RestartResult(compile_cache, first, ready, restarted, commits, service_ready)


def _time_restart(ray: Any, actor: Any, then: Callable[[], Any]) -> tuple[float, float]:
    """Kill `actor`'s process (`ray.kill`, restart allowed); seconds from the kill until a
    new process answers, and until `then()` (its first work) is done."""
    old_pid = ray.get(actor.pid.remote())
    killed = time.perf_counter()
    ray.kill(actor, no_restart=False)
    # The kill is asynchronous: the old process may still answer; wait for a new one.
    while time.perf_counter() - killed < 300:
        try:
            if ray.get(actor.pid.remote(), timeout=300) != old_pid:
                break
        except ray.exceptions.RayActorError:
            time.sleep(0.05)
    ready = time.perf_counter() - killed
    then()
    return ready, time.perf_counter() - killed


def ray_overhead(results: list[UEDBenchResult]) -> float | None:
    """The Ray path's seconds over the local driver's on the same work, minus one: the
    deterministic schedule with 0 Explorers plays exactly the local driver's steps, so step
    `i` does the same work on both; the median of the per-step ratios resists the machine's
    noise (a step slowed by another process) better than the ratio of the totals."""
    local = next((r for r in results if r.driver == "local"), None)
    same = next((r for r in results if r.driver == "ray-deterministic"), None)
    if local is None or same is None:
        return None
    if len(local.step_seconds) == len(same.step_seconds) > 0:
        return float(np.median(np.asarray(same.step_seconds)
                               / np.asarray(local.step_seconds))) - 1.0
    return (same.seconds / same.steps) / (local.seconds / local.steps) - 1.0


def _percent(fraction: float) -> str:
    return "-" if math.isnan(fraction) else f"{fraction:.0%}"


def format_table(results: list[UEDBenchResult]) -> str:
    width = max([len("setting"), *(len(r.label) for r in results)])
    lines = [f"{'setting':<{width}} {'trained/s':>10} {'explored/s':>11} {'total/s':>9} "
             f"{'busy':>5} {'wait s':>7} {'s/step':>7}  staleness"]
    for r in results:
        lag = " ".join(f"{k}:{v}" for k, v in r.staleness.items()) or "-"
        lines.append(f"{r.label:<{width}} {r.trained_per_s:>10,.0f} {r.explored_per_s:>11,.0f} "
                     f"{r.trained_per_s + r.explored_per_s:>9,.0f} "
                     f"{_percent(r.learner_busy_fraction):>5} {r.wait_for_levels_s:>7.1f} "
                     f"{r.seconds / r.steps:>7.3f}  {lag}")
    overhead = ray_overhead(results)
    if overhead is not None:
        lines.append(f"Ray overhead on the local driver's work (0 explorers, deterministic): "
                     f"{overhead:+.1%} seconds per step (median of the paired steps)")
    return "\n".join(lines)


def plot_results(results: list[UEDBenchResult], path: str, title: str = "") -> None:
    """Trained and explored env steps/s by setting, stacked bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [r.label.replace(", ", "\n") for r in results]
    trained = [r.trained_per_s for r in results]
    explored = [r.explored_per_s for r in results]
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(results), 3.6))
    ax.bar(labels, trained, label="trained", color="#3b6ea5")
    ax.bar(labels, explored, bottom=trained, label="explored", color="#e39b3b")
    ax.set_ylabel("env steps / s")
    ax.set_title(title or "UED throughput by driver and Explorer count")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def bench_ued(args: argparse.Namespace) -> int:
    overrides = [*args.overrides, "ued.eval_suites=[]"]  # evaluation is not timed here
    if args.address:  # a string as given (YAML would read `host:` as a mapping)
        overrides.append(f"ray.address={json.dumps(args.address)}")
    try:
        config = load_config(args.config, overrides)
        if not config.ued.enabled:
            raise ConfigError(f"{args.config}: ued.method: tabx bench ued needs a UED config")
        if args.simulate:
            return bench_simulated(config, args)
        restarts: list[RestartResult] | None = [] if args.restart else None
        results = run_ued_bench(config, args.explorers, args.warmup, args.steps,
                                local=not args.no_local, restarts=restarts,
                                learners=tuple(args.learners))
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(format_table(results))
    for r in restarts or []:
        print(f"Explorer restart, compilation cache {'on ' if r.compile_cache else 'off'}: "
              f"answers {r.ready_s:.1f} s after the kill, scores again after "
              f"{r.restarted_score_s:.1f} s (a fresh actor's first batch: "
              f"{r.first_score_s:.1f} s); LevelService restart with {r.service_commits} "
              f"logged commits: {r.service_ready_s:.1f} s")
    if args.json:
        lines = [json.dumps(r.to_json()) for r in results]
        lines += [json.dumps({"driver": "restart", **dataclasses.asdict(r)})
                  for r in restarts or []]
        atomic_write_text(Path(args.json), "".join(line + "\n" for line in lines))
    if args.plot:
        plot_results(results, args.plot)
        print(f"plot: {args.plot}")
    return 0


def bench_simulated(config: TrainConfig, args: argparse.Namespace) -> int:
    """`--simulate`: the control plane with stand-in Explorers (tabx_bench.ued_sim)."""
    from tabx_bench.ued_sim import format_sim_table, plot_sim, run_simulation

    results = run_simulation(config, args.simulate, args.batch_s, args.learner_s, args.seconds,
                             args.per_process)
    print(format_sim_table(results))
    if args.json:
        atomic_write_text(Path(args.json), "".join(json.dumps(r.to_json()) + "\n"
                                                   for r in results))
    if args.plot:
        plot_sim(results, args.plot)
        print(f"plot: {args.plot}")
    return 0


def add_ued_bench(which: argparse._SubParsersAction) -> None:
    """Add `ued` to the `tabx bench` sub-commands."""
    p = which.add_parser("ued", help="UED throughput: local driver and Ray by Explorer count")
    p.add_argument("config", nargs="?", default=DEFAULT_CONFIG,
                   help=f"UED config (default {DEFAULT_CONFIG})")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.add_argument("--explorers", type=int_list(0), default=[0, 1, 2],
                   help="comma-separated Explorer counts on Ray (default 0,1,2)")
    p.add_argument("--warmup", type=int_at_least(1), default=4,
                   help="untimed steps first: start-up, compilation (default 4)")
    p.add_argument("--steps", type=int_at_least(1), default=16,
                   help="timed curriculum steps per setting (default 16)")
    p.add_argument("--learners", type=int_list(1), default=[1],
                   help="comma-separated learner-group sizes (ray.learners) of the "
                        "asynchronous settings (default 1)")
    p.add_argument("--no-local", action="store_true", help="skip the local driver")
    p.add_argument("--restart", action="store_true",
                   help="also time the restart of an Explorer and of the LevelService (with "
                        "50 logged commits to replay) after a kill, without and with the "
                        "compilation cache")
    p.add_argument("--simulate", type=int_list(1, MAX_SIMULATED), metavar="N,...",
                   help="instead: the control plane with these counts of stand-in Explorers "
                        "(sleeping --batch-s per batch) on the continuous schedule, with the "
                        "real driver, level service and commit log")
    p.add_argument("--batch-s", type=seconds_up_to(MAX_SIM_STEP_S), default=0.5,
                   help="--simulate: seconds a stand-in Explorer takes per batch (default 0.5, "
                        f"at most {MAX_SIM_STEP_S:g})")
    p.add_argument("--learner-s", type=seconds_up_to(MAX_SIM_STEP_S), default=0.5,
                   help="--simulate: seconds the stand-in learner takes per step (default 0.5, "
                        f"at most {MAX_SIM_STEP_S:g})")
    p.add_argument("--seconds", type=seconds_up_to(MAX_SIM_SECONDS), default=20.0,
                   help="--simulate: timed seconds per Explorer count (default 20, at most "
                        f"{MAX_SIM_SECONDS:g})")
    p.add_argument("--per-process", type=int_at_least(1), default=8,
                   help="--simulate: stand-in Explorers per actor process (default 8)")
    p.add_argument("--address", help="join a running Ray cluster (auto, or HOST:PORT)")
    p.add_argument("--json", help="also write results as JSON lines to this file")
    p.add_argument("--plot", help="also draw trained/explored env steps/s to this PNG")
    p.set_defaults(func=bench_ued)


__all__ = ["RestartResult", "UEDBenchResult", "add_ued_bench", "bench_restart", "bench_simulated",
           "format_table",
           "ray_overhead", "run_ued_bench"]
