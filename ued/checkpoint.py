"""Checkpoints of a training run: orbax `CheckpointManager` over (train state, RNG key, update).

A checkpoint holds everything the loop needs to continue exactly where it stopped: the
learner's `TrainState` (parameters, optimiser state, update count) and the loop's PRNG key
(as raw uint32 key data). Saving is synchronous, so a checkpoint is complete on disk when
`save` returns and the next (donating) update cannot race it. Restoring against the
structure of a freshly initialised state gives the saved arrays back bit for bit.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp


class Checkpoints:
    """The checkpoints of one run folder (`RUN_DIR/checkpoints/<update>/`)."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3):
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True,
                                               enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest(self) -> int | None:
        """The newest saved update number, or None."""
        return self._manager.latest_step()

    def all(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def save(self, update: int, train_state: Any, key: jax.Array) -> None:
        item = {"train_state": train_state, "key": np.asarray(jax.random.key_data(key))}
        self._manager.save(int(update), args=ocp.args.StandardSave(item))
        self._manager.wait_until_finished()

    def restore(self, template: Any, update: int | None = None) -> tuple[Any, jax.Array, int]:
        """(train state, key, update) of checkpoint `update` (default: the newest), with the
        structure of `template` (a train state of the same learner)."""
        update = self.latest() if update is None else update
        if update is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        key_shape = jax.random.key_data(jax.random.key(0)).shape
        abstract = {"train_state": jax.tree.map(ocp.utils.to_shape_dtype_struct, template),
                    "key": jax.ShapeDtypeStruct(key_shape, np.uint32)}
        item = self._manager.restore(update, args=ocp.args.StandardRestore(abstract))
        key = jax.random.wrap_key_data(jnp.asarray(np.asarray(item["key"], np.uint32)))
        # Plain (uncommitted) arrays, like a freshly initialised state: a jitted update then
        # sees the same argument signature and does not compile again.
        state = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), item["train_state"])
        return state, key, int(update)

    def restore_params(self, template: Any, update: int | None = None) -> tuple[Any, int]:
        """(parameters, update) of checkpoint `update` (default: the newest) without reading
        the rest of the train state (the optimiser state, a Q-learner's replay buffer of some
        GB): what a policy needs. `template`: the train state's `params`, as arrays or
        `jax.ShapeDtypeStruct`s (`jax.eval_shape` of the learner's `init` allocates nothing)."""
        update = self.latest() if update is None else update
        if update is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        struct = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype)
        abstract = {"train_state": {"params": jax.tree.map(struct, template)}}
        restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), abstract)
        # The manager saved one item, named "default", in the step's folder.
        item = ocp.PyTreeCheckpointer().restore(
            self.directory / str(update) / "default",
            args=ocp.args.PyTreeRestore(item=abstract, restore_args=restore_args,
                                        partial_restore=True))
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


__all__ = ["Checkpoints"]
