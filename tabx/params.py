"""The static `EnvConfig` and the level pytree `EnvParams`, with helpers to build, pad, batch,
index and compare levels.

A *level* is data: every field of `EnvParams` is a fixed-shape array, so any two levels with the
same `EnvConfig` run through the same compiled step (different stats, positions, unit and zone
counts up to the maxima, zone layouts, opponent skill and physics never recompile). Only
`EnvConfig` is static.

Slot layout: unit slots `0 .. max_allies-1` belong to team 0 (the allies), slots
`max_allies .. max_allies+max_enemies-1` to team 1 (the enemies). Unused slots are *padding*:
`active = False`, with harmless non-zero denominators (max health, cooldown, radius, mass), so
no computation can divide by zero whatever the padding.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tabx import constants as C


@dataclass(frozen=True)
class EnvConfig:
    """Static sizes compiled into the step. Everything else is level data (`EnvParams`)."""

    max_allies: int = 10
    max_enemies: int = 10
    max_zones: int = 4
    max_steps: int = C.DEFAULT_MAX_STEPS
    win_reward: float = 1.0
    lose_reward: float = -1.0

    def __post_init__(self) -> None:
        for name in ("max_allies", "max_enemies"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"EnvConfig.{name} must be an integer >= 1, got {value!r}")
        if not isinstance(self.max_zones, int) or self.max_zones < 0:
            raise ValueError(f"EnvConfig.max_zones must be an integer >= 0, got {self.max_zones!r}")
        if (not isinstance(self.max_steps, int) or isinstance(self.max_steps, bool)
                or not 1 <= self.max_steps <= C.MAX_STEPS):
            raise ValueError(f"EnvConfig.max_steps must be an integer in [1, 2**31 - 1] (the "
                             f"step counter is int32), got {self.max_steps!r}")

    @property
    def num_units(self) -> int:
        return self.max_allies + self.max_enemies

    @property
    def obs_size(self) -> int:
        """Per-agent observation length: own 14 + 16 per other unit + 6 per zone slot."""
        return 14 + 16 * (self.num_units - 1) + 6 * self.max_zones

    @property
    def state_size(self) -> int:
        """Global state length: 15 features per unit (own features + team) + 6 per zone."""
        return 15 * self.num_units + 6 * self.max_zones

    def slot_teams(self) -> np.ndarray:
        return np.array([C.ALLY] * self.max_allies + [C.ENEMY] * self.max_enemies, np.int32)


@struct.dataclass
class UnitSlots:
    """Per-unit-slot arrays, shape (N,) or (N, 2) with N = max_allies + max_enemies."""

    team: jax.Array  # int32, 0 ally / 1 enemy (follows the slot layout)
    unit_type: jax.Array  # int32 index into constants.UNIT_SPECS (rendering and metrics only)
    position: jax.Array  # float32 (N, 2), world coordinates, origin at the arena centre, y up
    heading: jax.Array  # float32 radians, counter-clockwise from +x
    health: jax.Array  # float32 initial health, 0 < health <= max_health for active units
    max_health: jax.Array  # float32
    speed: jax.Array  # float32 world units per second
    damage: jax.Array  # float32 per hit; negative heals
    attack_range: jax.Array  # float32 hurtbox length
    cooldown: jax.Array  # float32 seconds between attacks
    radius: jax.Array  # float32 body radius
    mass: jax.Array  # float32 body mass
    sight_angle: jax.Array  # float32 total field-of-view angle, in (0, pi)
    heals: jax.Array  # bool: heals allies instead of damaging enemies
    active: jax.Array  # bool: a real unit (False = padding)


@struct.dataclass
class ZoneSlots:
    """Per-zone-slot arrays, shape (Z,) or (Z, 2). Type 0 = empty slot."""

    zone_type: jax.Array  # int32: 0 none, 1 lava, 2 bush, 3 swamp
    centre: jax.Array  # float32 (Z, 2)
    semi_axes: jax.Array  # float32 (Z, 2), axis-aligned ellipse
    effect: jax.Array  # float32: lava health per second; swamp slow fraction in [0, 1]; bush unused


@struct.dataclass
class HeuristicParams:
    """Scripted-opponent parameters, one entry per team (shape (2,))."""

    epsilon: jax.Array
    aggressive_threshold: jax.Array
    healer_aggressive_threshold: jax.Array
    assassin_speed: jax.Array
    ranger_attack_range: jax.Array


@struct.dataclass
class PhysicsParams:
    """Physics constants (scalars) and the arena size."""

    dt: jax.Array
    restitution: jax.Array
    slop: jax.Array
    percent: jax.Array
    boundary_damage_rate: jax.Array
    turn_rate: jax.Array
    arena_size: jax.Array  # (2,) width, height; centred on the origin


@struct.dataclass
class EnvParams:
    """One level (or, with a leading axis on every leaf, a batch of levels)."""

    units: UnitSlots
    zones: ZoneSlots
    heuristic: HeuristicParams
    physics: PhysicsParams
    reward_mode: jax.Array  # int32 scalar: constants.REWARD_MEAN_OF_RATIOS or RATIO_OF_SUMS
    profile: jax.Array  # int32 scalar: reference behaviours played, one bit each (tabx.profiles)
    # Randomised starts, drawn from the reset key (`tabx.starts`): with `shuffle_positions`
    # each team's units trade start positions, then each moves by up to `start_noise` world
    # units. Off (0, False) by default and in the paper's scenarios: a start is then the file's.
    start_noise: jax.Array = struct.field(default_factory=lambda: jnp.zeros((), jnp.float32))
    shuffle_positions: jax.Array = struct.field(default_factory=lambda: jnp.zeros((), bool))

    # Leaves that level files written before they existed lack, and the value they then take
    # (`level_buffer.tree.file_defaults`): such files load as levels with fixed starts.
    # The profile's default is the project's behaviour (no reference choice).
    FILE_DEFAULTS = {"start_noise": 0.0, "shuffle_positions": False, "profile": 0}


# --- defaults --------------------------------------------------------------------------------

# The reference's key spellings in its data files, and the order of the tiers by skill.
_REFERENCE_KEYS = {"assasin_speed": "assassin_speed"}
TIER_ORDER = ("random", "novice", "medium", "advanced", "expert")


def _load_presets(folder: str) -> dict[str, dict[str, float]]:
    """Presets shipped as the reference's JSON files (MIT, Copyright (c) 2025 TABX; see
    tabx/data/LICENSE-TABX): one file per name, each value a one-element list."""
    import json
    from importlib.resources import files

    out = {}
    for entry in sorted(files("tabx.data").joinpath(folder).iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".json"):
            raw = json.loads(entry.read_text())
            out[entry.name[:-5]] = {_REFERENCE_KEYS.get(k, k): float(v[0] if isinstance(v, list)
                                                                    else v)
                                    for k, v in raw.items()}
    return out


# The five opponent tiers (paper table "Heuristic policy parameters"): tabx/data/heuristic_policy.
HEURISTIC_TIERS: dict[str, dict[str, float]] = {
    name: preset for name, preset in sorted(_load_presets("heuristic_policy").items(),
                                            key=lambda item: TIER_ORDER.index(item[0]))}
HEURISTIC_COMMON = dict(healer_aggressive_threshold=0.85, assassin_speed=1.4,
                        ranger_attack_range=10.0)
# Physics presets (reference physics/*.json): tabx/data/physics.
PHYSICS_PRESETS: dict[str, dict[str, float]] = _load_presets("physics")


def heuristic_params(ally: str | dict = "medium", enemy: str | dict = "medium") -> HeuristicParams:
    """Heuristic parameters for both teams from tier names or explicit dicts."""

    def resolve(tier: str | dict) -> dict[str, float]:
        if isinstance(tier, str):
            if tier not in HEURISTIC_TIERS:
                raise ValueError(
                    f"unknown heuristic tier {tier!r}; expected one of {sorted(HEURISTIC_TIERS)}")
            return {**HEURISTIC_COMMON, **HEURISTIC_TIERS[tier]}
        return {**HEURISTIC_COMMON, **HEURISTIC_TIERS["medium"], **tier}

    a, e = resolve(ally), resolve(enemy)
    return HeuristicParams(**{k: jnp.asarray([a[k], e[k]], jnp.float32)
                              for k in HeuristicParams.__dataclass_fields__})


def physics_params(preset: str = "default", **overrides: float) -> PhysicsParams:
    """Physics constants from a preset name, with optional per-field overrides."""
    if preset not in PHYSICS_PRESETS:
        raise ValueError(
            f"unknown physics preset {preset!r}; expected one of {sorted(PHYSICS_PRESETS)}")
    values: dict[str, Any] = dict(
        boundary_damage_rate=C.BOUNDARY_DAMAGE_RATE, turn_rate=C.TURN_RATE,
        arena_size=(C.ARENA_WIDTH, C.ARENA_HEIGHT), **PHYSICS_PRESETS[preset])
    values.update(overrides)
    return PhysicsParams(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})


def empty_units(config: EnvConfig) -> dict[str, np.ndarray]:
    """Numpy arrays of an all-padding unit block (safe denominators, inactive)."""
    n = config.num_units
    return dict(
        team=config.slot_teams(),
        unit_type=np.zeros(n, np.int32),
        position=np.zeros((n, 2), np.float32),
        heading=np.zeros(n, np.float32),
        health=np.zeros(n, np.float32),
        max_health=np.ones(n, np.float32),
        speed=np.zeros(n, np.float32),
        damage=np.zeros(n, np.float32),
        attack_range=np.zeros(n, np.float32),
        cooldown=np.ones(n, np.float32),
        radius=np.ones(n, np.float32),
        mass=np.ones(n, np.float32),
        sight_angle=np.full(n, C.SIGHT_ANGLE, np.float32),
        heals=np.zeros(n, bool),
        active=np.zeros(n, bool),
    )


def empty_zones(config: EnvConfig) -> dict[str, np.ndarray]:
    z = config.max_zones
    return dict(
        zone_type=np.zeros(z, np.int32),
        centre=np.zeros((z, 2), np.float32),
        semi_axes=np.ones((z, 2), np.float32),
        effect=np.zeros(z, np.float32),
    )


def make_level(
    config: EnvConfig,
    allies: Sequence[dict[str, Any]],
    enemies: Sequence[dict[str, Any]],
    zones: Sequence[dict[str, Any]] = (),
    heuristic: HeuristicParams | None = None,
    physics: PhysicsParams | None = None,
    reward_mode: int = C.REWARD_MEAN_OF_RATIOS,
    start_noise: float = 0.0,
    shuffle_positions: bool = False,
) -> EnvParams:
    """Build one padded level from unit and zone records.

    A unit record needs `unit` (a name from constants.UNIT_NAMES) and `position`; `heading` and
    any stat (`health`, `max_health`, `speed`, `damage`, `attack_range`, `cooldown`, `radius`,
    `mass`, `sight_angle`, `heals`) override the unit type's defaults. A zone record has `type`
    (name or int), `centre`, `semi_axes` and `effect`. `start_noise` and `shuffle_positions`
    randomise the start from the reset key (`EnvParams`; `tabx.starts`).
    """
    if len(allies) > config.max_allies:
        raise ValueError(f"{len(allies)} allies exceed EnvConfig.max_allies={config.max_allies}")
    if len(enemies) > config.max_enemies:
        raise ValueError(
            f"{len(enemies)} enemies exceed EnvConfig.max_enemies={config.max_enemies}")
    if len(zones) > config.max_zones:
        raise ValueError(f"{len(zones)} zones exceed EnvConfig.max_zones={config.max_zones}")
    u = empty_units(config)
    slots = [(i, rec) for i, rec in enumerate(allies)]
    slots += [(config.max_allies + i, rec) for i, rec in enumerate(enemies)]
    for slot, rec in slots:
        if rec["unit"] not in C.UNIT_TYPE_BY_NAME:
            raise ValueError(f"unknown unit {rec['unit']!r}; expected one of {list(C.UNIT_NAMES)}")
        t = C.UNIT_TYPE_BY_NAME[rec["unit"]]
        spec = C.UNIT_SPECS[t]
        u["unit_type"][slot] = t
        u["position"][slot] = rec["position"]
        u["heading"][slot] = rec.get("heading", 0.0)
        health = rec.get("health", spec.health)
        u["health"][slot] = health
        u["max_health"][slot] = rec.get("max_health", health)
        u["speed"][slot] = rec.get("speed", spec.speed)
        damage = rec.get("damage", spec.damage)
        u["damage"][slot] = damage
        u["attack_range"][slot] = rec.get("attack_range", spec.attack_range)
        u["cooldown"][slot] = rec.get("cooldown", spec.cooldown)
        u["radius"][slot] = rec.get("radius", spec.radius)
        u["mass"][slot] = rec.get("mass", spec.mass)
        u["sight_angle"][slot] = rec.get("sight_angle", spec.sight_angle)
        u["heals"][slot] = rec.get("heals", damage < 0)
        u["active"][slot] = True
    zs = empty_zones(config)
    for i, rec in enumerate(zones):
        ztype = rec["type"]
        zs["zone_type"][i] = C.ZONE_TYPE_BY_NAME[ztype] if isinstance(ztype, str) else int(ztype)
        zs["centre"][i] = rec["centre"]
        zs["semi_axes"][i] = rec["semi_axes"]
        zs["effect"][i] = rec.get("effect", 0.0)
    return EnvParams(
        units=UnitSlots(**{k: jnp.asarray(v) for k, v in u.items()}),
        zones=ZoneSlots(**{k: jnp.asarray(v) for k, v in zs.items()}),
        heuristic=heuristic if heuristic is not None else heuristic_params(),
        physics=physics if physics is not None else physics_params(),
        reward_mode=jnp.asarray(reward_mode, jnp.int32),
        profile=jnp.zeros((), jnp.int32),
        start_noise=jnp.asarray(start_noise, jnp.float32),
        shuffle_positions=jnp.asarray(shuffle_positions, bool),
    )


# --- batches ---------------------------------------------------------------------------------


def stack_levels(levels: Sequence[EnvParams]) -> EnvParams:
    """Stack levels of one EnvConfig into a batch (leading axis on every leaf)."""
    if not levels:
        raise ValueError("stack_levels needs at least one level")
    shapes = [jax.tree.map(jnp.shape, lv) for lv in levels]
    for i, s in enumerate(shapes[1:], 1):
        if s != shapes[0]:
            raise ValueError(f"level {i} has other slot shapes than level 0: different EnvConfig?")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *levels)


def repeat_level(level: EnvParams, n: int) -> EnvParams:
    """A batch of n copies of one level."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x))), level)


def index_level(batch: EnvParams, i: int) -> EnvParams:
    """Level i of a batch."""
    return jax.tree.map(lambda x: x[i], batch)


def batch_size(batch: EnvParams) -> int:
    return int(jnp.shape(batch.reward_mode)[0]) if jnp.ndim(batch.reward_mode) else 1


def levels_equal(a: EnvParams, b: EnvParams, atol: float = 0.0) -> bool:
    """Exact (atol=0) or tolerant equality of two levels, leaf by leaf."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    if jax.tree.structure(a) != jax.tree.structure(b):
        return False
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            return False
        if x.dtype == bool or np.issubdtype(x.dtype, np.integer) or atol == 0.0:
            if not np.array_equal(x, y):
                return False
        elif not np.allclose(x, y, atol=atol, rtol=0.0):
            return False
    return True


def level_config(level: EnvParams, max_steps: int = C.DEFAULT_MAX_STEPS) -> EnvConfig:
    """The EnvConfig an (unbatched) level was padded for, read from its team layout."""
    team = np.asarray(level.units.team)
    return EnvConfig(max_allies=int((team == C.ALLY).sum()),
                     max_enemies=int((team == C.ENEMY).sum()),
                     max_zones=int(np.shape(level.zones.zone_type)[-1]), max_steps=max_steps)
