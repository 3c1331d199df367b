"""The `tabx` command's entry point and machinery: parse a command line, run one command, turn
its errors into one line.

`main` is the console script (`tabx`, also `python -m tabx` and `python -m tabx_ued`). It first
applies the XLA:CPU settings of the `tabx` command (`tabx.xla_flags.apply`: one CPU device per
usable core, YNN fusion off), before anything of JAX is imported, then loads the command table
(`tabx_ued.commands`).

A command is added by a *registrar*: a function `add_parser(subparsers)` that adds its
sub-command and sets `func` on its parser; `func(args) -> int` is the exit code. Errors the
user can fix (a bad file, a bad value) are raised as `tabx.errors.UserError` and printed as one
line, without a traceback.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from collections.abc import Callable, Iterable, Mapping

from tabx import xla_flags
from tabx.errors import UserError

Registrar = Callable[[argparse._SubParsersAction], object]
# Commands whose first argument is a fixed word next to a free positional of another command
# (`tabx eval heuristics NAME` beside `tabx eval RUN_DIR`): (command, word) -> a registrar that
# adds a parser named `word`.
Routes = Mapping[tuple[str, str], Registrar]


def version_text() -> str:
    """`tabx --version`: this package's version and the JAX it runs on."""
    import jax

    from tabx import __version__

    return f"tabx-ued {__version__} (jax {jax.__version__}, python {sys.version.split()[0]})"


def build_parser(registrars: Iterable[Registrar]) -> argparse.ArgumentParser:
    """The `tabx` parser with the sub-commands the registrars add."""
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


def command_parser(parser: argparse.ArgumentParser, command: str | None
                   ) -> argparse.ArgumentParser:
    """The parser of `command` among `parser`'s subcommands (`parser` itself if none)."""
    for action in parser._actions:  # argparse keeps its subparsers only here
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return parser


def build_route_parser(command: str, word: str, routes: Routes) -> argparse.ArgumentParser:
    """The parser of one route, `tabx COMMAND WORD ...`."""
    parser = argparse.ArgumentParser(prog=f"tabx {command}")
    sub = parser.add_subparsers(dest="route", metavar=word)
    sub.required = True
    routes[(command, word)](sub)
    return parser


# Names of a command's positional KEY=VALUE lists, which may also follow its options.
OVERRIDE_LISTS = ("items", "overrides")


def run(argv: list[str] | None, registrars: Iterable[Registrar], routes: Routes | None = None
        ) -> int:
    """Parse `argv` (default: sys.argv[1:]) against the registrars' commands and run one.

    Errors end in one line on stderr, never a traceback: a `UserError` (bad input, a damaged
    file) as `tabx COMMAND: error: ...` with exit code 2, anything else with its type and exit
    code 1. `tabx --debug COMMAND ...` (or TABX_DEBUG=1) lets the traceback through."""
    routes = {} if routes is None else routes
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
                # The command's own usage (`tabx eval RUN_A RUN_B`), not the list of commands.
                command_parser(parser, getattr(args, "command", None)).error(
                    f"unrecognized arguments: {' '.join(extra)}")
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
        problem = platform_problem()
        if problem is not None:
            print(f"tabx {args.command}: error: {problem}", file=sys.stderr)
            return 2
        print(f"tabx {args.command}: error: {error_line(err)} (unexpected: run `tabx --debug "
              f"{args.command} ...` or set TABX_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


def error_line(err: BaseException) -> str:
    """An unexpected error in one line: its type and first line. An error raised inside a Ray
    actor (Ray's `RayTaskError(...)`, whose text is the actor's traceback, perhaps around
    another actor's) is shown by the error the innermost actor raised, and its call."""
    call = ""
    while type(err).__name__.startswith("RayTaskError"):
        cause = getattr(err, "cause", None)
        if not isinstance(cause, BaseException) or cause is err:
            break
        first = re.sub(r"\x1b\[[0-9;]*m", "", str(err)).strip().split("\n")[0]
        if first.startswith("ray::"):
            call = first.removeprefix("ray::").split(" (pid=")[0]
        err = cause
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    where = f" (raised in the Ray actor call {call})" if call else ""
    return f"{type(err).__name__}{': ' if text else ''}{text}{where}"


def platform_problem() -> str | None:
    """Why the JAX platform `JAX_PLATFORMS` names cannot start here (JAX reports it at the first
    use of a device, for some platforms as a bare AssertionError), with the platforms this
    machine has; None when it starts or the variable is unset."""
    wanted = os.environ.get("JAX_PLATFORMS", "")
    if not wanted or "jax" not in sys.modules:
        return None
    import jax

    try:
        jax.devices()
        return None
    except Exception as err:  # noqa: BLE001 (JAX raises RuntimeError or AssertionError here)
        why = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    # What starts without the setting, asked of a fresh interpreter (this one's JAX is set).
    probe = "import jax; print(','.join(sorted({d.platform for d in jax.devices()})))"
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    try:
        found = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                               text=True, timeout=120).stdout.strip() or "none"
    except (OSError, subprocess.SubprocessError):
        found = "unknown"
    return (f"JAX_PLATFORMS={wanted}: JAX cannot start that platform here ({why[:200]}); "
            f"this machine has: {found}; unset JAX_PLATFORMS or set it to one of those")


def main(argv: list[str] | None = None) -> int:
    """The `tabx` command: its XLA settings, then every command (`tabx_ued.commands`)."""
    xla_flags.apply()  # before JAX starts its backend: the command table imports JAX
    from tabx_ued.commands import ROUTES, add_commands

    return run(argv, [add_commands], ROUTES)


__all__ = ["Registrar", "Routes", "UserError", "build_parser", "main", "platform_problem", "run",
           "version_text"]

if __name__ == "__main__":
    sys.exit(main())
