"""The sweep folder: its layout, its list of trials and each trial's record.

    SWEEP_DIR/              <dir>/<name> of the sweep file (workers.sweep.spec)
      sweep.json            the trials: name, labels, run folder, config sha256 (written
                            first), and the command line's KEY=VALUE overrides
      spec.yaml             a copy of the sweep file
      runs/<trial>/         each trial's ordinary run folder (ued.run_folder): `tabx train
                            --resume SWEEP_DIR/runs/<trial>` continues it on its own
      trials/<trial>.json   the trial's record: state, sessions, training seconds, error
      trials/<trial>.log    its training output (progress lines, evaluations, resume notes)
      tune/                 Ray Tune's experiment folders, one per session of the sweep

A record is written by the trial itself (`workers.sweep.tune`) as it goes, atomically; its
`seconds` add up the wall time of every session of the trial (an interrupted session counts
up to its last report). A trial is finished when its record says so and its run folder's
newest checkpoint is its last update.

Both files are checked when read: a `sweep.json` or a record that is not what this module
writes (a list, a missing or mistyped field, a trial name that is not one plain folder name) is
one `ConfigError` naming the file and the field.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tabx.files import atomic_write_text
from ued.config import ConfigError
from ued.run_folder import config_hash
from workers.sweep.spec import REPORT_KEYS, SweepSpec, check_folder_name

SWEEP_FILE = "sweep.json"
SPEC_COPY = "spec.yaml"
RUNS_DIR = "runs"
TRIALS_DIR = "trials"
TUNE_DIR = "tune"
STATES = ("pending", "running", "finished", "failed")


@dataclass
class TrialRecord:
    """What a trial says about itself (trials/<trial>.json)."""

    state: str = "pending"
    sessions: int = 0  # times the trial started or resumed
    seconds: float = 0.0  # training wall time over every session
    steps: int = 0  # env steps done
    total_steps: int = 0
    error: str = ""  # the error of a failed trial, one line
    nodes: list[str] = field(default_factory=list)  # the Ray nodes its sessions ran on
    updated: float = 0.0  # time.time() of the last write


@dataclass(frozen=True)
class SweepTrial:
    """A trial as sweep.json lists it."""

    name: str
    labels: dict[str, str]
    run_dir: str  # relative to the sweep folder
    config_sha256: str


class SweepFolder:
    """A sweep folder on disk (made by `create`, read by `open`)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    # --- layout --------------------------------------------------------------------------

    def run_dir(self, trial: str) -> Path:
        return self.path / RUNS_DIR / trial

    def record_path(self, trial: str) -> Path:
        return self.path / TRIALS_DIR / f"{trial}.json"

    def log_path(self, trial: str) -> Path:
        return self.path / TRIALS_DIR / f"{trial}.log"

    @property
    def tune_dir(self) -> Path:
        return self.path / TUNE_DIR

    # --- the list of trials ------------------------------------------------------------------

    def exists(self) -> bool:
        return (self.path / SWEEP_FILE).is_file()

    def write(self, spec: SweepSpec, *, resume: bool) -> None:
        """Write sweep.json for `spec`. A new sweep needs a folder without one; a resumed one
        must list the same config for every trial it already has (new trials may be added)
        and have been started with the same overrides (`SweepSpec.overrides`)."""
        listed = {t.name: SweepTrial(t.name, t.label_map, f"{RUNS_DIR}/{t.name}",
                                     config_hash(t.config)) for t in spec.trials}
        if self.exists():
            if not resume:
                raise ConfigError(f"{self.path} already holds a sweep; continue it with "
                                  f"--resume (or give another --dir)")
            started = self.overrides()
            if started is not None and list(spec.overrides) != started:
                raise ConfigError(
                    f"{self.path}: the sweep started with the overrides "
                    f"{' '.join(started) or '(none)'}, not {' '.join(spec.overrides) or '(none)'}; "
                    f"resume without overrides (those it started with are reused)")
            for name, old in self.trials().items():
                new = listed.get(name)
                if new is not None and new.config_sha256 != old.config_sha256:
                    source = self.read()["source"]
                    raise ConfigError(
                        f"{self.path}: trial {name} ran with another config than {spec.source} "
                        f"gives it now; resume with the sweep file it started with ({source}), "
                        f"or start a new sweep")
                if new is None:
                    listed[name] = old  # a trial the edited file dropped stays listed
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            (self.path / TRIALS_DIR).mkdir(exist_ok=True)
            (self.path / RUNS_DIR).mkdir(exist_ok=True)
        except OSError as err:
            raise ConfigError(f"{self.path}: cannot make the sweep folder "
                              f"({err.strerror or err}); give another dir (--dir)") from None
        body = {"name": spec.name, "source": spec.source, "overrides": list(spec.overrides),
                "axes": list(spec.axes), "report": asdict(spec.report_axes()),
                "trials": [asdict(t) for t in listed.values()]}
        atomic_write_text(self.path / SWEEP_FILE, json.dumps(body, indent=1) + "\n")
        with contextlib.suppress(OSError):
            atomic_write_text(self.path / SPEC_COPY, Path(spec.source).read_text())

    def read(self) -> dict[str, Any]:
        """sweep.json, checked (`check_sweep_file`)."""
        path = self.path / SWEEP_FILE
        if not path.is_file():
            raise ConfigError(f"{self.path}: not a sweep folder (no {SWEEP_FILE})")
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError) as err:
            raise ConfigError(f"{path}: cannot be read ({err})") from None
        return check_sweep_file(data, path)

    def trials(self) -> dict[str, SweepTrial]:
        return {t["name"]: SweepTrial(**t) for t in self.read()["trials"]}

    def overrides(self) -> list[str] | None:
        """The KEY=VALUE overrides the sweep was started with (None: not recorded)."""
        return self.read()["overrides"] if self.exists() else None

    # --- records -----------------------------------------------------------------------------

    def record(self, trial: str) -> TrialRecord:
        """The trial's record (a new one where it has none), checked (`check_record`)."""
        path = self.record_path(trial)
        if not path.exists():
            return TrialRecord()
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError) as err:
            raise ConfigError(f"{path}: cannot be read ({err}); {_RECORD_HINT}") from None
        return check_record(data, path)

    def write_record(self, trial: str, record: TrialRecord) -> None:
        record.updated = time.time()
        atomic_write_text(self.record_path(trial), json.dumps(asdict(record)) + "\n")


_RECORD_HINT = "delete it to run the trial again from its run folder"


def _expect(ok: bool, path: Path, field_: str, expected: str, value: Any, hint: str = "") -> None:
    if not ok:
        raise ConfigError(f"{path}: {field_}: expected {expected}, got {value!r:.80}"
                          + (f"; {hint}" if hint else ""))


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and (
        math.isfinite(value))


def check_record(data: Any, path: Path) -> TrialRecord:
    """A trial record read from `path`, each field of the type `TrialRecord` gives it (unknown
    fields are left out: a newer version's)."""
    _expect(isinstance(data, dict), path, "the record", "a JSON object", data, _RECORD_HINT)
    checks = {"state": (lambda v: v in STATES, f"one of {', '.join(STATES)}"),
              "sessions": (lambda v: _is_number(v) and v == int(v) and v >= 0,
                           "an integer >= 0"),
              "seconds": (lambda v: _is_number(v) and v >= 0, "a number >= 0"),
              "steps": (lambda v: _is_number(v) and v == int(v) and v >= 0, "an integer >= 0"),
              "total_steps": (lambda v: _is_number(v) and v == int(v) and v >= 0,
                              "an integer >= 0"),
              "error": (lambda v: isinstance(v, str), "a string"),
              "nodes": (lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
                        "a list of node ids"),
              "updated": (lambda v: _is_number(v), "a number")}
    out = {}
    for key, (ok, expected) in checks.items():
        if key in data:
            _expect(ok(data[key]), path, key, expected, data[key], _RECORD_HINT)
            out[key] = data[key]
    for key in ("sessions", "steps", "total_steps"):
        if key in out:
            out[key] = int(out[key])
    return TrialRecord(**out)


def check_sweep_file(data: Any, path: Path) -> dict[str, Any]:
    """sweep.json as `SweepFolder.write` writes it, checked: a mapping with `trials` (each a
    plain folder name with its labels, run folder and config hash), `axes`, `report` and
    `overrides` (those two may be missing: then none)."""
    _expect(isinstance(data, dict), path, SWEEP_FILE, "a JSON object", data)
    name = data.get("name", path.parent.name)
    _expect(isinstance(name, str), path, "name", "a string", name)
    source = data.get("source", "")
    _expect(isinstance(source, str), path, "source", "a string", source)
    axes = data.get("axes", [])
    _expect(isinstance(axes, list) and all(isinstance(a, str) for a in axes), path, "axes",
            "a list of axis names", axes)
    report = data.get("report", {})
    _expect(isinstance(report, dict) and all(
        k in REPORT_KEYS and (v is None or v in axes) for k, v in report.items()),
        path, "report", f"a mapping of {', '.join(REPORT_KEYS)} to axes", report)
    overrides = data.get("overrides")
    _expect(overrides is None or isinstance(overrides, list) and all(
        isinstance(o, str) and "=" in o for o in overrides), path, "overrides",
        "a list of KEY=VALUE strings", overrides)
    trials = data.get("trials")
    _expect(isinstance(trials, list), path, "trials", "a list", trials)
    seen = set()
    for i, trial in enumerate(trials):
        where = f"trials[{i}]"
        _expect(isinstance(trial, dict), path, where, "a JSON object", trial)
        for key in SweepTrial.__dataclass_fields__:
            if key not in trial:
                raise ConfigError(f"{path}: {where}.{key}: missing")
        unknown = set(trial) - set(SweepTrial.__dataclass_fields__)
        _expect(not unknown, path, where, "name, labels, run_dir, config_sha256",
                sorted(unknown))
        try:
            check_folder_name(trial["name"], f"{where}.name")
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
        _expect(trial["name"] not in seen, path, f"{where}.name", "a name no other trial has",
                trial["name"])
        seen.add(trial["name"])
        labels = trial["labels"]
        _expect(isinstance(labels, dict) and all(
            isinstance(k, str) and isinstance(v, str) for k, v in labels.items()),
            path, f"{where}.labels", "a mapping of axis to label", labels)
        for key in ("run_dir", "config_sha256"):
            _expect(isinstance(trial[key], str), path, f"{where}.{key}", "a string", trial[key])
    return {**data, "name": name, "source": source, "axes": axes,
            "report": {k: report.get(k) for k in REPORT_KEYS}, "overrides": overrides,
            "trials": trials}


__all__ = ["RUNS_DIR", "SPEC_COPY", "STATES", "SWEEP_FILE", "TRIALS_DIR", "TUNE_DIR",
           "SweepFolder", "SweepTrial", "TrialRecord", "check_record", "check_sweep_file"]
