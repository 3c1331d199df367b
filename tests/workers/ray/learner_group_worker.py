"""One member of a learner group for tests/workers/ray/test_learner_group.py (no tests of its own):

    python learner_group_worker.py ALGORITHM COORDINATOR N ID UPDATES MINIBATCHES OUT.npz

joins the group (`ued.learners.distributed.join`) with one CPU device, runs UPDATES updates of
the tiny learner of `group_updates` and saves the parameters, metrics and rollout statistics.
ALGORITHM `die`: `sum_until_the_group_breaks` instead (the other arguments unused).
"""

from __future__ import annotations

import os
import sys
from typing import Any


def group_updates(algorithm: str, devices: int, updates: int, minibatches: int
                  ) -> dict[str, Any]:
    """`updates` updates of the tiny learner (4 envs x 16 steps, hidden 16, 2 epochs of
    `minibatches` minibatches) with `devices` devices per process, flattened to numpy arrays
    by name."""
    import jax
    import numpy as np
    from test_learners_helpers import ENV_CONFIG, tiny_levels

    from ued.config import LearnerConfig
    from ued.learners import make_learner

    ppo = LearnerConfig(num_envs=4, num_steps=16, hidden_dim=16, num_minibatches=minibatches,
                        update_epochs=2, num_devices=devices)
    learner = make_learner(algorithm, ENV_CONFIG, ppo, "ally", "random", cached=False)
    state = learner.init(jax.random.key(0))
    out: dict[str, Any] = {}
    for u in range(updates):
        state, metrics, stats = learner.update(state, tiny_levels(), jax.random.key(1 + u))
    for path, leaf in jax.tree_util.tree_leaves_with_path(jax.device_get(state.params)):
        out["params" + jax.tree_util.keystr(path)] = np.asarray(leaf)
    for name, value in jax.device_get(metrics).items():
        out[f"metrics/{name}"] = np.asarray(value)
    for name in ("values", "advantages", "dones", "rewards", "wins"):
        out[f"stats/{name}"] = np.asarray(getattr(stats, name))
    out["global_devices"] = np.asarray(len(learner.learner_devices(4)))
    return out


def sum_until_the_group_breaks(process_id: int) -> None:
    """Member 1 dies (SIGKILL) once the group is up; member 0 sums over the global mesh
    until its collective fails, then exits with status 3 (a hang fails the test's timeout)."""
    import signal

    import jax
    import jax.numpy as jnp
    import numpy as np

    from ued.learners import distributed

    devices = distributed.group_devices(1)
    mesh = jax.sharding.Mesh(np.asarray(devices), ("envs",))
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("envs"))
    total = jax.jit(jnp.sum, out_shardings=jax.sharding.NamedSharding(
        mesh, jax.sharding.PartitionSpec()))
    x = distributed.to_global(np.ones(len(devices), np.float32), split)
    assert float(total(x).addressable_data(0)) == 2.0
    if process_id == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    try:
        while True:
            total(x).block_until_ready()
    except Exception as err:  # noqa: BLE001 - whatever the collective raises
        print(f"collective failed: {err}", flush=True)
        os._exit(3)


def main(argv: list[str]) -> None:
    algorithm, coordinator, n, process_id, updates, minibatches, path = argv
    # One CPU device per process, set before JAX starts (the test session's flags ask for 2).
    os.environ["XLA_FLAGS"] = " ".join(
        [f for f in os.environ.get("XLA_FLAGS", "").split()
         if "xla_force_host_platform_device_count" not in f]
        + ["--xla_force_host_platform_device_count=1"])
    os.environ["JAX_PLATFORMS"] = "cpu"
    # The tiny configs (tests/ued/test_learners_helpers.py).
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "ued"))
    from ued.learners import distributed

    distributed.join(coordinator, int(n), int(process_id), timeout_s=60,
                     heartbeat_timeout_s=5)
    if algorithm == "die":
        sum_until_the_group_breaks(int(process_id))
    import numpy as np

    out = group_updates(algorithm, 1, int(updates), int(minibatches))
    # What `join` did to gloo's event loop thread (`calm_gloo_loop`), for the test to check.
    loops = distributed.gloo_loop_threads()
    out["gloo_loop_niceness"] = np.asarray([os.getpriority(os.PRIO_PROCESS, t) for t in loops])
    np.savez(path, **out)
    distributed.leave()


if __name__ == "__main__":
    main(sys.argv[1:])
