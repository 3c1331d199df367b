"""The driver interface: who runs the workers of a training run, and where.

A driver takes a validated `TrainConfig` and a run folder that holds its `config.yaml`
(`ued.run_folder`), and trains: a plain MARL run, or a UED run whose LevelService, Learner,
Explorers and Evaluators it wires together. Two implementations:

    workers.local.LocalDriver     every worker in this process, sequentially (the default;
                                  Ray is not imported)
    workers.ray.driver.RayDriver  the workers as Ray actors, on this machine or a cluster

Both write the same run folder (checkpoints, level snapshots, TensorBoard events), so a run
started by one can be evaluated, plotted and resumed with the same commands.
`workers.train.train` is the entry point that makes or reopens the run folder and picks the
driver.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from ued.config import TrainConfig

# callback(update, train_state, metrics): after every logged update, metrics on the host.
Callback = Callable[[int, Any, dict[str, float]], None]


class RunStopped(RuntimeError):
    """A run stopped before its end for a reason outside the user's input (a worker died);
    the message says how to continue it. `lost`: the name of the lost actor that stopped it,
    where one did ("learner" for the learner or any member of its learner group)."""

    def __init__(self, message: str, lost: str = ""):
        super().__init__(message)
        self.lost = lost


class Driver(abc.ABC):
    """Runs (or continues) one training run in its run folder."""

    name: str = ""

    def check(self, config: TrainConfig) -> None:
        """Refuse, before the run folder is made, a run this driver cannot start (ConfigError
        naming the setting). The local driver can start any valid config."""
        return None

    @abc.abstractmethod
    def run(self, config: TrainConfig, run_dir: Path, *, resume: bool = False,
            max_updates: int | None = None, progress: bool = True,
            stream: TextIO | None = None, callback: Callback | None = None) -> Path:
        """Train `config` in `run_dir`; with `resume`, from the newest checkpoint there.
        `max_updates` stops after that many updates in this call (the run can be resumed);
        `progress` prints a progress line to `stream` (default stderr). Returns `run_dir`."""


__all__ = ["Callback", "Driver", "RunStopped"]
