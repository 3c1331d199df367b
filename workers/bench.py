"""`tabx bench ued`: a UED run's throughput on the local driver and on Ray, by Explorer count.

Protocol (docs/benchmarks.md, "Distributed UED"): one UED config (default
configs/ued/quickstart.yaml, evaluation off) runs `--warmup` curriculum steps (actor start-up
and compilation), then `--steps` timed steps, on

- the local driver: every worker in this process, one after another;
- the Ray driver's deterministic schedule with 0 Explorers: the local driver's very steps over
  actors, so its seconds per step against the local driver's are the Ray path's overhead;
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import jax

from tabx.bench_cli import int_at_least, int_list
from tabx.errors import UserError
from tabx.files import atomic_write_text
from ued.config import ConfigError, TrainConfig, load_config
from workers.learner import Learner
from workers.local import UEDRun

DEFAULT_CONFIG = "configs/ued/quickstart.yaml"


@dataclass
class UEDBenchResult:
    driver: str  # "local" | "ray" (asynchronous) | "ray-deterministic" (the local schedule)
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
        if self.driver == "ray-deterministic":
            return f"ray, {self.explorers} explorers, deterministic"
        return f"ray, {self.explorers} explorers"

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

    def __init__(self, run: UEDRun, steps: int, patience: int = 10):
        self.expected = set(run.curriculum.branches)
        self.seen: set = set()
        self.steps, self.limit, self.count = steps, steps * patience, 0

    def saw(self, branch: Any) -> None:
        self.seen.add(branch)
        self.count += 1

    @property
    def done(self) -> bool:
        return self.count >= self.limit or (self.count >= self.steps
                                            and self.seen >= self.expected)


def bench_local(config: TrainConfig, warmup: int, steps: int) -> UEDBenchResult:
    """The local driver's step loop, in this process."""
    run, ppo = UEDRun.local(config)
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    learner = Learner(ppo, ppo.init(k_init))
    warm = Warmup(run, warmup)
    step = 0
    while not warm.done:
        key, k_step = jax.random.split(key)
        warm.saw(run.step(learner, step, k_step)[0])
        step += 1
    jax.block_until_ready(learner.train_state)
    run.sfl_scoring_steps = 0
    branches: Counter = Counter()
    t0 = time.perf_counter()
    first = step
    for step in range(first, first + steps):
        key, k_step = jax.random.split(key)
        branches[run.step(learner, step, k_step)[0]] += 1
    jax.block_until_ready(learner.train_state)
    seconds = time.perf_counter() - t0
    trained, explored = _steps_of(run, config, branches)
    return UEDBenchResult("local", 0, config.ued.method, steps, seconds, trained, explored,
                          learner_busy_fraction=1.0, wait_for_levels_s=0.0,
                          branches={b.name.lower(): n for b, n in branches.items()})


def bench_ray(ray: Any, config: TrainConfig, warmup: int, steps: int,
              stream: TextIO) -> UEDBenchResult:
    """The Ray driver on fresh actors: its asynchronous schedule, or with `ray.deterministic`
    the local driver's schedule over the actors (the same work as `bench_local`)."""
    from workers.ray_driver import (
        AsyncRun,
        Blocking,
        ExplorerPool,
        RayStats,
        RemoteLearner,
        start_workers,
    )

    workers = start_workers(ray, config, stream)
    try:
        run = UEDRun(config, Blocking(ray, workers.service), ExplorerPool(ray, workers.scorers()))
        key = jax.random.key(config.seed)
        key, k_init = jax.random.split(key)
        ray.get(workers.learner.init.remote(k_init))
        learner = RemoteLearner(ray, workers.learner)
        schedule = AsyncRun(ray, config, run, learner, workers)
        if config.ray.deterministic:
            def step_once(step: int, key: jax.Array) -> Any:
                return run.step(learner, step, key)[0]
        else:
            def step_once(step: int, key: jax.Array) -> Any:
                return schedule.step(step, key)[0]
        warm = Warmup(run, warmup)
        step = 0
        while not warm.done:
            key, k_step = jax.random.split(key)
            warm.saw(step_once(step, k_step))
            step += 1
        schedule.drain()
        ray.get(workers.learner.version.remote())  # the learner is idle
        schedule.stats = RayStats()
        run.sfl_scoring_steps = 0
        branches: Counter = Counter()
        first = step
        for step in range(first, first + steps):
            key, k_step = jax.random.split(key)
            branches[step_once(step, k_step)] += 1
        schedule.drain()
        ray.get(workers.learner.version.remote())
        stats = schedule.stats
        seconds = time.perf_counter() - stats.t0
        counts = {b.name.lower(): n for b, n in branches.items()}
        if config.ray.deterministic:  # every call waited: the learner's share is unknown
            trained, explored = _steps_of(run, config, branches)
            return UEDBenchResult("ray-deterministic", len(workers.explorers),
                                  config.ued.method, steps, seconds, trained, explored,
                                  learner_busy_fraction=float("nan"), wait_for_levels_s=0.0,
                                  branches=counts)
        return UEDBenchResult(
            "ray", len(workers.explorers), config.ued.method, steps, seconds,
            stats.trained_steps, stats.explored_steps + run.sfl_scoring_steps,
            learner_busy_fraction=stats.learner_busy_s / seconds,
            wait_for_levels_s=stats.wait_for_levels_s,
            staleness={str(k): v for k, v in sorted(stats.staleness.items())},
            rescored=stats.rescored, branches=counts)
    finally:
        for actor in workers.all():
            ray.kill(actor)


def run_ued_bench(config: TrainConfig, explorers: list[int], warmup: int, steps: int,
                  local: bool = True, stream: TextIO | None = None) -> list[UEDBenchResult]:
    """Every setting in turn (see the module doc); a line per setting on `stream`."""
    from workers.ray_driver import connect

    stream = sys.stderr if stream is None else stream
    results = []

    def report(result: UEDBenchResult, started: float) -> None:
        stream.write(f"  {result.label}: {result.trained_per_s:,.0f} trained + "
                     f"{result.explored_per_s:,.0f} explored env steps/s, learner busy "
                     f"{_percent(result.learner_busy_fraction)}, waited "
                     f"{result.wait_for_levels_s:.1f} s for levels "
                     f"({time.perf_counter() - started:.0f} s)\n")
        stream.flush()

    ray_settings = ([(0, True)] if local else []) + [(n, False) for n in explorers]
    labels = (["local"] if local else []) + [
        UEDBenchResult("ray-deterministic" if det else "ray", n, "", 1, 1, 0, 0, 0, 0).label
        for n, det in ray_settings]
    stream.write(f"bench ued: {config.ued.method}, at least {warmup} warm-up + {steps} timed "
                 f"steps of {config.learner.steps_per_update:,} env steps; settings: "
                 f"{'; '.join(labels)}\n")
    stream.flush()
    if local:
        started = time.perf_counter()
        results.append(bench_local(config, warmup, steps))
        report(results[-1], started)
    if ray_settings:
        ray, connected_here = connect(config.ray)
        try:
            for n, deterministic in ray_settings:
                started = time.perf_counter()
                setting = dataclasses.replace(config, ray=dataclasses.replace(
                    config.ray, enabled=True, explorers=n, deterministic=deterministic)
                                              ).validate()
                results.append(bench_ray(ray, setting, warmup, steps, stream))
                report(results[-1], started)
        finally:
            if connected_here:
                ray.shutdown()
    return results


def ray_overhead(results: list[UEDBenchResult]) -> float | None:
    """The Ray path's seconds over the local driver's on the same work, minus one: the
    deterministic schedule with 0 Explorers plays exactly the local driver's steps."""
    local = next((r for r in results if r.driver == "local"), None)
    same = next((r for r in results if r.driver == "ray-deterministic"), None)
    if local is None or same is None:
        return None
    return (same.seconds / same.steps) / (local.seconds / local.steps) - 1.0


def _percent(fraction: float) -> str:
    return "-" if math.isnan(fraction) else f"{fraction:.0%}"


def format_table(results: list[UEDBenchResult]) -> str:
    lines = [f"{'setting':<20} {'trained/s':>10} {'explored/s':>11} {'total/s':>9} "
             f"{'busy':>5} {'wait s':>7} {'s/step':>7}  staleness"]
    for r in results:
        lag = " ".join(f"{k}:{v}" for k, v in r.staleness.items()) or "-"
        lines.append(f"{r.label:<20} {r.trained_per_s:>10,.0f} {r.explored_per_s:>11,.0f} "
                     f"{r.trained_per_s + r.explored_per_s:>9,.0f} "
                     f"{_percent(r.learner_busy_fraction):>5} {r.wait_for_levels_s:>7.1f} "
                     f"{r.seconds / r.steps:>7.3f}  {lag}")
    overhead = ray_overhead(results)
    if overhead is not None:
        lines.append(f"Ray overhead on the local driver's work (0 explorers, deterministic): "
                     f"{overhead:+.1%} seconds per step")
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
    if args.address:
        overrides.append(f"ray.address={args.address}")
    try:
        config = load_config(args.config, overrides)
        if not config.ued.enabled:
            raise ConfigError(f"{args.config}: ued.method: tabx bench ued needs a UED config")
        results = run_ued_bench(config, args.explorers, args.warmup, args.steps,
                                local=not args.no_local)
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(format_table(results))
    if args.json:
        atomic_write_text(Path(args.json), "".join(json.dumps(r.to_json()) + "\n"
                                                   for r in results))
    if args.plot:
        plot_results(results, args.plot)
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
    p.add_argument("--no-local", action="store_true", help="skip the local driver")
    p.add_argument("--address", help="join a running Ray cluster (auto, or HOST:PORT)")
    p.add_argument("--json", help="also write results as JSON lines to this file")
    p.add_argument("--plot", help="also draw trained/explored env steps/s to this PNG")
    p.set_defaults(func=bench_ued)


__all__ = ["UEDBenchResult", "add_ued_bench", "format_table", "ray_overhead", "run_ued_bench"]
