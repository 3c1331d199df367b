"""`tabx sweep report SWEEP_DIR`: a sweep's results as the paper tabulates them.

From the trials' run folders and records (`ued.sweep_folder`):

- per held-out suite, the zero-shot win rate (the suite's mean win rate at the run's last
  evaluation, `eval/<suite>/mean_win_rate`) of every cell of the sweep's axes: mean and 95 %
  interval (Student's t) over seeds. Seeds are the sweep's seed axis (`seed`) and the seeds of
  a multi-seed run (`seeds:`). A plain MARL trial has no suite: its cell is the training win
  rate at its last logged update (`episode/win_rate`), under the suite name `train`.
  With a line axis (`ued.method`, `method` or `algorithm`) its labels are the table's columns,
  as in the paper's tables; the rows are the other axes' cells.
- the training time of every trial (wall time over its sessions, from its record) and its
  mean per cell;
- one learning-curve figure per label of the figure axis (`env.scenario` or `scenario`): one
  panel per cell of the remaining axes, one line per label of the line axis, the mean over
  seeds in a band of one standard error (`ued.plot.curve`).

Written to SWEEP_DIR/report/ (or `out`): report.md, results.csv (one row per cell and suite),
trials.csv (one row per trial) and curves-<label>.png. An incomplete sweep is refused, naming
the trials that are not finished, unless `partial`.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from tabx.files import atomic_write_text
from ued.config import ConfigError
from ued.sweep_folder import SweepFolder

TRAIN_SUITE = "train"
REPORT_DIR = "report"
# Student's t, two-sided 95 %, by degrees of freedom (1-30); beyond: the normal 1.96.
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
       2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
       2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


def interval95(values: Sequence[float]) -> tuple[float, float]:
    """(mean, half-width of its 95 % interval) over `values`; half-width NaN for one value."""
    x = np.asarray([v for v in values if math.isfinite(v)], np.float64)
    if not x.size:
        return math.nan, math.nan
    if x.size == 1:
        return float(x[0]), math.nan
    t = T95[x.size - 2] if x.size - 1 <= len(T95) else 1.96
    return float(x.mean()), float(t * x.std(ddof=1) / math.sqrt(x.size))


@dataclass
class TrialResult:
    """What the report reads of one finished trial."""

    name: str
    labels: dict[str, str]
    seconds: float
    steps: int
    sessions: int
    finals: dict[str, list[float]]  # suite -> final win rate of each seed
    curves: list[dict[str, list[tuple[int, float]]]]  # each seed's scalars
    curve_tag: str


@dataclass
class Written:
    """The report's files."""

    markdown: Path
    results_csv: Path
    trials_csv: Path
    figures: list[Path] = field(default_factory=list)

    def files(self) -> list[Path]:
        return [self.markdown, self.results_csv, self.trials_csv, *self.figures]


def _trial_result(folder: SweepFolder, name: str, labels: dict[str, str]) -> TrialResult:
    from ued.plot import load_runs

    record = folder.record(name)
    (seeds,) = load_runs([str(folder.run_dir(name))]).values()
    finals: dict[str, list[float]] = {}
    suites = sorted({tag[len("eval/"):-len("/mean_win_rate")] for scalars in seeds
                     for tag in scalars
                     if tag.startswith("eval/") and tag.endswith("/mean_win_rate")})
    for suite in suites or [TRAIN_SUITE]:
        tag = f"eval/{suite}/mean_win_rate" if suites else "episode/win_rate"
        finals[suite] = [max(scalars[tag], key=lambda p: p[0])[1] if scalars.get(tag)
                         else math.nan for scalars in seeds]
    curve_tag = f"eval/{suites[0]}/mean_win_rate" if suites else "episode/win_rate"
    return TrialResult(name, labels, record.seconds, record.steps, record.sessions, finals,
                       seeds, curve_tag)


def not_finished(folder: SweepFolder) -> dict[str, str]:
    """Trials that are not finished: name -> their state (and error)."""
    from ued.run_folder import open_checkpoints, read_run_config

    out = {}
    for name in folder.trials():
        record = folder.record(name)
        state = record.state
        if state == "finished":
            run_dir = folder.run_dir(name)
            try:
                config = read_run_config(run_dir)
                with open_checkpoints(run_dir, config, create=False) as checkpoints:
                    latest = checkpoints.latest()
                if latest is None or latest < config.learner.num_updates:
                    state = "incomplete run folder"
            except Exception:  # noqa: BLE001 - a damaged run folder is not finished
                state = "damaged run folder"
        if state != "finished":
            out[name] = state + (f": {record.error}" if record.error else "")
    return out


def _cell(labels: dict[str, str], axes: Sequence[str]) -> tuple[str, ...]:
    return tuple(labels.get(a, "") for a in axes)


def _fmt(mean: float, half: float) -> str:
    if not math.isfinite(mean):
        return "-"
    return f"{mean:.2f}" if not math.isfinite(half) else f"{mean:.2f} ± {half:.2f}"


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _minutes(seconds: float) -> str:
    return "-" if not math.isfinite(seconds) else f"{seconds / 60:.1f}m"


def write_report(sweep_dir: str | Path, out: str | Path | None = None, partial: bool = False,
                 stream: TextIO | None = None) -> Written:
    """Write the report of the sweep in `sweep_dir` (see the module doc)."""
    folder = SweepFolder(sweep_dir)
    body = folder.read()
    trials = folder.trials()
    missing = not_finished(folder)
    if missing and not partial:
        listed = "; ".join(f"{n} ({s})" for n, s in list(missing.items())[:20])
        more = f" and {len(missing) - 20} more" if len(missing) > 20 else ""
        raise ConfigError(f"{folder.path}: {len(missing)} of {len(trials)} trials are not "
                          f"finished: {listed}{more}. Finish them with `tabx sweep SPEC "
                          f"--resume`, or report the others with --partial")
    axes: list[str] = list(body.get("axes", []))
    roles = body.get("report", {})
    seed_axis, line_axis, figure_axis = (roles.get("seed_axis"), roles.get("line_axis"),
                                         roles.get("figure_axis"))
    results = [_trial_result(folder, name, t.labels) for name, t in trials.items()
               if name not in missing]
    if not results:
        raise ConfigError(f"{folder.path}: no finished trial to report")
    cell_axes = [a for a in axes if a != seed_axis]
    row_axes = [a for a in cell_axes if a != line_axis]
    lines_ = (list(dict.fromkeys(r.labels.get(line_axis, "") for r in results))
              if line_axis else [])
    suites = list(dict.fromkeys(s for r in results for s in r.finals))

    # cell -> suite -> every seed's final win rate; cell -> training seconds of its trials
    finals: dict[tuple[str, ...], dict[str, list[float]]] = {}
    seconds: dict[tuple[str, ...], list[float]] = {}
    for r in results:
        cell = _cell(r.labels, cell_axes)
        for suite, values in r.finals.items():
            finals.setdefault(cell, {}).setdefault(suite, []).extend(values)
        seconds.setdefault(cell, []).append(r.seconds)
    cells = list(finals)

    out_dir = Path(out) if out is not None else folder.path / REPORT_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    md = [f"# Sweep {body.get('name', folder.path.name)}", "",
          f"{len(results)} of {len(trials)} trials"
          + (f" (missing: {', '.join(missing)})" if missing else "")
          + f"; axes: {', '.join(axes) or 'none'}"
          + (f"; seeds over `{seed_axis}`" if seed_axis else "") + ". Win rates: mean ± half "
          "the 95 % interval over seeds (Student's t), at the last evaluation of each run.", ""]

    # results.csv and the win-rate tables
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow([*cell_axes, "suite", "seeds", "mean", "ci95_low", "ci95_high", "values"])
    for cell in cells:
        for suite, values in finals[cell].items():
            mean, half = interval95(values)
            low, high = ((mean - half, mean + half) if math.isfinite(half) else ("", ""))
            writer.writerow([*cell, suite, sum(math.isfinite(v) for v in values),
                             _num(mean), _num(low), _num(high),
                             " ".join(_num(v) for v in values)])
    results_csv = out_dir / "results.csv"
    atomic_write_text(results_csv, buffer.getvalue())

    def table(values_of) -> str:
        if line_axis:
            rows: dict[tuple[str, ...], dict[str, str]] = {}
            for cell in cells:
                labels = dict(zip(cell_axes, cell, strict=True))
                row = _cell(labels, row_axes)
                text = values_of(cell)
                if text is not None:
                    rows.setdefault(row, {})[labels.get(line_axis, "")] = text
            first = row_axes or [""]  # no other axis: one row
            return _md_table([*first, *lines_],
                             [[*(row or ("all",)), *(cols.get(m, "-") for m in lines_)]
                              for row, cols in rows.items()])
        rows_ = [[*cell, v] for cell in cells if (v := values_of(cell)) is not None]
        return _md_table([*cell_axes, "value"], rows_)

    for suite in suites:
        md += [f"## Zero-shot win rate: {suite}" if suite != TRAIN_SUITE
               else "## Training win rate (last logged update)", ""]
        md += [table(lambda cell, suite=suite: _fmt(*interval95(finals[cell][suite]))
                     if suite in finals[cell] else None), ""]
    md += ["## Training time (mean wall time per trial)", ""]
    md += [table(lambda cell: _minutes(float(np.mean(seconds[cell])))), ""]

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["trial", *axes, "sessions", "env_steps", "seconds", "steps_per_s"])
    trial_rows = []
    for r in results:
        steps = r.steps * max(len(r.curves), 1)  # a multi-seed run plays each seed's steps
        rate = steps / r.seconds if r.seconds > 0 else math.nan
        writer.writerow([r.name, *_cell(r.labels, axes), r.sessions, steps,
                         _num(r.seconds), _num(rate)])
        trial_rows.append([r.name, str(r.sessions), f"{steps:,}", _minutes(r.seconds),
                           "-" if not math.isfinite(rate) else f"{rate:,.0f}"])
    trials_csv = out_dir / "trials.csv"
    atomic_write_text(trials_csv, buffer.getvalue())
    md += ["## Trials", "", _md_table(["trial", "sessions", "env steps (all seeds)", "time",
                                       "steps/s"],
                                      trial_rows), ""]

    figures = _figures(results, out_dir, seed_axis, line_axis, figure_axis, cell_axes)
    if figures:
        md += ["## Learning curves (mean ± s.e. over seeds)", ""]
        md += [f"![{p.stem}]({p.name})" for p in figures] + [""]
    markdown = out_dir / "report.md"
    atomic_write_text(markdown, "\n".join(md))
    return Written(markdown, results_csv, trials_csv, figures)


def _num(value: Any) -> str:
    return "" if not isinstance(value, int | float) or not math.isfinite(value) else f"{value:.4g}"


def _figures(results: list[TrialResult], out_dir: Path, seed_axis: str | None,
             line_axis: str | None, figure_axis: str | None, cell_axes: list[str]
             ) -> list[Path]:
    """One PNG per label of the figure axis: panels = cells of the other axes, lines = the
    line axis' labels, mean ± standard error over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ued.plot import curve, save_figure

    panel_axes = [a for a in cell_axes if a not in (line_axis, figure_axis)]
    by_figure: dict[str, list[TrialResult]] = {}
    for r in results:
        by_figure.setdefault(r.labels.get(figure_axis, "all") if figure_axis else "all",
                             []).append(r)
    written = []
    for label, members in by_figure.items():
        panels: dict[tuple[str, ...], dict[str, list[TrialResult]]] = {}
        for r in members:
            line = r.labels.get(line_axis, r.name) if line_axis else r.name
            panels.setdefault(_cell(r.labels, panel_axes), {}).setdefault(line, []).append(r)
        columns = min(2, len(panels))
        rows = math.ceil(len(panels) / columns)
        fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 3.4 * rows),
                                 squeeze=False)
        for ax, (panel, lines) in zip(axes.flat, panels.items(), strict=False):
            tags = set()
            for line, group in lines.items():
                seeds = [s for r in group for s in r.curves]
                tag = group[0].curve_tag
                tags.add(tag)
                drawn = curve(seeds, tag)
                if drawn is None:
                    continue
                (artist,) = ax.plot(drawn.steps, drawn.mean, label=f"{line} (n={len(seeds)})")
                if len(seeds) > 1:
                    ax.fill_between(drawn.steps, drawn.mean - drawn.stderr,
                                    drawn.mean + drawn.stderr, color=artist.get_color(),
                                    alpha=0.25, linewidth=0)
            title = ", ".join(f"{a}={v}" for a, v in zip(panel_axes, panel, strict=True))
            ax.set_title(f"{title}\n{', '.join(sorted(tags))}" if title
                         else ", ".join(sorted(tags)), fontsize=9)
            ax.set_xlabel("env steps")
            ax.set_ylabel("win rate")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        for ax in list(axes.flat)[len(panels):]:
            ax.axis("off")
        fig.suptitle(f"{figure_axis}={label}" if figure_axis else "learning curves",
                     fontsize=10)
        fig.tight_layout()
        safe = re.sub(r"[^A-Za-z0-9._+=-]+", "_", label)
        written.append(save_figure(fig, out_dir / f"curves-{safe}.png", dpi=100))
    return written


__all__ = ["REPORT_DIR", "TRAIN_SUITE", "TrialResult", "Written", "interval95",
           "not_finished", "write_report"]
