"""`tabx sweep report SWEEP_DIR`: a sweep's results in the paper's layout.

From the trials' run folders and records (`workers.sweep.folder`), with the sweep's report axes
(`workers.sweep.spec.ReportAxes`): the seed axis (averaged over), the line axis (`ued.method`,
`algorithm`: the tables' columns) and the figure axis (`teams`, `env.scenario`, `challenge`:
the training configurations, the tables' rows). The other axes (the free parameter `param`:
unit, zone, health, ...) make groups: one table each.

- **Zero-shot win rate**, one table per group: training configurations as rows plus a final
  `mean` row, methods as columns. A trial's value is its held-out suites' mean win rate at the
  last evaluation (`eval/<suite>/mean_win_rate`: the mean over the suite's scenarios; the mean
  over its held-out suites when it has several); tier suites (`tiers-*`) are not held-out
  suites. A cell is the mean over seeds and the standard error of that mean (sample standard
  deviation / sqrt(seeds)), or with `interval="t95"` half the 95 % Student-t interval; means
  and interval ends are clipped to [0, 1]. The `mean` row pools every (configuration, seed)
  value of its column. Seeds are the seed axis and the seeds of a multi-seed run (`seeds:`).
  A plain MARL trial has no suite: its value is the training win rate at its last logged
  update (`episode/win_rate`), in a table named so.
- **Win rate against the heuristic tiers**: per group and tier (random .. expert, then the
  mean over tiers), per method, the last evaluation's win rate against that tier
  (`eval/tiers-<teams>/<scenario>@heuristic:<tier>/win_rate`), pooled over the training
  configurations and seeds, as the paper's appendix "UED Experiments Across Heuristic Policy
  Difficulty Levels" averages over evaluation scenarios and seeds.
- **Training time**, as the paper's table "Training Time for UED Algorithms": rows are
  training configuration and group, columns the methods; a cell is the mean wall time per
  trial (its sessions added up, compilation included) and the mean env steps/s.
- **Learning curves**, one figure per training configuration: one panel per group, one line
  per method, the zero-shot win rate (the held-out suites', or the training win rate) at every
  evaluation, mean over seeds in a band of one standard error (`ued.plot.draw_curve`).

Written to SWEEP_DIR/report/ (or `out`): report.md, results.csv (every table's cells and the
per-configuration values behind the pooled ones, each with every seed's value), trials.csv
(one row per trial) and curves-<label>.png. An incomplete sweep is refused, naming the trials
that are not finished, unless `partial`.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from tabx.files import atomic_write_text
from tabx.params import TIER_ORDER
from ued.config import ConfigError
from ued.suites import TIER_SUITE_PREFIX
from workers.sweep.folder import SweepFolder

REPORT_DIR = "report"
MEAN_ROW = "mean"
INTERVALS = ("se", "t95")  # standard error of the mean; half the 95 % Student-t interval
ZERO_SHOT = "zero-shot"  # results.csv `table` values
TRAIN = "train"
TIERS = "tiers"
CURVE_TAG = "report/win_rate"  # the series a learning curve draws (added to each seed's scalars)
HEURISTIC_PREFIX = "heuristic:"
# Student's t, two-sided 95 %, by degrees of freedom (1-30); beyond: the normal 1.96.
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
       2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
       2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


@dataclass(frozen=True)
class Stat:
    """Mean over seeds with its interval (`low`, `high`: clipped to [0, 1]; NaN for fewer
    than two values) and standard error."""

    n: int
    mean: float
    se: float
    low: float
    high: float


def seed_stat(values: Sequence[float], interval: str = "se") -> Stat:
    """The mean of the finite `values` and its interval: mean ± the standard error
    (`interval="se"`, std(ddof=1) / sqrt(n)) or ± half the 95 % Student-t interval ("t95"),
    mean and ends clipped to [0, 1] (the values are win rates)."""
    if interval not in INTERVALS:
        raise ConfigError(f"interval: expected one of {', '.join(INTERVALS)}, not {interval!r}")
    x = np.asarray([v for v in values if math.isfinite(v)], np.float64)
    if not x.size:
        return Stat(0, math.nan, math.nan, math.nan, math.nan)
    mean = float(np.clip(x.mean(), 0.0, 1.0))
    if x.size == 1:
        return Stat(1, mean, math.nan, math.nan, math.nan)
    se = float(x.std(ddof=1) / math.sqrt(x.size))
    half = se * (1.0 if interval == "se" else T95[x.size - 2] if x.size - 1 <= len(T95)
                 else 1.96)
    return Stat(int(x.size), mean, se, float(np.clip(x.mean() - half, 0.0, 1.0)),
                float(np.clip(x.mean() + half, 0.0, 1.0)))


@dataclass
class TrialResult:
    """What the report reads of one finished trial (lists: one value per seed)."""

    name: str
    labels: dict[str, str]
    seconds: float
    steps: int
    sessions: int
    kind: str  # ZERO_SHOT (held-out suites) or TRAIN (no suite: the training win rate)
    suites: tuple[str, ...]  # the held-out suites (none for TRAIN)
    finals: list[float]  # the zero-shot (or training) win rate at the last evaluation
    tier_suites: tuple[str, ...]
    tiers: dict[str, list[float]]  # opponent (tier, then MEAN_ROW) -> win rate, last evaluation
    curves: list[dict[str, list[tuple[int, float]]]]  # each seed's scalars, with CURVE_TAG


@dataclass
class Written:
    """The report's files."""

    markdown: Path
    results_csv: Path
    trials_csv: Path
    figures: list[Path] = field(default_factory=list)

    def files(self) -> list[Path]:
        return [self.markdown, self.results_csv, self.trials_csv, *self.figures]


def _last(points: list[tuple[int, float]] | None) -> float:
    return max(points, key=lambda p: p[0])[1] if points else math.nan


def _mean_series(series: list[list[tuple[int, float]]]) -> list[tuple[int, float]]:
    """At every step any of `series` logged: the mean of those that logged there."""
    by_step: dict[int, list[float]] = {}
    for points in series:
        for step, value in dict(sorted(points)).items():
            by_step.setdefault(step, []).append(value)
    return [(step, float(np.mean(v))) for step, v in sorted(by_step.items())]


def _opponent_of(tag: str, prefix: str) -> str | None:
    """The opponent of a per-entry tag `<prefix><scenario>@<opponent>/win_rate` ("novice" for
    heuristic:novice), else None."""
    if not (tag.startswith(prefix) and tag.endswith("/win_rate")):
        return None
    label = tag[len(prefix):-len("/win_rate")]
    if "@" not in label or "/" in label:
        return None
    opponent = label.rsplit("@", 1)[1]
    return opponent[len(HEURISTIC_PREFIX):] if opponent.startswith(HEURISTIC_PREFIX) else opponent


def tier_order(opponent: str) -> tuple[int, str]:
    return (TIER_ORDER.index(opponent) if opponent in TIER_ORDER else len(TIER_ORDER), opponent)


def trial_result(folder: SweepFolder, name: str, labels: dict[str, str]) -> TrialResult:
    """Read one trial: its record and its run folder's scalars (every seed's)."""
    from ued.plot import load_runs

    record = folder.record(name)
    (seeds,) = load_runs([str(folder.run_dir(name))]).values()
    evaluated = sorted({tag[len("eval/"):-len("/mean_win_rate")] for scalars in seeds
                        for tag in scalars
                        if tag.startswith("eval/") and tag.endswith("/mean_win_rate")})
    suites = tuple(s for s in evaluated if not s.startswith(TIER_SUITE_PREFIX))
    tier_suites = tuple(s for s in evaluated if s.startswith(TIER_SUITE_PREFIX))
    curves = []
    for scalars in seeds:
        tags = [f"eval/{s}/mean_win_rate" for s in suites] or ["episode/win_rate"]
        curves.append({**scalars, CURVE_TAG: _mean_series([scalars.get(t, []) for t in tags])})
    finals = []
    for scalars in seeds:
        last = [_last(scalars.get(f"eval/{s}/mean_win_rate")) for s in suites] if suites \
            else [_last(scalars.get("episode/win_rate"))]
        finite = [v for v in last if math.isfinite(v)]
        finals.append(float(np.mean(finite)) if finite else math.nan)
    tiers: dict[str, list[float]] = {}
    if tier_suites:
        per_seed = []
        for scalars in seeds:
            by_opponent: dict[str, list[float]] = {}
            for suite in tier_suites:
                prefix = f"eval/{suite}/"
                for tag, points in scalars.items():
                    opponent = _opponent_of(tag, prefix)
                    if opponent is not None:
                        by_opponent.setdefault(opponent, []).append(_last(points))
            means = [_last(scalars.get(f"eval/{s}/mean_win_rate")) for s in tier_suites]
            by_opponent[MEAN_ROW] = means
            per_seed.append(by_opponent)
        opponents = sorted({o for d in per_seed for o in d if o != MEAN_ROW}, key=tier_order)
        for opponent in [*opponents, MEAN_ROW]:
            tiers[opponent] = []
            for by_opponent in per_seed:
                finite = [v for v in by_opponent.get(opponent, []) if math.isfinite(v)]
                tiers[opponent].append(float(np.mean(finite)) if finite else math.nan)
    return TrialResult(name, labels, record.seconds, record.steps, record.sessions,
                       ZERO_SHOT if suites else TRAIN, suites, finals, tier_suites, tiers,
                       curves)


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


def format_stat(stat: Stat) -> str:
    """`0.52 ± 0.08`; `0.97 +0.03 −0.05` where clipping made the interval asymmetric; the
    mean alone for one seed; `-` for none."""
    if not stat.n:
        return "-"
    if not math.isfinite(stat.low):
        return f"{stat.mean:.2f}"
    up, down = stat.high - stat.mean, stat.mean - stat.low
    if f"{up:.2f}" == f"{down:.2f}":
        return f"{stat.mean:.2f} ± {up:.2f}"
    return f"{stat.mean:.2f} +{up:.2f} −{down:.2f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _minutes(seconds: float) -> str:
    return "-" if not math.isfinite(seconds) else f"{seconds / 60:.1f}m"


def _num(value: object) -> str:
    return "" if not isinstance(value, int | float) or not math.isfinite(value) else f"{value:.4g}"


def _label(r: TrialResult, axis: str | None, default: str = "all") -> str:
    return r.labels.get(axis, default) if axis else default


class _Layout:
    """Where each trial goes in the tables: its group (the axes other than the seed, line and
    figure axes), its row (figure axis label) and its column (line axis label)."""

    def __init__(self, results: list[TrialResult], axes: list[str], seed_axis: str | None,
                 line_axis: str | None, figure_axis: str | None):
        self.line_axis, self.figure_axis = line_axis, figure_axis
        self.group_axes = [a for a in axes if a not in (seed_axis, line_axis, figure_axis)]
        self.columns = list(dict.fromkeys(_label(r, line_axis) for r in results))
        self.rows = list(dict.fromkeys(_label(r, figure_axis) for r in results))
        self.groups = list(dict.fromkeys(self.group(r) for r in results))

    def group(self, r: TrialResult) -> tuple[str, ...]:
        return tuple(r.labels.get(a, "") for a in self.group_axes)

    def column(self, r: TrialResult) -> str:
        return _label(r, self.line_axis)

    def row(self, r: TrialResult) -> str:
        return _label(r, self.figure_axis)

    def group_title(self, group: tuple[str, ...]) -> str:
        return ", ".join(f"{a} = {v}" for a, v in zip(self.group_axes, group, strict=True))


def _collect(results: list[TrialResult], key: Callable[[TrialResult], tuple | None],
             values: Callable[[TrialResult], list[float]]) -> dict[tuple, list[float]]:
    out: dict[tuple, list[float]] = {}
    for r in results:
        k = key(r)
        if k is not None:
            out.setdefault(k, []).extend(values(r))
    return out


def write_report(sweep_dir: str | Path, out: str | Path | None = None, partial: bool = False,
                 stream: TextIO | None = None, interval: str = "se") -> Written:
    """Write the report of the sweep in `sweep_dir` (see the module doc); `interval`: "se"
    (mean ± standard error over seeds) or "t95" (± half the 95 % Student-t interval)."""
    seed_stat([], interval)  # a bad interval before anything is read
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
    results = [trial_result(folder, name, t.labels) for name, t in trials.items()
               if name not in missing]
    if not results:
        raise ConfigError(f"{folder.path}: no finished trial to report")
    layout = _Layout(results, axes, seed_axis, line_axis, figure_axis)
    cell_axes = [a for a in axes if a != seed_axis]

    def stat(values: list[float]) -> Stat:
        return seed_stat(values, interval)

    spread = ("the standard error of the mean (std(ddof=1) / sqrt(seeds))" if interval == "se"
              else "half the 95 % Student-t interval")
    out_dir = Path(out) if out is not None else folder.path / REPORT_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    md = [f"# Sweep {body.get('name', folder.path.name)}", "",
          f"{len(results)} of {len(trials)} trials"
          + (f" ({len(missing)} not finished: {', '.join(list(missing)[:5])}"
             + (f" and {len(missing) - 5} more" if len(missing) > 5 else "") + ")"
             if missing else "")
          + f"; axes: {', '.join(axes) or 'none'}"
          + (f"; seeds over `{seed_axis}`" if seed_axis else "")
          + f". Win rates at the last evaluation of each run: mean over seeds ± {spread}, "
          "clipped to [0, 1]; `mean` rows pool every (configuration, seed) value.", ""]

    # results.csv: one row per table cell (pooled rows have the figure axis `mean`) and per
    # (trial cell, table entry), each with every seed's value
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow([*cell_axes, "table", "suite", "opponent", "seeds", "mean", "se",
                     "interval", "low", "high", "values"])

    def csv_row(labels: dict[str, str], table: str, suite: str, opponent: str,
                values: list[float]) -> None:
        s = stat(values)
        writer.writerow([*(labels.get(a, "") for a in cell_axes), table, suite, opponent, s.n,
                         _num(s.mean), _num(s.se), interval, _num(s.low), _num(s.high),
                         " ".join(_num(v) if math.isfinite(v) else "nan" for v in values)])

    for kind in (ZERO_SHOT, TRAIN):
        members = [r for r in results if r.kind == kind]
        for group in [g for g in layout.groups if any(layout.group(r) == g for r in members)]:
            in_group = [r for r in members if layout.group(r) == group]
            cells = _collect(in_group, lambda r: (layout.row(r), layout.column(r)),
                             lambda r: r.finals)
            pooled = _collect(in_group, lambda r: (layout.column(r),), lambda r: r.finals)
            rows = [row for row in layout.rows if any((row, c) in cells for c in layout.columns)]
            table_rows = [[row, *(format_stat(stat(cells[(row, c)])) if (row, c) in cells else "-"
                                  for c in layout.columns)] for row in rows]
            if figure_axis:
                table_rows.append([MEAN_ROW, *(format_stat(stat(pooled[(c,)])) if (c,) in pooled
                                               else "-" for c in layout.columns)])
            title = ("Zero-shot win rate (held-out suites, last evaluation)" if kind == ZERO_SHOT
                     else "Training win rate (last logged update)")
            where = layout.group_title(group)
            md += [f"## {title}" + (f": {where}" if where else ""), ""]
            md += [markdown_table([figure_axis or "", *layout.columns], table_rows), ""]
            for r_row, column in cells:
                r = next(r for r in in_group if layout.row(r) == r_row
                         and layout.column(r) == column)
                csv_row(r.labels, kind, "+".join(r.suites), "", cells[(r_row, column)])
            for (column,), values in pooled.items():
                if figure_axis:
                    labels = dict(zip(layout.group_axes, group, strict=True))
                    labels[figure_axis] = MEAN_ROW
                    if line_axis:
                        labels[line_axis] = column
                    csv_row(labels, kind, "", "", values)

    with_tiers = [r for r in results if r.tiers]
    if with_tiers:
        opponents = sorted({o for r in with_tiers for o in r.tiers if o != MEAN_ROW},
                           key=tier_order) + [MEAN_ROW]
        table_rows = []
        for group in layout.groups:
            in_group = [r for r in with_tiers if layout.group(r) == group]
            for opponent in opponents:
                pooled = _collect(in_group, lambda r, o=opponent: (layout.column(r),)
                                  if o in r.tiers else None,
                                  lambda r, o=opponent: r.tiers[o])
                if not pooled:
                    continue
                table_rows.append([*group, opponent, *(format_stat(stat(pooled[(c,)]))
                                                       if (c,) in pooled else "-"
                                                       for c in layout.columns)])
                for (column,), values in pooled.items():
                    labels = dict(zip(layout.group_axes, group, strict=True))
                    if figure_axis:
                        labels[figure_axis] = MEAN_ROW
                    if line_axis:
                        labels[line_axis] = column
                    csv_row(labels, TIERS, "", opponent, values)
            per_cell: dict[tuple, tuple[TrialResult, list[float]]] = {}
            for r in in_group:  # one row per cell and opponent, over the seed axis' trials
                for opponent, values in r.tiers.items():
                    key = (layout.row(r), layout.column(r), opponent)
                    per_cell.setdefault(key, (r, []))[1].extend(values)
            for (_, _, opponent), (r, values) in per_cell.items():
                csv_row(r.labels, TIERS, "+".join(r.tier_suites), opponent, values)
        md += ["## Win rate against the heuristic tiers (last evaluation, pooled over "
               "training configurations and seeds)", "",
               "The tier suites (`tiers-*`: each training configuration's scenario against "
               "every heuristic tier, random the noisiest, expert the least noisy); `mean`: the "
               "mean over tiers.", ""]
        md += [markdown_table([*layout.group_axes, "opponent", *layout.columns], table_rows), ""]

    atomic_write_text(out_dir / "results.csv", buffer.getvalue())

    # training time, as the paper's "Training Time for UED Algorithms"
    time_rows: dict[tuple[str, ...], dict[str, list[TrialResult]]] = {}
    for r in results:
        key = ((layout.row(r),) if figure_axis else ()) + layout.group(r)
        time_rows.setdefault(key, {}).setdefault(layout.column(r), []).append(r)

    def time_cell(group: list[TrialResult] | None) -> str:
        if not group:
            return "-"
        minutes = _minutes(float(np.mean([r.seconds for r in group])))
        rates = [_rate(r) for r in group if math.isfinite(_rate(r))]
        return minutes + (f" ({np.mean(rates):,.0f}/s)" if rates else "")

    def time_order(key: tuple[str, ...]) -> tuple[int, int]:
        # by training configuration, then group, as the paper's table
        row, group = (key[0], key[1:]) if figure_axis else ("all", key)
        return layout.rows.index(row), layout.groups.index(group)

    md += ["## Training time (mean wall time per trial, mean env steps/s)", ""]
    header = ([figure_axis] if figure_axis else []) + layout.group_axes
    md += [markdown_table([*(header or [""]), *layout.columns], [[*(key or ("all",)),
                                       *(time_cell(cols.get(c)) for c in layout.columns)]
                                      for key, cols in sorted(time_rows.items(),
                                                              key=lambda kv: time_order(kv[0]))]),
           ""]

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["trial", *axes, "sessions", "env_steps", "seconds", "steps_per_s"])
    trial_rows = []
    for r in results:
        steps = r.steps * max(len(r.curves), 1)  # a multi-seed run plays each seed's steps
        rate = _rate(r)
        writer.writerow([r.name, *(r.labels.get(a, "") for a in axes), r.sessions, steps,
                         _num(r.seconds), _num(rate)])
        trial_rows.append([r.name, str(r.sessions), f"{steps:,}", _minutes(r.seconds),
                           "-" if not math.isfinite(rate) else f"{rate:,.0f}"])
    trials_csv = out_dir / "trials.csv"
    atomic_write_text(trials_csv, buffer.getvalue())
    md += ["## Trials", "", markdown_table(["trial", "sessions", "env steps (all seeds)", "time",
                                       "steps/s"], trial_rows), ""]

    figures = _figures(results, out_dir, layout)
    if figures:
        md += ["## Learning curves (every evaluation; mean ± s.e. over seeds)", ""]
        md += [f"![{p.stem}]({p.name})" for p in figures] + [""]
    markdown = out_dir / "report.md"
    atomic_write_text(markdown, "\n".join(md))
    return Written(markdown, out_dir / "results.csv", trials_csv, figures)


def _rate(r: TrialResult) -> float:
    """Env steps per second of wall time of a trial (every seed's steps of a multi-seed run)."""
    steps = r.steps * max(len(r.curves), 1)
    return steps / r.seconds if r.seconds > 0 else math.nan


def _figures(results: list[TrialResult], out_dir: Path, layout: _Layout) -> list[Path]:
    """One PNG per training configuration (figure axis label): one panel per group, one line
    per column label, the zero-shot (or training) win rate at every evaluation, mean ±
    standard error over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ued.plot import curve, draw_curve, save_figure

    by_figure: dict[str, list[TrialResult]] = {}
    for r in results:
        by_figure.setdefault(layout.row(r), []).append(r)
    written = []
    for label, members in by_figure.items():
        panels: dict[tuple[str, ...], dict[str, list[TrialResult]]] = {}
        for r in members:
            line = layout.column(r) if layout.line_axis else r.name
            panels.setdefault(layout.group(r), {}).setdefault(line, []).append(r)
        columns = min(2, len(panels))
        rows = math.ceil(len(panels) / columns)
        fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 3.4 * rows),
                                 squeeze=False)
        for ax, (panel, lines) in zip(axes.flat, panels.items(), strict=False):
            kinds = set()
            for line, group in lines.items():
                seeds = [s for r in group for s in r.curves]
                kinds.add("zero-shot win rate (" + "+".join(group[0].suites) + ")"
                          if group[0].kind == ZERO_SHOT else "training win rate")
                drawn = curve(seeds, CURVE_TAG)
                if drawn is not None:
                    draw_curve(ax, drawn, f"{line} (n={len(seeds)})")
            title = layout.group_title(panel)
            ax.set_title(f"{title}\n{', '.join(sorted(kinds))}" if title
                         else ", ".join(sorted(kinds)), fontsize=9)
            ax.set_xlabel("env steps")
            ax.set_ylabel("win rate")
            ax.set_ylim(-0.02, 1.02)  # win rates, comparable across panels
            ax.set_xlim(left=0)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        for ax in list(axes.flat)[len(panels):]:
            ax.axis("off")
        fig.suptitle(f"{layout.figure_axis}={label}" if layout.figure_axis
                     else "learning curves", fontsize=10)
        fig.tight_layout()
        safe = re.sub(r"[^A-Za-z0-9._+=-]+", "_", label)
        written.append(save_figure(fig, out_dir / f"curves-{safe}.png", dpi=100))
    return written


__all__ = ["HEURISTIC_PREFIX", "INTERVALS", "MEAN_ROW", "REPORT_DIR", "Stat", "TrialResult",
           "Written", "format_stat", "markdown_table", "not_finished", "seed_stat", "tier_order",
           "trial_result", "write_report"]
