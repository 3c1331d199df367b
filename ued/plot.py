"""`tabx plot RUN_DIR ... --out curves.png`: learning curves of runs as a picture.

    tabx plot runs/quickstart_robust_plr_zone-* --out curves.png
    tabx plot runs/a runs/b --tag episode/win_rate --tag loss/value --out ab.png

One panel per tag (x: env steps), one line per run. Tags are TensorBoard scalar tags of the
runs' `events/` folders, with `*` as a wildcard (`eval/*/mean_win_rate`: every suite's mean).
Default tags: the training win rate, the zero-shot suites' mean win rates, and for UED runs
the buffer size and mean score.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from tabx.errors import UserError

DEFAULT_TAGS = ("episode/win_rate", "eval/*/mean_win_rate", "buffer/size",
                "buffer/score_mean")



def matching(tags: list[str], pattern: str) -> list[str]:
    """Tags matching `pattern` (`*` matches any characters, `/` included)."""
    import fnmatch

    if "*" not in pattern:
        return [pattern] if pattern in tags else []
    return sorted(t for t in tags if fnmatch.fnmatchcase(t, pattern))


def load_runs(run_dirs: list[str]) -> dict[str, dict[str, list[tuple[int, float]]]]:
    """Run folder name -> its scalars (tag -> [(step, value)])."""
    from ued.run_folder import EVENTS_DIR
    from ued.tensorboard import read_scalars

    out = {}
    for run in run_dirs:
        events = Path(run) / EVENTS_DIR
        if not events.is_dir():
            raise UserError(f"{run}: not a run folder (no events/ folder)")
        out[Path(run).name] = read_scalars(events)
    if not any(out.values()):
        raise UserError(f"{', '.join(map(str, run_dirs))}: no scalars in events/ (no event "
                        f"files yet, or only empty or damaged ones)")
    return out


def plot_runs(runs: dict[str, dict[str, list[tuple[int, float]]]], patterns: list[str],
              out: str) -> list[str]:
    """Draw one panel per matched tag; returns the tags drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    all_tags = sorted({tag for scalars in runs.values() for tag in scalars})
    tags: list[str] = []
    for pattern in patterns:
        for tag in matching(all_tags, pattern):
            if tag not in tags:
                tags.append(tag)
    if not tags:
        raise UserError(f"none of the tags {', '.join(patterns)} is in these runs (they have "
                        f"{', '.join(all_tags[:12])}{' ...' if len(all_tags) > 12 else ''})")
    columns = min(2, len(tags))
    rows = math.ceil(len(tags) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 3.2 * rows), squeeze=False)
    for ax, tag in zip(axes.flat, tags, strict=False):
        for name, scalars in runs.items():
            points = scalars.get(tag)
            if points:
                steps, values = zip(*sorted(points), strict=True)
                ax.plot(steps, values, label=name, marker="." if len(points) < 30 else None)
        ax.set_title(tag, fontsize=10)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(tags):]:
        ax.axis("off")
    if len(runs) > 1:
        axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return tags


def save_figure(fig: Any, out: str | Path, dpi: int = 120, **savefig: Any) -> Path:
    """Write a matplotlib figure as a PNG atomically (temp file, fsync, rename) and close it."""
    import io

    import matplotlib.pyplot as plt

    from tabx.files import atomic_write_bytes

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, **savefig)
    plt.close(fig)
    return atomic_write_bytes(out, buffer.getvalue())


def cmd_plot(args: argparse.Namespace) -> int:
    if not args.out.lower().endswith(".png"):
        raise UserError(f"--out must name a .png file, got {args.out!r}")
    tags = plot_runs(load_runs(args.runs), args.tag or list(DEFAULT_TAGS), args.out)
    print(f"wrote {len(tags)} panels ({', '.join(tags)}) to {args.out}")
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("plot", help="learning curves of run folders as a PNG")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders (tabx train)")
    p.add_argument("--tag", action="append", metavar="TAG",
                   help="a scalar tag to plot (repeatable; * matches, e.g. 'eval/*/mean_win_rate'"
                        f"); default: {', '.join(DEFAULT_TAGS)}")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.set_defaults(func=cmd_plot)


__all__ = ["DEFAULT_TAGS", "add_parser", "load_runs", "matching", "plot_runs",
           "save_figure"]
