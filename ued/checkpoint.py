"""Checkpoints of a training run: orbax `CheckpointManager` over (train state, RNG key, update).

A checkpoint holds everything the loop needs to continue exactly where it stopped: the
learner's `TrainState` (parameters, optimiser state, update count) and the loop's PRNG key
(as raw uint32 key data). Saving is synchronous, so a checkpoint is complete on disk when
`save` returns and the next (donating) update cannot race it. Restoring against the
structure of a freshly initialised state gives the saved arrays back bit for bit; a checkpoint
that cannot be restored (a damaged or missing file, a step metadata file that orbax rejects)
is a `CheckpointError` naming its folder; the other steps still restore.

Each checkpoint also carries orbax `custom_metadata`, a small JSON mapping that says what
produced it (`ued.run_folder.checkpoint_metadata`: config hash, update, policy version,
package versions); checkpoints written without it restore all the same, and read back `{}`.

Orbax keeps no checksum of the array values, so `save` records one beside that metadata (under
INTEGRITY_KEY, which `metadata` leaves out): the CRC-32 of every array as saved (dtype, shape and
bytes; a checksum made for damage, several times faster than SHA-256 on a Q-learner's GB replay
buffer), and the SHA-256 of each file the checkpoint goes with (`covers`: the level snapshot of
the same step, written just before it). `restore` and `restore_params` recompute the digests
of what they read: an array that differs is a `CheckpointError` naming the checkpoint, like
one that cannot be read. `file_problem` says which covered file changed (resume's snapshot
check asks it). Checkpoints saved without digests restore unchecked.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import logging
import os
import shutil
import sys
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from ued.errors import ConfigError, gist

INTEGRITY_KEY = "integrity"  # custom metadata: {"arrays": {name: crc32}, "files": {name: sha256}}


class CheckpointError(ConfigError):
    """A checkpoint that cannot be restored; the message names its folder and the cause."""


def leaf_name(path: tuple[Any, ...]) -> str:
    """`train_state/params/dense_0/kernel`: a leaf's key path, the same for a train state
    and for the nested dicts orbax reads back."""
    parts = []
    for entry in path:
        for attr in ("key", "name", "idx"):
            if hasattr(entry, attr):
                parts.append(str(getattr(entry, attr)))
                break
        else:
            parts.append(str(entry))
    return "/".join(parts)


def array_digests(tree: Any) -> dict[str, str]:
    """{leaf name: "crc32:<hex>" of its dtype, shape and bytes} of every array in `tree`
    (copied to the host)."""
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        array = np.ascontiguousarray(np.asarray(leaf))
        crc = zlib.crc32(f"{array.dtype.str} {array.shape}".encode())
        crc = zlib.crc32(array.reshape(-1).view(np.uint8), crc)
        out[leaf_name(path)] = f"crc32:{crc:08x}"
    return out


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


class Checkpoints:
    """The checkpoints of one run folder (`RUN_DIR/checkpoints/<update>/`)."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3, create: bool = True,
                 covers: Sequence[str] = ()):
        """`create=False` reads a run folder without making `directory` (it may be missing:
        no checkpoint yet). `covers`: files that go with a checkpoint, as paths relative to
        the folder above `directory` with `{}` for the update (`levels/state-{}.json`): the
        digest of each that exists when a checkpoint is saved is recorded and checked."""
        self.directory = Path(directory).absolute()
        self.covers = tuple(covers)
        self._options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create,
                                                     enable_async_checkpointing=False)
        _quiet_abandoned_reads()
        self._manager = open_manager(self.directory, self._options)

    def latest(self) -> int | None:
        """The newest saved update number, or None."""
        return self._manager.latest_step()

    def all(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def save(self, update: int, train_state: Any, key: jax.Array,
             metadata: Mapping[str, Any] | None = None) -> None:
        """Save checkpoint `update`, with `metadata` (JSON values) as its custom metadata."""
        item = {"train_state": train_state, "key": np.asarray(jax.random.key_data(key))}
        files = {name: file_digest(path) for name, path in self._covered(update)
                 if path.is_file()}
        custom = {**(metadata or {}),
                  INTEGRITY_KEY: {"arrays": array_digests(item), "files": files}}
        # A failed save's writer threads report themselves (each with a traceback): the caller
        # gets the failure as one CheckpointError instead.
        quiet = _MessageFilter("_SignalingThread.run() raised an exception")
        absl_logger = logging.getLogger("absl")
        absl_logger.addFilter(quiet)
        _quiet_abandoned_reads()
        try:
            self._manager.save(int(update), args=ocp.args.StandardSave(item),
                               custom_metadata=custom)
            self._manager.wait_until_finished()
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise self._save_error(int(update), item, err) from err
        finally:
            absl_logger.removeFilter(quiet)

    def _save_error(self, update: int, item: Any, err: BaseException) -> CheckpointError:
        """The one line a failed save ends in. Its temporary folder (never a checkpoint) is
        removed, so a full disk gets its space back; the checkpoints before stay as they
        were."""
        for partial in self.directory.glob(f"{update}.orbax-checkpoint-tmp*"):
            shutil.rmtree(partial, ignore_errors=True)
        previous = [step for step in self.all() if step != update]
        kept = (f"checkpoint {previous[-1]} is intact" if previous
                else "no checkpoint was saved before")
        chain, cause = [], err
        while cause is not None and len(chain) < 8:
            chain.append(cause)
            cause = cause.__cause__ or cause.__context__
        full = any(getattr(e, "errno", None) == errno.ENOSPC or "RESOURCE_EXHAUSTED" in str(e)
                   or "No space left" in str(e) for e in chain)
        if not full:
            return CheckpointError(f"{self.directory / str(update)}: cannot be saved "
                                   f"({gist(err)}); {kept}")
        need = sum(np.asarray(leaf).nbytes for leaf in jax.tree.leaves(item))
        try:
            free = shutil.disk_usage(self.directory).free
        except OSError:
            free = 0
        return CheckpointError(f"{self.directory / str(update)}: cannot be saved: no space left "
                               f"on the device of {self.directory} ({free / 1e6:.1f} MB free; "
                               f"the checkpoint needs about {need / 1e6:.1f} MB); {kept}; free "
                               f"some space and continue with tabx train --resume "
                               f"{self.directory.parent}")

    def metadata(self, update: int) -> dict[str, Any]:
        """The custom metadata of checkpoint `update`; {} for one saved without any."""
        meta = self._custom_metadata(update)
        meta.pop(INTEGRITY_KEY, None)
        return meta

    def _custom_metadata(self, update: int) -> dict[str, Any]:
        step = step_metadata(self._manager, update)
        return dict(getattr(step, "custom_metadata", None) or {})

    def _covered(self, update: int) -> list[tuple[str, Path]]:
        names = [pattern.format(int(update)) for pattern in self.covers]
        return [(name, self.directory.parent / name) for name in names]

    def _recorded(self, update: int) -> dict[str, Any]:
        """What `save` recorded of checkpoint `update` ({} for one saved without it)."""
        try:
            recorded = self._custom_metadata(update).get(INTEGRITY_KEY)
        except Exception:  # noqa: BLE001 (a damaged _CHECKPOINT_METADATA: nothing recorded)
            recorded = None
        return recorded if isinstance(recorded, dict) else {}

    def has_digests(self, update: int) -> bool:
        """Whether checkpoint `update` recorded the digests of its arrays (one without, or
        whose `_CHECKPOINT_METADATA` cannot be read, restores unchecked)."""
        return isinstance(self._recorded(update).get("arrays"), dict)

    def verify(self, update: int, item: Any) -> None:
        """CheckpointError unless every array of `item` (what was read of checkpoint
        `update`: all of it or a part) has the CRC-32 recorded when it was saved."""
        arrays = self._recorded(update).get("arrays")
        if not isinstance(arrays, dict):
            return  # saved without digests
        for name, digest in array_digests(item).items():
            if arrays.get(name) != digest:
                what = "differs from" if name in arrays else "is missing from"
                raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                      f"(damaged: array {name} {what} the digest recorded "
                                      f"when the checkpoint was saved)")

    def file_problem(self, update: int) -> str | None:
        """What changed in the files checkpoint `update` covers since it was saved (one whose
        SHA-256 differs from the recorded one), or None. A missing file is left to the
        reader of that file to report."""
        files = self._recorded(update).get("files")
        if not isinstance(files, dict):
            return None
        for name, path in self._covered(update):
            if name in files and path.is_file() and file_digest(path) != files[name]:
                return (f"{path}: changed after checkpoint {update} was saved (its SHA-256 "
                        f"differs from the one the checkpoint recorded)")
        return None

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
            step_metadata(self._manager, update)  # a step whose metadata orbax rejects
            item = self._manager.restore(update, args=ocp.args.StandardRestore(abstract))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        self.verify(update, item)
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
            with open_manager(self.directory, options,
                              item_handlers=ocp.StandardCheckpointHandler()) as manager:
                step_metadata(manager, update)  # a step whose metadata orbax rejects
                saved = manager.item_metadata(int(update)).tree
                abstract = jax.tree.map(
                    lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), saved)
                item = manager.restore(int(update), args=ocp.args.StandardRestore(abstract))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        self.verify(int(update), item)
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
            step_metadata(self._manager, update)  # a step whose metadata orbax rejects
            # The manager saved one item, named "default", in the step's folder.
            item = ocp.PyTreeCheckpointer().restore(
                self.directory / str(update) / "default",
                args=ocp.args.PyTreeRestore(item=abstract, restore_args=restore_args,
                                            partial_restore=True))
        except Exception as err:  # noqa: BLE001 (orbax and TensorStore raise many kinds)
            raise CheckpointError(f"{self.directory / str(update)}: cannot be restored "
                                  f"({gist(err)})") from err
        self.verify(update, item)
        params = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), item["train_state"]["params"])
        return params, int(update)

    def reload(self) -> None:
        """Read the step folders again (after some were moved away)."""
        try:
            self._manager.reload()
        except Exception:  # noqa: BLE001 (a damaged step's metadata: see open_manager)
            self._manager.close()
            self._manager = open_manager(self.directory, self._options)

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_manager(directory: Path, options: ocp.CheckpointManagerOptions,
                 **kwargs: Any) -> ocp.CheckpointManager:
    """Orbax's `CheckpointManager` over `directory`, even where a step's
    `_CHECKPOINT_METADATA` is damaged.

    Orbax reads every step's metadata file as it opens (for the step times of retention
    policies this module does not use), and one whose JSON parses into what it cannot take (a
    flipped byte in a key, a list) raises there, for every step at once. Then the manager is
    opened without that read (`lightweight_initialize`): the other steps restore, and the
    damaged one is a `CheckpointError` naming its step when it is read, as with any other
    damaged file."""
    try:
        return ocp.CheckpointManager(directory, options=options, **kwargs)
    except Exception:  # noqa: BLE001 (orbax's metadata parsers raise many kinds)
        light = dataclasses.replace(options, lightweight_initialize=True)
        return ocp.CheckpointManager(directory, options=light, **kwargs)


def step_metadata(manager: ocp.CheckpointManager, update: int) -> Any:
    """Orbax's metadata of step `update` (raises where orbax rejects it). Read without the
    item's handler, orbax warns each time that it cannot restore the item: true, and not
    asked for here, so that warning stays off the terminal."""
    quiet = _MessageFilter("could not be restored. Please provide a `CheckpointHandler")
    absl_logger = logging.getLogger("absl")
    absl_logger.addFilter(quiet)
    try:
        return manager.metadata(int(update))
    finally:
        absl_logger.removeFilter(quiet)


def _is_abandoned_read(unraisable: Any) -> bool:
    """A report of a read orbax abandoned: its reply into the event loop it closed, or one of
    its read coroutines closed unfinished (orbax turns the GeneratorExit of `close` into an
    "Encountered error while reading array index" exception, which Python can only report)."""
    exc = unraisable.exc_value
    if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
        return True
    code = getattr(unraisable.object, "cr_code", None)
    return (isinstance(exc, Exception) and isinstance(exc.__cause__, GeneratorExit)
            and code is not None and "orbax" in code.co_filename)


class _AbandonedTasks(logging.Filter):
    """Drops asyncio's "... exception was never retrieved" records of orbax's and
    TensorStore's tasks and futures."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "exception was never retrieved" not in message:
            return True
        text = message.lower()
        return not any(word in text for word in ("orbax", "tensorstore", "zarr", "ocdbt"))


class _MessageFilter(logging.Filter):
    """Drops the log records whose message contains `text`."""

    def __init__(self, text: str):
        super().__init__()
        self.text = text

    def filter(self, record: logging.LogRecord) -> bool:
        return self.text not in record.getMessage()


_QUIETED = False


def _quiet_abandoned_reads() -> None:
    """Keep the leftovers of a failed restore off the terminal (installed once, when the first
    checkpoints are opened).

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
        if not _is_abandoned_read(unraisable):
            previous(unraisable)

    sys.unraisablehook = hook
    logging.getLogger("asyncio").addFilter(_AbandonedTasks())
    # A step folder without its metadata file (a bogus `checkpoints/999/`) is a CheckpointError
    # naming the step; orbax warns about it once per look at it beforehand.
    logging.getLogger("absl").addFilter(_MessageFilter("Metadata file does not exist: "))


__all__ = ["INTEGRITY_KEY", "CheckpointError", "Checkpoints", "array_digests", "file_digest",
           "leaf_name", "open_manager", "step_metadata"]
