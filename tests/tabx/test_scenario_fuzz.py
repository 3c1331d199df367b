"""A fuzz corpus of malformed scenario files: each file is fed to `tabx scenarios
validate`, `show` and `render`; every one must end in a one-line `error:` naming the file (and the
field where there is one), a non-zero exit, no traceback, and the file unchanged on disk. A
hypothesis test mutates valid files (truncation, byte flips, repeated keys, extra nesting):
loading either succeeds or raises ScenarioError, nothing else.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx.scenarios import ScenarioError, load_file, load_named, load_scenario
from tabx.scenarios.format import MAX_DESCRIPTION, MAX_JSON_DEPTH, parse_json
from tabx_ued.cli import main as cli_main

BUNDLED = Path(__file__).resolve().parents[2] / "tabx" / "data" / "scenarios"
FUZZ = settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "60")),
                deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                      HealthCheck.data_too_large])


def duel(**top) -> dict:
    """A small valid scenario in our format."""
    doc = {
        "format": "tabx-scenario/1", "name": "duel", "category": "user",
        "units": [
            {"unit": "farmer", "team": "ally", "position": [-10.0, 0.0], "heading": 0.0,
             "overrides": {"health": 30.0, "max_health": 50.0}},
            {"unit": "archer", "team": "enemy", "position": [20.0, 0.0], "heading": math.pi},
        ],
        "zones": [{"type": "swamp", "centre": [0.0, 0.0], "semi_axes": [3.0, 2.0],
                   "effect": 0.5}],
    }
    doc.update(top)
    return doc


def reference_doc() -> dict:
    """A small valid file in the reference format: a farmer against an archer, one lava zone."""
    half = (C.ARENA_WIDTH / 2, C.ARENA_HEIGHT / 2)
    cols: dict[str, list] = {k: [] for k in (
        "attack_cooldowns", "attack_damages", "attack_ranges", "attack_types", "body_radiuss",
        "body_weights", "healths", "is_alive", "is_disabled", "pos_max", "pos_min", "positions",
        "rotations", "sight_angles", "speeds", "teams", "unit_ids")}
    for name, team, x in (("farmer", C.ALLY, -10.0), ("archer", C.ENEMY, 20.0)):
        uid = C.UNIT_TYPE_BY_NAME[name]
        spec = C.UNIT_SPECS[uid]
        for col, value in (("attack_cooldowns", spec.cooldown), ("attack_damages", spec.damage),
                           ("attack_ranges", spec.attack_range),
                           ("attack_types", int(spec.damage < 0)), ("body_radiuss", spec.radius),
                           ("body_weights", spec.mass), ("healths", spec.health),
                           ("is_alive", True), ("is_disabled", False), ("rotations", 0.0),
                           ("sight_angles", spec.sight_angle), ("speeds", spec.speed),
                           ("teams", team), ("unit_ids", uid)):
            cols[col].append([value])
        cols["positions"].append([x, 0.0])
        cols["pos_max"].append([half[0] - spec.radius, half[1] - spec.radius])
        cols["pos_min"].append([-(half[0] - spec.radius), -(half[1] - spec.radius)])
    zones = {"axes": [[3.0, 2.0]], "effect_value": [[10.0]], "n_zone": [1],
             "position": [[0.0, 5.0]], "zone_type": [[C.ZONE_LAVA]]}
    return {"scenario": cols, "zone_scenario": zones}


def text(doc) -> bytes:
    return json.dumps(doc).encode()


def unit0(**change) -> dict:
    """duel() with units[0] changed (a key set to None is removed)."""
    doc = duel()
    rec = dict(doc["units"][0])
    for key, value in change.items():
        if value is None:
            rec.pop(key, None)
        else:
            rec[key] = value
    doc["units"][0] = rec
    return doc


def overrides0(**stats) -> dict:
    return unit0(overrides={**duel()["units"][0]["overrides"], **stats})


def nested(depth: int, inner: str = "1") -> str:
    return "[" * depth + inner + "]" * depth


CROSSFIRE = (BUNDLED / "challenges" / "crossfire.json").read_bytes()
DUEL = text(duel())

# name -> (file content, a regex the error line must match beyond the file name)
CORPUS: dict[str, tuple[bytes, str]] = {
    # damaged files
    "truncated-half": (CROSSFIRE[: len(CROSSFIRE) // 2], r"invalid JSON"),
    "truncated-end": (CROSSFIRE.rstrip()[:-1], r"truncated"),
    "truncated-in-string": (CROSSFIRE[: CROSSFIRE.index(b"crossfire") + 4], r"invalid JSON"),
    "binary": (bytes(range(256)) * 4, r"not UTF-8"),
    "binary-nul": (b"\x00" * 64, r"invalid JSON"),
    "latin1": ('{"format": "tabx-scenario/1", "name": "caf\u00e9"}'.encode("latin-1"),
               r"not UTF-8"),
    "empty": (b"", r"empty file"),
    "whitespace": (b" \n\t\r\n", r"empty file"),
    "not-json": (b"format = 'tabx-scenario/1'\n", r"invalid JSON"),
    "trailing-garbage": (DUEL + b"}", r"invalid JSON"),
    # nesting
    "deep-arrays": (nested(100_000).encode(), r"nested deeper than 32"),
    "deep-objects": (('{"a":' * 5000 + "1" + "}" * 5000).encode(), r"nested deeper than 32"),
    "deep-in-unit": (DUEL.replace(b'"heading": 0.0', b'"heading": ' + nested(40).encode(), 1),
                     r"units\[0\]\.heading.*nested deeper"),
    "deep-unbalanced": (b"[" * 50_000, r"nested deeper than 32"),
    # repeated keys
    "duplicate-top": (DUEL.replace(b'"name": "duel"', b'"name": "duel", "name": "duel2"'),
                      r"name: key 'name' appears twice"),
    "duplicate-team": (DUEL.replace(b'"team": "ally"', b'"team": "ally", "team": "enemy"'),
                       r"units\[0\]\.team: key 'team' appears twice"),
    "duplicate-override": (DUEL.replace(b'"health": 30.0', b'"health": 30.0, "health": 40.0'),
                           r"units\[0\]\.overrides\.health: key 'health' appears twice"),
    "duplicate-escaped": (DUEL.replace(b'"category": "user"',
                                       b'"category": "user", "c\\u0061tegory": "user"'),
                          r"category: key 'category' appears twice"),
    # wrong types
    "top-list": (b"[1, 2, 3]", r"expected an object"),
    "top-string": (b'"crossfire"', r"expected an object"),
    "format-wrong": (text(duel(format="tabx-scenario/2")), r"format: expected 'tabx-scenario/1'"),
    "name-number": (text(duel(name=5)), r"name: expected a string"),
    "name-long": (text(duel(name="a" * 300)), r"name: expected 1-100 characters"),
    "units-object": (text(duel(units={})), r"units: expected a list"),
    "zones-null": (text(duel(zones=None)), r"zones: expected a list"),
    "position-string": (text(unit0(position="0,0")), r"units\[0\]\.position: expected a list"),
    "position-triple": (text(unit0(position=[0, 0, 0])), r"units\[0\]\.position: expected a pair"),
    "heading-bool": (text(unit0(heading=True)), r"units\[0\]\.heading: expected radians"),
    "stat-string": (text(overrides0(health="30")), r"units\[0\]\.overrides\.health: expected"),
    "stat-list": (text(overrides0(speed=[1.0])), r"units\[0\]\.overrides\.speed: expected"),
    "heals-int": (text(overrides0(heals=1)), r"units\[0\]\.overrides\.heals: expected true"),
    "overrides-list": (text(unit0(overrides=[])), r"units\[0\]\.overrides: expected an object"),
    "arena-list": (text(duel(arena=[100, 50])), r"arena: expected an object"),
    "description-number": (text(duel(description=7)), r"description: expected a string"),
    "description-long": (text(duel(description="x" * (MAX_DESCRIPTION + 1))),
                         rf"description: expected at most {MAX_DESCRIPTION} characters"),
    "missing-units": (text({k: v for k, v in duel().items() if k != "units"}),
                      r"missing required key 'units'"),
    "unknown-top-key": (text(duel(unitz=[])), r"unknown key 'unitz'"),
    # NaN and infinities
    "nan-stat": (DUEL.replace(b'"health": 30.0', b'"health": NaN'),
                 r"units\[0\]\.overrides\.health: NaN is not allowed"),
    "infinity-position": (DUEL.replace(b"[-10.0, 0.0]", b"[-10.0, Infinity]"),
                          r"units\[0\]\.position\[1\]: Infinity is not allowed"),
    "minus-infinity-zone": (DUEL.replace(b'"effect": 0.5', b'"effect": -Infinity'),
                            r"zones\[0\]\.effect: -Infinity is not allowed"),
    "overflow-float": (DUEL.replace(b'"health": 30.0', b'"health": 1e999'),
                       r"units\[0\]\.overrides\.health: expected a finite number"),
    "huge-int": (DUEL.replace(b'"health": 30.0', b'"health": ' + b"9" * 400),
                 r"units\[0\]\.overrides\.health: expected a number in"),
    "giant-int": (DUEL.replace(b'"health": 30.0', b'"health": ' + b"9" * 5000),
                  r"invalid JSON"),
    # out-of-range counts
    "too-many-units": (text(duel(units=[{"unit": "farmer", "team": team, "position": [0, 0]}
                                        for team in ["ally", "enemy"] * 101])),
                       r"units: at most 200 units"),
    "too-many-allies": (text(duel(units=[{"unit": "farmer", "team": "ally", "position": [0, 0]}
                                         ] * 101 + [{"unit": "farmer", "team": "enemy",
                                                     "position": [0, 0]}])),
                        r"units: at most 100 ally units"),
    "too-many-zones": (text(duel(zones=[{"type": "bush", "centre": [0, 0],
                                         "semi_axes": [1, 1]}] * 65)),
                       r"zones: at most 64 zones"),
    "no-enemy": (text(duel(units=duel()["units"][:1])), r"units: no enemy unit"),
    # out-of-range stats and places
    "health-negative": (text(overrides0(health=-5)), r"units\[0\]\.overrides\.health: .*-5"),
    "health-over-max": (text(overrides0(health=60.0)), r"exceeds max_health"),
    "speed-high": (text(overrides0(speed=11)), r"units\[0\]\.overrides\.speed: .*\[0, 10\]"),
    "radius-zero": (text(overrides0(radius=0)), r"units\[0\]\.overrides\.radius"),
    "sight-pi": (text(overrides0(sight_angle=math.pi)), r"overrides\.sight_angle"),
    "unknown-stat": (text(overrides0(helth=3)), r"unknown stat 'helth' \(did you mean 'health'"),
    "position-outside": (text(unit0(position=[70.0, 0.0])), r"units\[0\]\.position\[0\]"),
    "heading-deg-range": (text(unit0(heading=None, heading_deg=1000)), r"heading_deg"),
    "arena-zero": (text(duel(arena={"width": 0, "height": 78})), r"arena\.width"),
    "swamp-effect": (text(duel(zones=[{"type": "swamp", "centre": [0, 0], "semi_axes": [1, 1],
                                       "effect": 2.0}])), r"zones\[0\]\.effect"),
    "semi-axis-negative": (text(duel(zones=[{"type": "lava", "centre": [0, 0],
                                             "semi_axes": [-1, 1]}])),
                           r"zones\[0\]\.semi_axes\[0\]"),
    # unknown unit and zone types
    "unknown-unit": (text(unit0(unit="farmr")), r"units\[0\]\.unit: .*did you mean 'farmer'"),
    "unit-type-number": (text(unit0(unit=3)), r"units\[0\]\.unit: expected one of"),
    "unknown-team": (text(unit0(team="allies")), r"units\[0\]\.team"),
    "unknown-zone": (text(duel(zones=[{"type": "water", "centre": [0, 0],
                                       "semi_axes": [1, 1]}])), r"zones\[0\]\.type"),
    "unknown-physics": (text(duel(physics="warp")), r"physics: expected one of"),
    "unknown-tier": (text(duel(heuristic={"ally": "godlike"})), r"heuristic\.ally"),
}


def _reference_corpus() -> dict[str, tuple[bytes, str]]:
    """Damaged files in the reference format."""
    out: dict[str, tuple[bytes, str]] = {}

    def case(name: str, pattern: str, edit) -> None:
        doc = reference_doc()
        edit(doc)
        out[name] = (text(doc), pattern)

    case("ref-stat-strings", r"scenario\.healths: expected a list of rows of numbers",
         lambda d: d["scenario"].update(healths=[["100"], ["100"]]))
    case("ref-stat-bool", r"scenario\.speeds: expected a list of rows of numbers",
         lambda d: d["scenario"].update(speeds=[[True], [True]]))
    case("ref-short-column", r"scenario\.rotations: expected 2 rows",
         lambda d: d["scenario"].update(rotations=[[0.0]]))
    case("ref-unknown-unit", r"unit_ids must be",
         lambda d: d["scenario"].update(unit_ids=[[0], [42]]))
    case("ref-unknown-zone", r"zone_type must be",
         lambda d: d["zone_scenario"].update(zone_type=[[7]]))
    case("ref-missing-column", r"scenario: expected exactly the keys",
         lambda d: d["scenario"].pop("speeds"))
    case("ref-grid-string", r"grid_info\.max_field_width: expected a number",
         lambda d: d.update(grid_info={"max_field_width": "121"}))
    case("ref-negative-health", r"health",
         lambda d: d["scenario"].update(healths=[[-1.0], [100.0]]))
    doc = text(reference_doc())
    out["ref-nan"] = (doc.replace(b"[[0.0], [0.0]]", b"[[NaN], [0.0]]", 1),
                      r"scenario\.rotations\[0\]\[0\]: NaN is not allowed")
    out["ref-duplicate"] = (doc.replace(b'"scenario": {', b'"scenario": {"teams": [], ', 1),
                            r"scenario\.teams: key 'teams' appears twice")
    return out


CORPUS.update(_reference_corpus())


@pytest.fixture(autouse=True)
def empty_user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(tmp_path / "user-scenarios"))


def test_corpus_templates_are_valid(tmp_path: Path):
    """The corpus damages valid files: the undamaged ones load."""
    for name, doc in (("duel.json", duel()), ("ref.json", reference_doc())):
        (tmp_path / name).write_bytes(text(doc))
        scenario = load_file(tmp_path / name)
        assert len(scenario.allies) == 1 and len(scenario.enemies) == 1
    assert load_named(str(BUNDLED / "challenges" / "crossfire.json")).name == "crossfire"


@pytest.mark.parametrize("case", sorted(CORPUS))
def test_damaged_file_is_one_clear_error_in_every_command(case: str, tmp_path: Path, capsys):
    content, pattern = CORPUS[case]
    path = tmp_path / f"{case}.json"
    path.write_bytes(content)
    before = (path.read_bytes(), path.stat().st_mtime_ns)
    out_png = tmp_path / "out.png"
    commands = (["scenarios", "validate", str(path)], ["scenarios", "show", str(path)],
                ["scenarios", "render", str(path), "--out", str(out_png)])
    for argv in commands:
        code = cli_main(argv)
        captured = capsys.readouterr()
        lines = [line for line in captured.err.splitlines() if line.strip()]
        assert code != 0, (argv, captured)
        assert "Traceback" not in captured.err + captured.out, argv
        assert len(lines) == 1, (argv, captured.err[:2000])
        assert lines[0].startswith("tabx scenarios: error: "), lines[0][:300]
        assert str(path) in lines[0], lines[0][:300]
        assert re.search(pattern, lines[0]), (argv, pattern, lines[0][:500])
        assert len(lines[0]) < 2000, "the error line echoes too much of the file"
        assert (path.read_bytes(), path.stat().st_mtime_ns) == before, "the file was changed"
        assert not out_png.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_unreadable_paths(tmp_path: Path, capsys):
    folder = tmp_path / "folder.json"
    folder.mkdir()
    for target, pattern in ((folder, r"cannot read file"),
                            (tmp_path / "missing.json", r"cannot read file")):
        assert cli_main(["scenarios", "validate", str(target)]) != 0
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err
        assert str(target) in err and re.search(pattern, err), err
    assert cli_main(["scenarios", "show", str(folder)]) != 0
    err = capsys.readouterr().err
    assert "no such scenario file" in err and str(folder) in err


def test_depth_limit_is_exact():
    """MAX_JSON_DEPTH levels parse (and fail in the validator); one more is refused."""
    assert parse_json(nested(MAX_JSON_DEPTH - 1, "[]")) is not None
    with pytest.raises(ScenarioError, match=r"^x\.json: \[0\]\[0\].*nested deeper than 32"):
        parse_json(nested(MAX_JSON_DEPTH, "[]"), "x.json")
    # Brackets inside strings do not count.
    assert parse_json(json.dumps({"s": "[" * 1000 + "{" * 1000})) == {"s": "[" * 1000 + "{" * 1000}


def test_duplicate_key_position_is_reported():
    doc = '{\n  "a": {"b": 1,\n        "b": 2}\n}'
    with pytest.raises(ScenarioError, match=r"f: a\.b: key 'b' appears twice .*line 3, column"):
        parse_json(doc, "f")
    # Repeated keys in different objects are fine.
    assert parse_json('[{"a": 1}, {"a": 2}]') == [{"a": 1}, {"a": 2}]


def test_bom_is_accepted(tmp_path: Path):
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + DUEL)
    assert load_scenario(path).name == "duel"


# --- hypothesis: mutations of valid files ------------------------------------------------------

BASES = {
    "crossfire": CROSSFIRE,
    "units": (BUNDLED / "units" / "2F1M2Avs2S1K.json").read_bytes(),
    "zones": (BUNDLED / "zones" / "1S.json").read_bytes(),
    "duel": json.dumps(duel(description="a [test] {file}"), indent=1).encode(),
    "reference": json.dumps(reference_doc(), indent=1).encode(),
}
KEY = re.compile(rb'"([A-Za-z_]+)"\s*:')


@st.composite
def mutated(draw) -> tuple[bytes, str]:
    base = BASES[draw(st.sampled_from(sorted(BASES)))]
    kind = draw(st.sampled_from(["truncate", "flip", "duplicate", "splice", "nest"]))
    data = bytearray(base)
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, len(data) - 1))]), kind
    if kind == "flip":
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] = draw(st.sampled_from([data[i] ^ 0x01, data[i] ^ 0x80, ord("["), ord("}"),
                                            ord('"'), ord(","), ord("N"), 0, 0xFF]))
        return bytes(data), kind
    if kind == "duplicate":  # repeat a key in its own object, just before the key
        m = draw(st.sampled_from(list(KEY.finditer(base))))
        value = draw(st.sampled_from([b"0", b'"x"', b"null", b"[]", b"{}"]))
        return base[: m.start()] + m.group(0) + b" " + value + b", " + base[m.start():], kind
    if kind == "splice":  # a random byte string somewhere
        i = draw(st.integers(0, len(data)))
        return base[:i] + draw(st.binary(min_size=1, max_size=16)) + base[i:], kind
    # nest: wrap a value in many brackets
    m = draw(st.sampled_from(list(KEY.finditer(base))))
    depth = draw(st.integers(1, 3 * MAX_JSON_DEPTH))
    end = m.end()
    return base[:end] + b"[" * depth + b"0" + b"]" * depth + b"," + base[end:], kind


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@FUZZ
@given(mutated())
def test_mutated_files_load_or_raise_scenario_error(fuzz_dir: Path, case: tuple[bytes, str]):
    content, kind = case
    path = fuzz_dir / "mutant.json"
    path.write_bytes(content)
    for load in (load_file, lambda p: load_named(str(p))):
        try:
            load(path)
        except ScenarioError as err:
            assert str(path) in str(err)
            if kind == "duplicate":
                assert "appears twice" in str(err)
        else:
            assert kind != "duplicate", "a repeated key was accepted"
    assert path.read_bytes() == content


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=4),
    max_leaves=20)


@FUZZ
@given(JSON_VALUES, st.booleans())
def test_strict_reader_agrees_with_json_on_valid_documents(value, indent: bool):
    """No false alarms: any JSON without NaN, repeated keys or deep nesting reads as json reads
    it (strings full of brackets, quotes and escapes included)."""
    doc = json.dumps(value, indent=1 if indent else None, ensure_ascii=not indent)
    assert parse_json(doc) == json.loads(doc)
