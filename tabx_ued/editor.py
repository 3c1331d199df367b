"""`tabx editor [NAME] [--port P] [--no-browser]`: the scenario editor in the browser.

Starts the editor's server on 127.0.0.1, prints its address and opens it in a browser where one
can be shown. NAME (a scenario name, composition or file) is opened at start. Ctrl-C stops it.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
import threading
import webbrowser

DEFAULT_PORT = 8765


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Add `tabx editor`."""
    p = subparsers.add_parser("editor", help="the scenario editor (a local web page)",
                              description=__doc__)
    p.add_argument("name", nargs="?", help="scenario to open: a name (crossfire), a composition "
                   "(2F1M2Avs2S1K_2L2B2S) or a JSON file")
    p.add_argument("--port", type=int, default=None,
                   help=f"port on 127.0.0.1 (default {DEFAULT_PORT}, or a free one if that is "
                   "taken; 0 picks a free port)")
    p.add_argument("--no-browser", action="store_true", help="only print the address")
    p.add_argument("--no-warmup", action="store_true",
                   help="do not compile the default preview in the background at start")
    p.add_argument("--verbose", action="store_true", help="log every request")
    p.set_defaults(func=cmd_editor)


def can_open_browser() -> bool:
    """A graphical browser can be shown: macOS, Windows, or a Linux/BSD display. Console
    browsers (lynx, w3m) would take over the terminal, so they are not used."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _warm_up() -> None:
    """Compile the preview for small scenarios (4 v 4, up to 4 zones, 256 steps) so that the
    first preview of a typical scenario is quick."""
    try:
        from tabx.editor.preview import run_preview
        from tabx.scenarios import load_named

        run_preview(load_named("crossfire"), 256, "heuristic:medium", "heuristic:medium")
    except Exception as err:  # a warm-up must never stop the editor
        print(f"(preview warm-up failed: {err})", file=sys.stderr)


def cmd_editor(args: argparse.Namespace) -> int:
    """Serve the editor until Ctrl-C."""
    from tabx.editor.server import make_server
    from tabx.errors import UserError
    from tabx.scenarios import ScenarioError, load_named, user_scenario_dir

    initial = None
    if args.name:
        try:
            initial = load_named(args.name)
        except ScenarioError as err:
            raise UserError(str(err)) from None
    port = DEFAULT_PORT if args.port is None else args.port
    if not 0 <= port <= 65535:
        raise UserError(f"--port must be in [0, 65535], got {port}")
    try:
        server = make_server(port, initial, verbose=args.verbose)
    except OSError as err:
        if args.port is None and err.errno == errno.EADDRINUSE:
            server = make_server(0, initial, verbose=args.verbose)
        else:
            raise UserError(f"cannot listen on 127.0.0.1:{port}: {err.strerror or err} "
                            "(try --port 0 for a free port)") from None
    url = server.url
    print(f"TABX scenario editor at {url}", flush=True)
    print(f"saving into {user_scenario_dir()} (set TABX_SCENARIO_DIR to change); Ctrl-C stops",
          flush=True)
    if not args.no_warmup:
        threading.Thread(target=_warm_up, name="preview-warmup", daemon=True).start()
    if not args.no_browser and can_open_browser():
        try:
            webbrowser.open(url)
        except webbrowser.Error:
            pass
    try:
        server.serve_forever(poll_interval=0.25)
    except KeyboardInterrupt:
        print("\neditor stopped", flush=True)
    finally:
        server.server_close()
    return 0


__all__ = ["DEFAULT_PORT", "add_parser", "can_open_browser", "cmd_editor"]
