"""`tabx runs`: a run folder seen from outside, while it runs (a registrar of `tabx_ued.cli`).

    tabx runs status RUN_DIR     a Ray run's state: actors and nodes, deaths, rate, staleness
    tabx runs buffer RUN_DIR     the live level buffer of a running Ray run (its LevelService)

Both read `RUN_DIR/ray.json` (`workers.ray_live`); `buffer` joins the run's cluster.
"""

from __future__ import annotations

import argparse


def cmd_status(args: argparse.Namespace) -> int:
    from workers.ray_live import read_record, status_text

    print(status_text(args.run_dir, read_record(args.run_dir)))
    return 0


def cmd_buffer(args: argparse.Namespace) -> int:
    from level_buffer.cli import summary
    from workers.ray_live import live_buffer

    buffer, size = live_buffer(args.run_dir)
    print(summary(buffer, f"{args.run_dir} (live)", size))
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    runs = subparsers.add_parser("runs", help="look at a Ray run while it runs",
                                 description="Look at a run trained with --ray: its record, "
                                             "and its level buffer while it runs.")
    which = runs.add_subparsers(dest="runs_command", required=True)
    status = which.add_parser("status", help="a Ray run's actors, deaths, rate and staleness")
    status.add_argument("run_dir", help="the run folder")
    status.set_defaults(func=cmd_status)
    buffer = which.add_parser("buffer", help="the live level buffer of a running Ray run "
                                             "(the summary of tabx buffer inspect)")
    buffer.add_argument("run_dir", help="the run folder")
    buffer.set_defaults(func=cmd_buffer)


__all__ = ["add_parser", "cmd_buffer", "cmd_status"]
