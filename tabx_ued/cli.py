"""`tabx`: one entry point whose sub-commands come from the layer that owns each.

    tabx scenarios | rollout | bench | editor | eval heuristics     the simulator (tabx.cli)
    tabx rollout --ally RUN_DIR                  a trained policy (ued.evaluate.load_policy_team)
    tabx buffer ...                                               level_buffer.cli
    tabx levels sample, tabx plot, tabx bench train               ued
    tabx train, tabx eval                                         tabx_ued.train_eval_commands
    tabx eval payoff                                              ued.payoff
    tabx analyse value-error                                      ued.value_error
    tabx runs status | buffer | check | show                      tabx_ued.run_folder_commands
"""

from __future__ import annotations

import argparse
import sys

from level_buffer import cli as buffer_cli
from tabx import cli as simulator_cli
from tabx_ued import run_folder_commands, train_eval_commands
from ued import levels_cli, payoff, plot, value_error
from ued.evaluate import load_policy_team
from ued.learners.bench import add_train_bench
from workers.bench import add_ued_bench


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    simulator_cli.add_simulator_commands(subparsers, bench_extra=[add_train_bench, add_ued_bench],
                                         policy_loader=load_policy_team)
    buffer_cli.add_parser(subparsers)
    train_eval_commands.add_parser(subparsers)
    run_folder_commands.add_parser(subparsers)
    levels_cli.add_parser(subparsers)
    plot.add_parser(subparsers)
    value_error.add_parser(subparsers)


# `tabx eval WORD ...` routes beside `tabx eval RUN_DIR` (tabx.cli.ROUTES).
ROUTES = {**simulator_cli.ROUTES, ("eval", "payoff"): payoff.add_route_parser}


def main(argv: list[str] | None = None) -> int:
    return simulator_cli.run(argv, [add_commands], ROUTES)


__all__ = ["add_commands", "main"]

if __name__ == "__main__":
    sys.exit(main())
