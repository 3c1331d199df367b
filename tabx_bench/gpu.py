"""`tabx bench gpu --out DIR`: the numbers a GPU machine owes the paper's cost tables, in one
call (tools/gpu_check.sh runs it at the paper's sizes within about 8 minutes on one GPU).

Parts, each with its own size arguments so that a test runs all of them on a CPU at tiny
sizes:

1. **simulator**: env steps/s at 3v3 and 10v10 (`tabx bench env`'s `run_one`: random legal
   actions, observations computed, compile excluded), at each `--sim-envs`.
2. **learners**: MAPPO and IPPO env steps/s at `--train-envs` x `--train-steps` (the paper's
   128 x 512) on crossfire against the medium heuristic (`tabx bench train`'s protocol: cold
   first update, then the median of `--train-updates` updates).
3. **UED trials**: the paper's UED trial (Robust PLR over zone layouts, MAPPO, training
   configuration 2F1M2Avs2S1K_2L2B2S, `configs/ued/robust_plr_zone.yaml` at 128 envs x 512
   steps) run end to end by `tabx train` for `--ued-updates` steps, with one zero-shot
   evaluation on its held-out suite at the end; first alone, then `c` copies at once for each
   `--concurrency` c (separate processes without memory preallocation, as a sweep's trials
   sharing a GPU with fractional `gpus` run). Per trial: its wall time, the first update
   (compilation included: cold for the first trial, from the compilation cache after), the
   steady env steps/s (median of its logged rates after the first update), and the minutes
   projected for a trial of `--paper-steps` env steps (5e7): start-up, first update, the
   remaining steps at the steady rate, and one evaluation. For c at once: their summed steady
   rate, and trials per hour.

The projections print beside the paper's appendix tables (one RTX PRO 6000: 18-47 min per
UED trial, 22 min for this one; MAPPO 8 min and IPPO 5 min for crossfire's 2e7 steps).
Written to `--out`: gpu_check.json (every number), summary.txt (the tables), and each UED
trial's output log; the trials' run folders are temporary.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from tabx.files import atomic_write_text
from tabx_bench.arguments import int_at_least, int_list

PAPER_STEPS = 50_000_000  # env steps per UED trial in the paper
PAPER_MARL_STEPS = 20_000_000  # per MARL trial (crossfire)
# The paper's appendix "Training Time for UED Algorithms": 18-47 min per trial; this trial
# (2F1M2Avs2S1K_2L2B2S, zone, Robust PLR): 22 min. "Training Time for Challenges Scenarios":
# crossfire, MAPPO 8 min, IPPO 5 min.
PAPER_UED_MINUTES = (18, 47)
PAPER_THIS_TRIAL_MINUTES = 22
PAPER_CROSSFIRE_MINUTES = {"mappo": 8, "ippo": 5}
UED_CONFIG = "ued/robust_plr_zone"
UED_SCENARIO = "2F1M2Avs2S1K_2L2B2S"
UED_SUITE = "zones-2F1M2Avs2S1K"


@dataclasses.dataclass
class TrialTiming:
    """One `tabx train` UED trial of the concurrency part."""

    concurrent: int  # trials running at once, this one included
    index: int
    wall_s: float  # process start to exit
    first_update_s: float  # compilation included
    steady_steps_per_s: float  # median logged rate after the first update
    env_steps: int
    steps_per_update: int
    returncode: int
    log: str  # file name under --out
    zero_shot_win_rate: float = math.nan  # the closing evaluation's mean win rate (NaN: none)

    @property
    def overhead_s(self) -> float:
        """Wall time beyond the first update and the other updates at the steady rate:
        start-up (imports, config, run folder), the closing evaluation, checkpoints."""
        updates_s = (self.env_steps - self.steps_per_update) / self.steady_steps_per_s
        return max(0.0, self.wall_s - self.first_update_s - updates_s)

    def projected_minutes(self, env_steps: int = PAPER_STEPS) -> float:
        """Minutes for a trial of `env_steps`: this trial's start-up, evaluation and first
        update, and the rest at its steady rate."""
        rest = (env_steps - self.steps_per_update) / self.steady_steps_per_s
        return (self.overhead_s + self.first_update_s + rest) / 60.0


def _minutes(steps_per_s: float, env_steps: int) -> float:
    return env_steps / steps_per_s / 60.0 if steps_per_s > 0 else math.nan


def run_simulator(team_sizes: list[int], num_envs: list[int], steps: int, repeats: int,
                  log: Any) -> list[dict[str, Any]]:
    from tabx_bench.simulator import run_one

    rows = []
    for team in team_sizes:
        for envs in num_envs:
            r = run_one(team, 0, envs, steps=steps, repeats=repeats)
            rows.append(dataclasses.asdict(r))
            log(f"  simulator {team}v{team}, {envs} envs: {r.steps_per_s:,.0f} env steps/s "
                f"(compile {r.compile_s:.1f} s)")
    return rows


def run_learners(algorithms: list[str], num_envs: int, num_steps: int, updates: int,
                 log: Any) -> list[dict[str, Any]]:
    from tabx_bench.train import run_train_bench

    rows = []
    for algorithm in algorithms:
        r = run_train_bench(algorithm, num_envs=num_envs, num_steps=num_steps, updates=updates)
        rows.append(dataclasses.asdict(r))
        log(f"  {algorithm} {num_envs} x {num_steps}: {r.steps_per_s:,.0f} env steps/s "
            f"(first update {r.first_update_s:.1f} s)")
    return rows


def trial_command(run_dir: Path, num_envs: int, num_steps: int, updates: int,
                  eval_episodes: int) -> list[str]:
    """`tabx train` of the paper's UED trial for `updates` steps, one evaluation at the end."""
    return [sys.executable, "-m", "tabx_ued", "train", UED_CONFIG, "--quiet",
            "--run-dir", str(run_dir),
            f"env.scenario={UED_SCENARIO}", f"env.max_steps={num_steps}",
            f"learner.num_envs={num_envs}", f"learner.num_steps={num_steps}",
            f"learner.total_timesteps={updates * num_envs * num_steps}",
            f"ued.eval_suites=[{UED_SUITE}]", f"ued.eval_every={updates}",
            f"ued.eval_episodes={eval_episodes}", f"run.checkpoint_every={updates}",
            "run.log_every=1"]


def _trial_timing(run_dir: Path, concurrent: int, index: int, wall: float, code: int,
                  log: str, steps_per_update: int) -> TrialTiming:
    from ued.tensorboard import read_scalars

    events = run_dir / "events"
    scalars = read_scalars(events) if events.is_dir() else {}
    first = [v for _, v in scalars.get("time/first_update_s", [])]
    rates = [v for _, v in scalars.get("time/steps_per_s", []) if v > 0]
    done = max((s for points in scalars.values() for s, _ in points), default=0)
    evaluated = scalars.get(f"eval/{UED_SUITE}/mean_win_rate", [])
    return TrialTiming(concurrent, index, wall, first[0] if first else math.nan,
                       statistics.median(rates) if rates else math.nan, done,
                       steps_per_update, code, log,
                       max(evaluated)[1] if evaluated else math.nan)


def run_trials(concurrent: int, out: Path, work: Path, num_envs: int, num_steps: int,
               updates: int, eval_episodes: int, env: dict[str, str]) -> list[TrialTiming]:
    """`concurrent` trials started at once, each its own process; their timings."""
    procs = []
    for i in range(concurrent):
        run_dir = work / f"c{concurrent}-{i}"
        log_name = f"ued-c{concurrent}-{i}.log"
        stream = open(out / log_name, "w")  # noqa: SIM115 - closed below
        started = time.perf_counter()
        proc = subprocess.Popen(trial_command(run_dir, num_envs, num_steps, updates,
                                              eval_episodes),
                                stdout=stream, stderr=subprocess.STDOUT, env=env)
        procs.append((proc, stream, started, run_dir, log_name))
    timings = []
    try:
        for i, (proc, stream, started, run_dir, log_name) in enumerate(procs):
            code = proc.wait()
            wall = time.perf_counter() - started
            stream.close()
            timings.append(_trial_timing(run_dir, concurrent, i, wall, code, log_name,
                                         num_envs * num_steps))
    finally:  # stopped (Ctrl-C, the script's time limit): no trial outlives the check
        for proc, stream, *_ in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            stream.close()
    return timings


def trial_env(cache_dir: str) -> dict[str, str]:
    """The trials' environment: no GPU memory preallocation (trials share the GPU, as a
    sweep's do: workers.sweep.tune.worker_env) and one compilation cache, so that only the first
    trial compiles."""
    env = dict(os.environ)
    env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    env["TABX_COMPILE_CACHE_DIR"] = cache_dir
    return env


def summarise(result: dict[str, Any]) -> str:
    """The text summary: the tables with the projections beside the paper's."""
    lines = [f"# tabx bench gpu on {result['machine']} ({result['date']}, load "
             f"{result['load_avg']})", ""]
    if result["simulator"]:
        lines += ["## Simulator (random actions, observations, no zones)", "",
                  f"{'units':>6} {'envs':>7} {'env steps/s':>14} {'compile s':>10}"]
        for r in result["simulator"]:
            units = f"{r['team_size']}v{r['team_size']}"
            lines.append(f"{units:>6} {r['num_envs']:>7} {r['steps_per_s']:>14,.0f} "
                         f"{r['compile_s']:>10.1f}")
        lines.append("")
    if result["learners"]:
        lines += ["## Learners (crossfire vs heuristic:medium)", "",
                  f"{'learner':>8} {'envs x steps':>13} {'env steps/s':>12} "
                  f"{'first update s':>15} {'min per 2e7':>12} {'paper':>6}"]
        for r in result["learners"]:
            paper = PAPER_CROSSFIRE_MINUTES.get(r["algorithm"])
            size = f"{r['num_envs']} x {r['num_steps']}"
            quoted = f"{paper}m" if paper else "-"
            lines.append(f"{r['algorithm']:>8} {size:>13} {r['steps_per_s']:>12,.0f} "
                         f"{r['first_update_s']:>15.1f} "
                         f"{_minutes(r['steps_per_s'], PAPER_MARL_STEPS):>12.1f} {quoted:>6}")
        lines.append("")
    if result["ued"]:
        u = result["ued_settings"]
        lines += [f"## UED trials: Robust PLR, zone, {UED_SCENARIO}, {u['num_envs']} envs x "
                  f"{u['num_steps']} steps, {u['updates']} updates each, one evaluation",
                  "",
                  f"{'at once':>7} {'wall s':>7} {'first update s':>15} {'steps/s each':>13} "
                  f"{'steps/s all':>12} {'min per 5e7':>12} {'trials/hour':>12}"]
        for c, group in _by_concurrency(result["ued"]).items():
            ok = [t for t in group if t.returncode == 0 and math.isfinite(
                t.steady_steps_per_s)]
            if not ok:
                lines.append(f"{c:>7} failed: see {', '.join(t.log for t in group)}")
                continue
            each = statistics.mean(t.steady_steps_per_s for t in ok)
            minutes = statistics.mean(t.projected_minutes(result["paper_steps"]) for t in ok)
            lines.append(f"{c:>7} {max(t.wall_s for t in ok):>7.0f} "
                         f"{statistics.mean(t.first_update_s for t in ok):>15.1f} "
                         f"{each:>13,.0f} {sum(t.steady_steps_per_s for t in ok):>12,.0f} "
                         f"{minutes:>12.1f} {len(ok) * 60 / minutes:>12.1f}")
        lines += ["", f"The paper (one RTX PRO 6000, 5e7 env steps per trial): "
                  f"{PAPER_UED_MINUTES[0]}-{PAPER_UED_MINUTES[1]} min per UED trial, "
                  f"{PAPER_THIS_TRIAL_MINUTES} min for this one, one trial per GPU.",
                  "min per 5e7: this trial's start-up, first update and one evaluation, "
                  "then the rest at its steady rate (the paper's runs evaluate every 25 "
                  "updates)."]
    return "\n".join(lines) + "\n"


def _by_concurrency(rows: list[dict[str, Any]]) -> dict[int, list[TrialTiming]]:
    out: dict[int, list[TrialTiming]] = {}
    for row in rows:
        fields = {k: v for k, v in row.items() if k in TrialTiming.__dataclass_fields__}
        out.setdefault(row["concurrent"], []).append(TrialTiming(**fields))
    return out


def run_gpu_check(out: str | Path, *, team_sizes: list[int], sim_envs: list[int],
                  sim_steps: int, sim_repeats: int, algorithms: list[str], train_envs: int,
                  train_steps: int, train_updates: int, ued_envs: int, ued_steps: int,
                  ued_updates: int, eval_episodes: int, concurrency: list[int],
                  paper_steps: int = PAPER_STEPS, log: Any = print) -> dict[str, Any]:
    """Every part in turn (module doc); writes gpu_check.json and summary.txt to `out` as each
    part ends (so a run cut short keeps what it measured) and returns the result."""
    from tabx_bench.simulator import load_average, machine_summary

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "machine": machine_summary(), "date": time.strftime("%Y-%m-%d %H:%M"),
        "load_avg": load_average(), "paper_steps": paper_steps,
        "simulator": [], "learners": [], "ued": [],
        "ued_settings": {"num_envs": ued_envs, "num_steps": ued_steps, "updates": ued_updates,
                         "eval_episodes": eval_episodes, "concurrency": concurrency}}

    def save() -> None:
        atomic_write_text(out / "gpu_check.json", json.dumps(result, indent=1) + "\n")
        atomic_write_text(out / "summary.txt", summarise(result))

    started = time.perf_counter()
    if team_sizes and sim_envs:
        log("simulator:")
        result["simulator"] = run_simulator(team_sizes, sim_envs, sim_steps, sim_repeats, log)
        save()
    if algorithms:
        log("learners:")
        result["learners"] = run_learners(algorithms, train_envs, train_steps, train_updates,
                                          log)
        save()
    if concurrency:
        log("UED trials:")
        with tempfile.TemporaryDirectory(prefix="tabx-gpu-check-") as work:
            # the caller's compilation cache (tools/gpu_check.sh: a fresh one), else one here
            cache = os.environ.get("TABX_COMPILE_CACHE_DIR") or str(Path(work) / "xla-cache")
            env = trial_env(cache)
            for c in concurrency:
                timings = run_trials(c, out, Path(work), ued_envs, ued_steps, ued_updates,
                                     eval_episodes, env)
                for t in timings:
                    result["ued"].append({**dataclasses.asdict(t),
                                          "overhead_s": t.overhead_s,
                                          "projected_minutes": t.projected_minutes(
                                              paper_steps)})
                rates = ", ".join(f"{t.steady_steps_per_s:,.0f}" for t in timings)
                log(f"  {c} at once: steady env steps/s {rates}; exit codes "
                    f"{[t.returncode for t in timings]} ({time.perf_counter() - started:.0f} s "
                    f"since the start)")
                save()
    result["seconds"] = time.perf_counter() - started
    save()
    return result


def bench_gpu(args: argparse.Namespace) -> int:
    from tabx.errors import UserError

    if args.ued_envs * args.ued_steps * args.ued_updates <= 0:
        raise UserError("--ued-envs, --ued-steps, --ued-updates: must be positive")
    result = run_gpu_check(
        args.out, team_sizes=args.team_sizes, sim_envs=args.sim_envs, sim_steps=args.sim_steps,
        sim_repeats=args.sim_repeats, algorithms=args.algorithms, train_envs=args.train_envs,
        train_steps=args.train_steps, train_updates=args.train_updates,
        ued_envs=args.ued_envs, ued_steps=args.ued_steps, ued_updates=args.ued_updates,
        eval_episodes=args.eval_episodes, concurrency=args.concurrency,
        log=lambda line: print(line, flush=True))
    print(summarise(result), end="")
    failed = [t for t in result["ued"] if t["returncode"] != 0]
    return 1 if failed else 0


def _algorithms(text: str) -> list[str]:
    from tabx_bench.train import _algorithms as learners

    return [] if text == "none" else learners(text)


def add_gpu_bench(which: argparse._SubParsersAction) -> None:
    """Add `gpu` to the `tabx bench` sub-commands."""
    positive, positives = int_at_least(1), int_list(1)
    p = which.add_parser("gpu", help="simulator, learners and UED trials at the paper's sizes, "
                                     "with projected minutes per trial (tools/gpu_check.sh)")
    p.add_argument("--out", required=True, help="folder for gpu_check.json, summary.txt, logs")
    p.add_argument("--team-sizes", type=lambda t: [] if t == "none" else positives(t),
                   default=[3, 10], help="simulator units a side (default 3,10; none: skip)")
    p.add_argument("--sim-envs", type=positives, default=[16384, 65536],
                   help="simulator env counts (default 16384,65536)")
    p.add_argument("--sim-steps", type=positive, default=128,
                   help="simulator scan length (default 128)")
    p.add_argument("--sim-repeats", type=positive, default=3,
                   help="timed simulator calls (median; default 3)")
    p.add_argument("--algorithms", type=_algorithms, default=["mappo", "ippo"],
                   help="learners (default mappo,ippo; none: skip)")
    p.add_argument("--train-envs", type=positive, default=128, help="learner envs (128)")
    p.add_argument("--train-steps", type=positive, default=512,
                   help="learner rollout steps (512)")
    p.add_argument("--train-updates", type=positive, default=3,
                   help="timed learner updates after the first (default 3)")
    p.add_argument("--ued-envs", type=positive, default=128, help="UED trial envs (128)")
    p.add_argument("--ued-steps", type=positive, default=512,
                   help="UED trial rollout steps and episode length (512)")
    p.add_argument("--ued-updates", type=positive, default=16,
                   help="UED steps per trial (default 16)")
    p.add_argument("--eval-episodes", type=int_at_least(0), default=0,
                   help="episodes per suite entry of the closing evaluation (default 0: the "
                        "suite's own, 64)")
    p.add_argument("--concurrency", type=lambda t: [] if t == "none" else positives(t),
                   default=[1, 2, 4],
                   help="UED trials at once, in turn (default 1,2,4; none: skip)")
    p.set_defaults(func=bench_gpu)


__all__ = ["PAPER_STEPS", "TrialTiming", "add_gpu_bench", "run_gpu_check", "summarise",
           "trial_command"]
