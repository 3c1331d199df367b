"""`tabx train`: train MAPPO or IPPO from a config, in a run folder that can be resumed.

Run folder (`run.dir/<run name>-<YYYYmmdd-HHMMSS>/`):

    config.yaml     the resolved config (every field, defaults included), written atomically
    events/         TensorBoard event files (x axis: env steps)
    checkpoints/    orbax checkpoints every `run.checkpoint_every` updates and at the end,
                    the newest `run.keep_checkpoints` kept

The loop is `key, k = split(key); train_state, metrics, _ = learner.update(train_state,
levels, k)`; a checkpoint stores the train state and the key after an update, so
`train(resume=RUN_DIR)` continues with exactly the numbers an uninterrupted run would have
used: its parameters equal the uninterrupted run's bit for bit. Updates run back to back on the
device; metrics come back to the host only every `run.log_every` updates, and nothing is
compiled after the first update.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

import jax
import jax.numpy as jnp

from tabx.files import atomic_write_text
from tabx.params import EnvConfig, EnvParams, stack_levels
from ued import compile_cache
from ued.checkpoint import Checkpoints
from ued.config import ConfigError, TrainConfig, config_from_dict
from ued.learners import make_learner
from ued.learners.ppo import PPOLearner, TrainState
from ued.tensorboard import SummaryWriter

CONFIG_FILE = "config.yaml"
EVENTS_DIR = "events"
CHECKPOINT_DIR = "checkpoints"


def scenario_levels(config: TrainConfig) -> tuple[EnvConfig, list[EnvParams]]:
    """The EnvConfig that fits every scenario of the config, and one level per scenario."""
    from tabx.scenarios import ScenarioError, config_for, load_named

    scenarios = []
    for name in config.env.scenario:
        try:
            scenarios.append(load_named(name))
        except ScenarioError as err:
            raise ConfigError(f"env.scenario: {err}") from None
    env_config = config_for(scenarios, max_steps=config.env.max_steps)
    return env_config, [s.to_level(env_config) for s in scenarios]


def training_levels(config: TrainConfig) -> tuple[EnvConfig, EnvParams]:
    """The batch of `num_envs` levels: the scenarios in turn (env i plays scenario i mod n)."""
    env_config, levels = scenario_levels(config)
    n = config.learner.num_envs
    batch = stack_levels([levels[i % len(levels)] for i in range(n)])
    return env_config, jax.tree.map(jnp.asarray, batch)


def learner_for(config: TrainConfig, env_config: EnvConfig | None = None) -> PPOLearner:
    """The (per-process cached) learner of a config."""
    if env_config is None:
        env_config = scenario_levels(config)[0]
    return make_learner(config.algorithm, env_config, config.learner, config.env.team,
                        config.env.opponent)


def check_devices(config: TrainConfig) -> None:
    """ConfigError if this machine has fewer devices than `learner.num_devices` asks for."""
    from ued.learners.ppo import local_devices

    try:
        local_devices(config.learner.num_devices)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def new_run_dir(config: TrainConfig) -> Path:
    """A fresh folder `run.dir/<run name>-<timestamp>` (a suffix if that exists already)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(config.run.dir) / f"{config.run_name}-{stamp}"
    path, i = base, 1
    while path.exists():
        i += 1
        path = base.with_name(f"{base.name}-{i}")
    return path


def read_run_config(run_dir: str | Path) -> TrainConfig:
    """The resolved config saved in a run folder."""
    import yaml

    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(f"{run_dir}: not a run folder (no {CONFIG_FILE})")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})") from None
    if isinstance(data, dict) and isinstance(data.get("learner"), dict):
        # A resolved config lists every field; one without `matmul_dtype` was written before
        # that field existed, when the networks multiplied in float32: resume and evaluate it
        # that way (docs/learners.md, "Matmul precision").
        data["learner"].setdefault("matmul_dtype", "float32")
    return config_from_dict(data, source=str(path))


class Progress:
    """A one-line progress report on a stream: updates, env steps/s, ETA and the win rate.
    On a terminal the line is rewritten in place; otherwise a line is printed at most every
    `every_s` seconds (and at the end)."""

    def __init__(self, total: int, stream: TextIO | None = None, every_s: float = 10.0):
        self.total = total
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._last = -math.inf

    def show(self, update: int, steps: int, steps_per_s: float, eta_s: float,
             win_rate: float, final: bool = False, first_update_s: float | None = None,
             extra: str = "") -> None:
        now = time.monotonic()
        if not (self.tty or final or now - self._last >= self.every_s):
            return
        self._last = now
        win = "-" if not math.isfinite(win_rate) else f"{win_rate:.2f}"
        if first_update_s is not None:
            rate = f"first update {first_update_s:.1f} s (compilation included)"
        else:
            rate = f"{steps_per_s:,.0f} steps/s  ETA {format_duration(eta_s)}"
        line = f"update {update}/{self.total}  {steps:,} steps  {rate}  win {win}"
        if extra:
            line += f"  ({extra})"
        if self.tty:
            self.stream.write("\r" + line.ljust(110) + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


class ThroughputClock:
    """Wall-clock bookkeeping of a training loop: the first update's seconds (compilation
    included), then env steps/s between reads. Read it only after the device has finished the
    updates being timed (e.g. after `jax.device_get` of their metrics)."""

    def __init__(self, start_update: int, steps_per_update: int):
        self.steps_per_update = steps_per_update
        self.first_update_s: float | None = None
        self._t, self._update = time.perf_counter(), start_update

    @property
    def first_pending(self) -> bool:
        return self.first_update_s is None

    def read(self, done: int) -> tuple[dict[str, float], float]:
        """(metrics to log, steps/s) at update `done`: {"time/first_update_s": s} and NaN on
        the first read, then {} and the rate since the previous read."""
        now = time.perf_counter()
        if self.first_update_s is None:
            self.first_update_s = now - self._t
            out, rate = {"time/first_update_s": self.first_update_s}, math.nan
        else:
            out = {}
            rate = (done - self._update) * self.steps_per_update / max(now - self._t, 1e-9)
        self._t, self._update = now, done
        return out, rate


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"


def train(config: TrainConfig | None = None, *, run_dir: str | Path | None = None,
          resume: bool = False, max_updates: int | None = None, progress: bool = True,
          stream: TextIO | None = None,
          callback: Callable[[int, TrainState, dict[str, Any]], None] | None = None) -> Path:
    """Train; returns the run folder.

    New run: `config` is required; the folder is `run_dir` if given (it must not hold a run
    yet), else a fresh one under `config.run.dir`. Resume: `resume=True` with `run_dir`; the
    config is the run's own. `max_updates` stops after that many updates in this call (the run
    can be resumed later). `callback(update, train_state, metrics)` runs after each logged
    update, with metrics on the host."""
    stream = sys.stderr if stream is None else stream
    if resume:
        if run_dir is None:
            raise ConfigError("resume needs the run folder")
        run_dir = Path(run_dir)
        config = read_run_config(run_dir)
    elif config is None:
        raise ConfigError("a new run needs a config")
    check_devices(config)  # before a new run's folder exists
    if not resume:
        run_dir = Path(run_dir) if run_dir is not None else new_run_dir(config)
        if (run_dir / CONFIG_FILE).exists():
            raise ConfigError(f"{run_dir} already holds a run; continue it with --resume "
                              f"{run_dir}")
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run_dir / CONFIG_FILE, config.to_yaml())

    compile_cache.enable(config.run.compile_cache)
    if config.ued.enabled:
        from workers.driver import train_ued

        return train_ued(config, run_dir, resume=resume, max_updates=max_updates,
                         progress=progress, stream=stream, callback=callback)
    env_config, levels = training_levels(config)
    learner = learner_for(config, env_config)
    ppo = config.learner
    num_updates = ppo.num_updates
    key = jax.random.key(config.seed)
    key, k_init = jax.random.split(key)
    train_state = learner.init(k_init)
    start = 0
    checkpoints = Checkpoints(run_dir / CHECKPOINT_DIR, keep=config.run.keep_checkpoints)
    if resume and checkpoints.latest() is not None:
        train_state, key, start = checkpoints.restore(train_state)
    stop = num_updates if max_updates is None else min(num_updates, start + max_updates)
    bar = Progress(num_updates, stream) if progress else None
    if progress:
        what = "resuming" if resume else "training"
        stream.write(f"{what} {config.algorithm} on {', '.join(config.env.scenario)} "
                     f"({config.env.team} vs {config.env.opponent}) in {run_dir}; "
                     f"{num_updates} updates of {ppo.steps_per_update:,} steps"
                     f"{f', from update {start}' if start else ''}\n")
        stream.flush()

    writer = SummaryWriter(run_dir / EVENTS_DIR)
    try:
        clock = ThroughputClock(start, ppo.steps_per_update)
        for update in range(start, stop):
            key, k_update = jax.random.split(key)
            train_state, metrics, _ = learner.update(train_state, levels, k_update)
            done = update + 1
            last = done == stop
            if clock.first_pending or done % config.run.log_every == 0 or last:
                metrics = dict(jax.device_get(metrics))  # waits for the update
                timing, rate = clock.read(done)
                metrics.update(timing)
                log_update(writer, bar, callback, done, train_state, metrics,
                           ppo.steps_per_update, rate, num_updates, last)
            if done % config.run.checkpoint_every == 0 or last:
                checkpoints.save(done, train_state, key)
    finally:
        writer.close()
        checkpoints.close()
    return run_dir


def log_update(writer: SummaryWriter, bar: Progress | None, callback, done: int,
               train_state: TrainState, metrics: dict[str, Any], steps_per_update: int,
               steps_per_s: float, num_updates: int, last: bool, extra: str = "") -> None:
    """One logged update: TensorBoard scalars, the progress line, the callback."""
    values = {k: float(v) for k, v in metrics.items()}
    if math.isfinite(steps_per_s):
        values["time/steps_per_s"] = steps_per_s
    steps = done * steps_per_update
    writer.scalars(values, step=steps)
    if bar is not None:
        rate = steps_per_s if math.isfinite(steps_per_s) and steps_per_s > 0 else math.nan
        eta = (num_updates - done) * steps_per_update / rate
        bar.show(done, steps, rate, eta, values.get("episode/win_rate", math.nan), final=last,
                 first_update_s=values.get("time/first_update_s"), extra=extra)
    if callback is not None:
        callback(done, train_state, values)


__all__ = ["Progress", "ThroughputClock", "learner_for", "log_update", "new_run_dir",
           "read_run_config", "scenario_levels", "train", "training_levels"]
