"""`tabx plot RUN_DIR ... --out curves.png`: learning curves of runs as a picture.

    tabx plot runs/quickstart_robust_plr_zone-* --out curves.png
    tabx plot runs/a runs/b --tag episode/win_rate --tag loss/value --out ab.png

One panel per tag (x: env steps), one line per run. Tags are TensorBoard scalar tags of the
runs' `events/` folders, with `*` as a wildcard (`eval/*/mean_win_rate`: every suite's mean).
Default tags: the training win rate, the zero-shot suites' mean win rates, and for UED runs
the buffer size and mean score.

A multi-seed run (`seeds:`; its events in `RUN_DIR/seed-<s>/`) draws as one line, the mean
over its seeds, in a band of one standard error of that mean (sample standard deviation over
the seeds / sqrt(seeds)), as the paper's figures show their seeds. At each step the mean and
the error are over the seeds that logged the tag there (a NaN, e.g. a win rate of a rollout
in which no episode ended, is not logged). `RUN_DIR/seed-<s>` plots that seed alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tabx.errors import UserError

Scalars = dict[str, list[tuple[int, float]]]  # tag -> [(step, value), ...] (read_scalars)

DEFAULT_TAGS = ("episode/win_rate", "eval/*/mean_win_rate", "buffer/size",
                "buffer/score_mean")



def matching(tags: list[str], pattern: str) -> list[str]:
    """Tags matching `pattern` (`*` matches any characters, `/` included)."""
    import fnmatch

    if "*" not in pattern:
        return [pattern] if pattern in tags else []
    return sorted(t for t in tags if fnmatch.fnmatchcase(t, pattern))


@dataclass(frozen=True)
class Curve:
    """One run's line in one panel: at each step, the mean over the run's seeds that logged
    the tag there, its standard error (0 where fewer than two did) and that seed count."""

    steps: np.ndarray
    mean: np.ndarray
    stderr: np.ndarray
    seeds: np.ndarray


def seed_folders(run: Path) -> list[Path]:
    """The `seed-<s>` event folders of a multi-seed run, by seed; [] for any other folder."""
    from ued.run_folder import folder_seed

    found = [p for p in run.iterdir() if p.is_dir() and folder_seed(p) is not None]
    return sorted(found, key=folder_seed)


def load_runs(run_dirs: list[str]) -> dict[str, list[Scalars]]:
    """Run folder name -> the scalars of each of its seeds (one for a single-seed run, or a
    multi-seed run's `RUN_DIR/seed-<s>` folder)."""
    from ued.run_folder import EVENTS_DIR, folder_seed
    from ued.tensorboard import read_scalars

    out = {}
    for run in run_dirs:
        path = Path(run)
        if (folder_seed(path) is not None and path.is_dir()
                and not (path / EVENTS_DIR).is_dir()):
            # one seed of a multi-seed run: its event files
            out[f"{path.parent.name}/{path.name}"] = [read_scalars(path)]
            continue
        folders = ([path / EVENTS_DIR] if (path / EVENTS_DIR).is_dir()
                   else seed_folders(path) if path.is_dir() else [])
        if not folders:
            raise UserError(f"{run}: not a run folder (no events/ folder), nor a multi-seed "
                            f"run (no seed-<s>/ folders)")
        out[path.name] = [read_scalars(folder) for folder in folders]
    if not any(any(seed) for seed in out.values()):
        raise UserError(f"{', '.join(map(str, run_dirs))}: no scalars in their event folders "
                        f"(no event files yet, or only empty or damaged ones)")
    return out


def curve(seeds: list[Scalars], tag: str) -> Curve | None:
    """The mean and standard error over `seeds` of `tag` at every step any of them logged it
    (a step logged twice by one seed, as after a resume, counts with its last value); None
    when none did."""
    per_seed = [dict(sorted(scalars.get(tag, []), key=lambda p: p[0])) for scalars in seeds]
    steps = np.array(sorted({step for points in per_seed for step in points}), np.int64)
    if not steps.size:
        return None
    values = np.array([[points.get(int(step), np.nan) for step in steps]
                       for points in per_seed], np.float64)
    present = np.isfinite(values)
    count = present.sum(0)
    mean = np.nansum(values, 0) / count
    sq = np.nansum(np.square(values - mean), 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        stderr = np.where(count > 1, np.sqrt(sq / np.maximum(count - 1, 1) / count), 0.0)
    return Curve(steps, mean, stderr, count)


def draw_curve(ax: Any, line: Curve, label: str) -> Any:
    """Draw `line` on matplotlib axes `ax`: the mean over seeds, with markers where it has few
    points (a one-point series is its marker alone: a line through one point draws nothing),
    in a band of one standard error where several seeds logged it (an error bar for a single
    point). Returns the line's artist."""
    few = len(line.steps) < 30
    (artist,) = ax.plot(line.steps, line.mean, label=label, marker="o" if few else None,
                        markersize=6 if len(line.steps) == 1 else 3)
    if np.any(line.seeds > 1):
        if len(line.steps) == 1:
            ax.errorbar(line.steps, line.mean, yerr=line.stderr, color=artist.get_color(),
                        capsize=4, linestyle="none")
        else:
            ax.fill_between(line.steps, line.mean - line.stderr, line.mean + line.stderr,
                            color=artist.get_color(), alpha=0.25, linewidth=0)
    return artist


def plot_runs(runs: dict[str, list[Scalars]], patterns: list[str], out: str
              ) -> dict[str, dict[str, Curve]]:
    """Draw one panel per matched tag, one line per run (a band of one standard error for a
    run of several seeds); returns what was drawn: tag -> run name -> Curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    all_tags = sorted({tag for seeds in runs.values() for scalars in seeds for tag in scalars})
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
    drawn: dict[str, dict[str, Curve]] = {}
    for ax, tag in zip(axes.flat, tags, strict=False):
        drawn[tag] = {}
        for name, seeds in runs.items():
            line = curve(seeds, tag)
            if line is None:
                continue
            drawn[tag][name] = line
            label = name if len(seeds) == 1 else f"{name} ({len(seeds)} seeds, mean \u00b1 s.e.)"
            draw_curve(ax, line, label)
        ax.set_title(tag, fontsize=10)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(tags):]:
        ax.axis("off")
    if len(runs) > 1 or any(len(seeds) > 1 for seeds in runs.values()):
        axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return drawn


def save_figure(fig: Any, out: str | Path, dpi: int = 120, **savefig: Any) -> Path:
    """Write a matplotlib figure as a PNG atomically (temp file, fsync, rename) and close it."""
    import io

    import matplotlib.pyplot as plt

    from tabx.files import atomic_write_bytes

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, **savefig)
    plt.close(fig)
    return atomic_write_bytes(out, buffer.getvalue())


__all__ = ["DEFAULT_TAGS", "Curve", "curve", "draw_curve", "load_runs", "matching",
           "plot_runs", "save_figure", "seed_folders"]
