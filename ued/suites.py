"""Zero-shot evaluation suites: held-out scenarios and opponents, in YAML files.

A suite is a list of *entries*, each one scenario played against one opponent:

    name: units-2F1M2Avs2S1K          # default: the file name without .yaml
    description: "..."                # optional
    episodes: 64                      # episodes per entry (default 64)
    opponent: heuristic:novice        # default opponent of the entries (default heuristic:novice)
    team: ally                        # the team the evaluated policy plays (default ally)
    scenarios: [A, B, C]              # cross product: every scenario against every opponent
    opponents: [heuristic:novice]     #   (optional; default [opponent])

or, instead of `scenarios` / `opponents`, an explicit list:

    entries:
      - scenario: 2F1M2Avs2S1K_2L2B2S
      - scenario: 2F1M2Avs2S1K_2L2B2S-1
        opponent: heuristic:expert

A scenario is anything `tabx.scenarios.load_named` resolves (a bundled name, a composition
`UNITS_ZONES`, a user scenario or a JSON path). An opponent is `heuristic` (the level's own
heuristic settings), `heuristic:TIER`, `random` or `idle`. Every entry is labelled
`<scenario>@<opponent>` from what it actually plays, so a label never disagrees with its run
(the reference's UED scripts label their tier sweep with a product the runs do not follow).

Bare names are looked up among the suites shipped in `ued/data/suites/` (`list_suites()`);
anything ending in .yaml / .yml or containing a path separator is read as a file. Problems
raise `ConfigError` naming the file and the field (`entries[2].opponent: ...`).
"""

from __future__ import annotations

import difflib
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from ued.errors import ConfigError

SUITE_FOLDER = ("data", "suites")  # inside the `ued` package
DEFAULT_EPISODES = 64
DEFAULT_OPPONENT = "heuristic:novice"  # the paper's UED opponent (the reference's default)
TEAMS = ("ally", "enemy")
SUITE_KEYS = ("name", "description", "episodes", "opponent", "team", "scenarios", "opponents",
              "entries")
ENTRY_KEYS = ("scenario", "opponent")
# The shipped heuristic-tier suites (`tiers-<teams>`: a training configuration against every
# tier) are named with this prefix; a sweep report reads them as the tier table, not as
# held-out suites.
TIER_SUITE_PREFIX = "tiers-"


@dataclass(frozen=True)
class SuiteEntry:
    """One held-out evaluation: a scenario against an opponent (a normalised controller spec)."""

    scenario: str
    opponent: str

    @property
    def label(self) -> str:
        return f"{self.scenario}@{self.opponent}"


@dataclass(frozen=True)
class EvalSuite:
    """A validated suite (see the module docstring)."""

    name: str
    entries: tuple[SuiteEntry, ...]
    episodes: int = DEFAULT_EPISODES
    opponent: str = DEFAULT_OPPONENT
    team: str = "ally"
    description: str = ""
    source: str = field(default="", compare=False)

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(e.label for e in self.entries)

    @property
    def scenarios(self) -> tuple[str, ...]:
        """The distinct scenarios, in entry order."""
        return tuple(dict.fromkeys(e.scenario for e in self.entries))


def suite_dir() -> Any:
    """The folder of the shipped suites (an importlib.resources Traversable)."""
    folder = resources.files("ued")
    for part in SUITE_FOLDER:
        folder = folder / part
    return folder


def list_suites() -> list[str]:
    """Sorted names of the shipped suites."""
    folder = suite_dir()
    if not folder.is_dir():
        return []
    return sorted(e.name.rsplit(".", 1)[0] for e in folder.iterdir()
                  if e.name.endswith((".yaml", ".yml")))


def _looks_like_path(text: str) -> bool:
    return text.endswith((".yaml", ".yml")) or os.sep in text or "/" in text


def load_suite(name_or_path: str | os.PathLike) -> EvalSuite:
    """A shipped suite by name, or a suite file; validated (every scenario must resolve)."""
    text = os.fspath(name_or_path)
    if isinstance(name_or_path, Path) or _looks_like_path(text):
        path = Path(text).expanduser()
        try:
            content = path.read_bytes()
        except OSError as err:
            raise ConfigError(f"{path}: cannot read the suite ({err.strerror or err})") from None
        return parse_suite(content, source=str(path), default_name=path.stem)
    entry = suite_dir() / f"{text}.yaml"
    if not entry.is_file():
        names = list_suites()
        close = difflib.get_close_matches(text, names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"unknown suite {text!r}{hint} (shipped suites: {', '.join(names)}; "
                          f"or give a path to a .yaml file)")
    return parse_suite(entry.read_text(encoding="utf-8"),
                       source=f"ued/{'/'.join(SUITE_FOLDER)}/{text}.yaml", default_name=text)


def parse_suite(text: str | bytes, source: str = "<suite>", default_name: str = "suite"
                ) -> EvalSuite:
    """Validate the YAML text of a suite; errors name `source` and the field."""
    from ued.yaml_reader import read_yaml

    data = read_yaml(text, source)
    try:
        return suite_from_dict(data, default_name=default_name, source=source)
    except ConfigError as err:
        raise ConfigError(f"{source}: {err}") from None


def _unknown_keys(data: dict, allowed: tuple[str, ...], where: str) -> None:
    for key in data:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"{where}unknown key {key!r}{hint} (allowed: "
                              f"{', '.join(allowed)})")


def _string(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{key}: expected a non-empty string, got {value!r}")
    return value


def _string_list(value: Any, key: str) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{key}: expected a non-empty list, got {value!r}")
    return [_string(v, f"{key}[{i}]") for i, v in enumerate(value)]


def normalise_opponent(text: Any, key: str) -> str:
    """The canonical spec of an opponent controller (`heuristic:novice`, `random`, ...)."""
    from tabx.controllers import Controller

    text = _string(text, key)
    try:
        return str(Controller.parse_scripted(text, "an opponent"))
    except ValueError as err:
        raise ConfigError(f"{key}: {err}") from None


def _check_scenario(name: str, key: str) -> None:
    from tabx.scenarios import ScenarioError, load_named

    try:
        scenario = load_named(name)
    except ScenarioError as err:
        raise ConfigError(f"{key}: {err}") from None
    if not scenario.units:
        raise ConfigError(f"{key}: {name!r} has no units (a zone-only scenario); compose it "
                          f"with a unit scenario, e.g. 2F1M2Avs2S1K_{name}")


def suite_from_dict(data: Any, default_name: str = "suite", source: str = "") -> EvalSuite:
    """Validate a parsed suite (errors name the field, not the file: see `parse_suite`)."""
    if not isinstance(data, dict):
        raise ConfigError(f"expected a mapping of keys to values at the top level, got "
                          f"{type(data).__name__}")
    _unknown_keys(data, SUITE_KEYS, "")
    name = _string(data.get("name", default_name), "name")
    if any(c.isspace() for c in name):
        raise ConfigError(f"name: must not contain spaces (it is a TensorBoard tag), got "
                          f"{name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"description: expected a string, got {description!r}")
    episodes = data.get("episodes", DEFAULT_EPISODES)
    if isinstance(episodes, bool) or not isinstance(episodes, int):
        raise ConfigError(f"episodes: expected an integer, got {episodes!r}")
    if episodes < 1:
        raise ConfigError(f"episodes: must be >= 1, got {episodes}")
    team = data.get("team", "ally")
    if team not in TEAMS:
        raise ConfigError(f"team: must be one of {', '.join(TEAMS)}, got {team!r}")
    opponent = normalise_opponent(data.get("opponent", DEFAULT_OPPONENT), "opponent")

    entries: list[tuple[SuiteEntry, str]] = []  # (entry, its field for errors)
    if "entries" in data:
        if "scenarios" in data or "opponents" in data:
            raise ConfigError("entries: give either `entries` or `scenarios` (with optional "
                              "`opponents`), not both")
        items = data["entries"]
        if not isinstance(items, list) or not items:
            raise ConfigError(f"entries: expected a non-empty list, got {items!r}")
        for i, item in enumerate(items):
            key = f"entries[{i}]"
            if isinstance(item, str):
                item = {"scenario": item}
            if not isinstance(item, dict):
                raise ConfigError(f"{key}: expected a mapping with scenario (and opponent), "
                                  f"got {item!r}")
            _unknown_keys(item, ENTRY_KEYS, f"{key}: ")
            if "scenario" not in item:
                raise ConfigError(f"{key}.scenario: missing")
            scenario = _string(item["scenario"], f"{key}.scenario")
            opp = normalise_opponent(item.get("opponent", opponent), f"{key}.opponent")
            entries.append((SuiteEntry(scenario, opp), f"{key}.scenario"))
    elif "scenarios" in data:
        scenarios = _string_list(data["scenarios"], "scenarios")
        opponents = ([normalise_opponent(o, f"opponents[{i}]")
                      for i, o in enumerate(_string_list(data["opponents"], "opponents"))]
                     if "opponents" in data else [opponent])
        for i, scenario in enumerate(scenarios):
            for opp in opponents:
                entries.append((SuiteEntry(scenario, opp), f"scenarios[{i}]"))
    else:
        raise ConfigError("entries: missing; give `entries` or `scenarios`")

    seen: dict[str, str] = {}
    checked: set[str] = set()
    for entry, key in entries:
        if entry.label in seen:
            raise ConfigError(f"{key}: {entry.scenario!r} against {entry.opponent} is already "
                              f"in the suite ({seen[entry.label]})")
        seen[entry.label] = key
        if entry.scenario not in checked:
            _check_scenario(entry.scenario, key)
            checked.add(entry.scenario)
    return EvalSuite(name=name, entries=tuple(e for e, _ in entries), episodes=episodes,
                     opponent=opponent, team=team, description=description, source=source)


__all__ = ["DEFAULT_EPISODES", "DEFAULT_OPPONENT", "TIER_SUITE_PREFIX", "EvalSuite", "SuiteEntry",
           "list_suites", "load_suite", "normalise_opponent", "parse_suite", "suite_dir",
           "suite_from_dict"]
