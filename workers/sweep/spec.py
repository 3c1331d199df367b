"""Sweep files: a base training config, axes over any config key, and the trials they make.

A sweep file (YAML) names what an experiment is; `tabx sweep SPEC` runs it
(`workers.sweep.tune`), `tabx sweep report SWEEP_DIR` tabulates it (`workers.sweep.report`):

    name: smoke_ued                  # the sweep folder's name (default: the file's stem)
    dir: sweeps                      # where the sweep folder goes (default: sweeps)
    base: ued/quickstart             # a config file (relative to this file) or a shipped name
    set:                             # overrides of every trial: KEY: VALUE
      learner.total_timesteps: 65536
    grid:                            # axes; their cross product is the trials
      ued.method: [dr, plr]          #   a config key: its values
      param:                         #   a named axis: label -> the overrides it stands for
        unit: {levels.free: [unit_spec], ued.eval_suites: ["units-{teams}"]}
        zone: {levels.free: [zone], ued.eval_suites: ["zones-{teams}"]}
      teams: [2F1M2Avs2S1K]          #   a named axis of plain labels: used in {templates}
      seed: [0, 1]
    points:                          # listed trials (after the grid's): config keys, an
      - {name: lr-high, learner.lr: 1.0e-2}   # optional name, an optional base
    resources: {cpus: 1, gpus: 0, explorers: 0}   # what each trial holds while it runs
    max_concurrent: 0                # trials at once (0: as many as the resources allow)
    max_trials: 1000                 # refuse a file that makes more trials (a typo's guard)

`grid` may also be a list of such mappings: the union of their cross products (the paper's
main grid and its ablations). A string value may name the trial's label on another axis as
`{axis}` (`"units-{teams}"`); `base` may too. Axis keys are config keys as `key=value`
overrides write them (`ued.method`, `seed`, `lr`), or `base` (the trial's base config).
A key with a dot must be a config key; a bare name that is a config key's unambiguous field
name (`seed`, `lr`, `scenario`) is that key, any other bare name is a named axis.

Every trial's config is built and validated when the file is read: a mistake in the file, or a
value the config refuses, is one `ConfigError` naming the file, the field and (for a config
error) the trial, before anything runs. The number of trials is counted from the axes before
any is built: more than `max_trials` (default `MAX_TRIALS`) is refused. The sweep's and every
trial's name is one plain folder name (`check_folder_name`). What only a run can find (a
scenario or suite that does not exist, a device the machine lacks) fails that trial alone.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ued.config import (
    ConfigError,
    TrainConfig,
    apply_overrides,
    check_levels_admitted,
    check_ray_overrides,
    config_from_dict,
    read_config_file,
)
from ued.config_files import resolve_config
from ued.yaml_reader import read_yaml

SPEC_KEYS = ("name", "description", "dir", "base", "set", "grid", "points", "resources",
             "max_concurrent", "max_trials", "report")
RESOURCE_KEYS = ("cpus", "gpus", "explorers")
REPORT_KEYS = ("seed_axis", "line_axis", "figure_axis")
POINT_KEYS = ("name", "base")
BASE_KEY = "base"  # an axis or point key: the trial's base config
TEMPLATE = re.compile(r"\{([A-Za-z_][A-Za-z0-9_.]*)\}")
NAME_CHARS = re.compile(r"[^A-Za-z0-9._+=-]+")
# Trials a file may make unless its `max_trials` says more: every trial's config is built and
# validated when the file is read (paper_ued.yaml: 500 in 2.8 s on the 2-core development VM,
# busy), so a grid of 10^4 trials takes a minute or more to read, and a typo (an axis of 100
# values) makes a sweep nobody meant.
MAX_TRIALS = 1000
# A folder name of the sweep folder: `trials/<trial>.json` and Tune's folders must fit a file
# system's 255 bytes a name.
MAX_NAME_BYTES = 200
MAX_EXPLORERS = 1024  # resources.explorers: one placement-group bundle each


@dataclass(frozen=True)
class Resources:
    """What one trial holds while it runs: CPUs and a GPU fraction for the trial's process,
    and one more CPU for each Ray Explorer of a trial that trains with `ray.enabled`."""

    cpus: float = 1.0
    gpus: float = 0.0
    explorers: int = 0

    def bundles(self) -> list[dict[str, float]]:
        """Ray placement-group bundles: the trial's own, then one per Explorer."""
        own = {"CPU": self.cpus, **({"GPU": self.gpus} if self.gpus else {})}
        return [own] + [{"CPU": 1.0} for _ in range(self.explorers)]


@dataclass(frozen=True)
class ReportAxes:
    """Which axes the report uses for what (None: found by name, `SweepSpec.report_axes`)."""

    seed_axis: str | None = None  # results are averaged over this axis
    line_axis: str | None = None  # one line per label in a learning-curve panel
    figure_axis: str | None = None  # one learning-curve figure per label


@dataclass(frozen=True)
class Trial:
    """One run of a sweep: its folder name, its label on each axis, and its config."""

    name: str
    labels: tuple[tuple[str, str], ...]  # (axis, label), in axis order
    config: TrainConfig
    overrides: tuple[str, ...] = ()  # the `key=value` overrides that made it from its base
    base: str = ""

    @property
    def label_map(self) -> dict[str, str]:
        return dict(self.labels)


@dataclass(frozen=True)
class SweepSpec:
    """A read and validated sweep file."""

    name: str
    source: str
    trials: tuple[Trial, ...]
    axes: tuple[str, ...]
    resources: Resources = field(default_factory=Resources)
    max_concurrent: int = 0
    dir: str = "sweeps"
    description: str = ""
    report: ReportAxes = field(default_factory=ReportAxes)
    overrides: tuple[str, ...] = ()  # the command line's KEY=VALUE, applied to every trial

    def folder(self, parent: str | Path | None = None) -> Path:
        """The sweep folder: `parent` (default the file's `dir`) / name."""
        return Path(self.dir if parent is None else parent) / self.name

    def trial(self, name: str) -> Trial:
        for trial in self.trials:
            if trial.name == name:
                return trial
        raise KeyError(name)

    def report_axes(self) -> ReportAxes:
        """The report's axes: as the file names them, else by name: seeds `seed`; lines
        `ued.method`, `method` or `algorithm`; figures `env.scenario`, `teams` or
        `challenge`."""
        def first(*names: str) -> str | None:
            return next((n for n in names if n in self.axes), None)

        return ReportAxes(
            seed_axis=self.report.seed_axis or first("seed"),
            line_axis=self.report.line_axis or first("ued.method", "method", "algorithm"),
            figure_axis=self.report.figure_axis or first("env.scenario", "teams",
                                                         "challenge"))


def _label(value: Any) -> str:
    if isinstance(value, list | tuple):
        return "+".join(_label(v) for v in value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _fill(value: Any, labels: Mapping[str, str], where: str) -> Any:
    """`value` with `{axis}` in its strings replaced by the trial's label on that axis."""
    if isinstance(value, str):
        def sub(match: re.Match) -> str:
            axis = match.group(1)
            if axis not in labels:
                raise ConfigError(f"{where}: {{{axis}}} names no axis of this trial (axes: "
                                  f"{', '.join(labels) or 'none'})")
            return labels[axis]
        return TEMPLATE.sub(sub, value)
    if isinstance(value, list | tuple):
        return [_fill(v, labels, where) for v in value]
    return value


def _override(key: str, value: Any) -> str:
    # JSON is YAML: the override reads back as exactly this value.
    return f"{key}={json.dumps(value)}"


@dataclass(frozen=True)
class _Axis:
    name: str
    # (label, {key: value} of the config keys it sets) for each of its values
    values: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...]


class _ConfigKeys(frozenset):
    """The keys a sweep may set: the config's `section.field` keys, its unambiguous bare names,
    and `section.field` of a section that is not the config's own (the settings section of a
    method or learner given by path, `settings_section`): those are checked when each trial's
    config is read, against the class that trial names."""

    def __contains__(self, key: object) -> bool:
        if frozenset.__contains__(self, key):
            return True
        if not isinstance(key, str) or key.count(".") != 1:
            return False
        section, field_name = key.split(".")
        return (section.isidentifier() and field_name.isidentifier()
                and section not in self.top_level)

    top_level: frozenset[str] = frozenset()


def _config_keys() -> _ConfigKeys:
    """Every key an override may name: `section.field`, bare names that are unambiguous, and
    the fields of a by-path method's or learner's own section (`_ConfigKeys`)."""
    import dataclasses

    from ued.config import TrainConfig, _field_paths

    paths = _field_paths()
    keys = _ConfigKeys({p for ps in paths.values() for p in ps}
                       | {bare for bare, ps in paths.items() if len(ps) == 1})
    keys.top_level = frozenset(f.name for f in dataclasses.fields(TrainConfig))
    return keys


def _read_axis(name: Any, values: Any, where: str, keys: set[str]) -> _Axis:
    where = f"{where}.{name}"
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: an axis name must be a non-empty string")
    is_key = name in keys or name == BASE_KEY
    if "." in name and not is_key:
        raise ConfigError(f"{where}: unknown config key {name!r} (an axis with a dot is a "
                          "config key, e.g. ued.method, learner.lr)")
    if isinstance(values, Mapping):
        if not values:
            raise ConfigError(f"{where}: no values")
        out = []
        for label, sets in values.items():
            if not isinstance(sets, Mapping):
                if is_key:  # {label: value} on a config key: that value under that label
                    sets = {name: sets}
                else:
                    raise ConfigError(f"{where}.{label}: expected a mapping of config keys to "
                                      f"values, got {type(sets).__name__}")
            for key in sets:
                if key not in keys and key != BASE_KEY:
                    raise ConfigError(f"{where}.{label}: unknown config key {key!r}")
            out.append((str(label), tuple(sets.items())))
        return _Axis(name, tuple(out))
    if not isinstance(values, Sequence) or isinstance(values, str) or not values:
        raise ConfigError(f"{where}: expected a non-empty list of values, or a mapping of "
                          "labels to the overrides each stands for")
    return _Axis(name, tuple((_label(v), ((name, v),) if is_key else ())
                             for v in values))


def check_folder_name(name: Any, where: str) -> str:
    """`name` if it is one plain folder name of letters, digits and `. _ + = -`, not `.` or
    `..` (it would name the folder above), at most `MAX_NAME_BYTES`; else a ConfigError."""
    allowed = "letters, digits, . _ + = -; not . or .."
    if not isinstance(name, str) or not name or NAME_CHARS.search(name) or set(name) == {"."}:
        raise ConfigError(f"{where}: expected a folder name ({allowed}), got {name!r:.80}")
    if len(name.encode()) > MAX_NAME_BYTES:
        raise ConfigError(f"{where}: the folder name {name[:40]!r}... is {len(name.encode())} "
                          f"bytes; at most {MAX_NAME_BYTES} (shorten the name or its labels)")
    return name


def _trial_name(labels: Sequence[tuple[str, str]]) -> str:
    parts = []
    for axis, label in labels:
        short = axis.rsplit(".", 1)[-1]
        parts.append(f"{short}{label}" if re.fullmatch(r"-?[0-9.e+-]+", label) else label)
    return NAME_CHARS.sub("_", "-".join(parts)) or "trial"


def read_sweep_spec(path: str | Path, overrides: Sequence[str] = ()) -> SweepSpec:
    """Read and validate a sweep file (a path, or a shipped sweep's name such as
    `sweeps/smoke_ued`); `overrides` (`key=value`) apply to every trial after the file's
    `set`. ConfigError names the file and the field."""
    path = resolve_config(path)
    source = str(path)
    try:
        data = read_yaml(path.read_bytes(), source)
    except OSError as err:
        raise ConfigError(f"{source}: cannot read the sweep file ({err.strerror or err})"
                          ) from None
    try:
        return _spec_from_dict(data, path, tuple(overrides))
    except ConfigError as err:
        text = str(err)
        raise ConfigError(text if text.startswith(source) else f"{source}: {text}") from None


def _spec_from_dict(data: Any, path: Path, extra: tuple[str, ...]) -> SweepSpec:
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping (name, base, grid or points, ...)")
    for key in data:
        if key not in SPEC_KEYS:
            import difflib

            close = difflib.get_close_matches(str(key), SPEC_KEYS, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"unknown key {key!r}{hint} (allowed: {', '.join(SPEC_KEYS)})")
    if "base" not in data:
        raise ConfigError("base: missing (the training config every trial starts from)")
    if "grid" not in data and "points" not in data:
        raise ConfigError("grid: missing (give `grid`, `points`, or both)")
    name = check_folder_name(data.get("name", path.stem), "name")
    keys = _config_keys()
    settings = data.get("set") or {}
    if not isinstance(settings, Mapping):
        raise ConfigError("set: expected a mapping of config keys to values")
    for key in settings:
        if key not in keys:
            raise ConfigError(f"set.{key}: unknown config key {key!r}")
    grids = data.get("grid") or []
    if isinstance(grids, Mapping):
        grids = [grids]
    if not isinstance(grids, Sequence) or not all(isinstance(g, Mapping) for g in grids):
        raise ConfigError("grid: expected a mapping of axes, or a list of them")
    points = data.get("points") or []
    if not isinstance(points, Sequence) or not all(isinstance(p, Mapping) for p in points):
        raise ConfigError("points: expected a list of mappings (config key: value)")

    max_trials = data.get("max_trials", MAX_TRIALS)
    if isinstance(max_trials, bool) or not isinstance(max_trials, int) or max_trials < 1:
        raise ConfigError(f"max_trials: expected an integer >= 1, got {max_trials!r}")

    # (where, labels, {key: value}, explicit name) of each trial, in order
    drafts: list[tuple[str, list[tuple[str, str]], list[tuple[str, Any]], str | None]] = []
    axes: list[str] = []
    grid_axes = []
    for g, grid in enumerate(grids):
        where = "grid" if len(grids) == 1 else f"grid[{g}]"
        if not grid:
            raise ConfigError(f"{where}: no axes")
        grid_axes.append((where, [_read_axis(n, v, where, keys) for n, v in grid.items()]))
    # Counted before any trial is made: the product of the axes' lengths of every grid.
    count = len(points) + sum(math.prod(len(a.values) for a in read) for _, read in grid_axes)
    if count > max_trials:
        sizes = "; ".join(f"{where}: {' x '.join(str(len(a.values)) for a in read)}"
                          for where, read in grid_axes)
        raise ConfigError(f"{count:,} trials ({sizes}; {len(points)} points) is more than "
                          f"max_trials ({max_trials:,}); shrink the grid, or set `max_trials: "
                          f"{count}` in the file if you mean it")
    for where, read in grid_axes:
        axes += [a.name for a in read if a.name not in axes]
        for combo in itertools.product(*(a.values for a in read)):
            labels = [(a.name, label) for a, (label, _) in zip(read, combo, strict=True)]
            sets = [item for _, items in combo for item in items]
            drafts.append((where, labels, sets, None))
    for i, point in enumerate(points):
        where = f"points[{i}]"
        labels, sets = [], []
        for key, value in point.items():
            if key == "name":
                continue
            if key not in keys and key != BASE_KEY:
                raise ConfigError(f"{where}.{key}: unknown config key {key!r}")
            labels.append((key, _label(value)))
            sets.append((key, value))
            if key not in axes:
                axes.append(key)
        explicit = point.get("name")
        if explicit is not None:
            check_folder_name(explicit, f"{where}.name")
        drafts.append((where, labels, sets, explicit))
    if not drafts:
        raise ConfigError("no trials: the grid and the points are empty")

    bases: dict[str, Any] = {}
    trials: list[Trial] = []
    names: dict[str, str] = {}
    for where, labels, sets, explicit in drafts:
        label_map = dict(labels)
        items = [(k, v) for k, v in settings.items()] + sets
        base = next((v for k, v in reversed(items) if k == BASE_KEY), data["base"])
        base = _fill(base, label_map, f"{where}.base")
        if not isinstance(base, str):
            raise ConfigError(f"{where}.base: expected a config file or name, got {base!r}")
        trial_overrides = tuple(_override(k, _fill(v, label_map, f"{where}.{k}"))
                                for k, v in items if k != BASE_KEY) + extra
        trial_name = explicit or check_folder_name(_trial_name(labels),
                                                   f"{where}: a trial's name")
        if trial_name in names:
            raise ConfigError(f"{where}: two trials are named {trial_name!r} "
                              f"({names[trial_name]} and {where}); give points a `name`, or "
                              "axes distinct labels")
        names[trial_name] = where
        if base not in bases:
            candidate = Path(base)
            if not candidate.is_absolute() and (path.parent / candidate).is_file():
                candidate = path.parent / candidate
            resolved = resolve_config(candidate)
            bases[base] = (resolved, read_config_file(resolved))
        resolved, base_data = bases[base]
        try:
            config = config_from_dict(
                apply_overrides(base_data, trial_overrides, source=str(resolved)),
                source=str(resolved))
            check_ray_overrides(config, trial_overrides)
            check_levels_admitted(config)
        except ConfigError as err:
            raise ConfigError(f"{where}, trial {trial_name}: {err}") from None
        trials.append(Trial(trial_name, tuple(labels), config, trial_overrides, str(resolved)))

    seen: dict[str, str] = {}
    for trial in trials:
        # Two trials of one config are a mistake: typically a named axis that sets nothing (a
        # misspelt config key without a dot, a label no {template} uses).
        other = seen.setdefault(repr(trial.config), trial.name)
        if other != trial.name:
            unused = [a for a in axes if a not in keys and a != BASE_KEY]
            hint = (f"; does the named axis {', '.join(map(repr, unused))} set anything (a "
                    "misspelt config key, a label no {template} uses)?" if unused else "")
            raise ConfigError(f"trials {other} and {trial.name} have the same config{hint}")
    resources = resources_from(data.get("resources") or {})
    max_concurrent = data.get("max_concurrent", 0)
    if isinstance(max_concurrent, bool) or not isinstance(max_concurrent, int) or (
            max_concurrent < 0):
        raise ConfigError(f"max_concurrent: expected an integer >= 0 (0: as many as the "
                          f"resources allow), got {max_concurrent!r}")
    parent = data.get("dir", "sweeps")
    if not isinstance(parent, str) or not parent or "\0" in parent:
        raise ConfigError(f"dir: expected a folder, got {parent!r:.80}")
    report = data.get("report") or {}
    if not isinstance(report, Mapping):
        raise ConfigError("report: expected a mapping (seed_axis, line_axis, figure_axis)")
    for key, value in report.items():
        if key not in REPORT_KEYS:
            raise ConfigError(f"report.{key}: unknown key (allowed: {', '.join(REPORT_KEYS)})")
        if value not in axes:
            raise ConfigError(f"report.{key}: {value!r} is no axis (axes: {', '.join(axes)})")
    description = data.get("description", "")
    return SweepSpec(name, str(path), tuple(trials), tuple(axes), resources, max_concurrent,
                     parent, str(description), ReportAxes(**report), extra)


def resources_from(data: Any, base: Resources | None = None,
                   names: Mapping[str, str] | None = None) -> Resources:
    """`base` (default: the defaults) with the values of `data` (cpus, gpus, explorers),
    checked: finite numbers >= 0, explorers an integer up to `MAX_EXPLORERS`, some CPUs or a
    GPU fraction. `names`: what to call each key in an error (`--cpus`); default
    `resources.KEY`."""
    if not isinstance(data, Mapping):
        raise ConfigError("resources: expected a mapping (cpus, gpus, explorers)")
    for key in data:
        if key not in RESOURCE_KEYS:
            raise ConfigError(f"resources.{key}: unknown key (allowed: "
                              f"{', '.join(RESOURCE_KEYS)})")
    name = lambda key: (names or {}).get(key, f"resources.{key}")
    out = {}
    for key in RESOURCE_KEYS:
        if key not in data:
            continue
        value = data[key]
        if (isinstance(value, bool) or not isinstance(value, int | float)
                or not math.isfinite(value) or value < 0):
            raise ConfigError(f"{name(key)}: expected a finite number >= 0, got {value!r}")
        if key == "explorers":
            if value != int(value) or value > MAX_EXPLORERS:
                raise ConfigError(f"{name(key)}: expected an integer in [0, {MAX_EXPLORERS}] "
                                  f"(one CPU each beside the trial), got {value!r}")
            value = int(value)
        out[key] = value if key == "explorers" else float(value)
    resources = replace(base or Resources(), **out)
    if resources.cpus == 0 and resources.gpus == 0:
        raise ConfigError(f"{name('cpus')}, {name('gpus')}: a trial needs some CPUs or a GPU "
                          "fraction")
    return resources


__all__ = ["MAX_EXPLORERS", "MAX_NAME_BYTES", "MAX_TRIALS", "ReportAxes", "Resources",
           "SweepSpec", "Trial", "check_folder_name", "read_sweep_spec", "resources_from"]
