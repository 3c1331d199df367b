"""Every bundled scenario equals the reference data it was converted from, compared as level
arrays built straight from the reference JSON columns (independently of our reader)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tabx import params as P
from tabx.scenarios import (
    ScenarioError,
    config_for,
    list_scenarios,
    load_file,
    load_named,
    read_reference_scenario,
)

REFERENCE = Path(__file__).resolve().parents[3] / "shared" / "reference" / "tabx-data"
SCENARIOS = REFERENCE / "scenarios"
pytestmark = pytest.mark.skipif(
    not REFERENCE.is_dir(),
    reason=f"reference data folder {REFERENCE} absent (only dev/CI machines have it)")

FOLDERS = {  # reference folder -> (our category, split)
    "challenges": ("challenge", None), "units": ("units", None), "zones": ("zones", None),
    "eval_scenarios/units": ("units", "eval"), "eval_scenarios/zones": ("zones", "eval"),
}
COUNTS = {"challenges": 13, "units": 4, "eval_scenarios/units": 12, "zones": 5,
          "eval_scenarios/zones": 8}


def reference_files() -> list[tuple[str, Path]]:
    if not SCENARIOS.is_dir():
        return []
    return [(folder, p) for folder in FOLDERS for p in sorted((SCENARIOS / folder).glob("*.json"))]


def expected_arrays(raw: dict, config: P.EnvConfig) -> dict[str, np.ndarray]:
    """Level arrays from the reference columns: allies to slots 0.., enemies to max_allies.."""
    u = P.empty_units(config)
    s = raw.get("scenario") or {}
    next_slot = {0: 0, 1: config.max_allies}
    for i in range(len(s.get("teams", []))):
        team = s["teams"][i][0]
        k = next_slot[team]
        next_slot[team] += 1
        u["unit_type"][k] = s["unit_ids"][i][0]
        u["position"][k] = s["positions"][i]
        u["heading"][k] = s["rotations"][i][0]
        u["health"][k] = u["max_health"][k] = s["healths"][i][0]
        u["speed"][k] = s["speeds"][i][0]
        u["damage"][k] = s["attack_damages"][i][0]
        u["attack_range"][k] = s["attack_ranges"][i][0]
        u["cooldown"][k] = s["attack_cooldowns"][i][0]
        u["radius"][k] = s["body_radiuss"][i][0]
        u["mass"][k] = s["body_weights"][i][0]
        u["sight_angle"][k] = s["sight_angles"][i][0]
        u["heals"][k] = s["attack_types"][i][0] == 1
        u["active"][k] = s["is_alive"][i][0] and not s["is_disabled"][i][0]
    z = P.empty_zones(config)
    zs = raw.get("zone_scenario") or {}
    for j in range(len(zs.get("zone_type", []))):
        z["zone_type"][j] = zs["zone_type"][j][0]
        z["centre"][j] = zs["position"][j]
        z["semi_axes"][j] = zs["axes"][j]
        z["effect"][j] = zs["effect_value"][j][0]
    grid = raw.get("grid_info", {"max_field_width": 121.0, "max_field_height": 78.0})
    arena = np.array([grid["max_field_width"], grid["max_field_height"]], np.float32)
    return {**u, **{f"zone_{k}": v for k, v in z.items()}, "arena_size": arena}


def level_arrays(level: P.EnvParams) -> dict[str, np.ndarray]:
    out = {k: np.asarray(v) for k, v in vars(level.units).items()}
    out.update({f"zone_{k}": np.asarray(v) for k, v in vars(level.zones).items()})
    out["arena_size"] = np.asarray(level.physics.arena_size)
    return out


def assert_arrays_match(got: dict, want: dict, label: str) -> None:
    assert set(got) == set(want)
    for key in want:
        g, w = got[key], want[key]
        assert g.shape == w.shape, (label, key)
        if g.dtype == bool or np.issubdtype(g.dtype, np.integer):
            np.testing.assert_array_equal(g, w, err_msg=f"{label}: {key}")
        else:  # float32 tolerance
            np.testing.assert_allclose(g, w.astype(np.float32), rtol=1e-6, atol=1e-6,
                                       err_msg=f"{label}: {key}")


def test_reference_file_counts():
    for folder, n in COUNTS.items():
        assert len(list((SCENARIOS / folder).glob("*.json"))) == n, folder


@pytest.mark.parametrize("folder,path", reference_files(),
                         ids=[f"{f}/{p.stem}" for f, p in reference_files()])
def test_bundled_equals_reference(folder: str, path: Path):
    raw = json.loads(path.read_text())
    category, split = FOLDERS[folder]
    bundled = load_named(path.stem)
    assert bundled.name == path.stem
    assert (bundled.category, bundled.split) == (category, split)
    assert bundled.physics is None and bundled.heuristic is None
    # Zone-only files are compared through a composition with a one-v-one unit stub.
    has_units = bool((raw.get("scenario") or {}).get("teams"))
    assert bool(bundled.units) == has_units
    assert category != "zones" or not has_units
    scenario = bundled if has_units else load_named(f"2F1M2Avs2S1K_{path.stem}")
    config = config_for([scenario])
    want = expected_arrays(raw, config)
    if not has_units:
        stub = expected_arrays(json.loads((SCENARIOS / "units/2F1M2Avs2S1K.json").read_text()),
                               config)
        want.update({k: v for k, v in stub.items() if not k.startswith("zone_")})
    assert_arrays_match(level_arrays(scenario.to_level(config)), want, path.name)
    # The reader gives the same scenario from the reference file itself.
    direct = read_reference_scenario(path)
    assert direct.units == bundled.units and direct.zones == bundled.zones
    assert direct.arena == bundled.arena and direct.split == split
    assert load_file(path).units == bundled.units


def test_every_bundled_scenario_comes_from_the_reference():
    names = {p.stem for _, p in reference_files()}
    assert set(list_scenarios(include_user=False)) == names
    assert len(names) == 42


def test_known_overrides_and_misnamed_files():
    assert load_named("ambush").enemies[0].overrides == {"health": 800.0}
    assert load_named("encirclement").enemies[0].overrides == {"damage": 39.0}
    overridden = [s.name for s in map(load_named, list_scenarios(include_user=False))
                  if any(u.overrides for u in s.units)]
    assert sorted(overridden) == ["ambush", "encirclement"]
    lie = load_named("2F1S1A1C1Dvs7F1S1D1H")  # holds 2F2S1A1C2D
    assert sorted(u.unit for u in lie.allies).count("assassin") == 2
    assert "2F2S1A1C2D" in (lie.description or "")
    lie = load_named("4F1S1A1Cvs7F1S1D1H")  # holds 4F1S2A1C
    assert sorted(u.unit for u in lie.allies).count("archer") == 2


def test_headings_kept_exactly():
    raw = json.loads((SCENARIOS / "challenges/superking.json").read_text())
    got = [u.heading for u in load_named("superking").units]
    assert got == [r[0] for r in raw["scenario"]["rotations"]]
    assert all(math.isfinite(h) for h in got)


def test_reference_reader_checks_pos_bounds(tmp_path: Path):
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    raw["scenario"]["pos_max"][0] = [10.0, 10.0]
    bad = tmp_path / "ambush.json"
    bad.write_text(json.dumps(raw))
    with pytest.raises(ScenarioError, match=r"pos_min .* pos_max .*row 0|row 0.*pos_max"):
        read_reference_scenario(bad)


def test_reference_reader_rejects_padding_and_bad_ids(tmp_path: Path):
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    raw["scenario"]["is_alive"][1] = [False]
    (tmp_path / "a.json").write_text(json.dumps(raw))
    with pytest.raises(ScenarioError, match="dead or disabled"):
        read_reference_scenario(tmp_path / "a.json")
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    raw["scenario"]["unit_ids"][0] = [9]
    (tmp_path / "b.json").write_text(json.dumps(raw))
    with pytest.raises(ScenarioError, match="unit_ids must be 0..8"):
        read_reference_scenario(tmp_path / "b.json")
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    del raw["scenario"]["speeds"]
    (tmp_path / "c.json").write_text(json.dumps(raw))
    with pytest.raises(ScenarioError, match="missing \\['speeds'\\]"):
        read_reference_scenario(tmp_path / "c.json")


def test_reference_reader_accepts_enemies_first(tmp_path: Path):
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    for column in raw["scenario"].values():  # [ally, ally, enemy] -> [enemy, ally, ally]
        column.insert(0, column.pop())
    (tmp_path / "rev.json").write_text(json.dumps(raw))
    s = read_reference_scenario(tmp_path / "rev.json")
    assert s.units[0].team == "enemy"
    a, b = s.to_level(), load_named("ambush").to_level()
    assert P.levels_equal(a, b)


def test_reference_healing_flag_override(tmp_path: Path):
    raw = json.loads((SCENARIOS / "challenges/ambush.json").read_text())
    raw["scenario"]["attack_types"][0] = [1]  # a cannon that heals despite positive damage
    (tmp_path / "h.json").write_text(json.dumps(raw))
    s = read_reference_scenario(tmp_path / "h.json")
    assert s.allies[0].overrides == {"heals": True}
    assert bool(np.asarray(s.to_level().units.heals)[0])


def test_cli_validate_reference_file(capsys):
    from tabx_ued import cli

    path = SCENARIOS / "eval_scenarios/zones/2L2B2S-1.json"
    assert cli.main(["scenarios", "validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("OK: 2L2B2S-1 (zones, eval)") and "zone-only" in out
