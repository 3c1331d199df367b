"""Headless Chromium for the editor: the launch helper of the end-to-end test, and the script
that takes the documentation's screenshot.

    python tools/editor_screenshot.py docs/img/editor.png [--scenario superking]

Uses Debian's Chromium (`/usr/bin/chromium`, `apt-get install chromium`) driven by the
`playwright` Python package; it never downloads a browser. The flags keep Chromium off the
network (this machine has none) and out of any sandbox it cannot create as root.
"""

from __future__ import annotations

import argparse
import io
import os
import threading
from pathlib import Path
from typing import Any

CHROMIUM = os.environ.get("TABX_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--disable-quic"]
VIEWPORT = {"width": 1400, "height": 860}

__all__ = ["CHROMIUM", "CHROMIUM_FLAGS", "chromium_missing", "launch_chromium", "start_server",
           "take_docs_screenshot"]


def chromium_missing() -> str | None:
    """Why the browser tests cannot run here, or None when they can."""
    if not (Path(CHROMIUM).is_file() and os.access(CHROMIUM, os.X_OK)):
        return f"no Chromium at {CHROMIUM} (apt-get install -y chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install -e '.[dev]')"
    return None


def launch_chromium(playwright: Any) -> Any:
    """A headless Chromium browser from `sync_playwright()`, with the flags above."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS,
                                      headless=True)


def start_server(initial: Any = None):
    """(server, thread): an editor server on a free port, serving in a daemon thread."""
    from tabx.editor.server import make_server

    server = make_server(0, initial)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1},
                              daemon=True)
    thread.start()
    return server, thread


def save_png_small(png: bytes, path: str | os.PathLike, max_bytes: int = 300_000) -> Path:
    """Write a screenshot as a palette PNG (a UI has few colours), atomically."""
    from PIL import Image

    from tabx.files import atomic_write_bytes

    image = Image.open(io.BytesIO(png)).convert("RGB")
    for colours in (256, 128, 64):
        out = io.BytesIO()
        image.quantize(colours, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            out, format="PNG", optimize=True)
        if out.tell() <= max_bytes:
            break
    return atomic_write_bytes(path, out.getvalue())


def take_docs_screenshot(path: str | os.PathLike, scenario: str = "superking") -> Path:
    """Open the editor on a bundled scenario, select a unit, hover another (field of view),
    and save the page as a PNG."""
    from playwright.sync_api import sync_playwright

    from tabx.scenarios import load_named

    server, _ = start_server(load_named(scenario))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport=VIEWPORT, bypass_csp=True)  # CSP forbids eval
            page.goto(server.url)
            page.wait_for_function("window.editorDebug && window.editorDebug.ready")
            units = page.evaluate("editorDebug.scenario().units")
            chosen = max(range(len(units)), key=lambda i: units[i]["unit"] == "mammoth")
            page.evaluate(f"editorDebug.select('unit', {chosen})")
            hover = next((i for i, u in enumerate(units) if u["team"] == "enemy"), 0)
            x, y = units[hover]["position"]
            pt = page.evaluate(f"editorDebug.worldToClient({x}, {y})")
            page.mouse.move(pt["x"], pt["y"])
            page.wait_for_timeout(400)  # the debounced validation
            out = save_png_small(page.screenshot(), path)
            browser.close()
    finally:
        server.shutdown()
        server.server_close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output", help="PNG file to write")
    parser.add_argument("--scenario", default="superking", help="scenario to show")
    args = parser.parse_args(argv)
    reason = chromium_missing()
    if reason:
        parser.error(reason)
    out = take_docs_screenshot(args.output, args.scenario)
    print(f"wrote {out} ({out.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
