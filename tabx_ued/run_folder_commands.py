"""`tabx runs`: a run folder seen from outside, while it runs (a registrar of `tabx_ued.cli`).

    tabx runs status RUN_DIR     a Ray run's state: actors and nodes, deaths, rate, staleness
    tabx runs buffer RUN_DIR     the live level buffer of a running Ray run (its LevelService)
    tabx runs check RUN_DIR      every checkpoint and level snapshot: intact or damaged
    tabx runs show RUN_DIR       the config, and what produced each checkpoint (its metadata)

`status` and `buffer` read `RUN_DIR/ray.json` (`workers.ray.live`); `buffer` joins the run's
cluster. `check` (`workers.resume`) and `show` (`ued.run_folder.run_summary`) read any run
folder and change nothing.
"""

from __future__ import annotations

import argparse

from tabx.errors import UserError


def cmd_status(args: argparse.Namespace) -> int:
    from workers.ray.live import read_record, status_text

    print(status_text(args.run_dir, read_record(args.run_dir)))
    return 0


def cmd_buffer(args: argparse.Namespace) -> int:
    from tabx_ued.buffer_commands import summary
    from workers.ray.live import live_buffer

    buffer, size = live_buffer(args.run_dir)
    print(summary(buffer, f"{args.run_dir} (live)", size))
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from ued.config import ConfigError
    from workers.resume import check_run_folder, format_checks

    try:
        checks = check_run_folder(args.run_dir)
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(format_checks(args.run_dir, checks))
    return 0 if all(check.intact for check in checks) else 1


def cmd_show(args: argparse.Namespace) -> int:
    from ued.config import ConfigError
    from ued.run_folder import run_summary

    try:
        print(run_summary(args.run_dir))
    except ConfigError as err:
        raise UserError(str(err)) from None
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
    check = which.add_parser("check", help="every checkpoint and level snapshot of a run "
                                           "folder: intact or damaged (exit 1 if any is)")
    check.add_argument("run_dir", help="the run folder")
    check.set_defaults(func=cmd_check)
    show = which.add_parser("show", help="a run folder's config and each checkpoint's metadata "
                                         "(config hash, update, policy version, versions)")
    show.add_argument("run_dir", help="the run folder")
    show.set_defaults(func=cmd_show)


__all__ = ["add_parser", "cmd_buffer", "cmd_check", "cmd_show", "cmd_status"]
