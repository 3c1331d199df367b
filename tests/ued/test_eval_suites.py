"""Evaluation suites (`ued.suites`), the zero-shot `workers.roles.evaluator.Evaluator` and
`tabx eval RUN_DIR --suite`.

The evaluator tests use the tiny learner of the learner tests (2 archers v 1 farmer, 8 steps)
with fresh parameters, on two variants of its duel whose outcome does not depend on the policy:
in `weak_ally` the archers start at 10 % health, in `weak_enemy` the farmer does; nobody can hit
anybody within the episode, so the time-out gives the win to the healthier team. A suite that
alternates them (against four different opponents) shows win rates 0, 1, 0, 1 exactly when
every result lands on its own entry.
"""

from __future__ import annotations

import json
import math
import re

import jax
import numpy as np
import pytest
from test_learners_helpers import ENV_CONFIG, tiny_config

from tabx.compile_counter import CompileCounter
from tabx.params import HEURISTIC_TIERS, make_level
from tabx.scenarios import config_for, level_to_scenario, load_named, save_scenario
from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.errors import ConfigError
from ued.experiment import learner_for
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE
from ued.suites import EvalSuite, list_suites, load_suite, parse_suite
from ued.tensorboard import SummaryWriter, read_scalars
from workers.roles.evaluator import Evaluator, format_table, log, scalars, to_json

EPISODES = 3
OPPONENTS = ("idle", "heuristic:expert", "random", "heuristic")
EXPECTED_WINS = (0.0, 1.0, 0.0, 1.0)



def weak_level(weak: str):
    """The duel with the `weak` team ("ally" or "enemy") at 10 % health, far apart."""
    hp = {"ally": (10.0, 100.0), "enemy": (100.0, 100.0)}[weak]
    enemy_hp = {"ally": (100.0, 100.0), "enemy": (10.0, 100.0)}[weak]
    return make_level(
        ENV_CONFIG,
        [dict(unit="archer", position=(-40.0, y), heading=math.pi, health=hp[0],
              max_health=hp[1]) for y in (-4.0, 4.0)],
        [dict(unit="farmer", position=(40.0, 0.0), heading=0.0, health=enemy_hp[0],
              max_health=enemy_hp[1])])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Scenario files weak_ally.json / weak_enemy.json and a suite alternating them."""
    folder = tmp_path_factory.mktemp("suites")
    paths = {}
    for weak in ("ally", "enemy"):
        paths[weak] = folder / f"weak_{weak}.json"
        save_scenario(paths[weak], level_to_scenario(weak_level(weak), name=f"weak_{weak}"))
    entries = "".join(
        f"  - scenario: {paths['ally' if i % 2 == 0 else 'enemy']}\n    opponent: {opp}\n"
        for i, opp in enumerate(OPPONENTS))
    suite = folder / "alternating.yaml"
    suite.write_text(f"name: alternating\ndescription: weak allies, weak enemies\n"
                     f"episodes: {EPISODES}\nentries:\n{entries}")
    return {"folder": folder, "suite": suite, **paths}


@pytest.fixture(scope="module")
def learner():
    return learner_for(tiny_config())


@pytest.fixture(scope="module")
def evaluator(learner, files):
    return Evaluator(learner, load_suite(files["suite"]))


@pytest.fixture(scope="module")
def first_result(evaluator, learner):
    return evaluator.evaluate(learner.init(jax.random.key(0)).params, jax.random.key(0))


# --- suites --------------------------------------------------------------------------------


def test_every_shipped_suite_loads_and_fits_its_training_scenario():
    names = list_suites()
    trains = ("1F1M3A1Hvs2F1S1K1A1H", "2F1M2Avs2S1K", "4F1S1K2A1Pvs2M1C1P", "5F1S1A1Dvs7F1S1D1H")
    assert sorted(names) == sorted(f"{kind}-{t}" for kind in ("units", "zones", "tiers")
                                   for t in trains)
    for name in names:
        suite = load_suite(name)
        assert suite.name == name and suite.episodes == 64 and suite.team == "ally"
        kind, train = name.split("-", 1)
        trained = f"{train}_2L2B2S"
        config = config_for([load_named(trained)])
        assert suite.entries[0].scenario == trained  # (A) is the training scenario
        for entry in suite.entries:
            scenario = load_named(entry.scenario)  # resolves ...
            scenario.to_level(config)  # ... and fits the policy trained on `trained`
            assert entry.label == f"{entry.scenario}@{entry.opponent}"
        if kind == "tiers":
            assert [e.opponent for e in suite.entries] == [
                f"heuristic:{t}" for t in ("random", "novice", "medium", "advanced", "expert")]
            assert {e.scenario for e in suite.entries} == {trained}
        else:
            assert {e.opponent for e in suite.entries} == {"heuristic:novice"}
            assert len(suite.entries) == {"units": 4, "zones": 3}[kind]
            enemies = {s.split("vs")[1].split("-")[0] for s in suite.scenarios}
            assert enemies == {trained.split("vs")[1]}  # the same enemies and zones
        if kind == "zones":
            assert list(suite.scenarios) == [trained, f"{trained}-1", f"{trained}-2"]
    with pytest.raises(ConfigError, match="unknown suite 'units-2F1M2Avs2S1'; did you mean "
                                          "'units-2F1M2Avs2S1K'"):
        load_suite("units-2F1M2Avs2S1")


@pytest.mark.parametrize("text, field", [
    ("episodes: 3\nscenarios: [crossfire]\nbogus: 1\n", "unknown key 'bogus'"),
    ("scenarios: [crossfire]\nepisodes: 0\n", "episodes: must be >= 1"),
    ("scenarios: [crossfire]\nepisodes: many\n", "episodes: expected an integer"),
    ("scenarios: [crossfire, no-such-scenario]\n", "scenarios[1]: unknown scenario"),
    ("scenarios: [crossfire]\nopponent: heuristic:nope\n", "opponent: unknown heuristic tier"),
    ("scenarios: [crossfire]\nopponents: [idle, robot]\n", "opponents[1]: unknown controller"),
    ("entries:\n  - scenario: crossfire\n  - scenario: elbow\n    opponent: external\n",
     "entries[1].opponent: 'external' is not an opponent"),
    ("entries:\n  - scenario: crossfire\n    oponent: idle\n",
     "entries[0]: unknown key 'oponent'; did you mean 'opponent'"),
    ("entries:\n  - opponent: idle\n", "entries[0].scenario: missing"),
    ("entries: [crossfire]\nscenarios: [elbow]\n", "not both"),
    ("scenarios: [crossfire, crossfire]\n", "scenarios[1]: 'crossfire' against "
                                            "heuristic:novice is already in the suite"),
    ("scenarios: [2L2B2S]\n", "scenarios[0]: '2L2B2S' has no units"),
    ("team: both\nscenarios: [crossfire]\n", "team: must be one of ally, enemy"),
    ("name: crossfire\n", "entries: missing"),
    ("[1, 2]\n", "expected a mapping"),
    ("scenarios: [crossfire\n", "not valid YAML"),
])
def test_bad_suite_files_name_the_file_and_the_field(tmp_path, text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_suite(path)
    assert str(err.value).startswith(f"{path}: ") and field in str(err.value), err.value


def test_suite_cross_product_and_defaults():
    suite = parse_suite("scenarios: [crossfire, elbow]\nopponents: [idle, heuristic:expert]\n",
                        default_name="mine")
    assert isinstance(suite, EvalSuite) and suite.name == "mine" and suite.episodes == 64
    assert suite.labels == ("crossfire@idle", "crossfire@heuristic:expert", "elbow@idle",
                            "elbow@heuristic:expert")
    suite = parse_suite("opponent: heuristic:medium\nentries:\n  - crossfire\n"
                        "  - {scenario: crossfire, opponent: random}\n")
    assert suite.labels == ("crossfire@heuristic:medium", "crossfire@random")


# --- the evaluator -------------------------------------------------------------------------


def test_results_land_on_their_own_entries(evaluator, first_result, files):
    result = first_result
    assert [e.opponent for e in result.entries] == list(OPPONENTS)
    assert [e.scenario for e in result.entries] == [
        str(files["ally" if i % 2 == 0 else "enemy"]) for i in range(len(OPPONENTS))]
    assert [e.label for e in result.entries] == list(evaluator.suite.labels)
    assert [e.win_rate for e in result.entries] == list(EXPECTED_WINS)
    assert result.mean_win_rate == pytest.approx(0.5)
    for e in result.entries:
        assert e.episodes == EPISODES and e.mean_length == ENV_CONFIG.max_steps
        assert 0.0 <= e.win_low <= e.win_rate <= e.win_high <= 1.0
    # The opponent's tier is written into each entry's levels: expert for entry 1, the
    # scenario's own heuristic for the bare `heuristic` of entry 3.
    eps = np.asarray(evaluator.levels.heuristic.epsilon)[:, 1].reshape(len(OPPONENTS), EPISODES)
    np.testing.assert_allclose(eps[1], HEURISTIC_TIERS["expert"]["epsilon"])
    own = load_named(str(files["enemy"])).to_level(ENV_CONFIG).heuristic.epsilon[1]
    np.testing.assert_allclose(eps[3], own)
    np.testing.assert_array_equal(np.asarray(evaluator.kinds).reshape(-1, EPISODES)[:, 0],
                                  [2, 0, 1, 0])  # idle, heuristic, random, heuristic


def test_evaluate_never_recompiles(evaluator, first_result, learner):
    assert evaluator._run._cache_size() == 1
    with CompileCounter() as cc:
        for seed in (1, 2):
            params = learner.init(jax.random.key(seed)).params
            result = evaluator.evaluate(params, jax.random.key(seed))
    assert cc.traces == 0 and evaluator._run._cache_size() == 1, cc.traced
    assert [e.win_rate for e in result.entries] == list(EXPECTED_WINS)


def test_entries_that_do_not_fit_the_policy_name_the_entry_and_the_slots(learner):
    with pytest.raises(ConfigError) as err:
        Evaluator(learner, load_suite("units-2F1M2Avs2S1K"))
    message = str(err.value)
    assert "entry 0 (2F1M2Avs2S1K_2L2B2S@heuristic:novice)" in message
    assert "5 allies, 3 enemies and 6 zones" in message
    assert "max_allies=2, max_enemies=1, max_zones=0" in message
    suite = parse_suite(f"team: enemy\nscenarios: [{duel_scenario()}]\n", source="enemy.yaml")
    with pytest.raises(ConfigError, match="enemy.yaml: team: the suite evaluates the enemy "
                                          "team, the policy plays the ally team"):
        Evaluator(learner, suite)
    with pytest.raises(ConfigError, match="episodes"):
        Evaluator(learner, suite, episodes=0)


def duel_scenario() -> str:
    from test_learners_helpers import scenario_file

    return scenario_file()


def test_tensorboard_json_and_table(first_result, tmp_path):
    with SummaryWriter(tmp_path / "events") as writer:
        log(writer, 1234, first_result)
    logged = read_scalars(tmp_path / "events")
    expected = scalars(first_result)
    assert set(logged) == set(expected)
    for e, wins in zip(first_result.entries, EXPECTED_WINS, strict=True):
        assert logged[f"eval/alternating/{e.label}/win_rate"] == [(1234, wins)]
        assert f"eval/alternating/{e.label}/return" in logged
        assert f"eval/alternating/{e.label}/length" in logged
    assert logged["eval/alternating/mean_win_rate"] == [(1234, 0.5)]

    data = json.loads(json.dumps(to_json(first_result)))
    assert data["suite"] == "alternating" and data["mean_win_rate"] == 0.5
    assert [(d["opponent"], d["win_rate"]) for d in data["entries"]] == list(
        zip(OPPONENTS, EXPECTED_WINS, strict=True))
    table = format_table(first_result)
    assert "suite alternating: weak allies, weak enemies" in table
    assert "heuristic:expert  1.000 [" in table and "mean win rate over 4 entries: 0.500" in table


# --- the command line ----------------------------------------------------------------------


def test_cli_eval_suite(capsys, tmp_path, learner, files):
    run = tmp_path / "run"
    run.mkdir()
    (run / CONFIG_FILE).write_text(tiny_config().to_yaml())
    with Checkpoints(run / CHECKPOINT_DIR) as ck:
        ck.save(0, learner.init(jax.random.key(1)), jax.random.key(2))
    out_json = tmp_path / "out" / "eval.json"
    code = main(["eval", str(run), "--suite", str(files["suite"]), "--json", str(out_json),
                 "--seed", "3"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert f"policy {run} (mappo, update 0)" in out and "suite alternating" in out
    assert "win rate [95% CI]" in out and "mean win rate over 4 entries: 0.500" in out
    assert re.search(rf"{re.escape(str(files['ally']))} +idle +0\.000 \[", out), out
    assert re.search(rf"{re.escape(str(files['enemy']))} +heuristic:expert +1\.000 \[", out)
    data = json.loads(out_json.read_text())
    assert data["run_dir"] == str(run) and data["seed"] == 3 and data["update"] == 0
    assert [d["win_rate"] for d in data["entries"]] == list(EXPECTED_WINS)
    assert all(d["episodes"] == EPISODES for d in data["entries"])

    assert main(["eval", "--list-suites"]) == 0
    out, _ = capsys.readouterr()
    assert "tiers-2F1M2Avs2S1K" in out and "units-5F1S1A1Dvs7F1S1D1H" in out
    for argv, message in (
            (["eval", str(run), "--suite", "nope"], "unknown suite 'nope'"),
            (["eval", str(run), "--suite", "units-2F1M2Avs2S1K"], "max_allies=2"),
            (["eval", str(run), "--suite", str(files["suite"]), "--scenario", "crossfire"],
             "drop --scenario"),
            (["eval", "--suite", str(files["suite"])], "give RUN_DIR"),
            (["eval", str(run), "--json", "x.json"], "--json goes with --suite")):
        assert main(argv) == 2
        _, err = capsys.readouterr()
        assert message in err, (argv, err)
