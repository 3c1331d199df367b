"""A finished sweep evaluated again under another episode limit (`tabx sweep evaluate SWEEP_DIR
--max-steps 512`): every finished trial's final policy, each seed's, plays its own evaluation
suites (`ued.eval_suites`; a run without any, such as a plain MARL run, its training scenarios
against its training opponent) again, with episodes of `max_steps` steps, and the results are
tabulated as the report tabulates the training-time evaluations (mean ± the standard error over
seeds, held-out suites and tier suites apart).

Why: a study trained on short episodes (128 steps, decided by the health ratio at the limit)
is not the paper's protocol (512 steps, most battles decided by an elimination), and its win
rates say little about the paper's until its policies are played under the paper's limit.
Observations carry no clock, so a policy plays episodes of any length unchanged.

Each (trial, seed, suite) played is kept in OUT/evaluate-<max_steps>.csv as soon as it is
played (written atomically), so a stopped evaluation continues where it stopped; the tables go
to OUT/evaluate-<max_steps>.md.
"""

from __future__ import annotations

import csv
import io
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

import jax

from tabx import constants as C
from tabx.files import atomic_write_text
from ued.config import TrainConfig
from ued.errors import ConfigError
from ued.run_folder import TrainedPolicy, load_policy, read_run_config, seed_dir
from ued.suites import TIER_SUITE_PREFIX, EvalSuite, load_suite, suite_from_dict
from workers.progress import format_duration
from workers.roles.evaluator import Evaluator
from workers.sweep.folder import SweepFolder
from workers.sweep.report import (
    HEURISTIC_PREFIX,
    MEAN_ROW,
    REPORT_DIR,
    format_stat,
    markdown_table,
    not_finished,
    seed_stat,
    tier_order,
)

TRAINING_SUITE = "training"  # the suite of a run without evaluation suites
COLUMNS = ("trial", "seed", "suite", "scenario", "opponent", "episodes", "win_rate",
           "mean_length")


def _policies(run_dir: Path, max_steps: int) -> Iterator[tuple[int, TrainedPolicy]]:
    """(seed, policy at its newest checkpoint, playing `max_steps`-step episodes) for each
    seed of a run folder."""
    config = read_run_config(run_dir)
    if config.seeds:
        for seed in config.seeds:
            yield seed, load_policy(seed_dir(run_dir, seed)).with_episode_limit(max_steps)
    else:
        yield config.seed, load_policy(run_dir).with_episode_limit(max_steps)


def _suites(config: TrainConfig) -> list[EvalSuite]:
    """The run's evaluation suites; for a run without any (a plain MARL run, which the report
    tables by its training win rate), its training scenarios against its training opponent."""
    if config.ued.eval_suites:
        return [load_suite(name) for name in config.ued.eval_suites]
    return [suite_from_dict({"name": TRAINING_SUITE, "team": config.env.team,
                             "opponent": config.env.opponent,
                             "scenarios": list(config.env.scenario),
                             "description": "the run's training scenarios and opponent"},
                            source="the run's env section")]


def _read_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != COLUMNS:
            raise ConfigError(f"{path}: not an evaluation table (expected the columns "
                              f"{', '.join(COLUMNS)}); move it away or give another --out")
        return list(reader)


def _write_rows(path: Path, rows: list[dict[str, str]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())


def evaluate_sweep(sweep_dir: str | Path, max_steps: int, *, episodes: int | None = None,
                   seed: int = 0, out: str | Path | None = None,
                   stream: TextIO | None = None) -> Path:
    """Play every finished trial of the sweep in `sweep_dir` again with episodes of `max_steps`
    steps (see the module doc); `episodes` per suite entry (default: the suite's). Returns the
    Markdown file written."""
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) \
            or not 1 <= max_steps <= C.MAX_STEPS:
        raise ConfigError(f"--max-steps: expected an integer in [1, {C.MAX_STEPS}] (steps per "
                          f"episode), got {max_steps!r}")
    folder = SweepFolder(sweep_dir)
    body = folder.read()
    trials = folder.trials()
    missing = not_finished(folder)
    done = [name for name in trials if name not in missing]
    if not done:
        raise ConfigError(f"{folder.path}: no finished trial to evaluate")
    out_dir = Path(out) if out is not None else folder.path / REPORT_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / f"evaluate-{max_steps}.csv"
    rows = _read_rows(csv_path)
    played = {(r["trial"], r["seed"], r["suite"]) for r in rows}
    key = jax.random.key(seed)
    todo = [(name, s, p, suite) for name in done
            for s, p in _policies(folder.run_dir(name), max_steps)
            for suite in _suites(p.config)
            if (name, str(s), suite.name) not in played]
    started = time.monotonic()
    for index, (name, policy_seed, policy, suite) in enumerate(todo):
        evaluator = Evaluator(policy.learner, suite, episodes=episodes,
                              profile=policy.config.env.profile)
        result = evaluator.evaluate(policy.params, key)
        rows += [{"trial": name, "seed": str(policy_seed), "suite": suite.name,
                  "scenario": e.scenario, "opponent": e.opponent, "episodes": str(e.episodes),
                  "win_rate": repr(float(e.win_rate)), "mean_length": repr(float(e.mean_length))}
                 for e in result.entries]
        _write_rows(csv_path, rows)
        if stream is not None:
            elapsed = time.monotonic() - started
            left = elapsed / (index + 1) * (len(todo) - index - 1)
            print(f"[{index + 1}/{len(todo)}] {name} seed {policy_seed} {suite.name}: mean win "
                  f"rate {result.mean_win_rate:.3f} ({max_steps}-step episodes; "
                  f"ETA {format_duration(left)})", file=stream, flush=True)
    markdown = out_dir / f"evaluate-{max_steps}.md"
    atomic_write_text(markdown, _tables(body, trials, rows, max_steps, len(done), missing))
    return markdown


def _tables(body: dict, trials: dict, rows: list[dict[str, str]], max_steps: int,
            finished: int, missing: dict[str, str]) -> str:
    """The held-out table (each seed's mean over its held-out suites' entries) and the tier
    table (each opponent's win rate, and their mean), cells over seeds."""
    axes: list[str] = list(body.get("axes", []))
    roles = body.get("report", {})
    seed_axis, line_axis = roles.get("seed_axis"), roles.get("line_axis")
    row_axes = [a for a in axes if a not in (seed_axis, line_axis)]
    held: dict[tuple[str, str], list[float]] = {}  # (trial, seed) -> entries' win rates
    tiers: dict[tuple[str, str, str], list[float]] = {}  # (trial, seed, opponent)
    lengths: dict[tuple[str, str], list[float]] = {}
    for r in rows:
        if r["suite"].startswith(TIER_SUITE_PREFIX):
            opponent = r["opponent"].removeprefix(HEURISTIC_PREFIX)
            tiers.setdefault((r["trial"], r["seed"], opponent), []).append(float(r["win_rate"]))
        else:
            held.setdefault((r["trial"], r["seed"]), []).append(float(r["win_rate"]))
            lengths.setdefault((r["trial"], r["seed"]), []).append(float(r["mean_length"]))

    def label(trial: str, axis: str | None) -> str:
        return trials[trial].labels.get(axis, "all") if axis else "all"

    columns = list(dict.fromkeys(label(key[0], line_axis) for key in [*held, *tiers]))
    cells: dict[tuple[tuple[str, ...], str], list[float]] = {}
    tier_cells: dict[tuple[tuple[str, ...], str, str], list[float]] = {}
    for (trial, _seed), values in held.items():
        group = tuple(label(trial, a) for a in row_axes)
        cells.setdefault((group, label(trial, line_axis)), []).append(sum(values) / len(values))
    per_seed_tiers: dict[tuple[str, str], list[float]] = {}
    for (trial, seed, opponent), values in tiers.items():
        group = tuple(label(trial, a) for a in row_axes)
        tier_cells.setdefault((group, opponent, label(trial, line_axis)), []).append(
            sum(values) / len(values))
        per_seed_tiers.setdefault((trial, seed), []).extend(values)
    for (trial, _seed), values in per_seed_tiers.items():
        group = tuple(label(trial, a) for a in row_axes)
        tier_cells.setdefault((group, MEAN_ROW, label(trial, line_axis)), []).append(
            sum(values) / len(values))
    status = (f"{finished} of {len(trials)} trials finished and evaluated"
              + (f" ({len(missing)} not finished)" if missing else ""))
    mean_length = [v for values in lengths.values() for v in values]
    md = [f"# Sweep {body.get('name', '')}: evaluated with {max_steps}-step episodes", "",
          f"{status}. Each finished trial's final policy (every seed's) played its own "
          f"evaluation suites again with episodes of {max_steps} steps; cells: mean over seeds "
          f"± the standard error, clipped to [0, 1]."
          + (f" Mean episode length (tier suites aside): "
             f"{sum(mean_length) / len(mean_length):.1f} steps." if mean_length else ""), ""]
    groups = list(dict.fromkeys(g for g, _ in cells))
    if groups:
        trained_on = {r["suite"] for r in rows} == {TRAINING_SUITE}
        md += [f"## Win rate (the training scenarios and opponent, {max_steps}-step episodes)"
               if trained_on else
               f"## Zero-shot win rate (held-out suites, {max_steps}-step episodes)", "",
               markdown_table([*(row_axes or ["all"]), *columns],
                              [[*(g or ("all",)), *(format_stat(seed_stat(cells.get((g, c), [])))
                                                    for c in columns)] for g in groups]), ""]
    tier_keys = list(dict.fromkeys((g, o) for g, o, _ in tier_cells))
    tier_keys.sort(key=lambda k: (k[0], math.inf if k[1] == MEAN_ROW else tier_order(k[1])[0]))
    if tier_keys:
        md += [f"## Win rate against the heuristic tiers ({max_steps}-step episodes)", "",
               markdown_table([*(row_axes or ["all"]), "opponent", *columns],
                              [[*(g or ("all",)), o,
                                *(format_stat(seed_stat(tier_cells.get((g, o, c), [])))
                                  for c in columns)] for g, o in tier_keys]), ""]
    return "\n".join(md)


__all__ = ["COLUMNS", "evaluate_sweep"]
