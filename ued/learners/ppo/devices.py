"""Data parallel over devices: the one-axis mesh a PPO learner splits its envs over, placing
an update's arguments on it and bringing its results back, and the all-reduce of a shard's
gradients.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
from jax.flatten_util import ravel_pytree

from tabx.devices import available_devices
from tabx.params import EnvParams
from ued.learners import distributed

ENVS = "envs"  # the mesh axis data-parallel learners split their envs over


def local_devices(wanted: int = 0) -> list[jax.Device]:
    """This process's devices (of JAX's default backend); ValueError naming
    `learner.num_devices` if there are fewer than `wanted` (`tabx.devices.available_devices`)."""
    try:
        return available_devices(wanted)
    except ValueError as err:
        raise ValueError(f"learner.num_devices: {err}") from None


@functools.lru_cache(maxsize=8)
def env_mesh(devices: tuple[jax.Device, ...]) -> jax.sharding.Mesh:
    """The one-axis mesh (`ENVS`) over `devices`, built once per device set."""
    return jax.sharding.Mesh(devices, (ENVS,))


def on_devices(fn: Any, devices: tuple[jax.Device, ...], state: Any, levels: EnvParams,
                key: jax.Array) -> Any:
    """`fn(state, levels, key)` with `state` and `key` replicated on `devices` and `levels`
    split over them by env, the results brought back to the first device (where the caller's
    arrays live). On one device, `fn` as it is. Over a learner group's devices the same, with
    the arguments equal in every process and the results whole in every process."""
    if len(devices) == 1:
        return fn(state, levels, key)
    mesh = env_mesh(devices)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    by_env = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(ENVS))
    if distributed.spans_processes(devices):  # each process places its own share
        out = fn(distributed.to_global(state, replicated), distributed.to_global(levels, by_env),
                 distributed.to_global(key, replicated))
        return distributed.to_local(out, mesh, jax.local_devices()[0])
    out = fn(jax.device_put(state, replicated), jax.device_put(levels, by_env),
             jax.device_put(key, replicated))
    return jax.device_put(out, devices[0])



def psum_flat(tree: Any, axis_name: str) -> Any:
    """`lax.psum` of a whole tree as one flat vector: the same sums, one all-reduce. XLA's
    gloo collectives (CPU processes) run a tuple all-reduce leaf by leaf, a round trip each:
    MAPPO's 34 gradient and metric leaves took a 2-process group 2.39 s per update, one
    vector 1.83 s (docs/benchmarks_distributed.md, "Learner groups")."""
    flat, unflatten = ravel_pytree(tree)
    return unflatten(jax.lax.psum(flat, axis_name))



__all__ = ["ENVS", "env_mesh", "local_devices", "on_devices", "psum_flat"]
