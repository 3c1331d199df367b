"""The `tabx` command table: every sub-command, and the module that owns it.

    tabx scenarios list | show | validate | render               tabx_ued.scenarios
    tabx rollout [NAME] [--ally RUN_DIR|CONTROLLER] ...          tabx_ued.rollout
    tabx editor                                                  tabx_ued.editor
    tabx bench env | profile | scale | reconfig | compare | train | ued      tabx_bench.cli
    tabx buffer ...                                              tabx_ued.buffer_commands
    tabx levels sample                                           tabx_ued.levels_commands
    tabx plot                                                    tabx_ued.analysis_commands
    tabx train, tabx eval                                        tabx_ued.train_eval_commands
    tabx eval heuristics                                         tabx_ued.heuristics
    tabx eval payoff                                             tabx_ued.analysis_commands
    tabx analyse value-error                                     tabx_ued.analysis_commands
    tabx runs status | buffer                                    tabx_ued.run_folder_commands
    tabx sweep SPEC, tabx sweep report, tabx sweep evaluate       tabx_ued.sweep_commands
"""

from __future__ import annotations

import argparse

from tabx_bench import cli as bench_cli
from tabx_ued import (
    analysis_commands,
    buffer_commands,
    editor,
    heuristics,
    levels_commands,
    rollout,
    run_folder_commands,
    scenarios,
    sweep_commands,
    train_eval_commands,
)


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add every `tabx` sub-command (the registrar of `tabx_ued.cli.main`)."""
    scenarios.add_parser(subparsers)
    rollout.add_parser(subparsers)
    bench_cli.add_parser(subparsers)
    editor.add_parser(subparsers)
    buffer_commands.add_parser(subparsers)
    train_eval_commands.add_parser(subparsers)
    run_folder_commands.add_parser(subparsers)
    levels_commands.add_parser(subparsers)
    analysis_commands.add_plot_parser(subparsers)
    analysis_commands.add_analyse_parser(subparsers)
    sweep_commands.add_parser(subparsers)


# `tabx eval WORD ...` routes beside `tabx eval RUN_DIR`; `tabx sweep report` and
# `tabx sweep evaluate` beside `tabx sweep SPEC`.
ROUTES = {("eval", "heuristics"): heuristics.add_route_parser,
          ("eval", "payoff"): analysis_commands.add_payoff_route_parser,
          ("sweep", "report"): sweep_commands.add_route_parser,
          ("sweep", "evaluate"): sweep_commands.add_route_parser}


__all__ = ["ROUTES", "add_commands"]
