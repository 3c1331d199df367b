"""`tabx bench train --learners 1,2`: the training benchmark with its update run by a learner
group of N processes (`ued.learners.distributed`) beside the one-process update.

N = 1 runs in the benchmark's own process (all its devices: one per core on a CPU). N > 1
starts N member processes on this machine (`python -m tabx_bench.group_member`), each with
its share of the cores as CPU devices (cores / N, at least 1) and, by default, pinned to
them (`share_cores`), joined by JAX's multi-process
runtime (gloo collectives on 127.0.0.1); every member runs `run_train_bench`'s protocol in
step and member 0 reports. So 2 processes x 1 device against 1 process x 2 devices is the
cost of the processes and their gloo reductions on the same cores.

The cross-process reduction time per update is measured beside the update, not inside it
(XLA runs the update's collectives within one program): a jitted `psum` over the same devices
of a tree shaped as the parameters (the gradient reduction) and of a scalar (the losses'
counts and means), each timed as the median of `REPEATS` calls; per update, the update runs
`update_epochs x num_minibatches` gradient reductions and `SMALL_PER_STEP` small ones per
gradient step. Dispatch of the standalone program is included (tens of microseconds).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPEATS = 20
SMALL_PER_STEP = 1  # the valid count and advantage moments, in one (ppo.py `moments`)
MEMBER_TIMEOUT_S = 1800


def reduction_s(learner: Any, params: Any, num_envs: int) -> tuple[float, float]:
    """(seconds per gradient-sized psum, seconds per scalar psum) over the devices of
    `learner`'s update; (0, 0) on one device."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ued.learners import distributed

    devices = learner.learner_devices(num_envs)
    if len(devices) == 1:
        return 0.0, 0.0
    mesh = jax.sharding.Mesh(np.asarray(devices), ("envs",))
    P = jax.sharding.PartitionSpec
    split = jax.sharding.NamedSharding(mesh, P("envs"))
    total = jax.jit(jax.shard_map(lambda t: jax.lax.psum(t, "envs"), mesh=mesh,
                                  in_specs=P("envs"), out_specs=P(), check_vma=False))

    def timed(tree: Any) -> float:
        stacked = jax.tree.map(lambda x: np.zeros((len(devices), *np.shape(x)), np.float32),
                               tree)
        x = distributed.to_global(stacked, split)
        jax.block_until_ready(total(x))  # compile
        times = []
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            jax.block_until_ready(total(x))
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    return timed(params), timed(jnp.zeros(()))


def per_update_reduction_s(ppo: Any, big_s: float, small_s: float) -> float:
    """Reduction seconds per update (module doc)."""
    return ppo.update_epochs * ppo.num_minibatches * (big_s + SMALL_PER_STEP * small_s)


def param_bytes(params: Any) -> int:
    import jax
    import numpy as np

    return int(sum(np.asarray(x).nbytes for x in jax.tree.leaves(params)))


def run_group(learners: int, options: dict[str, Any], share_cores: bool = False
              ) -> dict[str, Any]:
    """`run_train_bench(**options)` in a group of `learners` member processes on this machine,
    each pinned to its share of the cores with `share_cores`: member 0's result (a dict)."""
    from tabx import xla_flags
    from ued.learners.distributed import free_address

    cores = xla_flags.usable_cores()
    per = max(1, cores // learners)
    address = free_address()
    with tempfile.TemporaryDirectory(prefix="tabx-bench-group-") as folder:
        out = Path(folder) / "member-0.json"
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": " ".join(
            [f for f in os.environ.get("XLA_FLAGS", "").split()
             if "xla_force_host_platform_device_count" not in f]
            + [f"--xla_force_host_platform_device_count={per}"])}
        procs = [subprocess.Popen([sys.executable, "-m", "tabx_bench.group_member", address,
                                   str(learners), str(i), str(int(share_cores)),
                                   json.dumps(options), str(out)],
                                  env=env) for i in range(learners)]
        try:
            for p in procs:
                p.wait(timeout=MEMBER_TIMEOUT_S)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
        failed = [i for i, p in enumerate(procs) if p.returncode != 0]
        if failed:
            raise RuntimeError(f"learner group members {failed} failed (see their output)")
        return json.loads(out.read_text())
