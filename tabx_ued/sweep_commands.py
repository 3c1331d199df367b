"""`tabx sweep SPEC`, `tabx sweep report SWEEP_DIR` and `tabx sweep evaluate SWEEP_DIR`:
experiments of many runs.

    tabx sweep configs/sweeps/smoke_ued.yaml                 # run it on a Ray started here
    tabx sweep configs/sweeps/smoke_ued.yaml --resume        # finish what a killed sweep left
    tabx sweep sweeps/paper_ued --address auto               # on the cluster this machine is in
    tabx sweep report sweeps/smoke_ued                       # its tables and learning curves
    tabx sweep report sweeps/smoke_ued --interval t95        # 95 % intervals, not s.e.
    tabx sweep evaluate sweeps/smoke_ued --max-steps 512     # its policies, 512-step episodes

The sweep file is `workers.sweep.spec`'s, the scheduling `workers.sweep.tune`'s (Ray Tune),
the report `workers.sweep.report`'s, the evaluation under another episode limit
`workers.sweep.reevaluate`'s; docs/experiments.md walks from one run to the paper's table.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from ued.errors import ConfigError


def cmd_sweep(args: argparse.Namespace) -> int:
    from workers.sweep.spec import read_sweep_spec, resources_from

    if args.num_cpus is not None and args.num_cpus < 1:
        raise ConfigError(f"--num-cpus: expected an integer >= 1 (the CPUs of the Ray started "
                          f"here), got {args.num_cpus}")
    if args.address is not None and not args.address.strip():
        raise ConfigError("--address: empty; give auto or HOST:PORT (or leave --address out "
                          "to start Ray here)")
    spec = read_sweep_spec(args.spec, args.overrides)  # every error before anything starts
    folder = spec.folder(args.dir)
    if args.resume and not args.overrides:
        from workers.sweep.folder import SweepFolder

        sweep = SweepFolder(folder)
        started = sweep.overrides()
        for name in sweep.trials() if started else ():  # its files, checked before the note
            sweep.record(name)
        if started:  # the overrides the sweep started with apply to every trial again
            print(f"{folder}: resuming with the overrides it started with: "
                  f"{' '.join(started)}", file=sys.stderr)
            spec = read_sweep_spec(args.spec, started)
    given = {k: v for k, v in (("cpus", args.cpus), ("gpus", args.gpus)) if v is not None}
    if given:
        spec = dataclasses.replace(spec, resources=resources_from(
            given, spec.resources, names={"cpus": "--cpus", "gpus": "--gpus"}))
    from workers.sweep.tune import run_sweep

    outcome = run_sweep(spec, folder,
                        resume=args.resume, address=args.address, num_cpus=args.num_cpus,
                        table_every_s=args.table_every)
    done = len(outcome.finished) + len(outcome.skipped)
    print(f"{outcome.folder}: {done} of {len(spec.trials)} trials finished"
          + (f", {len(outcome.failed)} failed ({', '.join(outcome.failed)})"
             if outcome.failed else "")
          + (f", {len(outcome.stopped)} stopped" if outcome.stopped else "")
          + f"; tabx sweep report {outcome.folder}")
    return 0 if outcome.ok else 1


def cmd_sweep_report(args: argparse.Namespace) -> int:
    from workers.sweep.report import write_report

    try:
        written = write_report(args.sweep_dir, out=args.out, partial=args.partial,
                               stream=sys.stderr, interval=args.interval)
    except OSError as err:  # the output folder cannot be made or written
        where = f"--out: {args.out}" if args.out is not None else str(err.filename or "")
        raise ConfigError(f"{where}: cannot write the report there ({err.strerror or err}); "
                          f"give a folder that can be made or written (--out)") from None
    print(written.markdown.read_text(), end="")
    print(f"written: {', '.join(str(p) for p in written.files())}", file=sys.stderr)
    return 0


def cmd_sweep_evaluate(args: argparse.Namespace) -> int:
    from ued import compile_cache
    from workers.sweep.reevaluate import evaluate_sweep

    if args.episodes is not None and args.episodes < 1:
        raise ConfigError(f"--episodes: expected an integer >= 1, got {args.episodes}")
    compile_cache.enable()
    try:
        markdown = evaluate_sweep(args.sweep_dir, args.max_steps, episodes=args.episodes,
                                  seed=args.seed, out=args.out, stream=sys.stderr)
    except OSError as err:
        where = f"--out: {args.out}" if args.out is not None else str(err.filename or "")
        raise ConfigError(f"{where}: cannot write the evaluation there ({err.strerror or err}); "
                          f"give a folder that can be made or written (--out)") from None
    print(markdown.read_text(), end="")
    print(f"written: {markdown}, {markdown.with_suffix('.csv')}", file=sys.stderr)
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sweep", help="run a sweep file's trials with Ray Tune (tabx sweep report: its tables)",
        description="Run every trial of a sweep file (a base config and axes over config keys: "
                    "docs/experiments.md) as an ordinary run folder under the sweep folder, "
                    "scheduled with Ray Tune on this machine or a cluster (--address). "
                    "`tabx sweep report SWEEP_DIR` makes its tables and figures.")
    p.add_argument("spec", metavar="SPEC", help="sweep file or shipped sweep name "
                                                "(sweeps/smoke_ued)")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="config overrides for every trial (after the file's `set`)")
    p.add_argument("--resume", action="store_true",
                   help="continue the sweep: finished trials are kept, the others continue "
                        "from their newest checkpoint")
    p.add_argument("--address", metavar="ADDRESS",
                   help="join a running Ray cluster (auto, or HOST:PORT) instead of starting "
                        "Ray here")
    p.add_argument("--dir", metavar="DIR",
                   help="the folder the sweep folder goes in (default: the file's `dir`)")
    p.add_argument("--cpus", type=float, metavar="N",
                   help="CPUs each trial holds (in place of the file's resources.cpus)")
    p.add_argument("--gpus", type=float, metavar="F",
                   help="GPU fraction each trial holds (in place of resources.gpus; 0.5: two "
                        "trials share a GPU)")
    p.add_argument("--num-cpus", type=int, metavar="N",
                   help="CPUs of the Ray started here (default: all)")
    p.add_argument("--table-every", type=float, default=30.0, metavar="S",
                   help="seconds between tables when the output is not a terminal (default 30)")
    p.set_defaults(func=cmd_sweep)


def add_route_parser(sub: argparse._SubParsersAction) -> None:
    """`report` under `tabx sweep` (a route of `tabx_ued.commands`)."""
    p = sub.add_parser("report", help="a sweep's tables (Markdown, CSV) and learning curves")
    p.add_argument("sweep_dir", metavar="SWEEP_DIR")
    p.add_argument("--out", metavar="DIR", help="where to write (default SWEEP_DIR/report)")
    p.add_argument("--partial", action="store_true",
                   help="report the finished trials of an incomplete sweep")
    p.add_argument("--interval", choices=("se", "t95"), default="se",
                   help="the spread of each cell: se, the standard error of the mean over "
                        "seeds (default, as the paper), or t95, half the 95 %% Student-t "
                        "interval")
    p.set_defaults(func=cmd_sweep_report)
    p = sub.add_parser("evaluate", help="a finished sweep's policies played again with another "
                                        "episode limit (the paper's: 512)")
    p.add_argument("sweep_dir", metavar="SWEEP_DIR")
    p.add_argument("--max-steps", type=int, required=True, metavar="M",
                   help="steps per episode (observations carry no clock)")
    p.add_argument("--episodes", type=int, metavar="K",
                   help="episodes per suite entry (default: the suite's)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", metavar="DIR", help="where to write (default SWEEP_DIR/report); a "
                                                "stopped evaluation continues from its CSV")
    p.set_defaults(func=cmd_sweep_evaluate)


__all__ = ["add_parser", "add_route_parser", "cmd_sweep", "cmd_sweep_evaluate",
           "cmd_sweep_report"]
