"""Where a batch of envs lives: split evenly over the local devices of JAX's default backend.

A vmapped rollout has no communication between envs, so a batch placed with `env_sharding` runs
as one program per device, each on its share of the envs, side by side. On a CPU, the `tabx`
command makes one device per core (`tabx.xla_flags.apply()`, which a program of your own may
call before JAX starts): XLA:CPU runs most of a simulator step's small kernels
on one thread, so two devices with half the envs each keep both cores busy (docs/benchmarks.md,
"Both cores"). The split changes where each env is computed, not what: the states are those of
one device bit for bit; an observation value may differ in its last bit (XLA compiles the split
program's fusions on their own, tests/ued/test_devices.py).
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

ENV_AXIS = "envs"


def available_devices(wanted: int = 0) -> list[jax.Device]:
    """This process's devices of JAX's default backend; ValueError if there are fewer than
    `wanted` (saying how to ask for more CPU devices)."""
    available = jax.local_devices()
    if wanted > len(available):
        hint = ("; the tabx command makes one CPU device per core (tabx.xla_flags.apply() "
                "before JAX starts), XLA_FLAGS=--xla_force_host_platform_device_count=N asks "
                "for N"
                if available[0].platform == "cpu" else "")
        raise ValueError(f"{wanted} devices asked for, {len(available)} available "
                         f"({available[0].platform}){hint}")
    return available


def env_devices(num_envs: int, wanted: int = 0) -> tuple[jax.Device, ...]:
    """The local devices a batch of `num_envs` envs is split over: `wanted` of them (an error
    if there are fewer, or if they do not split the envs evenly), or with 0 the most that split
    them evenly."""
    if num_envs < 1:
        raise ValueError(f"num_envs must be at least 1, got {num_envs}")
    if wanted < 0:
        raise ValueError(f"devices must be 0 (all that split the envs evenly) or more, "
                         f"got {wanted}")
    available = available_devices(wanted)
    if wanted:
        if num_envs % wanted:
            raise ValueError(f"{num_envs} envs do not split evenly over {wanted} devices")
        return tuple(available[:wanted])
    count = max(d for d in range(1, len(available) + 1) if num_envs % d == 0)
    return tuple(available[:count])


def env_sharding(devices: tuple[jax.Device, ...]) -> NamedSharding:
    """Leading (env) axis split over `devices`, every other axis whole."""
    return NamedSharding(Mesh(np.asarray(devices), (ENV_AXIS,)), PartitionSpec(ENV_AXIS))


__all__ = ["ENV_AXIS", "available_devices", "env_devices", "env_sharding"]
