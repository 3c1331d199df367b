"""Property tests: malformed input only ever raises ScenarioError; valid scenarios round-trip
through dicts, JSON and levels."""

from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx import params as P
from tabx.scenarios import (
    HEURISTIC_RANGES,
    UNIT_STAT_RANGES,
    ZONE_EFFECT_RANGES,
    Range,
    Scenario,
    ScenarioError,
    level_to_scenario,
    reference_to_scenario,
)

REFERENCE = Path(__file__).resolve().parents[3] / "shared" / "reference" / "tabx-data"
# TABX_HYPOTHESIS_EXAMPLES=2000 for a deeper run; the default keeps the file fast.
FAST = settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "60")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def f32floats(lo: float, hi: float, **kw) -> st.SearchStrategy:
    """float32-representable floats in [lo, hi] (bounds rounded inwards to float32)."""
    lo32, hi32 = np.float32(lo), np.float32(hi)
    # Compare as Python floats: under NEP 50 a float32 vs float comparison happens in float32.
    if float(lo32) < lo:
        lo32 = np.nextafter(lo32, np.float32(np.inf))
    if float(hi32) > hi:
        hi32 = np.nextafter(hi32, np.float32(-np.inf))
    return st.floats(float(lo32), float(hi32), allow_nan=False, width=32, **kw)


def in_range(rng: Range, lo: float | None = None, hi: float | None = None) -> st.SearchStrategy:
    """float32-representable values in a Range (levels hold float32)."""
    return f32floats(lo if lo is not None else rng.lo, hi if hi is not None else rng.hi,
                     exclude_min=rng.lo_open and lo is None, exclude_max=rng.hi_open and hi is None)


@st.composite
def unit_records(draw, team: str, arena: tuple[float, float]) -> dict:
    name = draw(st.sampled_from(C.UNIT_NAMES))
    spec = C.UNIT_SPECS[C.UNIT_TYPE_BY_NAME[name]]
    keys = draw(st.sets(st.sampled_from([k for k in UNIT_STAT_RANGES if k != "health"]
                                        + ["heals", "health"])))
    overrides: dict = {}
    for key in sorted(keys):
        if key == "heals":
            overrides[key] = draw(st.booleans())
        elif key == "radius":
            cap = min(20.0, min(arena) / 2 - 0.5)  # the unit must fit in the arena
            overrides[key] = draw(in_range(UNIT_STAT_RANGES[key], hi=cap))
        elif key != "health":
            overrides[key] = draw(in_range(UNIT_STAT_RANGES[key]))
    max_health = overrides.get("max_health")
    if "health" in keys or (max_health is not None and max_health < spec.health):
        cap = max_health if max_health is not None else UNIT_STAT_RANGES["health"].hi
        overrides["health"] = draw(in_range(UNIT_STAT_RANGES["health"], hi=cap))
    r = overrides.get("radius", spec.radius)
    hx, hy = arena[0] / 2 - r, arena[1] / 2 - r
    rec = {"unit": name, "team": team,
           "position": [draw(f32floats(-hx, hx)), draw(f32floats(-hy, hy))]}
    if draw(st.booleans()):
        rec["heading"] = draw(f32floats(-2 * math.pi, 2 * math.pi))
    if overrides:
        rec["overrides"] = overrides
    return rec


@st.composite
def zone_records(draw, arena: tuple[float, float]) -> dict:
    ztype = draw(st.sampled_from(sorted(ZONE_EFFECT_RANGES)))
    return {"type": ztype,
            "centre": [draw(f32floats(-arena[0] / 2, arena[0] / 2)),
                       draw(f32floats(-arena[1] / 2, arena[1] / 2))],
            "semi_axes": [draw(f32floats(0.1, 50)), draw(f32floats(0.1, 50))],
            "effect": draw(in_range(ZONE_EFFECT_RANGES[ztype]))}


tiers = st.sampled_from(sorted(P.HEURISTIC_TIERS)) | st.fixed_dictionaries(
    {}, optional={k: in_range(r) for k, r in HEURISTIC_RANGES.items()})


@st.composite
def scenario_dicts(draw) -> dict:
    arena = (draw(f32floats(20, 300)), draw(f32floats(20, 300)))
    units = ([draw(unit_records("ally", arena)) for _ in range(draw(st.integers(1, 4)))]
             + [draw(unit_records("enemy", arena)) for _ in range(draw(st.integers(1, 4)))])
    d = {"format": "tabx-scenario/1", "name": draw(st.from_regex(r"[a-z0-9][a-z0-9_.-]{0,8}",
                                                                 fullmatch=True)),
         "category": draw(st.sampled_from(["challenge", "units", "user"])),
         "arena": {"width": arena[0], "height": arena[1]},
         "units": draw(st.permutations(units)),  # any team order is valid
         "zones": [draw(zone_records(arena)) for _ in range(draw(st.integers(0, 3)))]}
    if draw(st.booleans()):
        d["physics"] = draw(st.sampled_from(["default", "fast"]) | st.fixed_dictionaries(
            {}, optional={"dt": f32floats(0.05, 2),
                          "restitution": f32floats(0, 1)}))
    if draw(st.booleans()):
        d["heuristic"] = draw(st.fixed_dictionaries({}, optional={"ally": tiers, "enemy": tiers}))
    return d


@FAST
@given(scenario_dicts())
def test_valid_scenarios_round_trip(d):
    s = Scenario.from_dict(d)
    assert Scenario.from_dict(s.to_dict()) == s
    assert Scenario.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    level = s.to_level()
    back = level_to_scenario(level, name=s.name)
    back.validate()  # an exported level is a valid scenario file
    assert P.levels_equal(back.to_level(), level)
    for u in back.units:  # values equal to the defaults (in float32) are never overrides
        spec = C.UNIT_SPECS[C.UNIT_TYPE_BY_NAME[u.unit]]
        for k, v in u.overrides.items():
            if k in UNIT_STAT_RANGES and k != "max_health":
                assert np.float32(v) != np.float32(getattr(spec, k)), (u.unit, k)
        if "max_health" in u.overrides:
            assert np.float32(u.overrides["max_health"]) != np.float32(u.stats()["health"])


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.text(max_size=8) | st.integers(), inner, max_size=4),
    max_leaves=20)


@FAST
@given(json_values)
def test_random_objects_raise_scenario_error(value):
    with pytest.raises(ScenarioError):
        Scenario.from_dict(value, source="fuzz.json")


def paths(obj, prefix=()):
    """Every (path) to a value inside nested dicts/lists."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from paths(v, (*prefix, i))


def mutate(data, draw):
    data = copy.deepcopy(data)
    target = draw(st.sampled_from(list(paths(data))[1:]))
    parent = data
    for k in target[:-1]:
        parent = parent[k]
    action = draw(st.sampled_from(["replace", "delete", "add"]))
    if action == "delete":
        del parent[target[-1]]
    elif action == "add" and isinstance(parent, dict):
        parent[draw(st.text(max_size=6))] = draw(json_values)
    else:
        parent[target[-1]] = draw(json_values)
    return data


@FAST
@given(st.data())
def test_mutated_scenarios_raise_only_scenario_error(data):
    d = mutate(data.draw(scenario_dicts()), data.draw)
    try:
        s = Scenario.from_dict(d)
    except ScenarioError:
        return
    try:  # still valid: it must also build a level (or say clearly why not)
        s.to_level()
    except ScenarioError:
        assert not s.units


@pytest.mark.skipif(not REFERENCE.is_dir(), reason=f"reference data {REFERENCE} absent")
@FAST
@given(st.data())
def test_mutated_reference_files_raise_only_scenario_error(data):
    name = data.draw(st.sampled_from(["challenges/ambush", "challenges/superking", "zones/3B"]))
    raw = json.loads((REFERENCE / "scenarios" / f"{name}.json").read_text())
    try:
        reference_to_scenario(mutate(raw, data.draw), "fuzzed")
    except ScenarioError:
        pass
