"""The command-line machinery, and the simulator's own commands.

A command is added by a *registrar*: a function `add_parser(subparsers)` that adds its
sub-command and sets `func` on its parser; `func(args) -> int` is the exit code. Errors the
user can fix (a bad file, a bad value) are raised as `tabx.errors.UserError` and printed as one
line, without a traceback.

The installed `tabx` command is `tabx_ued.cli:main`: it adds the commands of every layer
(buffer, train, eval, levels, plot, bench train) to the simulator's. This module's `main` is
the simulator alone (`python -m tabx.cli scenarios list`), usable without the learning side.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Iterable, Mapping

from tabx import bench_cli, rollout, tournament
from tabx.editor import cli as editor_cli
from tabx.errors import UserError
from tabx.policy_team import PolicyLoader
from tabx.scenarios import cli as scenarios_cli

Registrar = Callable[[argparse._SubParsersAction], object]
# Commands whose first argument is a fixed word next to a free positional of another command
# (`tabx eval heuristics NAME` beside `tabx eval RUN_DIR`): (command, word) -> a registrar that
# adds a parser named `word`.
Routes = Mapping[tuple[str, str], Registrar]

ROUTES: Routes = {("eval", "heuristics"): tournament.add_route_parser}


def add_simulator_commands(subparsers: argparse._SubParsersAction,
                           bench_extra: Iterable[Registrar] = (),
                           policy_loader: PolicyLoader | None = None) -> None:
    """`tabx scenarios | rollout | bench | editor`; `bench_extra` adds benchmarks of the layers
    above (see `tabx.bench_cli.add_parser`), `policy_loader` lets `tabx rollout` play a run
    folder's trained policy (see `tabx.policy_team`; without it the rollout plays controllers
    only)."""
    scenarios_cli.add_parser(subparsers)
    rollout.add_parser(subparsers, policy_loader)
    bench_cli.add_parser(subparsers, bench_extra)
    editor_cli.add_parser(subparsers)


def version_text() -> str:
    """`tabx --version`: this package's version and the JAX it runs on."""
    import jax

    from tabx import __version__

    return f"tabx-ued {__version__} (jax {jax.__version__}, python {sys.version.split()[0]})"


def build_parser(registrars: Iterable[Registrar]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tabx", description="TABX battle simulator, MARL learners and UED tools.")
    parser.add_argument("--version", action="version", version=version_text())
    parser.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an error (or set TABX_DEBUG=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in registrars:
        add(sub)
    return parser


def build_route_parser(command: str, word: str, routes: Routes) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"tabx {command}")
    sub = parser.add_subparsers(dest="route", metavar=word)
    sub.required = True
    routes[(command, word)](sub)
    return parser


# Names of a command's positional KEY=VALUE lists, which may also follow its options.
OVERRIDE_LISTS = ("items", "overrides")


def run(argv: list[str] | None, registrars: Iterable[Registrar], routes: Routes = ROUTES
        ) -> int:
    """Parse `argv` (default: sys.argv[1:]) against the registrars' commands and run one.

    Errors end in one line on stderr, never a traceback: a `UserError` (bad input, a damaged
    file) as `tabx COMMAND: error: ...` with exit code 2, anything else with its type and exit
    code 1. `tabx --debug COMMAND ...` (or TABX_DEBUG=1) lets the traceback through."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = os.environ.get("TABX_DEBUG", "") not in ("", "0")
    if argv[:1] == ["--debug"]:
        debug, argv = True, argv[1:]
    if tuple(argv[:2]) in routes:
        args = build_route_parser(argv[0], argv[1], routes).parse_args(argv[1:])
        args.command = argv[0]
    else:
        parser = build_parser(registrars)
        args, extra = parser.parse_known_args(argv)
        if extra:
            # KEY=VALUE overrides after options (`tabx train CONFIG --ray ray.explorers=2`):
            # argparse stops collecting positionals at the first option; gather them here.
            overrides = next((getattr(args, name) for name in OVERRIDE_LISTS
                              if isinstance(getattr(args, name, None), list)), None)
            if overrides is None or not all("=" in e and not e.startswith("-") for e in extra):
                parser.error(f"unrecognized arguments: {' '.join(extra)}")
            overrides.extend(extra)
    try:
        return int(args.func(args) or 0)
    except UserError as err:
        if debug:
            raise
        print(f"tabx {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        sys.stderr.close()
        return 0
    except Exception as err:  # noqa: BLE001 (the one place that turns any error into a line)
        if debug:
            raise
        text = str(err).strip().splitlines()[0] if str(err).strip() else ""
        print(f"tabx {args.command}: error: {type(err).__name__}{': ' if text else ''}{text} "
              f"(unexpected: run `tabx --debug {args.command} ...` or set TABX_DEBUG=1 for "
              f"the traceback)", file=sys.stderr)
        return 1


def main(argv: list[str] | None = None) -> int:
    """The simulator's commands only."""
    return run(argv, [add_simulator_commands])


__all__ = ["ROUTES", "Registrar", "UserError", "add_simulator_commands", "build_parser", "main",
           "run", "version_text"]

if __name__ == "__main__":
    sys.exit(main())
