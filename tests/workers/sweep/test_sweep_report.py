"""`tabx sweep report`: the paper's tables from fake sweep folders (no training).

Each test writes a sweep folder as `tabx sweep` leaves it (sweep.json, the trials' records,
their run folders' event files) with known win rates, and compares the report's tables and
results.csv with the mean and standard error computed here. Whether a trial is finished is
read from its checkpoints, which a fake run folder has none of: `not_finished` is stood in
for (tests/workers/sweep/test_sweep.py's end-to-end sweep reports real, finished trials).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from tabx_ued.cli import main
from ued.tensorboard import SummaryWriter
from workers.sweep import report as sweep_report
from workers.sweep.report import seed_stat, write_report

TIERS = ("random", "novice", "medium", "advanced", "expert")
STEPS = (4096, 8192, 12288, 16384, 20480)  # five evaluations


@pytest.fixture(autouse=True)
def every_trial_finished(monkeypatch):
    monkeypatch.setattr(sweep_report, "not_finished", lambda folder: {})


def se(values) -> float:
    return float(np.std(values, ddof=1) / np.sqrt(len(values)))


def fake_sweep(path: Path, trials: dict[str, dict], axes: list[str],
               report: dict[str, str | None]) -> Path:
    """A sweep folder whose trial `name` has `labels`, `seconds`, `steps` and per seed
    (`seeds`: a list of tag -> [(step, value)]) the scalars of its run folder."""
    listed = []
    for name, trial in trials.items():
        run = path / "runs" / name
        seeds = trial["seeds"]
        for s, scalars in enumerate(seeds):
            folder = run / "events" if len(seeds) == 1 else run / f"seed-{s}"
            with SummaryWriter(folder) as writer:
                for step in sorted({st for points in scalars.values() for st, _ in points}):
                    writer.scalars({tag: v for tag, points in scalars.items()
                                    for st, v in points if st == step}, step=step)
        (path / "trials").mkdir(parents=True, exist_ok=True)
        (path / "trials" / f"{name}.json").write_text(json.dumps(
            {"state": "finished", "sessions": 1, "seconds": trial.get("seconds", 60.0),
             "steps": trial.get("steps", STEPS[-1]), "total_steps": STEPS[-1]}))
        listed.append({"name": name, "labels": trial["labels"], "run_dir": f"runs/{name}",
                       "config_sha256": "0" * 64})
    (path / "sweep.json").write_text(json.dumps(
        {"name": path.name, "axes": axes, "report": report, "trials": listed}))
    return path


def ued_scalars(suite: str, final: float, tiers: dict[str, float] | None = None,
                teams: str = "2F1M2Avs2S1K") -> dict[str, list[tuple[int, float]]]:
    """One seed's evaluations: the held-out suite's mean win rate rising to `final` over five
    evaluations, and at each the tier suite (its entries' win rates, `tiers`, and their
    mean), whose values the report must not take for the zero-shot ones."""
    out = {f"eval/{suite}/mean_win_rate": [(s, final * (i + 1) / len(STEPS))
                                           for i, s in enumerate(STEPS)],
           f"eval/{suite}/{teams}_2L2B2S@heuristic:novice/win_rate": [(STEPS[-1], 0.123)],
           "episode/win_rate": [(s, 0.5) for s in STEPS]}
    if tiers:
        tier_suite = f"tiers-{teams}"
        for tier, value in tiers.items():
            out[f"eval/{tier_suite}/{teams}_2L2B2S@heuristic:{tier}/win_rate"] = [
                (STEPS[0], 0.0), (STEPS[-1], value)]
            out[f"eval/{tier_suite}/{teams}_2L2B2S@heuristic:{tier}/win_rate_low"] = [
                (STEPS[-1], 0.0)]
        out[f"eval/{tier_suite}/mean_win_rate"] = [(STEPS[0], 0.0), (STEPS[-1],
                                                                      np.mean(list(tiers.values())))]
    return out


UED_AXES = ["seed", "ued.method", "param", "teams"]
UED_ROLES = {"seed_axis": "seed", "line_axis": "ued.method", "figure_axis": "teams"}


def ued_sweep(path: Path, finals, tiers=None, seconds=None) -> Path:
    """Trials of `finals[(method, param, teams)] = [one final zero-shot win rate per seed]`."""
    trials = {}
    for (method, param, teams), values in finals.items():
        suite = f"{'units' if param != 'zone' else 'zones'}-{teams}"
        for seed, final in enumerate(values):
            name = f"seed{seed}-{method}-{param}-{teams}"
            tier_values = (tiers or {}).get((method, param, teams, seed))
            trials[name] = {"labels": {"seed": str(seed), "ued.method": method, "param": param,
                                       "teams": teams},
                            "seeds": [ued_scalars(suite, final, tier_values, teams)],
                            "seconds": (seconds or {}).get(name, 60.0)}
    return fake_sweep(path, trials, UED_AXES, UED_ROLES)


def md_section(markdown: str, heading: str) -> list[list[str]]:
    """The rows of the first table after the heading starting with `heading` (cells)."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## " + heading))
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("## "):
            break
        if line.startswith("|") and not line.startswith("|---"):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def fmt(values) -> str:
    return f"{np.mean(values):.2f} ± {se(values):.2f}"


# --- the zero-shot table -----------------------------------------------------------------------


def test_one_zero_shot_table_per_free_parameter_methods_as_columns_with_a_mean_row(tmp_path):
    finals = {("dr", "unit", "A"): [0.2, 0.4, 0.3], ("plr", "unit", "A"): [0.1, 0.1, 0.4],
              ("dr", "unit", "B"): [0.6, 0.8, 0.7], ("plr", "unit", "B"): [0.5, 0.9, 0.6],
              ("dr", "zone", "A"): [0.9, 0.7, 0.8], ("plr", "zone", "A"): [0.3, 0.2, 0.25],
              ("dr", "zone", "B"): [0.5, 0.5, 0.8], ("plr", "zone", "B"): [0.4, 0.6, 0.5]}
    tiers = {(m, p, t, s): {"novice": 0.99} for (m, p, t) in finals for s in range(3)}
    written = write_report(ued_sweep(tmp_path / "sw", finals, tiers))
    text = written.markdown.read_text()
    for param in ("unit", "zone"):
        rows = md_section(text, f"Zero-shot win rate (held-out suites, last evaluation): "
                                f"param = {param}")
        assert rows[0] == ["teams", "dr", "plr"]
        assert rows[1] == ["A", fmt(finals[("dr", param, "A")]), fmt(finals[("plr", param, "A")])]
        assert rows[2] == ["B", fmt(finals[("dr", param, "B")]), fmt(finals[("plr", param, "B")])]
        pooled = {m: finals[(m, param, "A")] + finals[(m, param, "B")] for m in ("dr", "plr")}
        assert rows[3] == ["mean", fmt(pooled["dr"]), fmt(pooled["plr"])]
        assert len(rows) == 4
    assert text.count("## Zero-shot win rate") == 2
    # results.csv: every seed's value, the cells and the pooled rows
    rows = list(csv.DictReader(written.results_csv.open()))
    zero = [r for r in rows if r["table"] == "zero-shot"]
    cell = next(r for r in zero
                if (r["ued.method"], r["param"], r["teams"]) == ("plr", "zone", "A"))
    assert cell["suite"] == "zones-A" and cell["seeds"] == "3" and cell["interval"] == "se"
    assert [float(v) for v in cell["values"].split()] == pytest.approx([0.3, 0.2, 0.25])
    assert float(cell["mean"]) == pytest.approx(0.25, abs=1e-4)
    assert float(cell["se"]) == pytest.approx(se([0.3, 0.2, 0.25]), rel=1e-3)
    assert float(cell["low"]) == pytest.approx(0.25 - se([0.3, 0.2, 0.25]), rel=1e-3)
    mean_row = next(r for r in zero if (r["ued.method"], r["param"], r["teams"])
                    == ("dr", "unit", "mean"))
    assert sorted(float(v) for v in mean_row["values"].split()) == pytest.approx(
        sorted(finals[("dr", "unit", "A")] + finals[("dr", "unit", "B")]))
    assert len(zero) == 8 + 4  # 8 cells, 2 parameters x 2 methods pooled


def test_t95_is_an_option_and_intervals_are_clipped_to_0_1(tmp_path):
    finals = {("dr", "zone", "A"): [1.0, 0.9, 0.95], ("plr", "zone", "A"): [0.0, 0.05, 0.3]}
    path = ued_sweep(tmp_path / "sw", finals)
    assert main(["sweep", "report", str(path), "--interval", "t95",
                 "--out", str(tmp_path / "t")]) == 0
    rows = {(r["ued.method"], r["teams"]): r
            for r in csv.DictReader((tmp_path / "t" / "results.csv").open())}
    ends = {}
    for method, clipped in (("dr", "high"), ("plr", "low")):
        values = finals[(method, "zone", "A")]
        half = 4.303 * se(values)  # Student's t, 2 degrees of freedom
        low, high = np.mean(values) - half, np.mean(values) + half
        assert (low < 0) == (clipped == "low") and (high > 1) == (clipped == "high")
        row = rows[(method, "A")]
        assert row["interval"] == "t95"
        assert float(row["low"]) == pytest.approx(max(0.0, low), abs=1e-4)
        assert float(row["high"]) == pytest.approx(min(1.0, high), abs=1e-4)
        ends[method] = (max(0.0, low), min(1.0, high))
    table = md_section((tmp_path / "t" / "report.md").read_text(), "Zero-shot")
    # clipped: the interval's ends as they are, not a symmetric ± past 0 or 1
    assert table[1][1] == f"0.95 +0.05 −{0.95 - ends['dr'][0]:.2f}"
    assert table[1][2] == f"0.12 +{ends['plr'][1] - np.mean([0.0, 0.05, 0.3]):.2f} −0.12"


def test_seed_stat_standard_error_never_leaves_0_1_for_rates():
    # the standard error of values in [0, 1] stays inside it (max - mean >= s.e.); the
    # t-interval does not, and is clipped
    values = [1.0, 1.0, 0.2]
    s = seed_stat(values)
    assert (s.n, s.mean, s.se) == (3, pytest.approx(0.7333333), pytest.approx(se(values)))
    assert s.high == pytest.approx(1.0) and s.low == pytest.approx(np.mean(values) - se(values))
    t = seed_stat(values, "t95")
    assert t.high == 1.0 and t.low == 0.0
    one = seed_stat([0.4, math.nan])
    assert (one.n, one.mean) == (1, 0.4) and math.isnan(one.low)
    with pytest.raises(sweep_report.ConfigError, match="interval: expected one of se, t95"):
        seed_stat([0.1], "ci")


# --- the tier table ----------------------------------------------------------------------------


def test_tier_table_pools_configurations_and_seeds_per_method_and_tier(tmp_path):
    finals = {(m, p, t): [0.5, 0.5] for m in ("dr", "sfl") for p in ("unit", "zone")
              for t in ("A", "B")}
    rng = np.random.default_rng(0)
    tiers = {(m, p, t, s): {tier: round(float(rng.uniform()), 3) for tier in reversed(TIERS)}
             for (m, p, t) in finals for s in range(2)}
    written = write_report(ued_sweep(tmp_path / "sw", finals, tiers))
    rows = md_section(written.markdown.read_text(), "Win rate against the heuristic tiers")
    assert rows[0] == ["param", "opponent", "dr", "sfl"]
    body = rows[1:]
    # tiers in order of skill, then their mean, per free parameter
    assert [r[:2] for r in body] == [[p, o] for p in ("unit", "zone") for o in (*TIERS, "mean")]
    for row in body:
        param, opponent = row[:2]
        for method, text in zip(("dr", "sfl"), row[2:], strict=True):
            values = [np.mean(list(v.values())) if opponent == "mean" else v[opponent]
                      for (m, p, _t, _s), v in tiers.items() if (m, p) == (method, param)]
            assert len(values) == 4  # 2 configurations x 2 seeds
            assert text == fmt(values), (param, opponent, method)
    rows = [r for r in csv.DictReader(written.results_csv.open()) if r["table"] == "tiers"]
    expert = next(r for r in rows if (r["ued.method"], r["param"], r["teams"], r["opponent"])
                  == ("sfl", "unit", "B", "expert"))
    assert expert["suite"] == "tiers-B" and [float(v) for v in expert["values"].split()] == \
        pytest.approx([tiers[("sfl", "unit", "B", s)]["expert"] for s in range(2)], abs=1e-6)
    pooled = next(r for r in rows if (r["ued.method"], r["param"], r["teams"], r["opponent"])
                  == ("dr", "zone", "mean", "random"))
    assert int(pooled["seeds"]) == 4
    # the tier suite is not a held-out suite: the zero-shot table reads units-/zones- only
    zero = md_section(written.markdown.read_text(), "Zero-shot win rate")
    assert zero[1][1] == fmt([0.5, 0.5])


def test_no_tier_suite_no_tier_table(tmp_path):
    written = write_report(ued_sweep(tmp_path / "sw", {("dr", "zone", "A"): [0.5, 0.7]}))
    text = written.markdown.read_text()
    assert "heuristic tiers" not in text
    assert not [r for r in csv.DictReader(written.results_csv.open()) if r["table"] == "tiers"]


# --- the training-time table -------------------------------------------------------------------


def test_training_time_table_is_shaped_as_the_papers(tmp_path):
    finals = {(m, p, t): [0.5, 0.5] for p in ("zone", "unit") for t in ("A", "B")
              for m in ("dr", "plr")}
    seconds = {f"seed{s}-{m}-{p}-{t}": 60.0 * (1 + s + 2 * (m == "plr") + 4 * (t == "B"))
               for (m, p, t) in finals for s in range(2)}
    written = write_report(ued_sweep(tmp_path / "sw", finals, seconds=seconds))
    rows = md_section(written.markdown.read_text(), "Training time")
    # the paper: Scenario | Param | DR | PLR ...
    assert rows[0] == ["teams", "param", "dr", "plr"]
    assert [r[:2] for r in rows[1:]] == [["A", "zone"], ["A", "unit"], ["B", "zone"],
                                         ["B", "unit"]]
    for row in rows[1:]:
        teams, param = row[:2]
        for method, text in zip(("dr", "plr"), row[2:], strict=True):
            times = [seconds[f"seed{s}-{method}-{param}-{teams}"] for s in range(2)]
            rate = np.mean([STEPS[-1] / t for t in times])
            assert text == f"{np.mean(times) / 60:.1f}m ({rate:,.0f}/s)"


# --- learning curves ---------------------------------------------------------------------------


def test_curves_draw_the_held_out_suite_at_every_evaluation(tmp_path):
    finals = {("dr", "unit", "A"): [0.5, 0.9]}
    tiers = {("dr", "unit", "A", s): {"novice": 0.7} for s in range(2)}
    path = ued_sweep(tmp_path / "sw", finals, tiers)
    from workers.sweep.folder import SweepFolder

    folder = SweepFolder(path)
    result = sweep_report.trial_result(folder, "seed1-dr-unit-A", folder.trials()[
        "seed1-dr-unit-A"].labels)
    assert result.suites == ("units-A",) and result.tier_suites == ("tiers-A",)
    (series,) = [seed[sweep_report.CURVE_TAG] for seed in result.curves]
    assert [s for s, _ in series] == list(STEPS)  # every evaluation, not the tier suite's two
    assert [v for _, v in series] == pytest.approx([0.9 * (i + 1) / 5 for i in range(5)])
    written = write_report(path)
    assert [p.name for p in written.figures] == ["curves-A.png"]


def blank(draw) -> bool:
    """Whether axes drawn by `draw` (no frame, ticks or legend) render all white."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 2), dpi=50)
    draw(ax)
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 1)
    ax.axis("off")
    fig.canvas.draw()
    pixels = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    plt.close(fig)
    return bool((pixels == 255).all())


def test_a_one_point_series_is_drawn_as_a_marker():
    from ued.plot import Curve, draw_curve

    one = Curve(np.array([5]), np.array([0.5]), np.array([0.1]), np.array([2]))
    assert blank(lambda ax: None)
    assert blank(lambda ax: ax.plot(one.steps, one.mean))  # what a plain line draws
    assert not blank(lambda ax: draw_curve(ax, one, "one point"))


def test_a_one_evaluation_sweep_still_draws_its_points(tmp_path):
    """One evaluation per run (the last): the curve is one point per method, drawn."""
    trials = {f"seed{s}-{m}": {"labels": {"seed": str(s), "ued.method": m},
                               "seeds": [{"eval/zones-A/mean_win_rate": [(100, 0.2 + s / 10)]}]}
              for m in ("dr", "plr") for s in range(2)}
    path = fake_sweep(tmp_path / "sw", trials, ["seed", "ued.method"],
                      {"seed_axis": "seed", "line_axis": "ued.method", "figure_axis": None})
    written = write_report(path)
    rows = md_section(written.markdown.read_text(), "Zero-shot")
    assert rows == [["", "dr", "plr"], ["all", fmt([0.2, 0.3]), fmt([0.2, 0.3])]]
    assert [p.name for p in written.figures] == ["curves-all.png"]


# --- MARL sweeps: multi-seed trials, the training win rate ---------------------------------------


def test_multi_seed_marl_trials_table_their_training_win_rate(tmp_path):
    trials = {}
    finals = {("mappo", "crossfire"): [0.2, 0.4, 0.9], ("ippo", "crossfire"): [0.5, 0.6, 0.7],
              ("mappo", "ambush"): [0.1, 0.1, 0.4]}
    for (algorithm, challenge), values in finals.items():
        trials[f"{algorithm}-{challenge}"] = {
            "labels": {"algorithm": algorithm, "challenge": challenge, "seed": "0-2"},
            "seeds": [{"episode/win_rate": [(s, v * s / STEPS[-1]) for s in STEPS]}
                      for v in values], "seconds": 120.0}
    path = fake_sweep(tmp_path / "sw", trials, ["algorithm", "challenge", "seed"],
                      {"seed_axis": "seed", "line_axis": "algorithm",
                       "figure_axis": "challenge"})
    written = write_report(path)
    text = written.markdown.read_text()
    rows = md_section(text, "Training win rate (last logged update)")
    assert rows[0] == ["challenge", "mappo", "ippo"]
    assert rows[1] == ["crossfire", fmt(finals[("mappo", "crossfire")]),
                       fmt(finals[("ippo", "crossfire")])]
    assert rows[2] == ["ambush", fmt(finals[("mappo", "ambush")]), "-"]
    assert rows[3] == ["mean", fmt(finals[("mappo", "crossfire")] + finals[("mappo", "ambush")]),
                       fmt(finals[("ippo", "crossfire")])]
    times = md_section(text, "Training time")
    # three seeds' steps in one program
    assert times[1] == ["crossfire", f"2.0m ({3 * STEPS[-1] / 120:,.0f}/s)",
                        f"2.0m ({3 * STEPS[-1] / 120:,.0f}/s)"]
    assert [p.name for p in written.figures] == ["curves-crossfire.png", "curves-ambush.png"]


def test_a_bad_interval_is_one_usage_error(tmp_path, capsys):
    path = ued_sweep(tmp_path / "sw", {("dr", "zone", "A"): [0.5]})
    before = sorted(p for p in path.rglob("*"))
    with pytest.raises(SystemExit) as info:
        main(["sweep", "report", str(path), "--interval", "ci"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--interval: invalid choice: 'ci'" in err and "Traceback" not in err
    assert sorted(p for p in path.rglob("*")) == before
