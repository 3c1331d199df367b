"""The sweep folder: its layout, its list of trials and each trial's record.

    SWEEP_DIR/              <dir>/<name> of the sweep file (ued.sweep_spec)
      sweep.json            the trials: name, labels, run folder, config sha256 (written first)
      spec.yaml             a copy of the sweep file
      runs/<trial>/         each trial's ordinary run folder (ued.run_folder): `tabx train
                            --resume SWEEP_DIR/runs/<trial>` continues it on its own
      trials/<trial>.json   the trial's record: state, sessions, training seconds, error
      trials/<trial>.log    its training output (progress lines, evaluations, resume notes)
      tune/                 Ray Tune's experiment folders, one per session of the sweep

A record is written by the trial itself (`workers.sweep`) as it goes, atomically; its
`seconds` add up the wall time of every session of the trial (an interrupted session counts
up to its last report). A trial is finished when its record says so and its run folder's
newest checkpoint is its last update.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tabx.files import atomic_write_text
from ued.config import ConfigError
from ued.run_folder import config_hash
from ued.sweep_spec import SweepSpec

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
        must list the same config for every trial it already has (new trials may be added)."""
        listed = {t.name: SweepTrial(t.name, t.label_map, f"{RUNS_DIR}/{t.name}",
                                     config_hash(t.config)) for t in spec.trials}
        if self.exists():
            if not resume:
                raise ConfigError(f"{self.path} already holds a sweep; continue it with "
                                  f"--resume (or give another --dir)")
            for name, old in self.trials().items():
                new = listed.get(name)
                if new is not None and new.config_sha256 != old.config_sha256:
                    raise ConfigError(
                        f"{self.path}: trial {name} ran with another config than {spec.source} "
                        f"gives it now; resume with the sweep file it started with (a copy is "
                        f"{self.path / SPEC_COPY}), or start a new sweep")
                if new is None:
                    listed[name] = old  # a trial the edited file dropped stays listed
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / TRIALS_DIR).mkdir(exist_ok=True)
        (self.path / RUNS_DIR).mkdir(exist_ok=True)
        body = {"name": spec.name, "source": spec.source, "axes": list(spec.axes),
                "report": asdict(spec.report_axes()),
                "trials": [asdict(t) for t in listed.values()]}
        atomic_write_text(self.path / SWEEP_FILE, json.dumps(body, indent=1) + "\n")
        with contextlib.suppress(OSError):
            atomic_write_text(self.path / SPEC_COPY, Path(spec.source).read_text())

    def read(self) -> dict[str, Any]:
        path = self.path / SWEEP_FILE
        if not path.is_file():
            raise ConfigError(f"{self.path}: not a sweep folder (no {SWEEP_FILE})")
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise ConfigError(f"{path}: cannot be read ({err})") from None

    def trials(self) -> dict[str, SweepTrial]:
        return {t["name"]: SweepTrial(**t) for t in self.read()["trials"]}

    # --- records -----------------------------------------------------------------------------

    def record(self, trial: str) -> TrialRecord:
        path = self.record_path(trial)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            return TrialRecord()
        known = TrialRecord.__dataclass_fields__
        return TrialRecord(**{k: v for k, v in data.items() if k in known})

    def write_record(self, trial: str, record: TrialRecord) -> None:
        record.updated = time.time()
        atomic_write_text(self.record_path(trial), json.dumps(asdict(record)) + "\n")


__all__ = ["RUNS_DIR", "SPEC_COPY", "STATES", "SWEEP_FILE", "TRIALS_DIR", "TUNE_DIR",
           "SweepFolder", "SweepTrial", "TrialRecord"]
