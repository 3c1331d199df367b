"""Scenario files: our `tabx-scenario/1` JSON format, the reference-format reader, the bundled
scenarios and composition by name. See docs/scenarios.md.

    from tabx.scenarios import load_named
    level = load_named("2F1M2Avs2S1K_2L2B2S").to_level()
"""

from tabx.scenarios.format import (
    ARENA_RANGE,
    CATEGORIES,
    FORMAT,
    HEURISTIC_RANGES,
    PHYSICS_RANGES,
    UNIT_OVERRIDE_FIELDS,
    UNIT_STAT_RANGES,
    ZONE_EFFECT_RANGES,
    Range,
    Scenario,
    ScenarioError,
    Unit,
    Zone,
    config_for,
    dumps_scenario,
    level_to_scenario,
    load_scenario,
    save_scenario,
)
from tabx.scenarios.reference import read_reference_scenario, reference_to_scenario
from tabx.scenarios.registry import (
    compose,
    list_scenarios,
    load_all,
    load_file,
    load_levels,
    load_named,
    user_scenario_dir,
)

__all__ = [
    "ARENA_RANGE", "CATEGORIES", "FORMAT", "HEURISTIC_RANGES", "PHYSICS_RANGES",
    "UNIT_OVERRIDE_FIELDS", "UNIT_STAT_RANGES", "ZONE_EFFECT_RANGES", "Range", "Scenario",
    "ScenarioError", "Unit", "Zone", "compose", "config_for", "dumps_scenario",
    "level_to_scenario", "list_scenarios", "load_all", "load_file", "load_levels", "load_named",
    "load_scenario", "read_reference_scenario", "reference_to_scenario", "save_scenario",
    "user_scenario_dir",
]
