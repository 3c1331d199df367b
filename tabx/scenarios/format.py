"""Our scenario file format (`tabx-scenario/1`): the `Scenario` dataclass, an explicit validator,
JSON load/save and conversion to and from levels (`EnvParams`).

The validator is table driven: `UNIT_STAT_RANGES`, `ZONE_EFFECT_RANGES`, `ARENA_RANGE`,
`PHYSICS_RANGES` and `HEURISTIC_RANGES` are plain data so that the scenario editor can enforce
the same ranges. Every problem is a `ScenarioError` naming the file, the field path
(`units[3].overrides.health`) and what was expected. Files are read with a strict JSON reader
(`read_json` / `parse_json`): no NaN/Infinity, no key repeated in an object, at most
MAX_JSON_DEPTH levels of nesting (checked before parsing), UTF-8, at most MAX_FILE_BYTES. See
docs/scenarios.md.
"""

from __future__ import annotations

import codecs
import difflib
import json
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tabx import constants as C
from tabx import params as P
from tabx.errors import UserError
from tabx.files import atomic_write_text

FORMAT = "tabx-scenario/1"
CATEGORIES = ("challenge", "units", "zones", "user")
SPLITS = ("train", "eval")
TEAMS = ("ally", "enemy")
ZONE_TYPES = ("lava", "bush", "swamp")
MAX_UNITS_PER_TEAM = 100  # far above any real scenario; guards against runaway files
MAX_ZONES = 64
# Always `fullmatch`: with `match`, `$` also matches before a final newline ("name\n"). The
# editor page uses the same pattern in JavaScript, where `$` ends the string.
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}$")
MAX_DESCRIPTION = 4000  # characters of the free-text description
MAX_JSON_DEPTH = 32  # nested arrays and objects; a scenario file nests 4 (an editor request 5)
MAX_FILE_BYTES = 8 * 1024 * 1024  # a scenario file is a few KiB; refuse to read more than this


class ScenarioError(UserError, ValueError):
    """A scenario that cannot be read: names the source file, the field path and the problem."""

    def __init__(self, message: str, path: str = "", source: str | None = None) -> None:
        self.message, self.path, self.source = message, path, source
        super().__init__(self._text())

    def _text(self) -> str:
        where = ": ".join(p for p in (self.source, self.path) if p)
        return f"{where}: {self.message}" if where else self.message

    def with_source(self, source: str | None) -> ScenarioError:
        """The same error attributed to a file (kept if it already names one)."""
        if self.source or not source:
            return self
        return ScenarioError(self.message, self.path, source)


@dataclass(frozen=True)
class Range:
    """A closed or open numeric interval, e.g. `(0, 1e5]`."""

    lo: float
    hi: float
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, value: float) -> bool:
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def __str__(self) -> str:
        left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
        return f"{left}{self.lo:.6g}, {self.hi:.6g}{right}"


# --- the field table (also used by the editor) -------------------------------------------------

UNIT_STAT_RANGES: dict[str, Range] = {
    "health": Range(0.0, 1e5, lo_open=True),  # and <= max_health
    "max_health": Range(0.0, 1e5, lo_open=True),
    "speed": Range(0.0, 10.0),
    "damage": Range(-1e4, 1e4),  # negative heals
    "attack_range": Range(0.0, 200.0),
    "cooldown": Range(0.0, 1000.0, lo_open=True),
    "radius": Range(0.0, 20.0, lo_open=True),
    "mass": Range(0.0, 1e4, lo_open=True),
    # Exclusive pi: the field-of-view test compares against cos(sight_angle / 2) and needs < pi.
    "sight_angle": Range(0.0, math.pi, lo_open=True, hi_open=True),
}
UNIT_BOOL_FIELDS = ("heals",)  # defaults to damage < 0
UNIT_OVERRIDE_FIELDS = (*UNIT_STAT_RANGES, *UNIT_BOOL_FIELDS)
HEADING_RANGE = Range(-4 * math.pi, 4 * math.pi)
ARENA_RANGE = Range(1.0, 1000.0)  # width and height
SEMI_AXIS_RANGE = Range(0.0, 1000.0, lo_open=True)
ZONE_EFFECT_RANGES: dict[str, Range] = {
    "lava": Range(0.0, 1e4),  # health lost per second
    "bush": Range(0.0, 1e4),  # unused by the dynamics; the reference files write 0
    "swamp": Range(0.0, 1.0),  # slow fraction: speed * (1 - effect)
}
PHYSICS_RANGES: dict[str, Range] = {
    "dt": Range(0.0, 10.0, lo_open=True),
    "percent": Range(0.0, 1.0),
    "slop": Range(0.0, 1.0),
    "restitution": Range(0.0, 1.0),
    "boundary_damage_rate": Range(0.0, 10.0),
    "turn_rate": Range(0.0, 2 * math.pi, lo_open=True),
}
HEURISTIC_RANGES: dict[str, Range] = {
    "epsilon": Range(0.0, 1.0),
    "aggressive_threshold": Range(0.0, 1.0),
    "healer_aggressive_threshold": Range(0.0, 1.0),
    "assassin_speed": Range(0.0, 10.0),
    "ranger_attack_range": Range(0.0, 200.0),
}
START_NOISE_RANGE = Range(0.0, 1000.0)  # world units; randomised starts (tabx.starts)
TOP_KEYS = ("format", "name", "category", "split", "description", "arena", "units", "zones",
            "physics", "heuristic", "start_noise", "shuffle_positions")
UNIT_KEYS = ("unit", "team", "position", "heading", "heading_deg", "overrides")
ZONE_KEYS = ("type", "centre", "semi_axes", "effect")


# --- dataclasses -------------------------------------------------------------------------------

Physics = str | dict[str, Any] | None
Heuristic = dict[str, Any] | None


@dataclass(frozen=True)
class Unit:
    """One unit: its type name, team, position, heading (radians) and non-default stats."""

    unit: str
    team: str
    position: tuple[float, float]
    heading: float = 0.0
    overrides: dict[str, Any] = field(default_factory=dict)

    def stats(self) -> dict[str, Any]:
        """All effective stats (type defaults with overrides applied), as make_level sees them."""
        spec = C.UNIT_SPECS[C.UNIT_TYPE_BY_NAME[self.unit]]
        s: dict[str, Any] = {k: getattr(spec, k) for k in UNIT_STAT_RANGES if k != "max_health"}
        s.update({k: v for k, v in self.overrides.items() if k != "max_health"})
        s["max_health"] = self.overrides.get("max_health", s["health"])
        s["heals"] = bool(self.overrides.get("heals", s["damage"] < 0))
        return s

    def record(self) -> dict[str, Any]:
        """The record params.make_level takes."""
        return {"unit": self.unit, "position": tuple(self.position), "heading": self.heading,
                **self.overrides}


@dataclass(frozen=True)
class Zone:
    """An axis-aligned elliptic zone."""

    type: str
    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    effect: float = 0.0


@dataclass(frozen=True)
class Scenario:
    """A scenario: units and zones in an arena, with optional physics and opponent settings."""

    name: str
    category: str = "user"
    units: tuple[Unit, ...] = ()
    zones: tuple[Zone, ...] = ()
    arena: tuple[float, float] = (C.ARENA_WIDTH, C.ARENA_HEIGHT)
    physics: Physics = None
    heuristic: Heuristic = None
    description: str | None = None
    split: str | None = None  # "eval" for the reference's held-out scenarios
    start_noise: float = 0.0  # randomised starts (tabx.starts); the paper's starts are fixed
    shuffle_positions: bool = False

    @property
    def allies(self) -> list[Unit]:
        return [u for u in self.units if u.team == "ally"]

    @property
    def enemies(self) -> list[Unit]:
        return [u for u in self.units if u.team == "enemy"]

    @property
    def playable(self) -> bool:
        return bool(self.allies) and bool(self.enemies)

    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> Scenario:
        """Validate a parsed JSON object; raises ScenarioError naming `source` and the field."""
        try:
            return _parse(data)
        except ScenarioError as err:
            raise err.with_source(source) from None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"format": FORMAT, "name": self.name, "category": self.category}
        if self.split is not None:
            out["split"] = self.split
        if self.description is not None:
            out["description"] = self.description
        out["arena"] = {"width": self.arena[0], "height": self.arena[1]}
        out["units"] = []
        for u in self.units:
            rec: dict[str, Any] = {"unit": u.unit, "team": u.team, "position": list(u.position),
                                   "heading": u.heading}
            if u.overrides:
                rec["overrides"] = dict(u.overrides)
            out["units"].append(rec)
        out["zones"] = [{"type": z.type, "centre": list(z.centre), "semi_axes": list(z.semi_axes),
                         "effect": z.effect} for z in self.zones]
        if self.physics is not None:
            out["physics"] = self.physics if isinstance(self.physics, str) else dict(self.physics)
        if self.heuristic is not None:
            out["heuristic"] = {k: v if isinstance(v, str) else dict(v)
                                for k, v in self.heuristic.items()}
        if self.start_noise:
            out["start_noise"] = self.start_noise
        if self.shuffle_positions:
            out["shuffle_positions"] = True
        return out

    def validate(self) -> Scenario:
        """Re-check a Scenario built in code (round trip through the dict validator)."""
        return Scenario.from_dict(self.to_dict(), source=f"scenario {self.name!r}")

    def to_level(self, config: P.EnvConfig | None = None, heuristic: Any = None,
                 physics: Any = None, reward_mode: int = C.REWARD_MEAN_OF_RATIOS) -> P.EnvParams:
        """The padded level for `config` (None: the tightest config for this scenario).

        `heuristic` / `physics` replace the scenario's own settings: a HeuristicParams or a
        {"ally": tier, "enemy": tier} mapping; a PhysicsParams, preset name or dict. The arena
        size always comes from the scenario.
        """
        if not self.units:
            raise ScenarioError("has no units (a zone-only scenario): compose it with a unit "
                                "scenario, e.g. load_named('2F1M2Avs2S1K_" + self.name + "')",
                                source=f"scenario {self.name!r}")
        config = config if config is not None else config_for([self])
        counts = (("allies", len(self.allies), config.max_allies),
                  ("enemies", len(self.enemies), config.max_enemies),
                  ("zones", len(self.zones), config.max_zones))
        for what, n, limit in counts:
            if n > limit:
                raise ScenarioError(f"{n} {what} do not fit EnvConfig.max_{what}={limit}",
                                    source=f"scenario {self.name!r}")
        return P.make_level(
            config,
            [u.record() for u in self.allies],
            [u.record() for u in self.enemies],
            [{"type": z.type, "centre": z.centre, "semi_axes": z.semi_axes, "effect": z.effect}
             for z in self.zones],
            heuristic=_heuristic_params(heuristic if heuristic is not None else self.heuristic),
            physics=_physics_params(physics if physics is not None else self.physics, self.arena),
            reward_mode=reward_mode,
            start_noise=self.start_noise,
            shuffle_positions=self.shuffle_positions,
        )


def config_for(scenarios: Iterable[Scenario], max_steps: int = C.DEFAULT_MAX_STEPS) -> P.EnvConfig:
    """The smallest EnvConfig that fits every scenario (at least one slot per team)."""
    scenarios = list(scenarios)
    return P.EnvConfig(
        max_allies=max([1, *(len(s.allies) for s in scenarios)]),
        max_enemies=max([1, *(len(s.enemies) for s in scenarios)]),
        max_zones=max([0, *(len(s.zones) for s in scenarios)]),
        max_steps=max_steps,
    )


# --- files ---------------------------------------------------------------------------------------


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read and validate a scenario file in our format."""
    path = Path(path)
    data = read_json(path)
    if isinstance(data, dict) and "format" not in data and ("scenario" in data
                                                            or "zone_scenario" in data):
        raise ScenarioError("this is a reference-format file; read it with "
                            "tabx.scenarios.read_reference_scenario or load_named",
                            source=str(path))
    return Scenario.from_dict(data, source=str(path))


def read_json(path: str | os.PathLike) -> Any:
    """Parse a JSON file with `parse_json`'s checks; unreadable, oversized, non-UTF-8 or
    malformed files become ScenarioError naming the file."""
    source = str(path)
    try:
        with Path(path).open("rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as err:
        raise ScenarioError(f"cannot read file: {err.strerror or err}", source=source) from None
    if len(raw) > MAX_FILE_BYTES:
        raise ScenarioError(f"file larger than {MAX_FILE_BYTES // (1024 * 1024)} MiB; expected a "
                            "scenario (a small JSON file)", source=source)
    return parse_json_bytes(raw, source)


def parse_json_bytes(raw: bytes, source: str | None = None, what: str = "file") -> Any:
    """`parse_json` of UTF-8 bytes (a leading byte-order mark is allowed)."""
    if raw.startswith(codecs.BOM_UTF8):
        raw = raw[len(codecs.BOM_UTF8):]
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ScenarioError(f"not UTF-8 text (byte 0x{raw[err.start]:02x} at offset {err.start}); "
                            f"expected a JSON scenario", source=source) from None
    return parse_json(text, source, what)


def parse_json(text: str, source: str | None = None, what: str = "file") -> Any:
    """Strict JSON: no NaN/Infinity, no repeated key in an object, at most MAX_JSON_DEPTH nested
    arrays and objects. Every problem is a ScenarioError naming `source`, the key path and, for
    syntax problems, the line and column."""
    if not text.strip():
        raise ScenarioError(f"empty {what}: expected a JSON object {{...}} (a scenario)",
                            source=source)
    problem = _scan_json(text, "depth")  # before json.loads, which recurses per level
    if problem is not None:
        raise ScenarioError(problem[0], problem[1], source)
    try:
        return json.loads(text, parse_constant=_bad_constant, object_pairs_hook=_unique_object)
    except _DuplicateKey as dup:
        problem = _scan_json(text, "duplicate")
        if problem is None:  # not expected: the scan and the parser agree on valid JSON
            problem = (f"key {_describe(dup.key)} appears twice in one object; expected each "
                       "key once", "")
        raise ScenarioError(problem[0], problem[1], source) from None
    except _NonFinite as bad:
        problem = _scan_json(text, "constant") or (
            f"{bad.name} is not allowed in JSON; expected a finite number", "")
        raise ScenarioError(problem[0], problem[1], source) from None
    except json.JSONDecodeError as err:
        where = f"line {err.lineno}, column {err.colno}"
        if err.pos >= len(text.rstrip()):
            raise ScenarioError(f"invalid JSON: {err.msg} at the end of the {what} ({where}); is "
                                f"the {what} truncated?", source=source) from None
        raise ScenarioError(f"invalid JSON: {err.msg} ({where})", source=source) from None
    except RecursionError:  # the depth scan should have caught it first
        raise ScenarioError(f"invalid JSON: nested deeper than {MAX_JSON_DEPTH} levels",
                            source=source) from None
    except ValueError as err:  # e.g. an integer longer than Python's digit limit
        msg = str(err)
        if "int_max_str_digits" in msg:
            msg = "a number with thousands of digits; expected a number in a field's range"
        raise ScenarioError(f"invalid JSON: {msg if len(msg) <= 200 else msg[:200] + '...'}",
                            source=source) from None


class _DuplicateKey(Exception):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


class _NonFinite(Exception):
    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _DuplicateKey(key)
            seen.add(key)
    return obj


def _bad_constant(name: str) -> Any:
    raise _NonFinite(name)


# Strings (escapes included), the structural characters, NaN/Infinity outside strings, and a lone
# quote (an unterminated string, which ends the scan).
_JSON_TOKEN = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[\[\]{}:,]|-?Infinity|NaN|"', re.DOTALL)


def _scan_json(text: str, find: str) -> tuple[str, str] | None:
    """A cheap scan of JSON text that tracks the key path of every value without building it.

    Always checks the nesting depth; `find="duplicate"` also finds the first repeated key of an
    object and `find="constant"` the first NaN/Infinity. Returns (message, key path) of the
    first problem, or None. The scan does not check the syntax: json.loads does that.
    """
    stack: list[list[Any]] = []  # [bracket, key or index, keys seen, pending key string]

    def where(pos: int) -> str:
        line = text.count("\n", 0, pos) + 1
        column = pos - text.rfind("\n", 0, pos)
        return f"line {line}, column {column}"

    def path() -> str:
        out = ""
        for _, place, _, _ in stack:
            if place is not None:
                out = _join(out, place if isinstance(place, int) else _describe_key(place))
        return out

    for m in _JSON_TOKEN.finditer(text):
        tok = m.group()
        if tok in ("[", "{"):
            if len(stack) >= MAX_JSON_DEPTH:
                return (f"nested deeper than {MAX_JSON_DEPTH} levels of arrays and objects "
                        f"({where(m.start())}); expected a scenario, which nests at most "
                        "a few levels", path())
            stack.append([tok, 0 if tok == "[" else None, set(), None])
        elif tok in ("]", "}"):
            if stack:
                stack.pop()
        elif tok == ",":
            if stack and stack[-1][0] == "[":
                stack[-1][1] += 1
        elif tok == ":":
            if stack and stack[-1][0] == "{" and stack[-1][3] is not None:
                top = stack[-1]
                key, top[3] = top[3], None
                top[1] = key
                if find == "duplicate" and key in top[2]:
                    return (f"key {_describe(key)} appears twice in the same object "
                            f"({where(m.start())}); expected each key once (JSON readers "
                            "would silently keep the last value)", path())
                top[2].add(key)
        elif tok == '"':
            return None  # an unterminated string: json.loads reports it
        elif tok[0] == '"':
            if stack and stack[-1][0] == "{":
                stack[-1][3] = _decode_string(tok)
        elif find == "constant":  # NaN, Infinity, -Infinity
            return (f"{tok} is not allowed in JSON ({where(m.start())}); expected a finite "
                    "number", path())
    return None


def _decode_string(token: str) -> str:
    if "\\" not in token:
        return token[1:-1]
    try:
        return json.loads(token)
    except ValueError:
        return token[1:-1]


def _describe_key(key: str) -> str:
    return key if len(key) <= 60 else key[:60] + "..."


def save_scenario(path: str | os.PathLike, scenario: Scenario) -> Path:
    """Validate and write a scenario atomically, one unit or zone per line."""
    scenario.validate()
    return atomic_write_text(path, dumps_scenario(scenario))


def dumps_scenario(scenario: Scenario) -> str:
    """Readable JSON: indented top level, each unit and zone record on one line."""
    d = scenario.to_dict()
    lines = ["{"]
    items = list(d.items())
    for i, (key, value) in enumerate(items):
        comma = "," if i < len(items) - 1 else ""
        if key in ("units", "zones") and value:
            lines.append(f"  {json.dumps(key)}: [")
            lines += [f"    {json.dumps(rec)}{',' if j < len(value) - 1 else ''}"
                      for j, rec in enumerate(value)]
            lines.append(f"  ]{comma}")
        else:
            lines.append(f"  {json.dumps(key)}: {json.dumps(value)}{comma}")
    lines.append("}")
    return "\n".join(lines) + "\n"


# --- levels -> scenarios ------------------------------------------------------------------------


def _f32(x: Any) -> float:
    """The shortest decimal that reads back as the same float32 (readable exported files)."""
    return float(str(np.float32(x)))  # numpy prints float32 as its shortest round-trip decimal


def _f32_equal(a: float, b: float) -> bool:
    """Equal once stored as float32: the level cannot tell the two values apart."""
    return bool(np.float32(a) == np.float32(b))


def level_to_scenario(level: P.EnvParams, name: str = "exported", category: str = "user",
                      description: str | None = None) -> Scenario:
    """The scenario of one (unbatched) level: active unit slots and non-empty zone slots.

    Stats equal (in float32) to the unit type's defaults are not written as overrides;
    `max_health` only when it differs from `health`, `heals` only when it differs from
    `damage < 0`. Physics and heuristic are written only when they differ from the defaults.
    The reward mode is not part of a scenario; randomised starts are (`start_noise`,
    `shuffle_positions`), written only when on.
    """
    u = {k: np.asarray(v) for k, v in vars(level.units).items()}
    if u["active"].ndim != 1:
        raise ScenarioError(f"expected one level, got a batch of shape {u['active'].shape}")
    units: list[Unit] = []
    for i in np.flatnonzero(u["active"]):
        spec = C.UNIT_SPECS[int(u["unit_type"][i])]
        overrides: dict[str, Any] = {}
        for stat in UNIT_STAT_RANGES:
            value = _f32(u[stat][i])
            default = _f32(u["health"][i]) if stat == "max_health" else getattr(spec, stat)
            if not _f32_equal(value, default):
                overrides[stat] = value
        if bool(u["heals"][i]) != bool(u["damage"][i] < 0):
            overrides["heals"] = bool(u["heals"][i])
        team = "ally" if int(u["team"][i]) == C.ALLY else "enemy"
        units.append(Unit(spec.name, team, (_f32(u["position"][i, 0]), _f32(u["position"][i, 1])),
                          _f32(u["heading"][i]), overrides))
    z = {k: np.asarray(v) for k, v in vars(level.zones).items()}
    zones = [Zone(C.ZONE_NAMES[int(z["zone_type"][j])],
                  (_f32(z["centre"][j, 0]), _f32(z["centre"][j, 1])),
                  (_f32(z["semi_axes"][j, 0]), _f32(z["semi_axes"][j, 1])),
                  _f32(z["effect"][j]))
             for j in np.flatnonzero(z["zone_type"] != C.ZONE_NONE)]
    arena = np.asarray(level.physics.arena_size)
    return Scenario(name=name, category=category, units=tuple(units), zones=tuple(zones),
                    arena=(_f32(arena[0]), _f32(arena[1])),
                    physics=_physics_from_level(level.physics),
                    heuristic=_heuristic_from_level(level.heuristic), description=description,
                    start_noise=_f32(np.asarray(level.start_noise)),
                    shuffle_positions=bool(np.asarray(level.shuffle_positions)))


def _physics_from_level(ph: P.PhysicsParams) -> Physics:
    values = {k: _f32(np.asarray(getattr(ph, k))) for k in PHYSICS_RANGES}
    defaults = {"boundary_damage_rate": C.BOUNDARY_DAMAGE_RATE, "turn_rate": C.TURN_RATE}
    for preset, fields in P.PHYSICS_PRESETS.items():
        if all(_f32_equal(values[k], v) for k, v in {**defaults, **fields}.items()):
            return None if preset == "default" else preset
    return values


def _heuristic_from_level(h: P.HeuristicParams) -> Heuristic:
    teams = {}
    for t, team in enumerate(TEAMS):
        values = {k: _f32(np.asarray(getattr(h, k))[t]) for k in HEURISTIC_RANGES}
        teams[team] = values
        for tier, fields in P.HEURISTIC_TIERS.items():
            if all(_f32_equal(values[k], v) for k, v in {**P.HEURISTIC_COMMON, **fields}.items()):
                teams[team] = tier
                break
    return None if teams == {"ally": "medium", "enemy": "medium"} else teams


def _heuristic_params(h: Any) -> P.HeuristicParams:
    if h is None:
        return P.heuristic_params()
    if isinstance(h, P.HeuristicParams):
        return h
    if isinstance(h, str):
        return P.heuristic_params(h, h)
    return P.heuristic_params(h.get("ally", "medium"), h.get("enemy", "medium"))


def _physics_params(ph: Any, arena: tuple[float, float]) -> P.PhysicsParams:
    import jax.numpy as jnp  # local: only levels need jax

    size = jnp.asarray(arena, jnp.float32)
    if isinstance(ph, P.PhysicsParams):
        return ph.replace(arena_size=size)
    if ph is None or isinstance(ph, str):
        return P.physics_params(ph or "default", arena_size=arena)
    fields = dict(ph)
    preset = fields.pop("preset", "default")
    return P.physics_params(preset, **fields, arena_size=arena)


# --- the validator ------------------------------------------------------------------------------


def _did_you_mean(word: str, options: Sequence[str]) -> str:
    if len(word) > 100:  # no option is this long; spare difflib a long string
        return ""
    close = difflib.get_close_matches(word, list(options), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _check_keys(obj: Mapping, allowed: Sequence[str], path: str, required: Sequence[str] = ()):
    for key in obj:
        if not isinstance(key, str) or key not in allowed:
            hint = _did_you_mean(key, allowed) if isinstance(key, str) else ""
            raise ScenarioError(f"unknown key {_describe(key)}{hint}; allowed keys: "
                                f"{', '.join(allowed)}", path)
    for key in required:
        if key not in obj:
            raise ScenarioError(f"missing required key {key!r}", path)


def _join(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def _describe(value: Any) -> str:
    text = repr(value)
    return (text[:60] + "...") if len(text) > 60 else text


def _mapping(value: Any, path: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise ScenarioError(f"expected an object {{...}}, got {_describe(value)}", path)
    return value


def _list(value: Any, path: str) -> list:
    if not isinstance(value, list | tuple):
        raise ScenarioError(f"expected a list [...], got {_describe(value)}", path)
    return list(value)


def _number(value: Any, path: str, rng: Range | None = None, what: str = "a number") -> float:
    # bool is an int subclass in Python but never a valid number in a scenario.
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ScenarioError(f"expected {what}, got {_describe(value)}", path)
    try:
        x = float(value)
    except OverflowError:  # a huge JSON integer
        raise ScenarioError(f"expected {what} in {rng}, got {_describe(value)}", path) from None
    if not math.isfinite(x):
        raise ScenarioError(f"expected a finite number, got {_describe(value)}", path)
    if rng is not None and not rng.contains(x):
        raise ScenarioError(f"expected {what} in {rng}, got {x:.6g}", path)
    return x


def _string(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise ScenarioError(f"expected a string, got {_describe(value)}", path)
    return value


def _choice(value: Any, options: Sequence[str], path: str) -> str:
    if not isinstance(value, str) or value not in options:
        hint = _did_you_mean(value, options) if isinstance(value, str) else ""
        raise ScenarioError(f"expected one of {', '.join(options)}; got {_describe(value)}{hint}",
                            path)
    return value


def _pair(value: Any, path: str, rng: Range | None = None, what: str = "a number"
          ) -> tuple[float, float]:
    items = _list(value, path)
    if len(items) != 2:
        raise ScenarioError(f"expected a pair [x, y], got {len(items)} values", path)
    return (_number(items[0], _join(path, 0), rng, what),
            _number(items[1], _join(path, 1), rng, what))


def _parse(data: Any) -> Scenario:
    d = _mapping(data, "")
    _check_keys(d, TOP_KEYS, "", required=("format", "name", "category", "units", "zones"))
    if d["format"] != FORMAT:
        raise ScenarioError(f"expected {FORMAT!r}, got {_describe(d['format'])}", "format")
    name = _string(d["name"], "name")
    if not NAME_PATTERN.fullmatch(name):
        raise ScenarioError("expected 1-100 characters from A-Z a-z 0-9 _ . -, starting with a "
                            f"letter or digit; got {_describe(name)}", "name")
    category = _choice(d["category"], CATEGORIES, "category")
    split = _choice(d["split"], SPLITS, "split") if "split" in d else None
    description = None
    if "description" in d:
        description = _string(d["description"], "description")
        if len(description) > MAX_DESCRIPTION:
            raise ScenarioError(f"expected at most {MAX_DESCRIPTION} characters, got "
                                f"{len(description)}", "description")
    arena = (C.ARENA_WIDTH, C.ARENA_HEIGHT)
    if "arena" in d:
        a = _mapping(d["arena"], "arena")
        _check_keys(a, ("width", "height"), "arena", required=("width", "height"))
        arena = (_number(a["width"], "arena.width", ARENA_RANGE),
                 _number(a["height"], "arena.height", ARENA_RANGE))
    units_in = _list(d["units"], "units")
    if len(units_in) > 2 * MAX_UNITS_PER_TEAM:
        raise ScenarioError(f"at most {2 * MAX_UNITS_PER_TEAM} units, got {len(units_in)}", "units")
    units = tuple(_parse_unit(u, _join("units", i), arena) for i, u in enumerate(units_in))
    if units:
        for team in TEAMS:
            n = sum(u.team == team for u in units)
            if n == 0:
                raise ScenarioError(f"no {team} unit: a playable scenario needs at least one ally "
                                    "and one enemy (a zone-only scenario has no units at all)",
                                    "units")
            if n > MAX_UNITS_PER_TEAM:
                raise ScenarioError(f"at most {MAX_UNITS_PER_TEAM} {team} units, got {n}", "units")
    zones_in = _list(d["zones"], "zones")
    if len(zones_in) > MAX_ZONES:
        raise ScenarioError(f"at most {MAX_ZONES} zones, got {len(zones_in)}", "zones")
    zones = tuple(_parse_zone(z, _join("zones", i), arena) for i, z in enumerate(zones_in))
    physics = _parse_physics(d["physics"]) if "physics" in d else None
    heuristic = _parse_heuristic(d["heuristic"]) if "heuristic" in d else None
    start_noise = 0.0
    if "start_noise" in d:
        start_noise = _number(d["start_noise"], "start_noise", START_NOISE_RANGE)
    shuffle = d.get("shuffle_positions", False)
    if not isinstance(shuffle, bool):
        raise ScenarioError(f"expected true or false, got {_describe(shuffle)}",
                            "shuffle_positions")
    return Scenario(name=name, category=category, units=units, zones=zones, arena=arena,
                    physics=physics, heuristic=heuristic, description=description, split=split,
                    start_noise=start_noise, shuffle_positions=shuffle)


def _f32_slack(*values: float) -> float:
    """Allowance for float32 rounding in bound checks: a level exported with level_to_scenario
    stores every value as float32, so a unit exactly on the bound must still pass."""
    return 1e-6 * sum(abs(v) for v in values) + 1e-9


def _parse_unit(value: Any, path: str, arena: tuple[float, float]) -> Unit:
    rec = _mapping(value, path)
    _check_keys(rec, UNIT_KEYS, path, required=("unit", "team", "position"))
    unit = _choice(rec["unit"], C.UNIT_NAMES, _join(path, "unit"))
    team = _choice(rec["team"], TEAMS, _join(path, "team"))
    if "heading" in rec and "heading_deg" in rec:
        raise ScenarioError("give either heading (radians) or heading_deg, not both", path)
    heading = 0.0
    if "heading" in rec:
        heading = _number(rec["heading"], _join(path, "heading"), HEADING_RANGE, "radians")
    elif "heading_deg" in rec:
        deg = _number(rec["heading_deg"], _join(path, "heading_deg"), Range(-720.0, 720.0),
                      "degrees")
        heading = math.radians(deg)
    position = _pair(rec["position"], _join(path, "position"))
    overrides: dict[str, Any] = {}
    opath = _join(path, "overrides")
    for key, v in _mapping(rec.get("overrides", {}), opath).items():
        if not isinstance(key, str) or key not in UNIT_OVERRIDE_FIELDS:
            hint = _did_you_mean(key, UNIT_OVERRIDE_FIELDS) if isinstance(key, str) else ""
            raise ScenarioError(f"unknown stat {_describe(key)}{hint}; allowed: "
                                f"{', '.join(UNIT_OVERRIDE_FIELDS)}", opath)
        if key == "heals":
            if not isinstance(v, bool):
                raise ScenarioError(f"expected true or false, got {_describe(v)}",
                                    _join(opath, key))
            overrides[key] = v
        else:
            overrides[key] = _number(v, _join(opath, key), UNIT_STAT_RANGES[key])
    u = Unit(unit, team, position, heading, overrides)
    stats = u.stats()
    if stats["health"] > stats["max_health"]:
        key = "health" if "health" in overrides else "max_health"
        raise ScenarioError(f"health {stats['health']:.6g} exceeds max_health "
                            f"{stats['max_health']:.6g}; expected 0 < health <= max_health",
                            _join(opath, key))
    r = stats["radius"]
    for axis, (coord, half) in enumerate(zip(position, (arena[0] / 2, arena[1] / 2), strict=True)):
        if abs(coord) > half - r + _f32_slack(coord, half, r):
            label, size = ("x", "width") if axis == 0 else ("y", "height")
            raise ScenarioError(
                f"{label}={coord:.6g} puts the unit (radius {r:.6g}) outside the "
                f"{arena[0]:g} x {arena[1]:g} arena: expected |{label}| <= {size}/2 - radius = "
                f"{half - r:.6g}", _join(_join(path, "position"), axis))
    return u


def _parse_zone(value: Any, path: str, arena: tuple[float, float]) -> Zone:
    rec = _mapping(value, path)
    _check_keys(rec, ZONE_KEYS, path, required=("type", "centre", "semi_axes"))
    ztype = _choice(rec["type"], ZONE_TYPES, _join(path, "type"))
    centre = _pair(rec["centre"], _join(path, "centre"))
    for axis, half in enumerate((arena[0] / 2, arena[1] / 2)):
        if abs(centre[axis]) > half + _f32_slack(centre[axis], half):
            raise ScenarioError(f"centre outside the {arena[0]:g} x {arena[1]:g} arena: expected "
                                f"|{'xy'[axis]}| <= {half:g}", _join(_join(path, "centre"), axis))
    semi_axes = _pair(rec["semi_axes"], _join(path, "semi_axes"), SEMI_AXIS_RANGE, "a semi-axis")
    effect = 0.0
    if "effect" in rec:
        effect = _number(rec["effect"], _join(path, "effect"), ZONE_EFFECT_RANGES[ztype],
                         f"a {ztype} effect")
    return Zone(ztype, centre, semi_axes, effect)


def _parse_physics(value: Any) -> Physics:
    if isinstance(value, str):
        return _choice(value, tuple(P.PHYSICS_PRESETS), "physics")
    rec = _mapping(value, "physics")
    _check_keys(rec, ("preset", *PHYSICS_RANGES), "physics")
    out: dict[str, Any] = {}
    for key, v in rec.items():
        if key == "preset":
            out[key] = _choice(v, tuple(P.PHYSICS_PRESETS), "physics.preset")
        else:
            out[key] = _number(v, _join("physics", key), PHYSICS_RANGES[key])
    return out


def _parse_heuristic(value: Any) -> Heuristic:
    rec = _mapping(value, "heuristic")
    _check_keys(rec, TEAMS, "heuristic")
    out: dict[str, Any] = {}
    for team, v in rec.items():
        path = _join("heuristic", team)
        if isinstance(v, str):
            out[team] = _choice(v, tuple(P.HEURISTIC_TIERS), path)
            continue
        params = _mapping(v, path)
        _check_keys(params, tuple(HEURISTIC_RANGES), path)
        out[team] = {k: _number(x, _join(path, k), HEURISTIC_RANGES[k]) for k, x in params.items()}
    return out
