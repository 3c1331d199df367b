"""Random scenarios for the reconfiguration benchmark (`tabx bench reconfig`, docs/benchmarks.md).

Each level draws its own unit composition (types uniformly from the nine units, `min_units ..
max_units` a side, independently per team), positions (allies in the left third, enemies in
the right third, random headings) and zones (`min_zones .. max_zones`, types uniformly from
lava, bush and swamp, random centres, semi-axes and effects). Every level is padded to one
`EnvConfig` (10 v 10 and 6 zone slots by default), so all of them run through one compiled
step, and each is checked the way scenario files are:
`tabx.scenarios.format.level_to_scenario(level).validate()`.

    levels = random_levels(100, seed=0)            # list of EnvParams
    batch = stack_levels(levels)                   # or one batch
"""

from __future__ import annotations

import math

import numpy as np

from tabx import constants as C
from tabx.params import EnvConfig, EnvParams, make_level

RECONFIG_CONFIG = EnvConfig(max_allies=10, max_enemies=10, max_zones=6)
ZONE_KINDS = ("lava", "bush", "swamp")


def _check_ranges(config: EnvConfig, min_units: int, max_units: int, min_zones: int,
                  max_zones: int) -> None:
    if not 1 <= min_units <= max_units:
        raise ValueError(f"expected 1 <= min_units <= max_units, got {min_units}..{max_units}")
    if max_units > min(config.max_allies, config.max_enemies):
        raise ValueError(f"max_units={max_units} exceeds the slots of {config} "
                         f"({config.max_allies} v {config.max_enemies})")
    if not 0 <= min_zones <= max_zones:
        raise ValueError(f"expected 0 <= min_zones <= max_zones, got {min_zones}..{max_zones}")
    if max_zones > config.max_zones:
        raise ValueError(f"max_zones={max_zones} exceeds EnvConfig.max_zones={config.max_zones}")


def random_records(rng: np.random.Generator, config: EnvConfig = RECONFIG_CONFIG,
                   min_units: int = 3, max_units: int = 10, min_zones: int = 0,
                   max_zones: int | None = None) -> tuple[list[dict], list[dict], list[dict]]:
    """(allies, enemies, zones) records of one random level, as `make_level` takes them."""
    max_zones = config.max_zones if max_zones is None else max_zones
    _check_ranges(config, min_units, max_units, min_zones, max_zones)
    width, height = C.ARENA_WIDTH, C.ARENA_HEIGHT

    def team(count: int, x_lo: float, x_hi: float, facing: float) -> list[dict]:
        out = []
        for _ in range(count):
            t = int(rng.integers(0, len(C.UNIT_SPECS)))
            spec = C.UNIT_SPECS[t]
            half_h = height / 2 - spec.radius - 0.5
            out.append(dict(unit=spec.name,
                            position=(float(rng.uniform(x_lo, x_hi)),
                                      float(rng.uniform(-half_h, half_h))),
                            heading=float(facing + rng.uniform(-math.pi / 4, math.pi / 4))))
        return out

    third = width / 6  # allies in [-w/2 + 8, -w/6], enemies mirrored
    allies = team(int(rng.integers(min_units, max_units + 1)), -width / 2 + 8, -third, 0.0)
    enemies = team(int(rng.integers(min_units, max_units + 1)), third, width / 2 - 8, math.pi)
    zones = []
    for _ in range(int(rng.integers(min_zones, max_zones + 1))):
        kind = ZONE_KINDS[int(rng.integers(0, 3))]
        effect = {"lava": float(rng.uniform(5.0, 25.0)), "bush": 0.0,
                  "swamp": float(rng.uniform(0.2, 0.7))}[kind]
        zones.append(dict(type=kind, centre=(float(rng.uniform(-width / 2 + 5, width / 2 - 5)),
                                             float(rng.uniform(-height / 2 + 5, height / 2 - 5))),
                          semi_axes=(float(rng.uniform(3.0, 15.0)), float(rng.uniform(3.0, 12.0))),
                          effect=effect))
    return allies, enemies, zones


def random_level(rng: np.random.Generator, config: EnvConfig = RECONFIG_CONFIG,
                 min_units: int = 3, max_units: int = 10, min_zones: int = 0,
                 max_zones: int | None = None, validate: bool = True) -> EnvParams:
    """One random level padded to `config`, validated like a scenario file (ScenarioError)."""
    allies, enemies, zones = random_records(rng, config, min_units, max_units, min_zones,
                                            max_zones)
    level = make_level(config, allies, enemies, zones)
    if validate:
        from tabx.scenarios.format import level_to_scenario

        level_to_scenario(level, name="random").validate()
    return level


def random_levels(count: int, seed: int = 0, config: EnvConfig = RECONFIG_CONFIG,
                  min_units: int = 3, max_units: int = 10, min_zones: int = 0,
                  max_zones: int | None = None, validate: bool = True) -> list[EnvParams]:
    """`count` random levels from `np.random.default_rng(seed)` (same seed, same levels)."""
    if count < 1:
        raise ValueError(f"expected count >= 1, got {count}")
    rng = np.random.default_rng(seed)
    return [random_level(rng, config, min_units, max_units, min_zones, max_zones, validate)
            for _ in range(count)]


def composition(level: EnvParams, config: EnvConfig = RECONFIG_CONFIG) -> str:
    """Short text of a level's units and zones, e.g. `FSAvsKMH_2L1B` (for progress lines)."""
    active = np.asarray(level.units.active)
    types = np.asarray(level.units.unit_type)
    short = [C.UNIT_SPECS[int(t)].char for t in types]
    allies = "".join(s for s, a in zip(short[:config.max_allies], active[:config.max_allies],
                                       strict=True) if a)
    enemies = "".join(s for s, a in zip(short[config.max_allies:], active[config.max_allies:],
                                        strict=True) if a)
    ztypes = np.asarray(level.zones.zone_type)
    zones = "".join(f"{int((ztypes == k).sum())}{name[0].upper()}"
                    for k, name in enumerate(C.ZONE_NAMES) if k and (ztypes == k).any())
    return f"{allies}vs{enemies}" + (f"_{zones}" if zones else "")


__all__ = ["RECONFIG_CONFIG", "composition", "random_level", "random_levels", "random_records"]
