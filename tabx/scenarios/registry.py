"""Bundled scenarios by name, unit + zone composition, user scenario folder and file paths.

Names resolve in this order: a path to a JSON file (ours or the reference format, detected);
a bundled scenario (tabx/data/scenarios/{challenges,units,zones}, read with importlib.resources
so it works from an installed package); a scenario in `user_scenario_dir()`; a composition
`UNITS_ZONES` such as `2F1M2Avs2S1K_2L2B2S` (the part before `_` is a unit scenario, the part
after a zone scenario). A unit scenario alone gets no zones (the reference's `void`). Challenges
carry their own zones and cannot take a zone suffix.
"""

from __future__ import annotations

import difflib
import functools
import os
import sys
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

from tabx import constants as C
from tabx import params as P
from tabx.scenarios.format import (
    CATEGORIES,
    Scenario,
    ScenarioError,
    config_for,
    parse_json,
    read_json,
)
from tabx.scenarios.reference import (
    is_reference_format,
    read_reference_scenario,
    reference_to_scenario,
)

BUNDLED_FOLDERS = {"challenge": "challenges", "units": "units", "zones": "zones"}
USER_DIR_ENV = "TABX_SCENARIO_DIR"


def user_scenario_dir() -> Path:
    """Where user scenarios live: $TABX_SCENARIO_DIR or ~/.local/share/tabx/scenarios. A
    $TABX_SCENARIO_DIR that exists but is not a folder is named in one warning line (once):
    no user scenario is read from it."""
    env = os.environ.get(USER_DIR_ENV)
    path = Path(env).expanduser() if env else Path.home() / ".local/share/tabx/scenarios"
    if env and path.exists() and not path.is_dir():
        _warn_once(f"warning: {USER_DIR_ENV}={env}: not a folder; no user scenario is read "
                   "from it (point it at a folder)")
    return path


@functools.cache
def _warn_once(message: str) -> None:
    print(message, file=sys.stderr)


@functools.lru_cache(maxsize=1)
def _bundled() -> dict[str, tuple[str, Any]]:
    """name -> (category, file) of every bundled scenario (names are unique across folders)."""
    root = resources.files("tabx") / "data" / "scenarios"
    index: dict[str, tuple[str, Any]] = {}
    for category, folder in BUNDLED_FOLDERS.items():
        directory = root / folder
        if not directory.is_dir():
            continue
        for entry in directory.iterdir():
            if entry.name.endswith(".json"):
                index[entry.name[: -len(".json")]] = (category, entry)
    return index


# Sub-folders of the user folder that hold scenarios too (the editor saves into them by category).
USER_FOLDERS = {**BUNDLED_FOLDERS, "user": "user"}


def _user_files() -> dict[str, Path]:
    """name -> file of every user scenario: the folder itself, then its category sub-folders;
    the first file of a name wins."""
    root = user_scenario_dir()
    found: dict[str, Path] = {}
    for folder in (root, *(root / f for f in USER_FOLDERS.values())):
        if folder.is_dir():
            for path in sorted(folder.glob("*.json")):
                found.setdefault(path.stem, path)
    return found


def list_scenarios(category: str | None = None, include_user: bool = True) -> list[str]:
    """Sorted names of bundled (and user) scenarios, optionally of one category.

    User files are listed under the category their file declares ("user" if unreadable); a user
    name that repeats a bundled name is skipped, since the bundled one wins on load.
    """
    if category is not None and category not in CATEGORIES:
        raise ScenarioError(f"unknown category {category!r}; expected one of "
                            f"{', '.join(CATEGORIES)}")
    names = {n for n, (c, _) in _bundled().items() if category in (None, c)}
    if include_user:
        for name, path in _user_files().items():
            if name in _bundled():
                continue
            if category is None or _declared_category(path) == category:
                names.add(name)
    return sorted(names)


def _declared_category(path: Path) -> str:
    try:
        data = read_json(path)
    except ScenarioError:
        return "user"
    if isinstance(data, dict) and isinstance(data.get("category"), str):
        return data["category"]
    return "user"


def bundled_category(name: str) -> str | None:
    """The category of a bundled scenario, or None."""
    entry = _bundled().get(name)
    return entry[0] if entry else None


def load_file(path: str | os.PathLike, name: str | None = None) -> Scenario:
    """Load a scenario file in our format or the reference format (detected from its keys)."""
    path = Path(path)
    data = read_json(path)
    if is_reference_format(data):
        return read_reference_scenario(path, name=name)
    return Scenario.from_dict(data, source=str(path))


def _load_bundled(name: str) -> Scenario:
    category, entry = _bundled()[name]
    source = f"tabx/data/scenarios/{BUNDLED_FOLDERS[category]}/{entry.name}"
    data = parse_json(entry.read_text(encoding="utf-8"), source)
    if is_reference_format(data):  # not expected for bundled files, but harmless
        return reference_to_scenario(data, name)
    return Scenario.from_dict(data, source=source)


def _load_single(name: str) -> Scenario | None:
    """A bundled or user scenario by exact name, or None."""
    if name in _bundled():
        return _load_bundled(name)
    user = _user_files().get(name)
    if user is not None:
        return load_file(user, name=name)
    return None


def _looks_like_path(name: str) -> bool:
    return name.endswith(".json") or os.sep in name or "/" in name


def load_named(name: str) -> Scenario:
    """A scenario by name, composition `UNITS_ZONES`, or path (see the module docstring)."""
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"expected a scenario name or path, got {name!r}")
    if _looks_like_path(name):
        if not Path(name).expanduser().is_file():
            raise ScenarioError(f"no such scenario file: {name}")
        return load_file(Path(name).expanduser())
    single = _load_single(name)
    if single is not None:
        return single
    if "_" not in name:
        raise _unknown(name)
    parts = name.split("_")
    if len(parts) != 2 or not all(parts):
        raise ScenarioError(f"cannot read {name!r}: a composed name is UNITS_ZONES with exactly "
                            "one '_', e.g. 2F1M2Avs2S1K_2L2B2S")
    unit_name, zone_name = parts
    units = _load_single(unit_name)
    if units is None:
        raise _unknown(unit_name, f"unit scenario of {name!r}")
    zones = _load_single(zone_name)
    if zones is None:
        raise _unknown(zone_name, f"zone scenario of {name!r}")
    return compose(units, zones, name)


def compose(units: Scenario, zones: Scenario, name: str | None = None) -> Scenario:
    """The units of one scenario with the zones of another (same arena)."""
    name = name or f"{units.name}_{zones.name}"
    if not units.units:
        raise ScenarioError(f"{units.name!r} has no units: the part before '_' must be a unit "
                            "scenario", source=name)
    if units.category == "challenge" or units.zones:
        what = "is a challenge" if units.category == "challenge" else "has its own zones"
        raise ScenarioError(f"{units.name!r} {what} and cannot take a zone suffix: load "
                            f"{units.name!r} alone", source=name)
    if zones.units:
        raise ScenarioError(f"{zones.name!r} has units: the part after '_' must be a zone "
                            "scenario (zone-only file)", source=name)
    if units.arena != zones.arena:
        raise ScenarioError(f"arena {units.arena} of {units.name!r} differs from arena "
                            f"{zones.arena} of {zones.name!r}", source=name)
    split = "eval" if "eval" in (units.split, zones.split) else units.split
    return replace(units, name=name, zones=zones.zones, split=split,
                   physics=units.physics if units.physics is not None else zones.physics,
                   heuristic=units.heuristic if units.heuristic is not None else zones.heuristic,
                   description=f"units of {units.name}, zones of {zones.name}")


def _unknown(name: str, what: str = "scenario") -> ScenarioError:
    candidates = list(_bundled()) + list(_user_files())
    close = difflib.get_close_matches(name, candidates, n=5, cutoff=0.5)
    hint = f"; close matches: {', '.join(close)}" if close else ""
    return ScenarioError(f"unknown {what} {name!r}{hint} (see `tabx scenarios list`; a user "
                         f"scenario goes in {user_scenario_dir()})")


def load_all(category: str | None = None) -> dict[str, Scenario]:
    """name -> Scenario for every listed scenario of a category (bundled and user)."""
    return {n: load_named(n) for n in list_scenarios(category)}


def load_levels(names: Any, max_steps: int = C.DEFAULT_MAX_STEPS
                ) -> tuple[P.EnvConfig, P.EnvParams]:
    """Named scenarios (names, compositions or paths, as `load_named` takes them) as one batch
    of levels: `(config, levels)`, `config` the smallest `EnvConfig` that fits them all and
    every leaf of `levels` with a leading axis of `len(names)`, in the order given."""
    if isinstance(names, str):
        raise ScenarioError(f"expected a sequence of scenario names, got the string {names!r}")
    scenarios = [load_named(name) for name in names]
    if not scenarios:
        raise ScenarioError("load_levels needs at least one scenario name")
    config = config_for(scenarios, max_steps=max_steps)
    return config, P.stack_levels([s.to_level(config) for s in scenarios])
