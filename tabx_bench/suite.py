"""`tabx bench scale | reconfig | compare`: scalability, reconfiguration, and a side by
side comparison with SMAX. The machinery (`make_rollout`, `run_one`, `BenchResult`, progress,
JSON lines) is tabx_bench/simulator.py's; the SMAX side lives in tabx_bench/peers/smax.py.

scale     env steps/s versus num_envs for 3v3, 5v5, 8v8 and 10v10, random actions for both
          teams and random allies versus the scripted enemy; compile time per configuration;
          JSON lines and a log-x plot (one line per team size and controller).
reconfig  the paper's protocol: 100 random scenarios (tabx/random_levels.py: unit types from the
          nine units, 3..10 a side, zones of all three types, one EnvConfig of 10 v 10 and 6
          zone slots), 128 envs x 128 steps each, random policy, timed from the first call to
          the last result with compilation included. Every scenario runs through ONE compiled
          rollout (the levels are jit arguments); XLA compilations are counted with a
          `jax.monitoring` listener and by the jitted function's cache, and any recompilation
          after the first scenario is an error.
compare   ours and SMAX (jaxmarl, the optional `peers` extra) in one process on one machine:
          fixed-configuration throughput at matched team sizes and the reconfiguration
          protocol; a table of ratios and a plot.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import jax
import numpy as np

from tabx.compile_counter import CompileCounter
from tabx.controllers import Controller
from tabx.devices import env_devices, env_sharding
from tabx.env import TabxEnv
from tabx.native_lib import native_available
from tabx.params import EnvConfig, EnvParams
from tabx_bench.simulator import (
    RANDOM_BOTH,
    BenchResult,
    Progress,
    ReconfigResult,
    check_devices,
    load_average,
    machine_summary,
    make_rollout,
    run_one,
    write_results,
)

SCALE_TEAM_SIZES = (3, 5, 8, 10)
SCALE_NUM_ENVS = (1, 4, 16, 64, 256, 1024, 4096)
SCALE_ENEMIES = ("random", "heuristic:medium")


# --- scale -------------------------------------------------------------------------------------


def run_scale(team_sizes: Sequence[int], num_envs: Sequence[int], enemies: Sequence[str],
              steps: int = 128, repeats: int = 3, with_obs: bool = True, zones: int = 0,
              log: Callable[[str], None] = print, devices: int = 0) -> list[BenchResult]:
    """One `run_one` per (enemy controller, team size, num_envs), with progress lines; the
    envs split over `devices` local devices (0: all that split them evenly)."""
    controllers = [(Controller("random"), Controller.parse(e)) for e in enemies]
    configs = [(c, t, n) for c in controllers for t in team_sizes for n in num_envs]
    log(f"{'controllers':>24} {'units':>6} {'envs':>6} {'devices':>7} {'compile s':>9} "
        f"{'run s':>8} {'steps/s':>12} {'load':>5}")
    progress = Progress(len(configs))
    results = []
    for ctrl, team, envs in configs:
        r = run_one(team, zones, envs, steps=steps, repeats=repeats, with_obs=with_obs,
                    controllers=ctrl, devices=devices)
        results.append(r)
        log(f"{r.controllers:>24} {f'{team}v{team}':>6} {envs:>6} {r.devices:>7} "
            f"{r.compile_s:>9.2f} {r.run_s:>8.3f} {r.steps_per_s:>12,.0f} "
            f"{r.load_avg or 0:>5.2f}   {progress.step()}")
    return results


def load_results(path: str) -> list[BenchResult]:
    """BenchResult rows of a `--json` file written by `tabx bench env` or `scale`."""
    import json

    fields = set(BenchResult.__dataclass_fields__)
    with open(path) as f:
        return [BenchResult(**{k: v for k, v in json.loads(line).items() if k in fields})
                for line in f if line.strip()]


def plot_scale(results: Sequence[BenchResult], path: str, title: str = "") -> None:
    """steps/s versus num_envs (log-log), one line per team size and controller pair."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 5))
    series: dict[tuple[str, int], list[BenchResult]] = {}
    for r in results:
        series.setdefault((r.controllers, r.team_size), []).append(r)
    sizes = sorted({t for _, t in series})
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, max(len(sizes), 1)))
    for (ctrl, team), rows in sorted(series.items()):
        rows = sorted(rows, key=lambda r: r.num_envs)
        heuristic = "heuristic" in ctrl
        ax.plot([r.num_envs for r in rows], [r.steps_per_s for r in rows],
                marker="s" if heuristic else "o", linestyle="--" if heuristic else "-",
                color=colours[sizes.index(team)],
                label=f"{team}v{team} ({2 * team} units), {ctrl}")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    envs = sorted({r.num_envs for r in results})
    ax.set_xticks(envs, [str(n) for n in envs])
    ax.set_xlabel("parallel environments (num_envs)")
    ax.set_ylabel("env steps / s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(title or "TABX-UED scalability", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- reconfig ----------------------------------------------------------------------------------


def host_batch(level: EnvParams, num_envs: int) -> EnvParams:
    """num_envs copies of a level as numpy arrays (no JAX op, so nothing to compile)."""
    return jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (num_envs, *np.shape(x))),
                        level)


def run_reconfig(levels: Sequence[EnvParams], config: EnvConfig, num_envs: int = 128,
                 steps: int = 128, seed: int = 0, with_obs: bool = True,
                 controllers: tuple[Controller, Controller] = RANDOM_BOTH,
                 log: Callable[[str], None] | None = None,
                 describe: Callable[[EnvParams], str] | None = None,
                 generate_s: float = 0.0, rollout=None, devices: int = 0) -> ReconfigResult:
    """Every level (num_envs copies each) through one compiled `steps`-long rollout, timed from
    the first call to the last result, the envs split over `devices` local devices (0: all that
    split them evenly). `rollout` (a jitted `make_rollout`) may be passed in to share its
    compiled executable across calls; by default a fresh one is made."""
    if not levels:
        raise ValueError("run_reconfig needs at least one level")
    fn = rollout if rollout is not None else make_rollout(TabxEnv(config), steps, with_obs,
                                                          controllers)
    hosts = [host_batch(level, num_envs) for level in levels]
    placement = env_sharding(env_devices(num_envs, devices))
    keys = [jax.random.key(seed + i) for i in range(len(levels))]
    progress = Progress(len(levels))
    load_avg = load_average()
    native_available()  # built (or found cached) before the clock starts
    with CompileCounter() as cc:
        t0 = time.perf_counter()
        first_s, after_first = 0.0, 0
        last = t0

        def finish(i: int, result) -> None:
            nonlocal last
            jax.block_until_ready(result)
            now = time.perf_counter()
            if log is not None:
                label = describe(levels[i]) if describe is not None else ""
                log(f"  scenario {i + 1:>3} {label:<32} {now - last:7.3f} s "
                    f"compilations {cc.compiles}   {progress.step()}")
            last = now

        # Each scenario is dispatched before waiting for the one in flight, so the devices never
        # wait for the host (placing the next levels, logging); a log line gives the time from
        # one scenario's result to the next.
        in_flight = None
        for i, host in enumerate(hosts):
            result = fn(jax.device_put(host, placement), keys[i])
            if i == 0:  # the first alone: its time is the compile-inclusive one
                jax.block_until_ready(result)
                first_s, after_first = time.perf_counter() - t0, cc.compiles
                finish(0, result)
                continue
            if in_flight is not None:
                finish(*in_flight)
            in_flight = (i, result)
        if in_flight is not None:
            finish(*in_flight)
        total_s = time.perf_counter() - t0
    # Every XLA compilation in the process counts (the listener sees eager ops too); the jitted
    # rollout's own executable cache must hold one entry.
    recompilations = cc.compiles - after_first
    if rollout is None and fn._cache_size() != 1:
        recompilations = max(recompilations, fn._cache_size() - 1)
    n = len(levels)
    return ReconfigResult("tabx", n, num_envs, steps, total_s, first_s, cc.seconds, cc.compiles,
                          recompilations, n * num_envs * steps / total_s, n, False, generate_s,
                          load_avg)


def bench_reconfig(args: argparse.Namespace) -> int:
    from tabx.errors import UserError
    from tabx.random_levels import RECONFIG_CONFIG, composition, random_levels

    print(f"# tabx bench reconfig on {machine_summary()}; {args.scenarios} random scenarios "
          f"(3..10 a side, 0..6 zones, EnvConfig 10v10 + 6 zone slots), {args.num_envs} envs "
          f"x {args.steps} steps each, random actions, observations "
          f"{'computed' if args.obs else 'not computed'}; load average {load_average()}",
          flush=True)
    check_devices(args.devices, [args.num_envs])
    t0 = time.perf_counter()
    levels = random_levels(args.scenarios, seed=args.seed)
    generate_s = time.perf_counter() - t0
    print(f"generated and validated {len(levels)} levels in {generate_s:.2f} s", flush=True)
    result = run_reconfig(levels, RECONFIG_CONFIG, args.num_envs, args.steps, args.seed,
                          with_obs=args.obs, log=lambda s: print(s, flush=True),
                          describe=composition, generate_s=generate_s, devices=args.devices)
    print(format_reconfig(result), flush=True)
    if args.json:
        write_results(args.json, [reconfig_row(result)])
    if result.recompilations:
        raise UserError(f"{result.recompilations} recompilation(s) after the first scenario: "
                        "a level changed something static")
    return 0


def reconfig_row(r: ReconfigResult) -> dict:
    return {**asdict(r), "env_steps": r.env_steps}


def format_reconfig(r: ReconfigResult) -> str:
    label = (f" (extrapolated from {r.measured_scenarios} measured scenarios)"
             if r.extrapolated else "")
    return (f"{r.simulator}: {r.scenarios} scenarios x {r.num_envs} envs x {r.steps} steps = "
            f"{r.env_steps:,} env steps in {r.total_s:.2f} s{label}; first scenario "
            f"{r.first_s:.2f} s; compile {r.compile_s:.2f} s; {r.compilations} compilations, "
            f"{r.recompilations} after the first; effective {r.effective_steps_per_s:,.0f} "
            f"env steps/s")


# --- compare -----------------------------------------------------------------------------------


class TabxSimulator:
    """Our side of `tabx bench compare`, behind the same interface as a peer."""

    name = "tabx"

    def __init__(self, devices: int = 0):
        self.devices = devices  # local devices the envs are split over (0: all that divide)

    def version(self) -> str:
        import tabx

        return getattr(tabx, "__version__", "0.1.0")

    def throughput(self, team_size: int, num_envs: int, steps: int, repeats: int,
                   with_obs: bool) -> BenchResult:
        return run_one(team_size, 0, num_envs, steps=steps, repeats=repeats, with_obs=with_obs,
                       devices=self.devices)

    def reconfig(self, scenarios: int, num_envs: int, steps: int, seed: int, with_obs: bool,
                 measure: int | None = None, log: Callable[[str], None] | None = None
                 ) -> ReconfigResult:
        del measure  # ours always runs them all
        from tabx.random_levels import RECONFIG_CONFIG, composition, random_levels

        t0 = time.perf_counter()
        levels = random_levels(scenarios, seed=seed)
        generate_s = time.perf_counter() - t0
        return run_reconfig(levels, RECONFIG_CONFIG, num_envs, steps, seed, with_obs, log=log,
                            devices=self.devices,
                            describe=composition, generate_s=generate_s)


@dataclass
class CompareRow:
    team_size: int
    num_envs: int
    ours: float
    peer: float

    @property
    def ratio(self) -> float:
        return self.ours / self.peer if self.peer > 0 else float("inf")


def compare_rows(ours: Sequence[BenchResult], peer: Sequence[BenchResult]) -> list[CompareRow]:
    """Match results by (team size, num_envs); every one of ours needs its peer result."""
    theirs = {(r.team_size, r.num_envs): r for r in peer}
    rows = []
    for r in ours:
        key = (r.team_size, r.num_envs)
        if key not in theirs:
            raise ValueError(f"no peer result for {r.team_size}v{r.team_size} at "
                             f"{r.num_envs} envs")
        rows.append(CompareRow(r.team_size, r.num_envs, r.steps_per_s, theirs[key].steps_per_s))
    return rows


def reconfig_ratio(ours: ReconfigResult, peer: ReconfigResult) -> float:
    """Ratio of effective throughputs (env steps per second, compilation included)."""
    if peer.effective_steps_per_s <= 0:
        return float("inf")
    return ours.effective_steps_per_s / peer.effective_steps_per_s


def format_compare(rows: Sequence[CompareRow], peer_name: str,
                   ours_reconfig: ReconfigResult | None = None,
                   peer_reconfig: ReconfigResult | None = None) -> str:
    lines = [f"{'units':>6} {'envs':>6} {'tabx steps/s':>14} {peer_name + ' steps/s':>16} "
             f"{'ratio':>7}"]
    for row in rows:
        lines.append(f"{f'{row.team_size}v{row.team_size}':>6} {row.num_envs:>6} "
                     f"{row.ours:>14,.0f} {row.peer:>16,.0f} {row.ratio:>6.2f}x")
    if ours_reconfig is not None and peer_reconfig is not None:
        ratio = reconfig_ratio(ours_reconfig, peer_reconfig)
        lines.append("")
        lines.append(f"reconfiguration ({ours_reconfig.scenarios} scenarios x "
                     f"{ours_reconfig.num_envs} envs x {ours_reconfig.steps} steps):")
        lines.append("  " + format_reconfig(ours_reconfig))
        lines.append("  " + format_reconfig(peer_reconfig))
        lines.append(f"  effective throughput ratio {ratio:,.1f}x; tabx recompilations after "
                     f"the first: {ours_reconfig.recompilations}")
    return "\n".join(lines)


def plot_compare(rows: Sequence[CompareRow], path: str, peer_name: str,
                 ours_reconfig: ReconfigResult | None = None,
                 peer_reconfig: ReconfigResult | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 2 if ours_reconfig is not None and peer_reconfig is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.2), squeeze=False)
    ax = axes[0][0]
    units = [2 * r.team_size for r in rows]
    ax.plot(units, [r.ours for r in rows], "o-", label="TABX-UED (ours)")
    ax.plot(units, [r.peer for r in rows], "s--", label=peer_name)
    for u, r in zip(units, rows, strict=True):
        ax.annotate(f"{r.ratio:.1f}x", (u, r.ours), textcoords="offset points", xytext=(0, 6),
                    ha="center", fontsize=8)
    ax.set_yscale("log")
    ax.set_xlabel("units in total (N v N)")
    ax.set_ylabel("env steps / s")
    envs = sorted({r.num_envs for r in rows})
    ax.set_title(f"fixed configuration, {', '.join(map(str, envs))} envs", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if panels == 2:
        ax = axes[0][1]
        values = [ours_reconfig.effective_steps_per_s, peer_reconfig.effective_steps_per_s]
        labels = ["TABX-UED (ours)", peer_name + (" (extrap.)" if peer_reconfig.extrapolated
                                                   else "")]
        ax.bar(labels, values, color=["tab:blue", "tab:orange"])
        for i, v in enumerate(values):
            ax.annotate(f"{v:,.0f}", (i, v), textcoords="offset points", xytext=(0, 3),
                        ha="center", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylim(min(values) / 4, max(values) * 2)
        ax.set_ylabel("effective env steps / s (compile included)")
        ax.set_title(f"reconfiguration: {ours_reconfig.scenarios} scenarios, "
                     f"{reconfig_ratio(ours_reconfig, peer_reconfig):,.0f}x", fontsize=9)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def load_peer(name: str, devices: int = 0):
    """The peer simulator object, its envs split over `devices` local devices like ours; a
    UserError telling how to install it when it is missing."""
    from tabx.errors import UserError
    from tabx_bench.peers import PeerUnavailable

    if name != "smax":
        raise UserError(f"unknown peer {name!r}; expected smax")
    try:
        from tabx_bench.peers.smax import SmaxSimulator

        return SmaxSimulator(devices)
    except PeerUnavailable as err:
        raise UserError(str(err)) from None


def run_compare(ours, peer, team_sizes: Sequence[int], num_envs: int, steps: int, repeats: int,
                with_obs: bool, scenarios: int, reconfig_envs: int, reconfig_steps: int,
                seed: int, peer_scenarios: int | None, log: Callable[[str], None] = print
                ) -> tuple[list[BenchResult], list[BenchResult], ReconfigResult | None,
                           ReconfigResult | None]:
    """Both simulators through both protocols, alternating so that load changes hit both."""
    ours_fixed, peer_fixed = [], []
    progress = Progress(2 * len(team_sizes) + (2 if scenarios else 0))
    for team in team_sizes:
        for sim, out in ((ours, ours_fixed), (peer, peer_fixed)):
            r = sim.throughput(team, num_envs, steps, repeats, with_obs)
            out.append(r)
            log(f"{sim.name:>6} {team}v{team} {num_envs} envs: compile {r.compile_s:.2f} s, "
                f"{r.steps_per_s:,.0f} steps/s, load {r.load_avg}   {progress.step()}")
    ours_rc = peer_rc = None
    if scenarios:
        for sim in (ours, peer):
            rc = sim.reconfig(scenarios, reconfig_envs, reconfig_steps, seed, with_obs,
                              measure=peer_scenarios)
            log("  " + format_reconfig(rc) + f"   {progress.step()}")
            if sim is ours:
                ours_rc = rc
            else:
                peer_rc = rc
    return ours_fixed, peer_fixed, ours_rc, peer_rc


def bench_compare(args: argparse.Namespace) -> int:
    # The peer first: fail fast when the extra is not installed. Both split their envs alike.
    peer = load_peer(args.peer, args.devices)
    check_devices(args.devices, [args.num_envs, args.reconfig_envs])
    ours = TabxSimulator(args.devices)
    print(f"# tabx bench compare on {machine_summary()}; {peer.name} {peer.version()}; "
          f"random actions, {args.steps}-step scan of vmap(step) with auto-reset into the start "
          f"states, observations {'carried' if args.obs else 'dropped'}; load average "
          f"{load_average()}", flush=True)
    ours_fixed, peer_fixed, ours_rc, peer_rc = run_compare(
        ours, peer, args.team_sizes, args.num_envs, args.steps, args.repeats, args.obs,
        args.scenarios, args.reconfig_envs, args.reconfig_steps, args.seed,
        args.peer_scenarios, log=lambda s: print(s, flush=True))
    rows = compare_rows(ours_fixed, peer_fixed)
    print(format_compare(rows, peer.name, ours_rc, peer_rc), flush=True)
    if args.json:
        out: list[dict] = []
        for sim, results in ((ours.name, ours_fixed), (peer.name, peer_fixed)):
            out += [{"kind": "fixed", "simulator": sim, **asdict(r)} for r in results]
        out += [{"kind": "ratio", "team_size": r.team_size, "num_envs": r.num_envs,
                 "ratio": r.ratio} for r in rows]
        for rc in (ours_rc, peer_rc):
            if rc is not None:
                out.append({"kind": "reconfig", **reconfig_row(rc)})
        if ours_rc is not None and peer_rc is not None:
            out.append({"kind": "reconfig_ratio", "ratio": reconfig_ratio(ours_rc, peer_rc)})
        write_results(args.json, out)
    if args.plot:
        plot_compare(rows, args.plot, peer.name, ours_rc, peer_rc)
        print(f"wrote {args.plot}")
    return 0


# --- the command line --------------------------------------------------------------------------


def bench_scale(args: argparse.Namespace) -> int:
    from tabx.errors import UserError

    for text in args.enemy:
        try:
            Controller.parse_scripted(text)
        except ValueError as err:
            raise UserError(f"--enemy: {err}") from None
    print(f"# tabx bench scale on {machine_summary()}; {args.steps}-step scan, median of "
          f"{args.repeats}; observations {'computed every step' if args.obs else 'not computed'}"
          f"; {args.zones} zones; load average {load_average()}", flush=True)
    check_devices(args.devices, args.num_envs)
    results = run_scale(args.team_sizes, args.num_envs, args.enemy, args.steps, args.repeats,
                        args.obs, args.zones, log=lambda s: print(s, flush=True),
                        devices=args.devices)
    if args.json:
        write_results(args.json, [{**asdict(r), "units": 2 * r.team_size} for r in results])
    if args.plot:
        plot_scale(results, args.plot, title=f"TABX-UED scalability ({args.steps}-step scan, "
                   f"obs {'on' if args.obs else 'off'}; {machine_summary()})")
        print(f"wrote {args.plot}")
    return 0


__all__ = ["TabxSimulator", "compare_rows", "format_compare",
           "plot_compare", "plot_scale", "reconfig_ratio", "run_compare", "run_reconfig",
           "run_scale"]
