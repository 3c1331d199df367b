"""The run folder: one place for its layout, its config, its checkpoints and the policy in them.

`tabx train` makes and fills it, `--resume` continues it, `tabx eval`, `tabx plot` and
`tabx runs show` read it:

    RUN_DIR/            run.dir/<run name>-<YYYYmmdd-HHMMSS>/
      config.yaml       the resolved config (every field, defaults included), written atomically
      events/           TensorBoard event files (x axis: env steps)
      seed-<s>/         a multi-seed run (`seeds:`): each seed's event files in place of
                        events/; as a policy address (`tabx eval RUN_DIR/seed-<s>`), that
                        seed's policy
      checkpoints/      orbax checkpoints (train state and key chain), the newest
                        `run.keep_checkpoints` kept
      levels/           UED runs: level-buffer snapshots, one per checkpoint (docs/ued.md)
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import jax

from tabx.files import atomic_write_text, not_a_file
from ued.checkpoint import CheckpointError, Checkpoints
from ued.config import (
    TEAMS,
    ConfigError,
    RaySection,
    TrainConfig,
    config_from_dict,
    read_config_file,
)
from ued.experiment import learner_for, seed_keys
from ued.learners.ppo import PPOLearner

CONFIG_FILE = "config.yaml"
EVENTS_DIR = "events"
CHECKPOINT_DIR = "checkpoints"
LEVELS_DIR = "levels"
SET_ASIDE_DIR = "set-aside"  # files a resume or a restart moved away, kept for inspection
SEED_DIR_PREFIX = "seed-"  # RUN_DIR/seed-<s>/: seed s of a multi-seed run
# The level snapshot of a step, in LEVELS_DIR; each checkpoint records their digests.
SNAPSHOT_FILES = ("buffer-{}.msgpack", "learnable-{}.msgpack", "sfl-window-{}.msgpack",
                  "parents-{}.msgpack", "state-{}.json")


def seed_dir(run_dir: str | Path, seed: int) -> Path:
    """The folder of seed `seed` of a multi-seed run: its TensorBoard events."""
    return Path(run_dir) / f"{SEED_DIR_PREFIX}{seed}"


def folder_seed(path: str | Path) -> int | None:
    """The seed a folder named `seed-<s>` is of; None for any other name."""
    name = Path(path).name
    digits = name[len(SEED_DIR_PREFIX):]
    return int(digits) if name.startswith(SEED_DIR_PREFIX) and digits.isdigit() else None


def split_seed_dir(path: str | Path) -> tuple[Path, int | None]:
    """(run folder, seed) of a policy address: a run folder itself (seed None), or the
    `seed-<s>` folder of a multi-seed run (its parent holds the run's config.yaml)."""
    path = Path(path)
    seed = folder_seed(path)
    if (seed is not None and not (path / CONFIG_FILE).is_file()
            and (path.parent / CONFIG_FILE).is_file()):
        return path.parent, seed
    return path, None


def new_run_dir(config: TrainConfig) -> Path:
    """A fresh folder `run.dir/<run name>-<timestamp>` (a suffix if that exists already)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(config.run.dir) / f"{config.run_name}-{stamp}"
    path, i = base, 1
    while path.exists():
        i += 1
        path = base.with_name(f"{base.name}-{i}")
    return path


def create_run_dir(config: TrainConfig, run_dir: str | Path | None = None) -> Path:
    """Make the folder of a new run (`run_dir`, or a fresh one under `config.run.dir`) and
    write its resolved config; ConfigError if it already holds a run."""
    path = Path(run_dir) if run_dir is not None else new_run_dir(config)
    if (path / CONFIG_FILE).exists():
        raise ConfigError(f"{path} already holds a run; continue it with --resume {path}")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{path}: cannot make the run folder ({err.strerror})") from None
    atomic_write_text(path / CONFIG_FILE, config.to_yaml())
    return path


def written_folders(run_dir: str | Path, config: TrainConfig) -> list[Path]:
    """The folders a run writes into: the run folder, its event folders, checkpoints/ and,
    for a UED run, levels/."""
    run_dir = Path(run_dir)
    events = ([seed_dir(run_dir, seed) for seed in config.seeds] if config.seeds
              else [run_dir / EVENTS_DIR])
    levels = [run_dir / LEVELS_DIR] if config.ued.enabled else []
    return [run_dir, *events, run_dir / CHECKPOINT_DIR, *levels]


def check_writable(run_dir: str | Path, config: TrainConfig) -> None:
    """ConfigError naming the first folder a run writes into that is not a folder or cannot
    be written (a read-only file system or permissions), before any work: a file is made in
    each that exists (else in the run folder) and removed again."""
    for folder in written_folders(run_dir, config):
        if folder.exists() and not folder.is_dir():
            raise ConfigError(f"{folder}: not a folder (the run writes its files in it); "
                              "move it away")
        if not folder.exists():
            continue
        try:
            fd, probe = tempfile.mkstemp(dir=folder, prefix=".tabx-write-check-")
            os.close(fd)
            os.unlink(probe)
        except OSError as err:
            raise ConfigError(f"{folder}: not writable ({err.strerror}); the run writes its "
                              "files there") from None


@contextlib.contextmanager
def lock_run_dir(run_dir: str | Path, wait_s: float = 0.0) -> Iterator[None]:
    """Hold the run folder for one writer (a training process) while the block runs;
    ConfigError if another process holds it (at once, or after waiting up to `wait_s` seconds
    for it to let go). The lock is the kernel's `flock` on the folder itself: no file is added,
    and it ends with the process however that ends (a killed run never leaves a stale lock)."""
    path = Path(run_dir)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as err:
        raise ConfigError(f"{path}: cannot open the run folder ({err.strerror})") from None
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    waited = f" (waited {wait_s:.0f} s)" if wait_s else ""
                    raise ConfigError(f"{path}: another process is training this run{waited}; "
                                      "wait for it to end (or stop it) before resuming"
                                      ) from None
                time.sleep(0.5)
        yield
    finally:
        os.close(fd)  # releases the lock


def read_run_config(run_dir: str | Path) -> TrainConfig:
    """The resolved config saved in a run folder."""
    path = Path(run_dir) / CONFIG_FILE
    kind = not_a_file(path)
    if kind == "missing":
        raise ConfigError(f"{run_dir}: not a run folder (no {CONFIG_FILE})")
    if kind is not None:  # never opened: a device or FIFO could block or never end
        raise ConfigError(f"{path}: {kind}; a run folder's config is a YAML file")
    data = read_config_file(path)
    if isinstance(data, dict) and isinstance(data.get("learner"), dict):
        # A resolved config lists every field; one without `matmul_dtype` was written before
        # that field existed, when the networks multiplied in float32: resume and evaluate it
        # that way (docs/learners_internals.md, "Matmul precision").
        data["learner"].setdefault("matmul_dtype", "float32")
    return config_from_dict(data, source=str(path))


def open_checkpoints(run_dir: str | Path, config: TrainConfig, create: bool = True
                     ) -> Checkpoints:
    """The orbax checkpoints of a run folder (close it, or use it as a context manager);
    `create=False` to read them without making the folder. Each checkpoint covers the level
    snapshot of its step (the digests of its files are recorded and checked)."""
    return Checkpoints(Path(run_dir) / CHECKPOINT_DIR, keep=config.run.keep_checkpoints,
                       create=create, covers=[f"{LEVELS_DIR}/{name}" for name in SNAPSHOT_FILES])


def config_hash(config: TrainConfig) -> str:
    """The sha256 of a resolved config as `config.yaml` holds it (every field, in order)."""
    return hashlib.sha256(config.to_yaml().encode()).hexdigest()


def training_hash(config: TrainConfig) -> str:
    """`config_hash` without the `ray:` section: what a resumed run must still match
    (`--resume --ray` may continue a run on another cluster)."""
    return config_hash(dataclasses.replace(config, ray=RaySection()))


def config_change(run_dir: str | Path, config: TrainConfig, checkpoints: Checkpoints
                  ) -> str | None:
    """What says that `config.yaml` (read as `config`) is not the config the newest
    checkpoint was trained with (its recorded `training_sha256` differs), or None; None too
    for checkpoints that record none, or whose metadata cannot be read (resume reports
    those)."""
    for update in reversed(checkpoints.all()):
        try:
            recorded = checkpoints.metadata(update).get("training_sha256")
        except Exception:  # noqa: BLE001 (a damaged checkpoint: resume's checks name it)
            continue
        if not isinstance(recorded, str):
            return None
        if recorded != training_hash(config):
            return (f"{Path(run_dir) / CONFIG_FILE}: differs from the config checkpoint "
                    f"{update} was trained with (its sha256 was recorded then); restore the "
                    "file, or start a new run with this config")
        return None
    return None


def checkpoint_metadata(config: TrainConfig, update: int, policy_version: int
                        ) -> dict[str, Any]:
    """What a checkpoint carries as orbax custom metadata: enough to say, from the checkpoint
    alone, which config, update and policy produced it, and with which software."""
    import flax
    import orbax.checkpoint

    from tabx import __version__

    return {"config_sha256": config_hash(config), "training_sha256": training_hash(config),
            "update": int(update),
            "policy_version": int(policy_version), "algorithm": config.algorithm,
            "ued_method": config.ued.method, "tabx_ued": __version__, "jax": jax.__version__,
            "flax": flax.__version__, "orbax_checkpoint": orbax.checkpoint.__version__}


def run_summary(run_dir: str | Path) -> str:
    """`tabx runs show RUN_DIR`: the run's config and each checkpoint's metadata ("no
    metadata" for checkpoints saved without it)."""
    run_dir = Path(run_dir)
    config = read_run_config(run_dir)
    digest = config_hash(config)
    method = f", ued {config.ued.method}" if config.ued.enabled else ""
    if config.seeds:
        method += f", seeds {', '.join(map(str, config.seeds))}"
    lines = [f"{run_dir}", f"  config       {CONFIG_FILE}: {config.algorithm}{method} on "
                           f"{', '.join(config.env.scenario)}, {config.learner.num_updates} "
                           f"updates; sha256 {digest[:12]}"]
    with open_checkpoints(run_dir, config) as checkpoints:
        updates = checkpoints.all()
        if not updates:
            lines.append("  checkpoints  none yet")
        for update in updates:
            meta = checkpoints.metadata(update)
            if not meta:
                lines.append(f"  checkpoint {update}: no metadata")
                continue
            matches = meta.get("config_sha256") == digest
            same = "= config.yaml" if matches else "differs from config.yaml"
            lines.append(f"  checkpoint {update}: update {meta.get('update')}, policy version "
                         f"{meta.get('policy_version')}, config sha256 "
                         f"{str(meta.get('config_sha256'))[:12]} ({same}); tabx-ued "
                         f"{meta.get('tabx_ued')}, jax {meta.get('jax')}, flax "
                         f"{meta.get('flax')}, orbax-checkpoint {meta.get('orbax_checkpoint')}")
    return "\n".join(lines)


@dataclass(frozen=True)
class TrainedPolicy:
    """A policy loaded from a run folder."""

    run_dir: Path
    config: TrainConfig
    learner: PPOLearner
    params: Any
    update: int
    seed: int | None = None  # the seed of a multi-seed run this policy is

    @property
    def team(self) -> int:
        return TEAMS.index(self.config.env.team)

    def __str__(self) -> str:
        seed = "" if self.seed is None else f", seed {self.seed}"
        return f"{self.run_dir} ({self.config.algorithm}, update {self.update}{seed})"

    def with_episode_limit(self, max_steps: int) -> TrainedPolicy:
        """The same parameters playing episodes of `max_steps` steps. Observations carry no
        clock, so a policy plays a longer or shorter episode than it trained on unchanged;
        only the battle's end (an elimination, or the health ratio at the limit) moves."""
        config = dataclasses.replace(self.config,
                                     env=dataclasses.replace(self.config.env, max_steps=max_steps))
        return dataclasses.replace(self, config=config, learner=learner_for(config))


def load_policy(run_dir: str | Path, checkpoint: int | None = None) -> TrainedPolicy:
    """The policy of a run folder at its newest (or the given) checkpoint. A multi-seed run
    has one policy per seed: `run_dir` names one by its folder, `RUN_DIR/seed-<s>`."""
    address = Path(run_dir)
    run_dir, seed = split_seed_dir(address)
    config = read_run_config(run_dir)
    if config.seeds and seed is None:
        raise ConfigError(f"{run_dir}: a run of seeds {', '.join(map(str, config.seeds))}, "
                          f"one policy each: name one by its folder, e.g. "
                          f"{seed_dir(run_dir, config.seeds[0])}")
    if seed is not None and seed not in config.seeds:
        raise ConfigError(f"{address}: this run has no seed {seed} (its seeds: "
                          f"{', '.join(map(str, config.seeds))})")
    learner = learner_for(config)
    # The parameters alone: their shapes need no allocation, and the rest of the train state
    # (a Q-learner's replay buffer: GBs) is not read.
    if seed is None:
        template = jax.eval_shape(learner.init_params, jax.random.key(0))
    else:  # every seed's parameters, stacked on a leading axis
        template = jax.eval_shape(jax.vmap(learner.init_params), seed_keys(config.seeds))
    with open_checkpoints(run_dir, config, create=False) as ckpts:
        if ckpts.latest() is None:
            raise ConfigError(f"{run_dir}: no checkpoint yet")
        if checkpoint is not None and checkpoint not in ckpts.all():
            raise ConfigError(f"{run_dir}: no checkpoint {checkpoint} (have "
                              f"{', '.join(map(str, ckpts.all()))})")
        try:
            params, update = ckpts.restore_params(template, checkpoint)
        except CheckpointError as err:
            raise CheckpointError(f"{err}; `tabx runs check {run_dir}` lists the intact "
                                  f"checkpoints, `--checkpoint N` picks one") from None
    if seed is not None:
        index = config.seeds.index(seed)
        params = jax.tree.map(lambda x: x[index], params)
    return TrainedPolicy(address, config, learner, params, update, seed)


__all__ = ["CHECKPOINT_DIR", "CONFIG_FILE", "EVENTS_DIR", "LEVELS_DIR", "SEED_DIR_PREFIX",
           "SET_ASIDE_DIR", "SNAPSHOT_FILES", "TrainedPolicy", "check_writable",
           "checkpoint_metadata", "config_change", "config_hash", "create_run_dir",
           "folder_seed", "load_policy", "lock_run_dir", "new_run_dir", "open_checkpoints",
           "read_run_config", "run_summary", "seed_dir", "split_seed_dir", "training_hash",
           "written_folders"]
