"""Scenario format, validation errors, levels, registry/composition and the CLI."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from tabx import constants as C
from tabx import params as P
from tabx.scenarios import (
    UNIT_STAT_RANGES,
    Scenario,
    ScenarioError,
    Unit,
    Zone,
    config_for,
    level_to_scenario,
    list_scenarios,
    load_named,
    load_scenario,
    save_scenario,
    user_scenario_dir,
)
from tabx_ued import cli

BASE = {
    "format": "tabx-scenario/1",
    "name": "duel",
    "category": "user",
    "units": [
        {"unit": "farmer", "team": "enemy", "position": [10, 0], "heading_deg": 180},
        {"unit": "archer", "team": "ally", "position": [-10, 0], "heading": 0.0,
         "overrides": {"health": 30, "max_health": 50}},
    ],
    "zones": [{"type": "lava", "centre": [0, 0], "semi_axes": [3, 4], "effect": 5}],
}


@pytest.fixture(autouse=True)
def _empty_user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Keep the developer's own user scenarios out of the tests."""
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(tmp_path / "user"))


def with_change(path: str, value) -> dict:
    d = copy.deepcopy(BASE)
    *head, last = path.split(".")
    obj = d
    for k in head:
        obj = obj[int(k)] if k.isdigit() else obj[k]
    if value is KeyError:
        del obj[int(last) if last.isdigit() else last]
    elif last.isdigit():
        obj[int(last)] = value
    else:
        obj[last] = value
    return d


# --- format -------------------------------------------------------------------------------------


def test_from_dict_normalises_and_round_trips():
    s = Scenario.from_dict(BASE)
    assert s.units[0].heading == pytest.approx(math.pi)
    assert s.units[0].position == (10.0, 0.0) and isinstance(s.units[0].position[0], float)
    assert [u.team for u in s.allies] == ["ally"] and s.playable
    assert s.arena == (121.0, 78.0)
    assert Scenario.from_dict(s.to_dict()) == s
    assert Scenario.from_dict(json.loads(json.dumps(s.to_dict()))) == s


def test_save_and_load(tmp_path: Path):
    s = Scenario.from_dict(BASE)
    path = save_scenario(tmp_path / "sub" / "duel.json", s)
    assert load_scenario(path) == s
    text = path.read_text()
    assert text.count("\n") < 20  # one record per line: readable
    assert not list(path.parent.glob(".*.tmp"))  # atomic write left no temp file


def test_to_level_slots_and_padding():
    s = Scenario.from_dict(BASE)
    lv = s.to_level()  # tightest config: 1 ally, 1 enemy, 1 zone
    assert np.asarray(lv.units.team).tolist() == [0, 1]
    assert np.asarray(lv.units.unit_type).tolist() == [C.UNIT_TYPE_BY_NAME["archer"], 0]
    assert np.asarray(lv.units.health).tolist() == [30.0, 60.0]
    assert np.asarray(lv.units.max_health).tolist() == [50.0, 60.0]
    lv = s.to_level(P.EnvConfig(max_allies=3, max_enemies=2, max_zones=4))
    assert np.asarray(lv.units.active).tolist() == [True, False, False, True, False]
    assert np.asarray(lv.zones.zone_type).tolist() == [C.ZONE_LAVA, 0, 0, 0]
    with pytest.raises(ScenarioError, match="max_zones=0"):
        s.to_level(P.EnvConfig(max_zones=0))


def test_to_level_heuristic_physics_and_arena():
    d = dict(BASE, arena={"width": 60, "height": 40}, physics={"preset": "fast", "slop": 0.02},
             heuristic={"ally": "expert", "enemy": {"epsilon": 0.3}})
    s = Scenario.from_dict(d)
    lv = s.to_level()
    assert np.asarray(lv.physics.arena_size).tolist() == [60.0, 40.0]
    assert float(lv.physics.dt) == 1.0 and float(lv.physics.slop) == pytest.approx(0.02)
    assert np.asarray(lv.heuristic.epsilon).tolist() == pytest.approx([0.01, 0.3])
    lv2 = s.to_level(heuristic={"ally": "random", "enemy": "novice"}, physics="default")
    assert np.asarray(lv2.heuristic.epsilon).tolist() == pytest.approx([1.0, 0.5])
    assert float(lv2.physics.dt) == 0.5
    assert np.asarray(lv2.physics.arena_size).tolist() == [60.0, 40.0]  # arena is the scenario's
    back = level_to_scenario(lv, name="duel")
    assert back.arena == (60.0, 40.0)
    assert back.heuristic["ally"] == "expert" and back.heuristic["enemy"]["epsilon"] == \
        pytest.approx(0.3)
    assert P.levels_equal(back.to_level(), lv)


def test_level_to_scenario_inverse():
    s = load_named("ambush")
    lv = s.to_level(P.EnvConfig(max_allies=4, max_enemies=3, max_zones=5))
    back = level_to_scenario(lv, name="ambush", category="challenge")
    assert back.zones == s.zones
    assert [(u.unit, u.team, u.overrides) for u in back.units] == \
        [(u.unit, u.team, u.overrides) for u in s.units]
    # Exported values are the shortest decimals of the level's float32 values (readable files).
    assert back.units[0].position == (-19.446428, -10.833333)
    assert back.enemies[0].heading == 3.1415927
    assert back.physics is None and back.heuristic is None
    assert back.enemies[0].overrides == {"health": 800.0}
    assert P.levels_equal(back.to_level(), s.to_level())
    batch = P.stack_levels([lv, lv])
    with pytest.raises(ScenarioError, match="batch"):
        level_to_scenario(batch)


def test_level_to_scenario_heals_and_max_health():
    s = Scenario.from_dict(with_change("units.0.overrides", {"damage": -3, "heals": False,
                                                             "max_health": 90}))
    back = level_to_scenario(s.to_level())
    assert back.units[1].overrides == {"damage": -3.0, "heals": False, "max_health": 90.0}


def test_config_for_maxima():
    a, b = load_named("ambush"), load_named("5F1S1A1Dvs7F1S1D1H_2L2B2S")
    c = config_for([a, b], max_steps=100)
    assert (c.max_allies, c.max_enemies, c.max_zones, c.max_steps) == (8, 10, 6, 100)
    assert config_for([load_named("grid")]).max_zones == 0
    assert config_for([]).max_allies == 1


def test_zone_only_scenario_has_no_level():
    with pytest.raises(ScenarioError, match="zone-only"):
        load_named("2L").to_level()


# --- validation errors --------------------------------------------------------------------------

BAD = [
    ("format", "tabx/2", "format: expected 'tabx-scenario/1'"),
    ("name", "", "name: expected 1-100 characters"),
    ("category", "challenges", "category: expected one of .*did you mean 'challenge'"),
    ("colour", "red", "unknown key 'colour'"),
    ("units", KeyError, "missing required key 'units'"),
    ("units.0.unit", "farmr", r"units\[0\].unit: expected one of .*did you mean 'farmer'"),
    ("units.0.team", 1, r"units\[0\].team: expected one of ally, enemy"),
    ("units.0.position", [1, 2, 3], r"units\[0\].position: expected a pair"),
    ("units.0.position", [60, 0], r"units\[0\].position\[0\]: x=60 .*\|x\| <= width/2 - radius"),
    ("units.0.position", [0, -38.5], r"units\[0\].position\[1\]: y=-38.5 .*= 38\b"),
    ("units.0.position", ["a", 0], r"units\[0\].position\[0\]: expected a number, got 'a'"),
    ("units.0.position", [True, 0], r"units\[0\].position\[0\]: expected a number, got True"),
    ("units.0.heading", 0.5, r"units\[0\]: give either heading"),
    ("units.0.speedd", 1, r"units\[0\]: unknown key 'speedd'"),
    ("units.1.overrides.health", 0, r"units\[1\].overrides.health: expected a number in \(0, "),
    ("units.1.overrides.health", 51, r"units\[1\].overrides.health: health 51 exceeds max_health"),
    ("units.1.overrides.max_health", 2e5, r"max_health: expected a number in \(0, 100000\]"),
    ("units.1.overrides.speed", 11, r"overrides.speed: expected a number in \[0, 10\]"),
    ("units.1.overrides.damage", -1e5, r"overrides.damage: expected a number in \[-10000, 10000\]"),
    ("units.1.overrides.attack_range", 201, r"attack_range: expected a number in \[0, 200\]"),
    ("units.1.overrides.cooldown", 0, r"cooldown: expected a number in \(0, 1000\]"),
    ("units.1.overrides.radius", 25, r"radius: expected a number in \(0, 20\]"),
    ("units.1.overrides.mass", -1, r"mass: expected a number in \(0, 10000\]"),
    ("units.1.overrides.sight_angle", math.pi, r"sight_angle: expected a number in \(0, 3.14159\)"),
    ("units.1.overrides.heals", 1, r"overrides.heals: expected true or false"),
    ("units.1.overrides.hp", 1, r"unknown stat 'hp'"),
    ("units.0", "farmer", r"units\[0\]: expected an object"),
    ("units", [BASE["units"][1]], r"units: no enemy unit"),
    ("zones.0.type", "water", r"zones\[0\].type: expected one of lava, bush, swamp"),
    ("zones.0.semi_axes", [0, 1], r"semi_axes\[0\]: expected a semi-axis in \(0, 1000\]"),
    ("zones.0.effect", -1, r"zones\[0\].effect: expected a lava effect in \[0, 10000\]"),
    ("zones.0.centre", [0, 40], r"zones\[0\].centre\[1\]: centre outside"),
    ("zones", {}, r"zones: expected a list"),
    ("arena", {"width": 0, "height": 5}, r"arena.width: expected a number in \[1, 1000\]"),
    ("arena", {"width": 10}, r"arena: missing required key 'height'"),
    ("physics", "slow", r"physics: expected one of default, fast"),
    ("physics", {"dt": 0}, r"physics.dt: expected a number in \(0, 10\]"),
    ("heuristic", {"ally": "godlike"}, r"heuristic.ally: expected one of random, novice"),
    ("heuristic", {"both": "expert"}, r"heuristic: unknown key 'both'"),
    ("heuristic", {"enemy": {"epsilon": 2}}, r"heuristic.enemy.epsilon: expected .* \[0, 1\]"),
    ("split", "test", r"split: expected one of train, eval"),
]


@pytest.mark.parametrize("path,value,pattern", BAD, ids=[f"{p}={v!r}" for p, v, _ in BAD])
def test_validation_errors(path, value, pattern):
    with pytest.raises(ScenarioError, match=pattern) as err:
        Scenario.from_dict(with_change(path, value), source="my.json")
    assert str(err.value).startswith("my.json: ")
    assert isinstance(err.value, ValueError)


def test_position_bound_uses_the_overridden_radius():
    d = with_change("units.1.overrides", {"radius": 15})
    d["units"][1]["position"] = [-46, 0]
    with pytest.raises(ScenarioError, match=r"units\[1\].position\[0\]: .*radius 15.* = 45.5"):
        Scenario.from_dict(d)
    d["units"][1]["position"] = [-45.5, 24]
    Scenario.from_dict(d)  # on the boundary is inside


def test_swamp_effect_range_and_zone_only_files():
    d = with_change("zones.0", {"type": "swamp", "centre": [0, 0], "semi_axes": [1, 1],
                                "effect": 1.5})
    with pytest.raises(ScenarioError, match=r"swamp effect in \[0, 1\]"):
        Scenario.from_dict(d)
    Scenario.from_dict(with_change("units", []))  # zone-only
    Scenario.from_dict(with_change("zones", []))  # unit-only


def test_file_errors(tmp_path: Path):
    with pytest.raises(ScenarioError, match="cannot read file"):
        load_scenario(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"format": "tabx-scenario/1",\n "name": }')
    with pytest.raises(ScenarioError, match=r"bad.json: invalid JSON: .*line 2"):
        load_scenario(tmp_path / "bad.json")
    (tmp_path / "nan.json").write_text(json.dumps(with_change("units.0.heading_deg", 1))
                                       .replace(": 1", ": NaN", 1))
    with pytest.raises(ScenarioError, match="NaN is not allowed"):
        load_scenario(tmp_path / "nan.json")
    (tmp_path / "ref.json").write_text('{"zone_scenario": {}}')
    with pytest.raises(ScenarioError, match="reference-format"):
        load_scenario(tmp_path / "ref.json")


def test_stat_ranges_table_covers_defaults():
    for spec in C.UNIT_SPECS:
        for stat, rng in UNIT_STAT_RANGES.items():
            value = spec.health if stat == "max_health" else getattr(spec, stat)
            assert rng.contains(value), (spec.name, stat)


def test_code_built_scenario_validate():
    s = Scenario("x", units=(Unit("farmer", "ally", (0.0, 0.0)),
                             Unit("farmer", "enemy", (70.0, 0.0))))
    with pytest.raises(ScenarioError, match=r"units\[1\].position\[0\]"):
        s.validate()
    ok = Scenario("x", units=(Unit("farmer", "ally", (0.0, 0.0)),), zones=(Zone("bush", (0, 0),
                                                                                (1, 1)),))
    with pytest.raises(ScenarioError, match="no enemy"):
        ok.validate()


# --- registry -----------------------------------------------------------------------------------


def test_list_and_categories():
    assert len(list_scenarios("challenge")) == 13
    assert len(list_scenarios("units")) == 16
    assert len(list_scenarios("zones")) == 13
    assert "crossfire" in list_scenarios() and "void" in list_scenarios("zones")
    with pytest.raises(ScenarioError, match="unknown category"):
        list_scenarios("maps")


def test_composition():
    s = load_named("2F1M2Avs2S1K_2L2B2S")
    assert (len(s.allies), len(s.enemies), len(s.zones)) == (5, 3, 6)
    assert s.name == "2F1M2Avs2S1K_2L2B2S" and s.category == "units"
    e = load_named("5F1S1A1Dvs7F1S1D1H_2L2B2S-1")
    assert e.split == "eval" and e.zones == load_named("2L2B2S-1").zones
    plain = load_named("2F1M2Avs2S1K")
    assert plain.zones == () and plain.units == s.units
    assert load_named("2F1M2Avs2S1K_void").zones == ()


@pytest.mark.parametrize("name,pattern", [
    ("crossfire_2L", "challenge .*cannot take a zone suffix"),
    ("2F1M2Avs2S1K_2L_3B", "exactly one '_'"),
    ("crosfire", "unknown scenario 'crosfire'; close matches: crossfire"),
    ("2F1M2Avs2S1K_2LL", "unknown zone scenario of .*close matches: 2L"),
    ("2L_2F1M2Avs2S1K", "'2L' has no units"),
    ("2F1M2Avs2S1K_1F1M3A1Hvs2F1S1K1A1H", "has units: the part after '_' must be a zone"),
    ("nowhere/file.json", "no such scenario file"),
])
def test_named_errors(name, pattern):
    with pytest.raises(ScenarioError, match=pattern):
        load_named(name)


def test_user_dir_and_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    user = tmp_path / "mine"
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(user))
    assert user_scenario_dir() == user
    save_scenario(user / "duel.json", Scenario.from_dict(BASE))
    zone_only = Scenario.from_dict({**with_change("units", []), "name": "pond",
                                    "category": "zones"})
    save_scenario(user / "pond.json", zone_only)
    assert "duel" in list_scenarios() and "duel" in list_scenarios("user")
    assert "pond" in list_scenarios("zones") and "duel" not in list_scenarios("challenge")
    assert load_named("duel") == Scenario.from_dict(BASE)
    assert len(load_named("2F1M2Avs2S1K_pond").zones) == 1
    # a path, in our format or the reference one
    assert load_named(str(user / "duel.json")).name == "duel"
    # the editor's category folders are read too; the folder itself wins on a name clash
    save_scenario(user / "challenges" / "cave.json", Scenario.from_dict({**BASE, "name": "cave"}))
    save_scenario(user / "units" / "duel.json", Scenario.from_dict({**BASE, "name": "other"}))
    assert "cave" in list_scenarios() and load_named("cave").name == "cave"
    assert load_named("duel") == Scenario.from_dict(BASE)
    monkeypatch.delenv("TABX_SCENARIO_DIR")
    assert user_scenario_dir() == Path.home() / ".local/share/tabx/scenarios"


def test_bundled_files_load_from_package_resources(tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not the repo: loading must not depend on the cwd
    assert load_named("crossfire").category == "challenge"


# --- CLI ----------------------------------------------------------------------------------------


def test_cli_list(capsys):
    assert cli.main(["scenarios", "list", "--category", "challenge"]) == 0
    out = capsys.readouterr().out
    assert "crossfire" in out and "3 v 3" in out and "4L" in out
    assert "2F1M2Avs2S1K " not in out and len(out.splitlines()) == 1 + 13 + 1
    assert cli.main(["scenarios", "list"]) == 0
    out = capsys.readouterr().out
    assert "2L2B2S-1" in out and "eval" in out and "42 scenarios" in out


def test_cli_show(capsys):
    assert cli.main(["scenarios", "show", "ambush"]) == 0
    out = capsys.readouterr().out
    assert "2 v 1 units (2C vs 1K)" in out and "800*" in out and "bush" in out
    assert cli.main(["scenarios", "show", "2F1M2Avs2S1K_2L"]) == 0
    assert "lava" in capsys.readouterr().out
    assert cli.main(["scenarios", "show", "crossfire_2L"]) == 2
    assert "cannot take a zone suffix" in capsys.readouterr().err


def test_cli_validate(capsys, tmp_path: Path):
    good = save_scenario(tmp_path / "duel.json", Scenario.from_dict(BASE))
    assert cli.main(["scenarios", "validate", str(good)]) == 0
    assert capsys.readouterr().out.startswith("OK: duel (user): 1 v 1 units")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(with_change("units.1.overrides.health", -5)))
    assert cli.main(["scenarios", "validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "units[1].overrides.health" in err and "(0, 100000]" in err
    assert "Traceback" not in err


def test_docs_example_is_valid():
    doc = Path(__file__).resolve().parents[2] / "docs" / "scenarios.md"
    if not doc.is_file():
        pytest.skip("docs/scenarios.md not present")
    block = doc.read_text().split("```json\n", 1)[1].split("```", 1)[0]
    s = Scenario.from_dict(json.loads(block), source="docs/scenarios.md")
    assert s.name == "ambush" and len(s.zones) == 2 and s.heuristic["enemy"] == "expert"
    assert s.to_level() is not None
