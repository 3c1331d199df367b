"""Checkpoints of a training run: orbax `CheckpointManager` over (train state, RNG key, update).

A checkpoint holds everything the loop needs to continue exactly where it stopped: the
learner's `TrainState` (parameters, optimiser state, update count) and the loop's PRNG key
(as raw uint32 key data). Saving is synchronous, so a checkpoint is complete on disk when
`save` returns and the next (donating) update cannot race it. Restoring against the
structure of a freshly initialised state gives the saved arrays back bit for bit; a checkpoint
that cannot be restored (a damaged or missing file) is a `CheckpointError` naming its folder.

Each checkpoint also carries orbax `custom_metadata`, a small JSON mapping that says what
produced it (`ued.run_folder.checkpoint_metadata`: config hash, update, policy version,
package versions); checkpoints written without it restore all the same, and read back `{}`.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from ued.errors import ConfigError, gist


class CheckpointError(ConfigError):
    """A checkpoint that cannot be restored; the message names its folder and the cause."""



class Checkpoints:
    """The checkpoints of one run folder (`RUN_DIR/checkpoints/<update>/`)."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3, create: bool = True):
        """`create=False` reads a run folder without making `directory` (it may be missing:
        no checkpoint yet)."""
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create,
                                               enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest(self) -> int | None:
        """The newest saved update number, or None."""
        return self._manager.latest_step()

    def all(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def save(self, update: int, train_state: Any, key: jax.Array,
             metadata: Mapping[str, Any] | None = None) -> None:
        """Save checkpoint `update`, with `metadata` (JSON values) as its custom metadata."""
        item = {"train_state": train_state, "key": np.asarray(jax.random.key_data(key))}
        self._manager.save(int(update), args=ocp.args.StandardSave(item),
                           custom_metadata=dict(metadata) if metadata else None)
        self._manager.wait_until_finished()

    def metadata(self, update: int) -> dict[str, Any]:
        """The custom metadata of checkpoint `update`; {} for one saved without any."""
        step = self._manager.metadata(int(update))
        return dict(getattr(step, "custom_metadata", None) or {})

    def restore(self, template: Any, update: int | None = None,
                key_template: jax.Array | None = None) -> tuple[Any, jax.Array, int]:
        """(train state, key, update) of checkpoint `update` (default: the newest), with the
        structure of `template` (a train state of the same learner) and the key's shape that
        of `key_template` (default: one key; a multi-seed run stores one per seed)."""
        update = self.latest() if update is None else update
        if update is None:
            raise CheckpointError(f"{self.directory}: no checkpoint")
        key_template = jax.random.key(0) if key_template is None else key_template
        key_shape = jax.random.key_data(key_template).shape
        abstract = {"train_state": jax.tree.map(ocp.utils.to_shape_dtype_struct, template),
                    "key": jax.ShapeDtypeStruct(key_shape, np.uint32)}
        _quiet_abandoned_reads()
        try:
            item = self._manager.restore(update, args=ocp.args.StandardRestore(abstract))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        key = jax.random.wrap_key_data(jnp.asarray(np.asarray(item["key"], np.uint32)))
        # Plain (uncommitted) arrays, like a freshly initialised state: a jitted update then
        # sees the same argument signature and does not compile again.
        state = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), item["train_state"])
        return state, key, int(update)

    def restore_saved(self, update: int) -> tuple[Any, jax.Array, int]:
        """(train state, key, update) of checkpoint `update`, read with the structure, shapes
        and dtypes it was saved with (its `_METADATA`) instead of a template: what checking a
        run folder needs, without building the learner. Every array is read, so a checkpoint
        that `restore` cannot read fails here too; the train state comes back as nested dicts
        and lists of arrays on this process's first device."""
        device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        options = ocp.CheckpointManagerOptions(create=False, enable_async_checkpointing=False)
        _quiet_abandoned_reads()
        try:
            with ocp.CheckpointManager(self.directory, options=options,
                                       item_handlers=ocp.StandardCheckpointHandler()) as manager:
                saved = manager.item_metadata(int(update)).tree
                abstract = jax.tree.map(
                    lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), saved)
                item = manager.restore(int(update), args=ocp.args.StandardRestore(abstract))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        key = jax.random.wrap_key_data(jnp.asarray(np.asarray(item["key"], np.uint32)))
        return item["train_state"], key, int(update)

    def restore_params(self, template: Any, update: int | None = None) -> tuple[Any, int]:
        """(parameters, update) of checkpoint `update` (default: the newest) without reading
        the rest of the train state (the optimiser state, a Q-learner's replay buffer of some
        GB): what a policy needs. `template`: the train state's `params`, as arrays or
        `jax.ShapeDtypeStruct`s (`jax.eval_shape` of the learner's `init` allocates nothing)."""
        update = self.latest() if update is None else update
        if update is None:
            raise CheckpointError(f"{self.directory}: no checkpoint")
        struct = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype)
        abstract = {"train_state": {"params": jax.tree.map(struct, template)}}
        restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), abstract)
        _quiet_abandoned_reads()
        try:
            # The manager saved one item, named "default", in the step's folder.
            item = ocp.PyTreeCheckpointer().restore(
                self.directory / str(update) / "default",
                args=ocp.args.PyTreeRestore(item=abstract, restore_args=restore_args,
                                            partial_restore=True))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        params = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), item["train_state"]["params"])
        return params, int(update)

    def reload(self) -> None:
        """Read the step folders again (after some were moved away)."""
        self._manager.reload()

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_abandoned_read(exc: BaseException | None) -> bool:
    return isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"


class _AbandonedTasks(logging.Filter):
    """Drops asyncio's "... exception was never retrieved" records of orbax's and
    TensorStore's tasks and futures."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "exception was never retrieved" not in message:
            return True
        text = message.lower()
        return not any(word in text for word in ("orbax", "tensorstore", "zarr", "ocdbt"))


_QUIETED = False


def _quiet_abandoned_reads() -> None:
    """Keep the leftovers of a failed restore off the terminal (installed once, at the first
    restore).

    Orbax reads a checkpoint's arrays concurrently on an event loop that it closes as soon as
    the first read fails; the reads still in flight then complete into the closed loop, and
    Python reports each (one "RuntimeError: Event loop is closed" traceback per array, some
    at exit) while asyncio logs the tasks and futures whose errors nobody retrieved, some
    before the restore has returned. The caller gets the error that matters (a
    `CheckpointError`), so those two kinds of report are dropped; every other one is
    reported as before."""
    global _QUIETED
    if _QUIETED:
        return
    _QUIETED = True
    previous = sys.unraisablehook

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if not _is_abandoned_read(unraisable.exc_value):
            previous(unraisable)

    sys.unraisablehook = hook
    logging.getLogger("asyncio").addFilter(_AbandonedTasks())


__all__ = ["CheckpointError", "Checkpoints"]
