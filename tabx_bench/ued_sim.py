"""`tabx bench ued --simulate N,...`: the Ray driver's control plane, measured with stand-in
Explorers.

Each stand-in Explorer sleeps `--batch-s` seconds per batch (a GPU rollout, as far as the
driver can tell) and returns what a real one returns: episode metrics and `learner.num_envs`
scores and best returns (float64). It pulls the policy parameters of each new version, as a
real Explorer does. The learner is a stand-in too (`--learner-s` per replay step, the replayed
ids and their scores back). Everything else is real: the continuous schedule's driver
(`workers.ray.continuous.ContinuousRun`), the `LevelServiceActor` (it inserts every batch) and its
commit log, fsynced in a temporary folder; the stand-ins make each batch's fresh levels with
the config's real generator, as Explorers do on the continuous schedule.

Per Explorer count it reports committed Explorer batches/s against the ideal N / batch time,
the driver's CPU seconds per committed batch (its process time over the window), the level
service's CPU (of one core; from /proc) and its numbered calls/s and fsyncs/s, the learner's
steps/s, and the staleness histogram (policy versions between a score's policy and the
learner's at commit).

Stand-ins share processes (`--per-process` threads of one Ray actor each; a sleep releases the
interpreter), so 64 of them fit on a small machine; each has its own name, queue bound
(`ray.max_inflight`) and accounting in the driver, which sees them as 64 Explorers. A process
runs as many batches at once as it holds stand-ins, so in all one batch per stand-in runs at a
time, as with real Explorers (which one of a process's stand-ins it is does not matter).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import jax
import numpy as np

from ued.config import TrainConfig


class SleepExplorer:
    """A stand-in Explorer: each batch takes `batch_s` seconds; scores of the right size; fresh
    levels made with the config's real generator, as a real Explorer makes them."""

    def __init__(self, batch_s: float, num_envs: int, config: TrainConfig | None = None):
        self.batch_s, self.num_envs = batch_s, num_envs
        self.version = -1
        self.rng = np.random.default_rng(0)
        self.generator = None
        if config is not None:
            from ued.experiment import learner_for
            from workers.ued_step import generator_for

            self.generator = generator_for(config, learner_for(config))

    def ready(self) -> bool:
        return True

    def pid(self) -> int:
        return os.getpid()

    def score_fresh(self, params: Any, levels_key: Any, n: int, key: Any, score: str
                    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, Any]:
        """`ExplorerActor.score_fresh`: the levels made here (real generator), then a sleep."""
        from workers.roles.level_service import to_host

        levels = to_host(self.generator.sample(levels_key, n))
        return (*self.score_levels(params, levels, key, score), levels)

    def score_levels(self, params: Any, levels: Any, key: Any, score: str,
                     max_returns: Any = None, num_steps: int | None = None
                     ) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
        if params.version != self.version:  # a new policy: pulled once, as a real Explorer
            import ray

            ray.get(params.ref[0])
            self.version = params.version
        time.sleep(self.batch_s)
        n = self.num_envs
        return ({"episode_return": np.float32(0.0)}, self.rng.normal(size=n),
                self.rng.normal(size=n))


class SleepLearner:
    """A stand-in learner: each replay step takes `step_s` seconds; parameters of `param_mb`
    megabytes."""

    def __init__(self, step_s: float, param_mb: float):
        self.step_s = step_s
        self.params_ = {"w": np.zeros(int(param_mb * 2**20 / 4), np.float32)}
        self.rng = np.random.default_rng(1)

    def ready(self) -> bool:
        return True

    def params(self) -> Any:
        return self.params_

    def train_replay(self, replay: Any, key: Any, score: str
                     ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray]:
        time.sleep(self.step_s)
        n = len(replay.ids)
        return ({"loss": np.float32(0.0)}, np.asarray(replay.ids), self.rng.normal(size=n),
                self.rng.normal(size=n))


@dataclass
class SimResult:
    explorers: int
    batch_s: float
    learner_s: float
    seconds: float
    committed: int  # Explorer batches committed in the window
    learner_steps: int
    driver_cpu_s: float
    service_calls: int  # numbered (state-changing) calls sent to the level service
    service_fsyncs: int  # commit-log fsyncs they cost (one per call, one per group commit)
    service_cpu_s: float = float("nan")  # the level service's process (Linux: /proc)
    explorers_cpu_s: float = float("nan")  # the stand-ins' processes
    staleness: dict[str, int] = field(default_factory=dict)

    @property
    def ideal_per_s(self) -> float:
        return self.explorers / self.batch_s

    @property
    def committed_per_s(self) -> float:
        return self.committed / self.seconds

    @property
    def efficiency(self) -> float:
        return self.committed_per_s / self.ideal_per_s

    @property
    def cpu_ms_per_batch(self) -> float:
        return 1000 * self.driver_cpu_s / max(self.committed, 1)

    def to_json(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out.update(ideal_per_s=self.ideal_per_s, committed_per_s=self.committed_per_s,
                   efficiency=self.efficiency, cpu_ms_per_batch=self.cpu_ms_per_batch)
        return out


def simulate(ray: Any, config: TrainConfig, explorers: int, batch_s: float, learner_s: float,
             seconds: float, per_process: int = 8, param_mb: float = 1.0) -> SimResult:
    """One setting: `explorers` stand-ins, timed for `seconds` after the buffer filled."""
    from workers.ray.actor_manager import ActorDeaths, ActorManager
    from workers.ray.actors import LevelServiceActor
    from workers.ray.continuous import ContinuousRun
    from workers.ray.handles import ExplorerPool, RemoteLearner
    from workers.ray.restarts import RemoteService
    from workers.ray.start import Workers, actor_env
    from workers.ued_step import UEDRun

    # The buffer's fill is not what is measured: replay from the first committed batch.
    config = dataclasses.replace(
        config, ray=dataclasses.replace(config.ray, enabled=True, schedule="continuous",
                                        deterministic=False),
        ued=dataclasses.replace(config.ued, min_fill_ratio=0.0)).validate()
    env = {"env_vars": actor_env(False)}
    with tempfile.TemporaryDirectory(prefix="tabx-sim-levels-") as folder:
        service_actor = ray.remote(LevelServiceActor).options(
            num_cpus=0, runtime_env=env, max_task_retries=0).remote(config, folder, "sim")
        learner_actor = ray.remote(SleepLearner).options(num_cpus=0).remote(learner_s, param_mb)
        # A host runs as many batches at once as it holds stand-ins: in all, one batch per
        # stand-in at a time, as real Explorers.
        hosts = [ray.remote(SleepExplorer).options(
            num_cpus=0, runtime_env=env,
            max_concurrency=min(per_process, explorers - start)
        ).remote(batch_s, config.learner.num_envs, config)
            for start in range(0, explorers, per_process)]
        handles = [hosts[i // per_process] for i in range(explorers)]
        actors = [service_actor, learner_actor, *hosts]
        try:
            ray.get([a.ready.remote() for a in actors])
            workers = Workers(service_actor, learner_actor, handles, None, 0.0)
            manager = ActorManager(ray, ActorDeaths(None))
            workers.register(manager)
            service = RemoteService(ray, service_actor, manager)
            run = UEDRun(config, service, ExplorerPool(ray, workers.scorers(),
                                                       workers.scorer_names(), manager))
            schedule = ContinuousRun(ray, config, run, RemoteLearner(ray, learner_actor,
                                                                     manager),
                                     workers, service)
            key = jax.random.key(config.seed)
            step = 0

            def one_step() -> None:
                nonlocal key, step
                key, k_step = jax.random.split(key)
                schedule.step(step, k_step)
                step += 1

            for _ in range(3):  # the buffer's fill, the first parameters: not timed
                one_step()
            committed0, steps0 = schedule.stats.committed, step
            calls0, groups0 = service.seq, schedule.group_commits
            staleness0 = Counter(schedule.stats.staleness)
            service_pid = ray.get(service_actor.pid.remote())
            host_pids = ray.get([h.pid.remote() for h in hosts])
            service0, hosts0 = process_cpu_s([service_pid]), process_cpu_s(host_pids)
            cpu0, t0 = time.process_time(), time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                one_step()
            elapsed = time.perf_counter() - t0
            cpu = time.process_time() - cpu0
            service_cpu = process_cpu_s([service_pid]) - service0
            hosts_cpu = process_cpu_s(host_pids) - hosts0
            committed = schedule.stats.committed - committed0
            calls = service.seq - calls0
            groups = schedule.group_commits - groups0
            group_calls = committed  # one insert per committed batch, inside group commits
            staleness = Counter(schedule.stats.staleness)
            staleness.subtract(staleness0)
            schedule.drain()
        finally:
            for actor in actors:
                ray.kill(actor)
    return SimResult(explorers, batch_s, learner_s, elapsed, committed, step - steps0, cpu,
                     calls, calls - group_calls + groups, service_cpu, hosts_cpu,
                     {str(k): v for k, v in sorted(staleness.items()) if v > 0})


def process_cpu_s(pids: list[int]) -> float:
    """CPU seconds (user + system) the processes `pids` of this machine have used; NaN where
    /proc cannot tell (not Linux, another node)."""
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def run_simulation(config: TrainConfig, explorers: list[int], batch_s: float, learner_s: float,
                   seconds: float, per_process: int = 8, stream: TextIO | None = None
                   ) -> list[SimResult]:
    """Every Explorer count in turn, on a Ray of this machine (or `ray.address`'s)."""
    import sys

    from workers.ray.start import connect

    stream = sys.stderr if stream is None else stream
    ray, connected_here = connect(config.ray)
    results = []
    try:
        for n in explorers:
            result = simulate(ray, config, n, batch_s, learner_s, seconds, per_process)
            stream.write(f"  {n} stand-in explorers: {result.committed_per_s:.1f} batches/s "
                         f"({result.efficiency:.0%} of ideal), driver "
                         f"{result.cpu_ms_per_batch:.1f} ms CPU per batch\n")
            stream.flush()
            results.append(result)
    finally:
        if connected_here:
            ray.shutdown()
    return results


def format_sim_table(results: list[SimResult]) -> str:
    lines = [f"{'explorers':>9} {'batches/s':>10} {'ideal/s':>8} {'of ideal':>8} "
             f"{'driver CPU':>10} {'CPU ms/batch':>12} {'service CPU':>11} {'calls/s':>8} "
             f"{'fsyncs/s':>8} {'learner/s':>9}  staleness"]
    for r in results:
        lag = " ".join(f"{k}:{v}" for k, v in r.staleness.items()) or "-"
        lines.append(f"{r.explorers:>9} {r.committed_per_s:>10.1f} {r.ideal_per_s:>8.1f} "
                     f"{r.efficiency:>8.0%} {r.driver_cpu_s / r.seconds:>10.0%} "
                     f"{r.cpu_ms_per_batch:>12.2f} {r.service_cpu_s / r.seconds:>11.0%} "
                     f"{r.service_calls / r.seconds:>8.1f} "
                     f"{r.service_fsyncs / r.seconds:>8.1f} "
                     f"{r.learner_steps / r.seconds:>9.2f}  {lag}")
    return "\n".join(lines)


def plot_sim(results: list[SimResult], path: str) -> None:
    """Committed batches/s against the ideal, by Explorer count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r.explorers for r in results]
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    ax.plot(n, [r.ideal_per_s for r in results], "--", color="grey", label="ideal N / batch time")
    ax.plot(n, [r.committed_per_s for r in results], "o-", color="#3b6ea5",
            label="committed")
    for r in results:
        ax.annotate(f"{r.efficiency:.0%}", (r.explorers, r.committed_per_s),
                    textcoords="offset points", xytext=(4, -12), fontsize=8)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log", base=2)
    ax.set_xlabel("stand-in Explorers")
    ax.set_ylabel("committed batches / s")
    ax.set_title(f"Control plane, {results[0].batch_s:g} s batches" if results else "")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["SimResult", "SleepExplorer", "SleepLearner", "format_sim_table", "plot_sim",
           "run_simulation", "simulate"]
