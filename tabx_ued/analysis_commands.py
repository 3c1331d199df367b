"""The analysis commands over run folders: `tabx plot`, `tabx eval payoff`, `tabx analyse
value-error`. Each parses its arguments here and calls the library function that owns the work
(`ued.plot`, `ued.payoff`, `ued.value_error`).

    tabx plot RUN_DIR... --out curves.png [--tag TAG]
    tabx eval payoff RUN_DIR... --tiers heuristic:medium,random --scenario crossfire
    tabx analyse value-error RUN_DIR... [--scenario NAME] [--json OUT] [--plot PNG]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tabx.errors import UserError
from ued.config import ConfigError
from ued.payoff import DEFAULT_EPISODES, payoff_table, plot_payoff
from ued.plot import DEFAULT_TAGS, load_runs, plot_runs
from ued.value_error import (
    DEFAULT_HORIZON,
    DEFAULT_ROLLOUTS,
    DEFAULT_STATES,
    analyse_runs,
    plot_value_errors,
)


def cmd_plot(args: argparse.Namespace) -> int:
    if not args.out.lower().endswith(".png"):
        raise UserError(f"--out must name a .png file, got {args.out!r}")
    tags = list(plot_runs(load_runs(args.runs), args.tag or list(DEFAULT_TAGS), args.out))
    print(f"wrote {len(tags)} panels ({', '.join(tags)}) to {args.out}")
    return 0


def add_plot_parser(subparsers: argparse._SubParsersAction) -> None:
    """`tabx plot`."""
    p = subparsers.add_parser("plot", help="learning curves of run folders as a PNG")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR",
                   help="run folders (tabx train); a multi-seed run draws its seeds' mean and "
                        "standard error, RUN_DIR/seed-<s> one seed")
    p.add_argument("--tag", action="append", metavar="TAG",
                   help="a scalar tag to plot (repeatable; * matches, e.g. 'eval/*/mean_win_rate'"
                        f"); default: {', '.join(DEFAULT_TAGS)}")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.set_defaults(func=cmd_plot)


def cmd_payoff(args: argparse.Namespace) -> int:
    from tabx.files import atomic_write_json
    from ued import compile_cache

    if (args.scenario is None) == (args.suite is None):
        raise UserError("give one of --scenario NAME or --suite NAME_OR_FILE")
    tiers = [t.strip() for t in (args.tiers or "").split(",") if t.strip()]
    try:
        if args.suite is not None:
            from ued.suites import load_suite

            scenarios = list(load_suite(args.suite).scenarios)
        else:
            scenarios = [args.scenario]
        compile_cache.enable()
        table = payoff_table(args.runs, tiers, scenarios, episodes=args.episodes,
                             seed=args.seed, greedy=args.greedy, max_steps=args.max_steps,
                             checkpoint=args.checkpoint)
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(table.format())
    out = Path(args.out)
    json_path = out.with_name(out.name + ".json")
    png_path = out.with_name(out.name + ".png")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    data = {"runs": [str(r) for r in args.runs], "tiers": tiers, "seed": args.seed,
            "greedy": args.greedy, **table.to_json()}
    atomic_write_json(json_path, data)
    plot_payoff(table, png_path)
    print(f"wrote {json_path} and {png_path}")
    return 0


def add_payoff_route_parser(subparsers: argparse._SubParsersAction) -> None:
    """`tabx eval payoff ...` (a route beside `tabx eval RUN_DIR`, see tabx.cli.ROUTES)."""
    p = subparsers.add_parser(
        "payoff", help="policy-vs-policy payoff table of runs and scripted tiers",
        description="Play every pairing of the given run folders and scripted controllers, "
                    "each on the ally team against each on the enemy team (a policy plays "
                    "either team), and write the ally win-rate matrix as JSON and a heatmap.")
    p.add_argument("runs", nargs="*", metavar="RUN_DIR", help="run folders (any algorithm)")
    p.add_argument("--tiers", metavar="LIST",
                   help="comma-separated scripted sides, e.g. heuristic:novice,"
                        "heuristic:medium,random")
    p.add_argument("--scenario", help="the scenario every pairing plays")
    p.add_argument("--suite", metavar="NAME_OR_FILE",
                   help="play the distinct scenarios of an evaluation suite instead")
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"episodes per cell (default {DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--greedy", action="store_true",
                   help="take the most likely action instead of sampling")
    p.add_argument("--checkpoint", type=int,
                   help="checkpoint (update number) of every run (default: each run's newest)")
    p.add_argument("--max-steps", type=int, default=512,
                   help="episode limit when only tiers play (default 512)")
    p.add_argument("--out", default="payoff",
                   help="output path without extension: writes OUT.json and OUT.png "
                        "(default payoff)")
    p.set_defaults(func=cmd_payoff)


def cmd_value_error(args: argparse.Namespace) -> int:
    from tabx.files import atomic_write_json
    from ued import compile_cache

    for name in ("states", "rollouts", "horizon"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name} must be >= 1, got {getattr(args, name)}")
    compile_cache.enable()
    try:
        records = analyse_runs(args.runs, args.scenario, args.states, args.rollouts,
                               args.horizon, args.seed, args.checkpoint)
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(f"value error |V - V*|: {args.states} states x {args.rollouts} rollouts "
          f"(95 % interval over states; MC stderr: the noise of V*)")
    print(f"  {'run':40s} {'scenario':22s} {'|V - V*|':>18s} {'V':>8s} {'V*':>8s} "
          f"{'MC stderr':>9s}")
    for r in records:
        run = f"{Path(r['run']).name} ({r['algorithm']})"
        print(f"  {run:40s} {r['scenario']:22s} {r['mean_abs_error']:9.4f} ± "
              f"{r['ci95']:6.4f} {r['mean_value']:8.4f} {r['mean_mc_value']:8.4f} "
              f"{r['mean_mc_stderr']:9.4f}")
    if args.json:
        atomic_write_json(args.json, {"states": args.states, "rollouts": args.rollouts,
                                      "horizon": args.horizon, "seed": args.seed,
                                      "results": records})
        print(f"wrote {args.json}")
    if args.plot:
        plot_value_errors(records, args.plot, args.by)
        print(f"wrote {args.plot}")
    return 0


def add_analyse_parser(subparsers: argparse._SubParsersAction) -> None:
    """`tabx analyse value-error`."""
    analyse = subparsers.add_parser("analyse", help="analyses of trained policies",
                                    description="Analyses of trained policies.")
    sub = analyse.add_subparsers(dest="analysis", metavar="ANALYSIS")
    sub.required = True
    p = sub.add_parser(
        "value-error", help="value estimation error |V - V*| against Monte-Carlo values",
        description="Estimate V* by Monte-Carlo continuations from states of the policy's "
                    "own rollouts (recurrent state restored) and report mean |V - V*| per "
                    "run and scenario (the paper's value-error protocol).")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders")
    p.add_argument("--scenario", action="append",
                   help="scenario to analyse (repeatable; default: each run's own)")
    p.add_argument("--states", type=int, default=DEFAULT_STATES,
                   help=f"kept states, one per rollout env (default {DEFAULT_STATES})")
    p.add_argument("--rollouts", type=int, default=DEFAULT_ROLLOUTS,
                   help=f"Monte-Carlo continuations per state (default {DEFAULT_ROLLOUTS})")
    p.add_argument("--horizon", type=int, default=DEFAULT_HORIZON,
                   help=f"steps of the rollout the states are drawn from (default "
                        f"{DEFAULT_HORIZON})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--checkpoint", type=int, help="checkpoint of every run (default: newest)")
    p.add_argument("--json", metavar="OUT", help="also write the results as JSON")
    p.add_argument("--plot", metavar="PNG", help="also draw the per-scenario comparison")
    p.add_argument("--by", choices=("algorithm", "run"), default="algorithm",
                   help="bars of the plot: one per algorithm, pooling its runs (seeds) as mean "
                        "and standard error (default), or one per run")
    p.set_defaults(func=cmd_value_error)


__all__ = ["add_analyse_parser", "add_payoff_route_parser", "add_plot_parser", "cmd_payoff",
           "cmd_plot", "cmd_value_error"]
