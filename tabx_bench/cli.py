"""The `tabx bench` command: its sub-commands and their arguments.

    tabx bench env | scale | reconfig | compare    the simulator (tabx_bench.simulator, .suite)
    tabx bench profile                             per-stage step time (tabx_bench.stage_profile)
    tabx bench train                               training throughput (tabx_bench.train)
    tabx bench ued                                 a UED run, local and on Ray (tabx_bench.ued)
    tabx bench gpu                                 all of it at the paper's sizes (tabx_bench.gpu)

The measuring code lives in those modules; this one only turns command lines into calls.
"""

from __future__ import annotations

import argparse

from tabx_bench.arguments import (
    controllers,
    int_at_least,
    int_list,
    non_negative_ints,
    team_sizes,
)
from tabx_bench.gpu import add_gpu_bench
from tabx_bench.simulator import NUM_ENVS, TEAM_SIZES, bench_env
from tabx_bench.stage_profile import bench_profile
from tabx_bench.suite import (
    SCALE_ENEMIES,
    SCALE_NUM_ENVS,
    SCALE_TEAM_SIZES,
    bench_compare,
    bench_reconfig,
    bench_scale,
)
from tabx_bench.train import add_train_bench
from tabx_bench.ued import add_ued_bench


def add_parser(subparsers: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """Add `tabx bench` with every benchmark; returns its sub-command group."""
    bench = subparsers.add_parser("bench", help="benchmarks (throughput, compile time)")
    which = bench.add_subparsers(dest="bench_command", metavar="BENCH")
    which.required = True
    env = which.add_parser("env", help="simulator steps/s with random legal actions")
    env.add_argument("--team-sizes", type=non_negative_ints, default=list(TEAM_SIZES),
                     help="comma-separated units per team (default 3,5,10)")
    env.add_argument("--zones", type=non_negative_ints, default=[0, 6],
                     help="comma-separated zone counts (default 0,6)")
    env.add_argument("--num-envs", type=non_negative_ints, default=list(NUM_ENVS),
                     help="comma-separated env counts (default 1,16,128,1024)")
    env.add_argument("--steps", type=int, default=128, help="scan length (default 128)")
    env.add_argument("--repeats", type=int, default=3, help="timed calls (median; default 3)")
    add_rollout_arguments(env)
    add_devices_argument(env)
    env.add_argument("--json", help="also write results as JSON lines to this file")
    env.set_defaults(func=bench_env)
    add_profile_parser(which)
    add_suite_parsers(which)
    add_train_bench(which)
    add_ued_bench(which)
    add_gpu_bench(which)
    return which


def add_devices_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--devices", type=int_at_least(0), default=0,
                        help="local devices to split the envs over (default 0: all that split "
                             "them evenly; on a CPU one per core; 1: one device)")


def add_rollout_arguments(parser: argparse.ArgumentParser) -> None:
    """--no-obs, --ally and --enemy: what the benchmark rollout
    (`tabx_bench.simulator.make_rollout`) computes besides the step."""
    parser.add_argument("--no-obs", dest="obs", action="store_false",
                        help="do not compute observations (random policy; state only)")
    parser.add_argument("--ally", default="random",
                        help="ally controller: random, idle, heuristic[:TIER] (default random)")
    parser.add_argument("--enemy", default="random",
                        help="enemy controller (default random; the scripted-enemy "
                             "benchmark uses heuristic:medium)")


def add_profile_parser(which: argparse._SubParsersAction) -> None:
    profile = which.add_parser(
        "profile", help="per-stage time of a simulator step from XLA:CPU's kernel profile")
    profile.add_argument("--team-sizes", type=team_sizes, default=list(TEAM_SIZES),
                         help="comma-separated units per team (default 3,5,10)")
    profile.add_argument("--zones", type=int_at_least(0), default=6,
                         help="zones per level (default 6)")
    profile.add_argument("--num-envs", type=int_at_least(1), default=1024,
                         help="envs (default 1024)")
    profile.add_argument("--steps", type=int_at_least(1), default=128,
                         help="scan length (default 128)")
    profile.add_argument("--repeats", type=int_at_least(1), default=2,
                         help="timed calls, then as many traced calls (default 2)")
    add_rollout_arguments(profile)
    profile.add_argument("--trace-dir",
                         help="keep the traces and HLO texts in this folder (default: a "
                              "temporary folder, removed)")
    profile.add_argument("--debug-stages", action="store_true",
                         help="list the call chains each stage's time comes from")
    profile.add_argument("--bandwidth-mb", type=int_at_least(1), default=256,
                         help="array size of the bandwidth measurement (default 256)")
    profile.add_argument("--json", help="write the profiles as JSON lines to this file")
    profile.add_argument("--plot", help="write a PNG of stacked stage times to this file")
    profile.set_defaults(func=bench_profile)


def add_suite_parsers(which: argparse._SubParsersAction) -> None:
    positive, positive_list = int_at_least(1), int_list(1)
    scale = which.add_parser("scale", help="steps/s versus num_envs for 3v3..10v10 (plot)")
    scale.add_argument("--team-sizes", type=team_sizes, default=list(SCALE_TEAM_SIZES),
                       help="comma-separated units per team (default 3,5,8,10)")
    scale.add_argument("--num-envs", type=positive_list, default=list(SCALE_NUM_ENVS),
                       help="comma-separated env counts (default 1,4,16,64,256,1024,4096)")
    scale.add_argument("--enemy", type=controllers, default=list(SCALE_ENEMIES),
                       help="comma-separated enemy controllers, allies random (default "
                            "random,heuristic:medium)")
    scale.add_argument("--zones", type=int_at_least(0), default=0,
                       help="zones per level (default 0)")
    scale.add_argument("--steps", type=positive, default=128, help="scan length (default 128)")
    scale.add_argument("--repeats", type=positive, default=3,
                       help="timed calls (median; default 3)")
    scale.add_argument("--no-obs", dest="obs", action="store_false",
                       help="do not compute observations (random policy; state only)")
    add_devices_argument(scale)
    scale.add_argument("--json", help="write results as JSON lines to this file")
    scale.add_argument("--plot", help="write a PNG plot (steps/s vs num_envs) to this file")
    scale.set_defaults(func=bench_scale)

    reconfig = which.add_parser(
        "reconfig", help="100 random scenarios through one compiled rollout (compile included)")
    reconfig.add_argument("--scenarios", type=positive, default=100,
                          help="random scenarios (default 100)")
    reconfig.add_argument("--num-envs", type=positive, default=128,
                          help="envs per scenario (default 128)")
    reconfig.add_argument("--steps", type=positive, default=128,
                          help="steps per scenario (default 128)")
    reconfig.add_argument("--seed", type=int, default=0, help="scenario generator seed")
    reconfig.add_argument("--no-obs", dest="obs", action="store_false",
                          help="do not compute observations")
    add_devices_argument(reconfig)
    reconfig.add_argument("--json", help="write the result as JSON lines to this file")
    reconfig.set_defaults(func=bench_reconfig)

    compare = which.add_parser(
        "compare", help="side by side with SMAX (needs the peers extra: pip install -e "
                        "'.[peers]')")
    compare.add_argument("--peer", default="smax", help="peer simulator (default smax)")
    compare.add_argument("--team-sizes", type=team_sizes, default=list(SCALE_TEAM_SIZES),
                         help="comma-separated units per team (default 3,5,8,10)")
    compare.add_argument("--num-envs", type=positive, default=1024,
                         help="envs for the fixed configuration (default 1024)")
    compare.add_argument("--steps", type=positive, default=128, help="scan length (default 128)")
    compare.add_argument("--repeats", type=positive, default=3,
                         help="timed calls (median; default 3)")
    compare.add_argument("--no-obs", dest="obs", action="store_false",
                         help="drop observations in both simulators")
    compare.add_argument("--scenarios", type=int_at_least(0), default=100,
                         help="reconfiguration scenarios (default 100; 0 skips reconfiguration)")
    compare.add_argument("--peer-scenarios", type=positive, default=None,
                         help="scenarios to really run on the peer, the rest extrapolated "
                              "(default: all)")
    compare.add_argument("--reconfig-envs", type=positive, default=128,
                         help="envs per reconfiguration scenario (default 128)")
    compare.add_argument("--reconfig-steps", type=positive, default=128,
                         help="steps per reconfiguration scenario (default 128)")
    compare.add_argument("--seed", type=int, default=0, help="scenario generator seed")
    add_devices_argument(compare)
    compare.add_argument("--json", help="write all results as JSON lines to this file")
    compare.add_argument("--plot", help="write a PNG plot to this file")
    compare.set_defaults(func=bench_compare)


__all__ = ["add_devices_argument", "add_parser", "add_profile_parser", "add_rollout_arguments",
           "add_suite_parsers"]
