"""`tabx sweep evaluate`: a finished sweep's policies played again with another episode limit.

The sweep folder is written as `tabx sweep` leaves it (sweep.json, finished trial records, run
folders with their config and a final checkpoint), with untrained tiny policies (no training,
no Ray): two methods x two seeds, each evaluated on a held-out suite and a tier suite.
"""

from __future__ import annotations

import csv
import json

import jax
import numpy as np
import pytest
from test_learners_helpers import scenario_file, tiny_config
from test_sweep_report import fmt, md_section

from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.config import ConfigError
from ued.experiment import learner_for
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE
from workers.sweep import reevaluate
from workers.sweep.reevaluate import evaluate_sweep

METHODS, SEEDS = ("dr", "plr"), (0, 1)
LIMIT = 20  # the tiny runs trained with 8-step episodes


def write_suites(folder):
    held = folder / "held.yaml"
    held.write_text(f"name: held-duel\nepisodes: 3\nopponent: idle\n"
                    f"scenarios: ['{scenario_file()}']\n")
    tiers = folder / "tiers.yaml"
    tiers.write_text(f"name: tiers-duel\nepisodes: 3\nscenarios: ['{scenario_file()}']\n"
                     f"opponents: [idle, random]\n")
    return [str(held), str(tiers)]


def make_sweep(path, suites: list[str] | None, methods=METHODS, seeds=SEEDS):
    """A sweep folder of finished trials with untrained policies; `suites`: each run's
    `ued.eval_suites` (None: none, as a plain MARL run)."""
    listed = []
    for method in methods:
        for seed in seeds:
            name = f"seed{seed}-{method}"
            overrides = {"ued.eval_suites": json.dumps(suites)} if suites else {}
            config = tiny_config(seed=seed, **overrides)
            run = path / "runs" / name
            run.mkdir(parents=True)
            (run / CONFIG_FILE).write_text(config.to_yaml())
            learner = learner_for(config)
            with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
                checkpoints.save(config.learner.num_updates, learner.init(jax.random.key(seed)),
                                 jax.random.key(0))
            (path / "trials").mkdir(exist_ok=True)
            (path / "trials" / f"{name}.json").write_text(json.dumps(
                {"state": "finished", "sessions": 1, "seconds": 1.0, "steps": 256,
                 "total_steps": 256}))
            listed.append({"name": name, "labels": {"seed": str(seed), "method": method},
                           "run_dir": f"runs/{name}", "config_sha256": "0" * 64})
    (path / "sweep.json").write_text(json.dumps(
        {"name": path.name, "axes": ["seed", "method"], "trials": listed,
         "report": {"seed_axis": "seed", "line_axis": "method", "figure_axis": None}}))
    return path


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    path = tmp_path_factory.mktemp("sweep") / "duel"
    return make_sweep(path, write_suites(path.parent))


def test_every_finished_policy_plays_its_suites_with_the_new_limit_and_is_tabulated(
        sweep, tmp_path, monkeypatch):
    played = []
    original = reevaluate.Evaluator.evaluate
    monkeypatch.setattr(reevaluate.Evaluator, "evaluate",
                        lambda self, *a, **k: played.append(self.suite.name) or original(
                            self, *a, **k))
    markdown = evaluate_sweep(sweep, LIMIT, out=tmp_path).read_text()
    rows = list(csv.DictReader((tmp_path / f"evaluate-{LIMIT}.csv").open()))
    # 4 policies x (1 held-out entry + 2 tier entries), each episode the new limit long (no
    # elimination against idle or random in 20 steps from these starting positions)
    assert len(played) == 4 * 2 and len(rows) == 4 * 3
    assert {float(r["mean_length"]) for r in rows if r["opponent"] == "idle"} == {LIMIT}
    # The tables come from the CSV: given other win rates there (as a stopped evaluation would
    # have left), a second call plays nothing and tabulates them.
    rng = np.random.default_rng(0)
    for r in rows:
        r["win_rate"] = repr(float(rng.integers(0, 4)) / 3)
    with (tmp_path / f"evaluate-{LIMIT}.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, reevaluate.COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    played.clear()
    markdown = evaluate_sweep(sweep, LIMIT, out=tmp_path).read_text()
    assert played == []
    held = {(r["trial"]): float(r["win_rate"]) for r in rows if r["suite"] == "held-duel"}
    table = md_section(markdown, "Zero-shot win rate")
    assert table[0] == ["all", *METHODS]
    assert table[1] == ["all", *(fmt([held[f"seed{s}-{m}"] for s in SEEDS]) for m in METHODS)]
    tiers = md_section(markdown, "Win rate against the heuristic tiers")
    assert [r[1] for r in tiers[1:]] == ["random", "idle", "mean"]  # tier order, then mean
    for method in METHODS:
        per_seed = {opponent: [float(r["win_rate"]) for s in SEEDS for r in rows
                               if r["trial"] == f"seed{s}-{method}" and r["opponent"] == opponent
                               and r["suite"] == "tiers-duel"] for opponent in ("random", "idle")}
        column = 2 + METHODS.index(method)
        assert tiers[1][column] == fmt(per_seed["random"])
        assert tiers[2][column] == fmt(per_seed["idle"])
        assert tiers[3][column] == fmt([(a + b) / 2 for a, b in zip(per_seed["random"],
                                                                    per_seed["idle"], strict=True)])


def test_bad_input_is_one_error_naming_the_file_or_option(sweep, tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"--max-steps: expected an integer in \[1, "):
        evaluate_sweep(sweep, 0, out=tmp_path)
    bad = tmp_path / f"evaluate-{LIMIT}.csv"
    bad.write_text("something,else\n1,2\n")
    with pytest.raises(ConfigError, match=f"{bad}: not an evaluation table"):
        evaluate_sweep(sweep, LIMIT, out=tmp_path)
    assert bad.read_text() == "something,else\n1,2\n"  # left as it was
    assert main(["sweep", "evaluate", str(tmp_path / "nothing"), "--max-steps", "512"]) == 2
    assert "sweep.json" in capsys.readouterr().err


def test_a_run_without_suites_plays_its_training_scenario_against_its_opponent(tmp_path):
    sweep = make_sweep(tmp_path / "marl", None, methods=("mappo",), seeds=(0,))
    markdown = evaluate_sweep(sweep, LIMIT, episodes=2, out=tmp_path / "out").read_text()
    (row,) = csv.DictReader((tmp_path / "out" / f"evaluate-{LIMIT}.csv").open())
    assert (row["suite"], row["opponent"], row["episodes"]) == ("training", "random", "2")
    assert row["scenario"] == scenario_file() and float(row["mean_length"]) <= LIMIT
    assert md_section(markdown, "Win rate (the training scenarios and opponent")[1] == [
        "all", f"{float(row['win_rate']):.2f}"]
