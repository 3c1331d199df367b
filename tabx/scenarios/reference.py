"""Reader for the reference implementation's scenario JSON (docs/differences.md).

A reference file has up to three top-level keys: `grid_info` (editor metadata; we take the arena
size from it), `scenario` (17 per-unit column lists, scalars wrapped as `[v]`) and
`zone_scenario`. `unit_ids` are 0-based indices into constants.UNIT_SPECS, `rotations` radians,
`attack_types` 1 = heals. `pos_min`/`pos_max` are derived in the reference from the arena and the
unit radius; we check them and drop them (our format derives bounds the same way). Allies and
enemies may come in any order here: the team column decides the slot.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from tabx import constants as C
from tabx.scenarios.format import (
    ARENA_RANGE,
    MAX_UNITS_PER_TEAM,
    MAX_ZONES,
    UNIT_STAT_RANGES,
    Scenario,
    ScenarioError,
    _number,
    read_json,
)

UNIT_COLUMNS = ("attack_cooldowns", "attack_damages", "attack_ranges", "attack_types",
                "body_radiuss", "body_weights", "healths", "is_alive", "is_disabled", "pos_max",
                "pos_min", "positions", "rotations", "sight_angles", "speeds", "teams", "unit_ids")
ZONE_COLUMNS = ("axes", "effect_value", "n_zone", "position", "zone_type")
GRID_KEYS = ("grid_width", "grid_height", "max_field_width", "max_field_height", "margin_width",
             "margin_height")
# Reference column -> our stat name.
STAT_COLUMNS = {"healths": "health", "speeds": "speed", "attack_damages": "damage",
                "attack_ranges": "attack_range", "attack_cooldowns": "cooldown",
                "body_radiuss": "radius", "body_weights": "mass", "sight_angles": "sight_angle"}
REFERENCE_CATEGORIES = {"challenges": "challenge", "units": "units", "zones": "zones"}
BOUND_TOL = 1e-4  # pos_min/pos_max are float32 arithmetic in the reference


def is_reference_format(data: Any) -> bool:
    """True for a parsed reference file (no `format` key, has `scenario` or `zone_scenario`)."""
    return isinstance(data, dict) and "format" not in data and bool(
        {"scenario", "zone_scenario"} & set(data))


def read_reference_scenario(path: str | os.PathLike, name: str | None = None,
                            category: str | None = None) -> Scenario:
    """Convert one reference-format file into a validated Scenario.

    `name` defaults to the file stem; `category` to the reference folder the file sits in
    (challenges/units/zones, with `split="eval"` under eval_scenarios/), else "user".
    """
    path = Path(path)
    data = read_json(path)
    parents = [p.name for p in path.parents][:3]
    if category is None:
        category = REFERENCE_CATEGORIES.get(path.parent.name, "user")
    split = "eval" if "eval_scenarios" in parents else None
    try:
        return reference_to_scenario(data, name or path.stem, category, split)
    except ScenarioError as err:
        raise err.with_source(str(path)) from None


def reference_to_scenario(data: Any, name: str, category: str = "user",
                          split: str | None = None) -> Scenario:
    """Convert a parsed reference object; the result goes through our validator."""
    if not isinstance(data, dict):
        raise ScenarioError(f"expected a reference scenario object, got {type(data).__name__}")
    unknown = set(data) - {"grid_info", "scenario", "zone_scenario"}
    if unknown:
        raise ScenarioError(f"unknown top-level keys {sorted(unknown)}; a reference file has "
                            "grid_info, scenario and zone_scenario")
    arena = _arena(data.get("grid_info"))
    units = _units(data.get("scenario") or {}, arena)
    zones = _zones(data.get("zone_scenario") or {})
    d: dict[str, Any] = {"format": "tabx-scenario/1", "name": name, "category": category,
                         "arena": {"width": arena[0], "height": arena[1]},
                         "units": units, "zones": zones}
    if split is not None:
        d["split"] = split
    return Scenario.from_dict(d)


def _arena(grid: Any) -> tuple[float, float]:
    if grid is None:
        return (C.ARENA_WIDTH, C.ARENA_HEIGHT)
    if not isinstance(grid, dict) or set(grid) - set(GRID_KEYS):
        raise ScenarioError(f"expected an object with keys {', '.join(GRID_KEYS)}", "grid_info")
    for key in GRID_KEYS:  # the editor's grid settings: not used, but must be numbers
        if key in grid:
            _number(grid[key], f"grid_info.{key}")
    return (_number(grid.get("max_field_width", C.ARENA_WIDTH), "grid_info.max_field_width",
                    ARENA_RANGE),
            _number(grid.get("max_field_height", C.ARENA_HEIGHT), "grid_info.max_field_height",
                    ARENA_RANGE))


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _column(s: dict, key: str, n: int, width: int, path: str) -> np.ndarray:
    boolean = key in ("is_alive", "is_disabled")
    rows = s[key]
    if boolean and not (isinstance(rows, list) and all(
            isinstance(r, list) and all(isinstance(v, bool) for v in r) for r in rows)):
        raise ScenarioError("expected rows of true/false values", f"{path}.{key}")
    if not boolean and not (isinstance(rows, list) and all(
            isinstance(r, list) and all(_is_number(v) for v in r) for r in rows)):
        raise ScenarioError("expected a list of rows of numbers, e.g. [[1.0], [2.5]]",
                            f"{path}.{key}")
    try:
        arr = np.asarray(rows, dtype=bool if boolean else np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ScenarioError("expected a list of numeric rows", f"{path}.{key}") from None
    if arr.shape != (n, width):
        raise ScenarioError(f"expected {n} rows of {width} value(s), got shape {arr.shape}",
                            f"{path}.{key}")
    if not boolean and not np.isfinite(arr).all():
        raise ScenarioError("expected finite numbers (null, NaN or infinity found)",
                            f"{path}.{key}")
    return arr


def _units(s: Any, arena: tuple[float, float]) -> list[dict[str, Any]]:
    if not isinstance(s, dict):
        raise ScenarioError("expected an object of per-unit columns", "scenario")
    missing = [k for k in UNIT_COLUMNS if k not in s]
    unknown = [k for k in s if k not in UNIT_COLUMNS]
    if unknown or (missing and s):
        raise ScenarioError(f"expected exactly the keys {', '.join(UNIT_COLUMNS)}; "
                            f"missing {missing}, unknown {unknown}", "scenario")
    if not s or not s["teams"]:
        return []
    if not isinstance(s["teams"], list):
        raise ScenarioError("expected a list", "scenario.teams")
    n = len(s["teams"])
    if n > 2 * MAX_UNITS_PER_TEAM:
        raise ScenarioError(f"at most {2 * MAX_UNITS_PER_TEAM} units, got {n}", "scenario.teams")
    col = {k: _column(s, k, n, 2 if k in ("positions", "pos_min", "pos_max") else 1, "scenario")
           for k in UNIT_COLUMNS}
    units = []
    for i in range(n):
        path = f"scenario[row {i}]"
        uid, team = col["unit_ids"][i, 0], col["teams"][i, 0]
        if uid != int(uid) or not 0 <= uid < C.NUM_UNIT_TYPES:
            raise ScenarioError(f"unit_ids must be 0..{C.NUM_UNIT_TYPES - 1}, got {uid:g}", path)
        if team not in (C.ALLY, C.ENEMY):
            raise ScenarioError(f"teams must be 0 (ally) or 1 (enemy), got {team:g}", path)
        if not col["is_alive"][i, 0] or col["is_disabled"][i, 0]:
            raise ScenarioError("dead or disabled units (is_alive false / is_disabled true) are "
                                "padding in the reference and cannot be converted", path)
        if col["attack_types"][i, 0] not in (0, 1):
            raise ScenarioError(f"attack_types must be 0 or 1, got {col['attack_types'][i, 0]:g}",
                                path)
        spec = C.UNIT_SPECS[int(uid)]
        overrides: dict[str, Any] = {}
        for column, stat in STAT_COLUMNS.items():
            value = float(col[column][i, 0])
            if np.float32(value) != np.float32(getattr(spec, stat)):
                overrides[stat] = value
        damage = overrides.get("damage", spec.damage)
        heals = bool(col["attack_types"][i, 0] == 1)
        if heals != (damage < 0):
            overrides["heals"] = heals
        _check_bounds(col, i, arena, overrides.get("radius", spec.radius), spec.radius, path)
        units.append({"unit": spec.name, "team": "ally" if team == C.ALLY else "enemy",
                      "position": [float(v) for v in col["positions"][i]],
                      "heading": float(col["rotations"][i, 0]), "overrides": overrides})
        if not overrides:
            del units[-1]["overrides"]
    return units


def _check_bounds(col: dict, i: int, arena: tuple[float, float], radius: float,
                  spec_radius: float, path: str) -> None:
    """pos_min/pos_max must be +-(arena/2 - radius); the editor used the spec radius (a bug), so
    either radius is accepted."""
    half = np.array(arena) / 2
    for r in (radius, spec_radius):
        if (np.allclose(col["pos_max"][i], half - r, atol=BOUND_TOL)
                and np.allclose(col["pos_min"][i], -(half - r), atol=BOUND_TOL)):
            return
    raise ScenarioError(
        f"pos_min {col['pos_min'][i].tolist()} / pos_max {col['pos_max'][i].tolist()} do not "
        f"match the arena {arena[0]:g} x {arena[1]:g} and radius {radius:g} (expected "
        f"+-{(half - radius).tolist()}); our format derives these bounds, so they must agree", path)


def _zones(z: Any) -> list[dict[str, Any]]:
    if not isinstance(z, dict):
        raise ScenarioError("expected an object", "zone_scenario")
    missing = [k for k in ZONE_COLUMNS if k not in z]
    unknown = [k for k in z if k not in ZONE_COLUMNS]
    if unknown or (missing and z):
        raise ScenarioError(f"expected exactly the keys {', '.join(ZONE_COLUMNS)}; "
                            f"missing {missing}, unknown {unknown}", "zone_scenario")
    if not z or not z["zone_type"]:
        return []
    if not isinstance(z["zone_type"], list):
        raise ScenarioError("expected a list", "zone_scenario.zone_type")
    n = len(z["zone_type"])
    if n > MAX_ZONES:
        raise ScenarioError(f"at most {MAX_ZONES} zones, got {n}", "zone_scenario.zone_type")
    types = _column(z, "zone_type", n, 1, "zone_scenario")
    centre = _column(z, "position", n, 2, "zone_scenario")
    axes = _column(z, "axes", n, 2, "zone_scenario")
    effect = _column(z, "effect_value", n, 1, "zone_scenario")
    # n_zone is never read by the reference env (and is max_n_zone for padded empty lists).
    zones = []
    for j in range(n):
        t = types[j, 0]
        if t not in (C.ZONE_LAVA, C.ZONE_BUSH, C.ZONE_SWAMP):
            raise ScenarioError(f"zone_type must be 1 (lava), 2 (bush) or 3 (swamp), got {t:g}",
                                f"zone_scenario[row {j}]")
        zones.append({"type": C.ZONE_NAMES[int(t)], "centre": [float(v) for v in centre[j]],
                      "semi_axes": [float(v) for v in axes[j]], "effect": float(effect[j, 0])})
    return zones


assert set(STAT_COLUMNS.values()) == set(UNIT_STAT_RANGES) - {"max_health"}
