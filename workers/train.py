"""`train`: the library entry of `tabx train`. Makes or reopens the run folder, then hands the
run to a driver (`workers.driver`).

    from workers.train import train
    run_dir = train(load_config("configs/ued/quickstart.yaml"))      # a new run
    train(run_dir=run_dir, resume=True)                              # continue it

New run: `config` is required; the folder is `run_dir` if given (it must not hold a run yet),
else a fresh one under `config.run.dir` (`ued.run_folder`). Resume: `resume=True` with
`run_dir`; the config is the run's own `config.yaml`, with `ray` (if given) in place of its
`ray:` section, so a run can continue on another machine or cluster, with another number of
Explorers. The persistent compilation cache is switched on per `run.compile_cache` before
anything compiles.
"""

from __future__ import annotations

import dataclasses
import sys
from contextlib import nullcontext
from pathlib import Path
from typing import TextIO

from ued import compile_cache
from ued.config import ConfigError, RaySection, TrainConfig, check_levels_admitted
from ued.experiment import check_devices, check_memory, scenario_levels
from ued.run_folder import (
    check_writable,
    config_change,
    create_run_dir,
    lock_run_dir,
    open_checkpoints,
    read_run_config,
)
from workers.driver import Callback, Driver
from workers.local import LocalDriver
from workers.ray.continuous import ContinuousRun
from workers.ray.driver import RayDriver
from workers.ray.start import keep_driver_off_accelerators
from workers.resume import step_intact


def finished_at(run_dir: Path, config: TrainConfig) -> int | None:
    """The last update of a run whose newest checkpoint is its last and intact, else None (a
    damaged last step is resumed from the newest intact one, as any other)."""
    with open_checkpoints(run_dir, config) as checkpoints:
        latest = checkpoints.latest()
        if latest is None or latest < config.learner.num_updates:
            return None
        return latest if step_intact(run_dir, checkpoints, config, latest) else None


def driver_for(config: TrainConfig) -> Driver:
    """The driver a config asks for: Ray's with `ray.enabled` (with its continuous schedule),
    else the local one."""
    if not config.ray.enabled:
        return LocalDriver()
    return RayDriver(schedules={"continuous": ContinuousRun})


def train(config: TrainConfig | None = None, *, run_dir: str | Path | None = None,
          resume: bool = False, max_updates: int | None = None, progress: bool = True,
          stream: TextIO | None = None, callback: Callback | None = None,
          driver: Driver | None = None, ray: RaySection | None = None,
          locked: bool = False) -> Path:
    """Train; returns the run folder. `driver` overrides the one the config asks for; `ray`
    replaces a resumed run's `ray:` section; `locked`: the caller holds `run_dir`'s lock
    (`lock_run_dir`) already, as a sweep's trial does."""
    if resume:
        if run_dir is None:
            raise ConfigError("resume needs the run folder")
        run_dir = Path(run_dir)
        config = read_run_config(run_dir)
        if ray is not None:
            config = dataclasses.replace(config, ray=ray).validate()
    elif config is None:
        raise ConfigError("a new run needs a config")
    if config.ray.enabled:  # before anything below can start JAX's backends
        keep_driver_off_accelerators()
    driver = driver if driver is not None else driver_for(config)
    if resume:
        assert run_dir is not None
        # One writer: a second --resume of it is refused.
        with nullcontext() if locked else lock_run_dir(run_dir):
            check_writable(run_dir, config)
            with open_checkpoints(run_dir, config) as checkpoints:
                changed = config_change(run_dir, config, checkpoints)
            if changed is not None:
                raise ConfigError(changed)
            done = finished_at(Path(run_dir), config)
            if done is not None:
                out = sys.stderr if stream is None else stream
                out.write(f"{run_dir}: already complete ({done} of "
                          f"{config.learner.num_updates} updates); nothing to resume\n")
                return Path(run_dir)
            return _start(driver, config, Path(run_dir), resume, max_updates, progress,
                          stream, callback)
    check_levels_admitted(config)
    _check_start(driver, config)
    run_dir = create_run_dir(config, run_dir)
    with nullcontext() if locked else lock_run_dir(run_dir):
        return _start(driver, config, run_dir, resume, max_updates, progress, stream, callback)


def _check_start(driver: Driver, config: TrainConfig) -> None:
    """What is checked before a new run's folder exists: the driver (first: the Ray driver
    keeps JAX off accelerators before it starts), devices, scenarios, memory."""
    driver.check(config)
    if not config.ray.enabled:  # a Ray run's learner checks its devices on its own node
        check_devices(config)
    env_config, levels = scenario_levels(config)
    if not config.ray.enabled:  # a Ray run's learner and Explorers may live on other machines
        check_memory(config, env_config, levels[0])


def _start(driver: Driver, config: TrainConfig, run_dir: Path, resume: bool,
           max_updates: int | None, progress: bool, stream: TextIO | None,
           callback: Callback | None) -> Path:
    if resume:
        _check_start(driver, config)
    compile_cache.enable(config.run.compile_cache)
    return driver.run(config, run_dir, resume=resume, max_updates=max_updates,
                      progress=progress, stream=stream, callback=callback)


__all__ = ["driver_for", "train"]
