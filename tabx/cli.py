"""The `tabx` command line: one entry point, sub-commands registered by the modules that own them.

Each registrar module exposes `add_parser(subparsers)`, which adds its sub-command and sets
`func` on its parser; `func(args) -> int` is the exit code. Errors the user can fix (a bad file,
a bad value) are raised as `UserError` and printed without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

REGISTRARS = (
    "tabx.scenarios.cli",  # tabx scenarios list|show|validate|render
    "tabx.rollout",  # tabx rollout
    "tabx.bench",  # tabx bench env
    "level_buffer.cli",  # tabx buffer ...
    "tabx.editor.cli",  # tabx editor
    "ued.cli",  # tabx train, tabx eval
    "ued.levels_cli",  # tabx levels sample
    "ued.plot",  # tabx plot
)
# Commands whose first argument is a fixed word next to a free positional of another command
# (`tabx eval heuristics NAME` beside `tabx eval RUN_DIR`): (command, word) -> registrar module
# whose `add_route_parser(subparsers)` adds a parser named `word` under `command`.
ROUTES = {
    ("eval", "heuristics"): "tabx.tournament",  # tabx eval heuristics NAME
}


class UserError(Exception):
    """An error in the user's input (file, option, value): printed as one clear line."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tabx", description="TABX battle simulator, MARL learners and UED tools.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in REGISTRARS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            # A registrar that is not part of this install yet; anything else is a real error.
            if err.name is not None and name.startswith(err.name):
                continue
            raise
        module.add_parser(sub)
    return parser


def build_route_parser(command: str, word: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"tabx {command}")
    sub = parser.add_subparsers(dest="route", metavar=word)
    sub.required = True
    importlib.import_module(ROUTES[(command, word)]).add_route_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if tuple(argv[:2]) in ROUTES:
        args = build_route_parser(argv[0], argv[1]).parse_args(argv[1:])
        args.command = argv[0]
    else:
        args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as err:
        print(f"tabx {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    # Re-import so that UserError is the class the sub-commands raise (not __main__.UserError).
    from tabx.cli import main as _main

    sys.exit(_main())
