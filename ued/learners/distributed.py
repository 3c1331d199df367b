"""One PPO update over the devices of several processes: JAX's multi-process runtime.

A learner group is N processes (on one machine or many) that each call

    distributed.join(coordinator="HOST:PORT", num_processes=N, process_id=i)

before JAX starts its backend, then run the same program: the same `learner.init(key)`, then
`learner.update(train_state, levels, key)` with the same arguments in every process. Process 0
hosts the coordinator at HOST:PORT (a port free on its node). After `join`, the learner's
data-parallel update (`PPOLearner.learner_devices`, ued/learners/ppo/train.py) runs over a global
mesh of every process's devices: each process puts only its own share of the envs on its
devices (`to_global`), plays those envs, and the gradients and statistics are reduced across
processes by XLA's collectives inside the one jitted program (the `psum`s of the update),
over gloo between CPU processes and NCCL between GPUs; nothing else differs. The results
come back whole in every process (`to_local`): the parameters are replicated by
construction, and the per-env rollout statistics are gathered by one more XLA collective.

Process p's devices hold envs [p * E / N, (p + 1) * E / N) of the batch, in the order of the
global mesh (every process's devices, process 0's first), the split that one process with
all the devices makes: so 2 processes x 1 device compute what 1 process x 2 devices does.

Failures: a process that dies (SIGKILL, OOM) stops answering the coordinator's heartbeats;
after `heartbeat_timeout_s` the coordination service ends the other processes, whose
collective would otherwise wait for ever. A group is never repaired in place: whoever runs
it starts a new one (workers/ray/learner_group.py restarts a Ray learner group from the last
checkpoint).
"""

from __future__ import annotations

import functools
import os
import socket
from typing import Any

import jax
import numpy as np

JOIN_TIMEOUT_S = 120  # for every process of the group to reach the coordinator
HEARTBEAT_TIMEOUT_S = 10  # a process silent this long is dead: the group stops
GLOO_LOOP_NICENESS = 19  # `calm_gloo_loop`


def join(coordinator: str, num_processes: int, process_id: int, *,
         timeout_s: int = JOIN_TIMEOUT_S, heartbeat_timeout_s: int = HEARTBEAT_TIMEOUT_S,
         local_device_ids: list[int] | None = None) -> None:
    """Make this process member `process_id` of a group of `num_processes` whose coordinator
    is at `coordinator` (HOST:PORT; process 0 starts it there). Call before any JAX
    computation (it starts JAX's backend, then calms gloo's event loop: `calm_gloo_loop`);
    blocks until every member has joined (at most `timeout_s`). One process
    (`num_processes` 1) joins nothing."""
    if num_processes < 1 or not 0 <= process_id < num_processes:
        raise ValueError(f"process {process_id} of {num_processes}: expected 0 <= id < n")
    if num_processes == 1:
        return
    # The CPU client's collectives between processes; GPUs use NCCL whatever this says.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id, local_device_ids=local_device_ids,
                               initialization_timeout=int(timeout_s),
                               heartbeat_timeout_seconds=int(heartbeat_timeout_s),
                               shutdown_timeout_seconds=int(heartbeat_timeout_s))
    calm_gloo_loop()


def share_cores(rank: int, count: int) -> list[int]:
    """Pin this process to its share of the CPUs it may run on: the `rank`-th of `count` equal
    slices, for `count` members of a group on one machine (a remainder stays unused). Call
    before JAX starts its backend: XLA sizes its CPU thread pools by this process's CPUs, so
    the members' pools and gloo threads do not contend for the same cores. Returns the CPUs
    kept (all of them where there are fewer CPUs than members, or one member)."""
    cpus = sorted(os.sched_getaffinity(0))
    per = len(cpus) // max(count, 1)
    if count <= 1 or per == 0:
        return cpus
    mine = cpus[rank * per:(rank + 1) * per]
    os.sched_setaffinity(0, mine)
    return mine


# gloo's TCP event loop, told from the other threads by what it waits in: epoll_wait(fd,
# events, 64, 10 ms), as /proc/<tid>/syscall lists it on x86_64 Linux (syscall 232).
_GLOO_LOOP_SYSCALL = ("232", "0x40", "0xa")


def gloo_loop_threads(tries: int = 50) -> list[int]:
    """The thread ids of gloo's TCP event loop in this process: empty where none is found
    (no gloo collectives, not x86_64 Linux), after `tries` looks 20 ms apart (the loop is
    waiting whenever no message is in flight)."""
    import platform
    import time

    if platform.system() != "Linux" or platform.machine() != "x86_64":
        return []
    for attempt in range(tries):
        found = []
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/syscall") as f:
                    call = f.read().split()
            except OSError:  # the thread ended
                continue
            if len(call) >= 5 and (call[0], call[3], call[4]) == _GLOO_LOOP_SYSCALL:
                found.append(int(tid))
        if found or attempt == tries - 1:
            return found
        time.sleep(0.02)
    return []


def calm_gloo_loop(niceness: int = GLOO_LOOP_NICENESS) -> list[int]:
    """Give gloo's event loop thread the lowest priority; returns its thread ids. The loop
    polls without pause while a message waits for a receive this process has not posted yet
    (a peer ahead of it in the update), and took up to half of a core from this process's
    own compute (docs/benchmarks_distributed.md, "Learner groups"); at niceness 19 it runs
    when the compute waits, which is when its messages matter. Creates JAX's backend."""
    if jax.default_backend() != "cpu":  # GPUs reduce over NCCL: no gloo loop to calm
        return []
    tids = gloo_loop_threads()
    for tid in tids:
        os.setpriority(os.PRIO_PROCESS, tid, niceness)  # Linux: a thread's own niceness
    return tids


def leave() -> None:
    """Leave the group (a no-op outside one)."""
    if jax.process_count() > 1:
        jax.distributed.shutdown()


def free_address(host: str = "127.0.0.1") -> str:
    """HOST:PORT with a port free on this machine now: for a coordinator that starts here."""
    with socket.socket() as s:
        s.bind((host, 0))
        return f"{host}:{s.getsockname()[1]}"


def group_devices(per_process: int) -> tuple[jax.Device, ...]:
    """The first `per_process` devices of every process of the group, process 0's first:
    the global mesh's order (module doc)."""
    devices: list[jax.Device] = []
    for p in range(jax.process_count()):
        mine = sorted((d for d in jax.devices() if d.process_index == p), key=lambda d: d.id)
        if len(mine) < per_process:
            raise ValueError(f"learner.num_devices: process {p} has {len(mine)} devices, "
                             f"{per_process} asked for")
        devices.extend(mine[:per_process])
    return tuple(devices)


def spans_processes(devices: tuple[jax.Device, ...]) -> bool:
    """Whether `devices` include another process's (a group's global mesh)."""
    here = jax.process_index()
    return any(d.process_index != here for d in devices)


def to_global(tree: Any, sharding: jax.sharding.Sharding) -> Any:
    """`tree`, whole and equal in every process, as global arrays with `sharding`: each
    process puts only the parts its own devices hold."""
    def one(x: Any) -> jax.Array:
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            impl = jax.random.key_impl(x)
            data = to_global(jax.random.key_data(x), sharding)
            return jax.random.wrap_key_data(data, impl=impl)
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(one, tree)


@functools.lru_cache(maxsize=8)
def _gather(mesh: jax.sharding.Mesh) -> Any:
    """The jitted identity whose results are replicated over `mesh` (one per mesh, so its
    compiled programs are reused)."""
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    return jax.jit(lambda xs: xs, out_shardings=replicated)


def to_local(tree: Any, mesh: jax.sharding.Mesh, device: jax.Device) -> Any:
    """Global arrays of `tree` whole on this process's `device`: a replicated array's local
    copy; a split one gathered first (an XLA all-gather, which every process runs)."""
    leaves, treedef = jax.tree.flatten(tree)
    split = [i for i, x in enumerate(leaves) if not x.is_fully_replicated]
    if split:
        gathered = _gather(mesh)([leaves[i] for i in split])
        for i, x in zip(split, gathered, strict=True):
            leaves[i] = x
    return jax.device_put(jax.tree.unflatten(treedef, [x.addressable_data(0) for x in leaves]),
                          device)


__all__ = ["GLOO_LOOP_NICENESS", "HEARTBEAT_TIMEOUT_S", "JOIN_TIMEOUT_S", "calm_gloo_loop",
           "free_address", "gloo_loop_threads", "group_devices", "join", "leave", "share_cores",
           "spans_processes", "to_global", "to_local"]
