"""`tabx bench profile`: where a simulator step's time goes, stage by stage, from XLA's profile.

For each team size it builds the rollout of `tabx bench env` (same level, controllers and
observation protocol), compiles it, warms it up, times `--repeats` calls, then runs as many
under `jax.profiler` with XLA:CPU's per-kernel trace events. Those exist only when XLA_FLAGS
holds `--xla_cpu_enable_xprof_traceme=true` before JAX starts its backend, so the measuring
runs in a child process (`python -m tabx_bench.stage_profile`) whose XLA_FLAGS are the caller's plus
that flag. The child leaves, per team size, the compiled program's HLO text, the trace and a
`meta.json` in a folder (`--trace-dir`, else a temporary one, removed afterwards).

The parent then reads the kernel events (tabx_bench.xplane), finds each kernel's instructions and
their Python call chains in the HLO text (tabx_bench.hlo_text) and adds the kernel's exclusive time
to the stages of tabx_bench.step_stages (fused kernels spanning several stages split by output
elements: an estimate). It prints, per team size, each stage's microseconds per scan step for
the whole batch and per env, and its share of the kernel time; the summed kernel time against
the wall time (XLA:CPU runs some kernels on two threads at once); and a rough memory bound:
the bytes one env step must read and write at the least, against the memory bandwidth
measured here with a large jitted `x + 1`.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tabx import xla_flags
from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.errors import UserError
from tabx.native_lib import native_available
from tabx.params import EnvParams, repeat_level
from tabx_bench.hlo_text import parse_hlo
from tabx_bench.simulator import (
    Progress,
    bench_level,
    load_average,
    machine_summary,
    make_rollout,
    write_results,
)
from tabx_bench.step_stages import OTHER, STAGES, attribute
from tabx_bench.xplane import kernel_spans, newest_trace

TRACEME_FLAG = "--xla_cpu_enable_xprof_traceme=true"
_HLO_FILE, _META_FILE, _TRACE_FOLDER = "hlo.txt", "meta.json", "trace"
_SOURCES_KEPT = 12  # call chains kept per stage (the slowest)


@dataclass
class ProfileSpec:
    """What the child measures (JSON through its command line)."""

    team_sizes: list[int]
    zones: int = 6
    num_envs: int = 1024
    steps: int = 128
    repeats: int = 2
    with_obs: bool = True
    ally: str = "random"
    enemy: str = "random"


@dataclass
class StageProfile:
    """One team size's profile (a JSON line of `--json`). Times are microseconds per scan step
    of the whole batch (divide by num_envs for one env's step)."""

    team_size: int
    zones: int
    num_envs: int
    steps: int
    calls: int  # traced rollout calls
    with_obs: bool
    controllers: str
    stages_us: dict[str, float]  # stage -> kernel microseconds per batch step
    kernel_us: float  # summed (exclusive) kernel time per batch step
    wall_us: float  # wall time per batch step of the traced calls (median call)
    wall_untraced_us: float  # the same without the profiler running
    compile_s: float
    bytes_per_env_step: int  # the memory bound's bytes (see memory_bytes)
    memory_bytes: dict[str, int]  # state, params, observation bytes of one env
    bandwidth_gb_s: float = 0.0
    load_avg: float | None = None
    # stage -> {call chain: us per batch step}, the slowest sources of each stage
    sources_us: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def bound_us(self) -> float:
        """Batch step time if every byte moved at the measured bandwidth (0 if unmeasured)."""
        if self.bandwidth_gb_s <= 0:
            return 0.0
        return self.bytes_per_env_step * self.num_envs / (self.bandwidth_gb_s * 1e3)


# --- measuring (the child process) -----------------------------------------------------------


def memory_bytes(env: TabxEnv, level: EnvParams, with_obs: bool) -> dict[str, int]:
    """Bytes of one env's state, level and observation (shapes only, from `jax.eval_shape`)."""
    def nbytes(tree) -> int:
        return int(sum(np.prod(x.shape) * np.dtype(x.dtype).itemsize
                       for x in jax.tree.leaves(tree)))

    state = jax.eval_shape(env.initial_state, level)
    obs = jax.eval_shape(env.observe, state, level) if with_obs else None
    return {"state": nbytes(state), "params": nbytes(level),
            "observation": nbytes(obs) if with_obs else 0}


def bytes_per_env_step(sizes: dict[str, int]) -> int:
    """The least one env step moves: its state read and written, its level read, its
    observation written (random keys, actions and the auto-reset's start state ignored)."""
    return 2 * sizes["state"] + sizes["params"] + sizes["observation"]


def measure_team(team_size: int, spec: ProfileSpec, folder: Path, label: str) -> None:
    """Compile, time and trace one team size's rollout into `folder` (HLO, trace, meta)."""
    controllers = (Controller.parse_scripted(spec.ally), Controller.parse_scripted(spec.enemy))
    config, level = bench_level(team_size, spec.zones)
    env = TabxEnv(config)
    level = with_tiers(level, controllers)
    levels = jax.tree.map(jnp.array, repeat_level(level, spec.num_envs))
    fn = make_rollout(env, spec.steps, spec.with_obs, controllers)
    print(f"{label} compiling", flush=True)
    native_available()  # built (or found cached) outside the compile time
    t0 = time.perf_counter()
    compiled = fn.lower(levels, jax.random.key(0)).compile()
    compile_s = time.perf_counter() - t0
    folder.mkdir(parents=True, exist_ok=True)
    (folder / _HLO_FILE).write_text(compiled.as_text())
    load_avg = load_average()
    jax.block_until_ready(compiled(levels, jax.random.key(0)))  # warm-up

    def timed_calls(first_seed: int) -> list[float]:
        times = []
        for i in range(spec.repeats):
            key = jax.random.key(first_seed + i)
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(levels, key))
            times.append(time.perf_counter() - t0)
        return times

    print(f"{label} timing {spec.repeats} calls", flush=True)
    untraced = timed_calls(1)
    print(f"{label} tracing {spec.repeats} calls", flush=True)
    jax.profiler.start_trace(str(folder / _TRACE_FOLDER))
    try:
        traced = timed_calls(1 + spec.repeats)
    finally:
        jax.profiler.stop_trace()
    meta = dict(team_size=team_size, zones=spec.zones, num_envs=spec.num_envs,
                steps=spec.steps, calls=spec.repeats, with_obs=spec.with_obs,
                controllers="/".join(map(str, controllers)), compile_s=compile_s,
                wall_s=statistics.median(traced), wall_untraced_s=statistics.median(untraced),
                memory_bytes=memory_bytes(env, level, spec.with_obs), load_avg=load_avg)
    (folder / _META_FILE).write_text(json.dumps(meta))


def team_folder(root: Path, team_size: int) -> Path:
    return root / f"{team_size}v{team_size}"


def _child_main(argv: list[str]) -> int:
    """`python -m tabx_bench.stage_profile SPEC_JSON FOLDER`: measure every team size of the
    spec."""
    spec, root = ProfileSpec(**json.loads(argv[0])), Path(argv[1])
    if TRACEME_FLAG not in os.environ.get("XLA_FLAGS", ""):
        print(f"error: XLA_FLAGS lacks {TRACEME_FLAG}", file=sys.stderr)
        return 2
    progress = Progress(len(spec.team_sizes))
    for team in spec.team_sizes:
        measure_team(team, spec, team_folder(root, team), f"  {team}v{team}:")
        print(f"  {team}v{team}: measured {progress.step()}", flush=True)
    return 0


def child_environment() -> dict[str, str]:
    """The caller's environment with the kernel trace flag added to XLA_FLAGS (other flags
    kept), and this copy of `tabx` first on the path."""
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    if "xla_cpu_enable_xprof_traceme" not in flags:
        env["XLA_FLAGS"] = f"{flags} {TRACEME_FLAG}".strip()
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env


def run_child(spec: ProfileSpec, root: Path) -> None:
    """Measure `spec` in a child process with the kernel trace flag, into `root`."""
    command = [sys.executable, "-m", "tabx_bench.stage_profile", json.dumps(asdict(spec)),
               str(root)]
    result = subprocess.run(command, env=child_environment(), check=False)
    if result.returncode != 0:
        raise RuntimeError(f"the profiling process exited with code {result.returncode} "
                           f"(its error is printed above)")


# --- analysing (the parent) ------------------------------------------------------------------


def analyse(folder: Path) -> StageProfile:
    """The stage profile of one team size's folder written by `measure_team`."""
    meta = json.loads((folder / _META_FILE).read_text())
    module = parse_hlo((folder / _HLO_FILE).read_text())
    events = kernel_spans(newest_trace(folder / _TRACE_FOLDER).read_bytes())
    if not events:
        raise RuntimeError(f"no XLA:CPU kernel events in the trace under {folder}: was "
                           f"{TRACEME_FLAG} in XLA_FLAGS when JAX started?")
    batch_steps = meta["calls"] * meta["steps"]
    stages, sources = attribute(module, ((e.name, e.exclusive_ps / 1e6 / batch_steps)
                                         for e in events))
    sizes = meta["memory_bytes"]
    return StageProfile(
        team_size=meta["team_size"], zones=meta["zones"], num_envs=meta["num_envs"],
        steps=meta["steps"], calls=meta["calls"], with_obs=meta["with_obs"],
        controllers=meta["controllers"], stages_us=stages, kernel_us=sum(stages.values()),
        wall_us=meta["wall_s"] * 1e6 / meta["steps"],
        wall_untraced_us=meta["wall_untraced_s"] * 1e6 / meta["steps"],
        compile_s=meta["compile_s"], bytes_per_env_step=bytes_per_env_step(sizes),
        memory_bytes=sizes, load_avg=meta["load_avg"],
        sources_us={stage: dict(list(chains.items())[:_SOURCES_KEPT])
                    for stage, chains in sources.items()})


def measure_bandwidth(megabytes: int = 256, repeats: int = 5) -> float:
    """Memory bandwidth in GB/s: bytes read and written per second by a jitted `x + 1` over a
    float32 array of `megabytes`, best of `repeats` calls. The input is donated, so the result
    lands in memory already touched: a fresh output buffer would be first-touch page faults,
    timing the kernel's memory mapping rather than its bandwidth (about 9x slower here)."""
    x = jnp.ones((megabytes * 2**20 // 4,), jnp.float32)
    nbytes = x.nbytes
    add_one = jax.jit(lambda a: a + 1.0, donate_argnums=0)
    x = jax.block_until_ready(add_one(x))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        x = jax.block_until_ready(add_one(x))
        best = min(best, time.perf_counter() - t0)
    return 2 * nbytes / best / 1e9


def _us(value: float) -> str:
    return f"{value:,.1f}" if value >= 100 else f"{value:.3g}"


def format_profile(p: StageProfile, debug_stages: bool = False) -> str:
    """The table of one team size's profile, with totals and the memory bound."""
    n = p.num_envs
    lines = [f"{p.team_size}v{p.team_size} ({2 * p.team_size} units), {p.zones} zones, "
             f"{n} envs, {p.controllers}, observations "
             f"{'every step' if p.with_obs else 'off'}; {p.calls} traced calls x {p.steps} "
             f"steps; compile {p.compile_s:.1f} s",
             f"  {'stage':<26} {'us/step, ' + str(n) + ' envs':>20} {'us/step/env':>12} "
             f"{'share':>7}"]
    for stage in STAGES:
        us = p.stages_us[stage]
        share = us / p.kernel_us if p.kernel_us else 0.0
        lines.append(f"  {stage:<26} {_us(us):>20} {us / n:>12.4f} {share:>7.1%}")
    lines.append(f"  {'kernel time (summed)':<26} {_us(p.kernel_us):>20} "
                 f"{p.kernel_us / n:>12.4f} {'100.0%':>7}")
    lines.append(f"  {'wall time (traced)':<26} {_us(p.wall_us):>20} {p.wall_us / n:>12.4f}")
    lines.append(f"  {'wall time (untraced)':<26} {_us(p.wall_untraced_us):>20} "
                 f"{p.wall_untraced_us / n:>12.4f}")
    busy = p.kernel_us / p.wall_us if p.wall_us else 0.0
    lines.append(f"  kernel time / wall time: {busy:.2f} (threads busy on average); a fused "
                 f"kernel spanning stages is split by output elements (an estimate)")
    sizes = p.memory_bytes
    lines.append(f"  bytes per env step: {p.bytes_per_env_step:,} (state {sizes['state']:,} "
                 f"read and written, level {sizes['params']:,} read, observation "
                 f"{sizes['observation']:,} written)")
    if p.bandwidth_gb_s > 0:
        ratio = p.wall_untraced_us / p.bound_us
        lines.append(f"  bandwidth {p.bandwidth_gb_s:.1f} GB/s; step time at bandwidth limit "
                     f"{p.bound_us / n:.4f} us/env ({_us(p.bound_us)} us per {n}-env step); "
                     f"measured step (untraced) {ratio:.{1 if ratio < 10 else 0}f}x the bound")
    if debug_stages:
        lines.append("  where each stage's time comes from (us per batch step; call chain, "
                     "innermost first):")
        for stage in STAGES:
            chains = [(chain, us) for chain, us in p.sources_us.get(stage, {}).items()
                      if us >= 0.005]
            if chains:
                lines.append(f"   {stage}:")
                lines.extend(f"    {us:10.2f}  {chain}"
                             for chain, us in (chains if stage == OTHER else chains[:5]))
    return "\n".join(lines)


def plot_profiles(profiles: list[StageProfile], path: str, title: str = "") -> None:
    """Stacked bars: microseconds per env step by stage, one bar per team size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    x = np.arange(len(profiles))
    bottom = np.zeros(len(profiles))
    colours = plt.cm.tab10(np.arange(len(STAGES)) % 10)
    for stage, colour in zip(STAGES, colours, strict=True):
        heights = np.array([p.stages_us[stage] / p.num_envs for p in profiles])
        ax.bar(x, heights, width=0.6, bottom=bottom, color=colour, label=stage)
        bottom += heights
    ax.hlines([p.wall_untraced_us / p.num_envs for p in profiles], x - 0.4, x + 0.4,
              colors="k", linestyles="--", label="wall time (untraced)")
    ax.set_xticks(x, [f"{p.team_size}v{p.team_size}" for p in profiles])
    handles, names = ax.get_legend_handles_labels()
    ax.legend(handles[::-1], names[::-1], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.01, 1.0))  # top to bottom as the bars stack
    ax.set_ylabel("microseconds per env step (kernel time)")
    ax.set_xlabel("team size")
    ax.grid(True, axis="y", alpha=0.3)
    ax.set_title(title or "TABX-UED step profile", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- the command -----------------------------------------------------------------------------


def bench_profile(args: argparse.Namespace) -> int:
    try:
        controllers = (Controller.parse_scripted(args.ally), Controller.parse_scripted(args.enemy))
    except ValueError as err:
        raise UserError(f"--ally/--enemy: {err}") from None
    bad = [t for t in args.team_sizes if t < 1]
    if bad:
        raise UserError(f"--team-sizes: every team needs at least 1 unit, got {bad[0]}")
    if args.trace_dir and Path(args.trace_dir).exists() and not Path(args.trace_dir).is_dir():
        raise UserError(f"--trace-dir: {args.trace_dir} exists and is not a folder")
    spec = ProfileSpec(team_sizes=list(args.team_sizes), zones=args.zones,
                       num_envs=args.num_envs, steps=args.steps, repeats=args.repeats,
                       with_obs=args.obs, ally=str(controllers[0]), enemy=str(controllers[1]))
    print(f"# tabx bench profile on {machine_summary()}; observations "
          f"{'computed every step' if spec.with_obs else 'not computed (--no-obs)'}; allies "
          f"{controllers[0]}, enemies {controllers[1]}; measuring in a child process with "
          f"{TRACEME_FLAG}", flush=True)
    with tempfile.TemporaryDirectory(prefix="tabx-profile-") as scratch:
        root = Path(args.trace_dir) if args.trace_dir else Path(scratch)
        run_child(spec, root)
        print("reading the traces", flush=True)
        profiles = [analyse(team_folder(root, t)) for t in spec.team_sizes]
    print(f"measuring memory bandwidth ({args.bandwidth_mb} MB x + 1)", flush=True)
    bandwidth = measure_bandwidth(args.bandwidth_mb)
    for p in profiles:
        p.bandwidth_gb_s = bandwidth
        print(format_profile(p, args.debug_stages), flush=True)
    if args.trace_dir:
        print(f"traces and HLO kept in {args.trace_dir}")
    if args.json:
        write_results(args.json, [{**asdict(p), "bound_us": p.bound_us} for p in profiles])
    if args.plot:
        plot_profiles(profiles, args.plot, title=(
            f"Kernel time per env step by stage ({spec.num_envs} envs, {spec.zones} zones, "
            f"{'obs' if spec.with_obs else 'no obs'}, {controllers[0]}/{controllers[1]})"))
        print(f"wrote {args.plot}")
    return 0


__all__ = ["ProfileSpec", "StageProfile", "analyse", "bench_profile",
           "bytes_per_env_step", "format_profile", "measure_bandwidth", "memory_bytes",
           "plot_profiles"]


if __name__ == "__main__":
    # The child is a process of its own: the `tabx` command's XLA settings (those the parent
    # passed on win), before JAX starts its backend.
    xla_flags.apply()
    sys.exit(_child_main(sys.argv[1:]))
