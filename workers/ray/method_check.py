"""Check a UED method on every driver, as its author's tests would: `check_method(config, ...)`
trains the config's curriculum (a built-in name or an import path) for a few steps on

    the local driver                      the reference
    Ray's deterministic schedule          must equal it bit for bit: parameters, optimiser
                                          state, key and every level-snapshot file
    Ray's continuous schedule             must reach the same step with every Explorer batch it
                                          issued committed exactly once

and raises `MethodCheckError` naming the first thing that differs (docs/new_method.md). It runs
on the Ray this process has started (`ray.init`), or starts a local one. The asynchronous
schedule is the continuous one's machinery with sequential steps; the deterministic schedule is
the one whose results are defined, hence the equality.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ued.config import TrainConfig, apply_overrides
from ued.run_folder import CHECKPOINT_DIR, LEVELS_DIR
from workers.train import train


class MethodCheckError(AssertionError):
    """A method behaves differently on two drivers (the message says where)."""


@dataclass
class MethodCheck:
    """The three runs of `check_method`: their run folders and the continuous run's record."""

    local: Path
    deterministic: Path
    continuous: Path
    continuous_record: dict[str, Any]


def _with(config: TrainConfig, **overrides: Any) -> TrainConfig:
    from ued.config import config_from_dict

    data = apply_overrides(config.to_dict(), [f"{k}={v}" for k, v in overrides.items()])
    return config_from_dict(data, source="check_method")


def _final_state(run_dir: Path, config: TrainConfig) -> tuple[Any, np.ndarray, int]:
    from ued.checkpoint import Checkpoints
    from workers.ued_step import UEDRun

    template = UEDRun.local(config)[1].init(jax.random.key(0))
    with Checkpoints(run_dir / CHECKPOINT_DIR) as checkpoints:
        state, key, step = checkpoints.restore(template)
    return state, np.asarray(jax.random.key_data(key)), step


def _same(a: Any, b: Any) -> bool:
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(leaves_a) == len(leaves_b) and all(
        np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(leaves_a, leaves_b,
                                                                      strict=True))


def check_method(config: TrainConfig, folder: str | Path, steps: int = 4,
                 explorers: int = 2) -> MethodCheck:
    """Train `config` for `steps` steps on the three drivers in `folder` (module doc); raise
    `MethodCheckError` where they disagree."""
    import ray

    folder = Path(folder)
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=1 + explorers, include_dashboard=False, logging_level="ERROR")
    try:
        local = train(config, run_dir=folder / "local", stream=io.StringIO(),
                      max_updates=steps)
        deterministic = train(_with(config, **{"ray.enabled": "true",
                                               "ray.deterministic": "true",
                                               "ray.explorers": explorers}),
                              run_dir=folder / "deterministic", stream=io.StringIO(),
                              max_updates=steps)
        continuous = train(_with(config, **{"ray.enabled": "true",
                                            "ray.schedule": "continuous",
                                            "ray.explorers": explorers}),
                           run_dir=folder / "continuous", stream=io.StringIO(),
                           max_updates=steps)
    finally:
        if started:
            ray.shutdown()
    a, b = _final_state(local, config), _final_state(deterministic, config)
    if a[2] != b[2] or a[2] != steps:
        raise MethodCheckError(f"steps reached: local {a[2]}, deterministic {b[2]}, asked "
                               f"for {steps}")
    for what, x, y in (("parameters", a[0].params, b[0].params),
                       ("optimiser state", a[0].opt_state, b[0].opt_state), ("key", a[1], b[1])):
        if not _same(x, y):
            raise MethodCheckError(f"the deterministic Ray schedule's {what} differ from the "
                                   f"local driver's after {steps} steps")
    for path in sorted((local / LEVELS_DIR).iterdir()):
        other = deterministic / LEVELS_DIR / path.name
        if not other.is_file() or other.read_bytes() != path.read_bytes():
            raise MethodCheckError(f"level snapshot {path.name}: the deterministic Ray "
                                   f"schedule's differs from the local driver's")
    record = json.loads((continuous / "ray.json").read_text())
    if record.get("ledger") != {"committed": steps}:
        raise MethodCheckError(f"continuous schedule: steps {record.get('ledger')}, expected "
                               f"{steps} committed")
    batches = record.get("explorer_batches", {})
    if set(batches) - {"committed"}:
        raise MethodCheckError(f"continuous schedule: Explorer batches {batches}: each must be "
                               f"committed exactly once")
    return MethodCheck(local, deterministic, continuous, record)


__all__ = ["MethodCheck", "MethodCheckError", "check_method"]
