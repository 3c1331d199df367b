"""One-line descriptions of a scenario: its unit composition (`2F1M`), its zones (`2L1B`), and
a summary line naming both (`tabx scenarios list | show`, the editor's validation)."""

from __future__ import annotations

from collections import Counter

from tabx import constants as C
from tabx.scenarios.format import Scenario

ZONE_LETTER = {"lava": "L", "bush": "B", "swamp": "S"}


def composition(units: list) -> str:
    """`2F1M` style composition string of a list of units."""
    counts = Counter(u.unit for u in units)
    return "".join(f"{counts[s.name]}{s.char}" for s in C.UNIT_SPECS if counts[s.name]) or "-"


def zone_summary(scenario: Scenario) -> str:
    """`2L1B` style count of a scenario's zones by type (`-`: none)."""
    counts = Counter(z.type for z in scenario.zones)
    return "".join(f"{counts[t]}{ZONE_LETTER[t]}" for t in ZONE_LETTER if counts[t]) or "-"


def summary(s: Scenario) -> str:
    """One line: name, category, allies v enemies, zones."""
    return (f"{s.name} ({s.category}{', ' + s.split if s.split else ''}): "
            f"{len(s.allies)} v {len(s.enemies)} units "
            f"({composition(s.allies)} vs {composition(s.enemies)}), "
            f"{len(s.zones)} zones ({zone_summary(s)}), arena {s.arena[0]:g} x {s.arena[1]:g}")


__all__ = ["ZONE_LETTER", "composition", "summary", "zone_summary"]
