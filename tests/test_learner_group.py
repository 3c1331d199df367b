"""A learner group (`ued.learners.distributed`): 2 processes of 1 CPU device each, joined by
JAX's multi-process runtime on 127.0.0.1 with gloo collectives, run the update that one
process with 2 devices runs, bit for bit.

The two members are subprocesses (`learner_group_worker.py`); the reference runs in the test
process (2 CPU devices, tests/conftest.py). Both split the envs the same way (process p's
device holds the envs that device p holds in one process) and compile the same partitioned
program; a sum over 2 shards is the same float sum in either order, so the results are equal
bit for bit, not only to `rounding_bound`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from learner_group_worker import group_updates

from ued.learners import distributed
from ued.learners.distributed import free_address

WORKER = Path(__file__).with_name("learner_group_worker.py")
GROUP_TIMEOUT_S = 240  # compiles included; a hung collective fails the test, not the suite


def run_group(tmp_path: Path, algorithm: str, updates: int, minibatches: int,
              meanwhile: Callable[[], Any] = lambda: None
              ) -> tuple[list[dict[str, np.ndarray]], Any]:
    """The worker's results of each member of a 2-process group, and what `meanwhile()`
    returned (it runs here while the members start and compile)."""
    address = free_address()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(WORKER.parent.parent), os.environ.get("PYTHONPATH", "")])}
    outs = [tmp_path / f"member-{i}.npz" for i in range(2)]
    procs = [subprocess.Popen([sys.executable, str(WORKER), algorithm, address, "2", str(i),
                               str(updates), str(minibatches), str(outs[i])],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True) for i in range(2)]
    try:
        here = meanwhile()
        logs = [p.communicate(timeout=GROUP_TIMEOUT_S)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, log in zip(procs, logs, strict=True):
        assert p.returncode == 0, log[-3000:]
    return [dict(np.load(out)) for out in outs], here


def assert_same(reference: dict[str, np.ndarray], member: dict[str, np.ndarray]) -> None:
    assert member["global_devices"] == 2 == reference["global_devices"]
    assert sorted(member) == sorted(reference)
    for name, value in reference.items():
        np.testing.assert_array_equal(member[name], value, err_msg=name)


@pytest.mark.parametrize(("algorithm", "updates", "minibatches"), [
    ("mappo", 1, 1),
    pytest.param("mappo", 2, 2, marks=pytest.mark.slow),
    pytest.param("ippo", 2, 2, marks=pytest.mark.slow),
])
def test_two_processes_update_as_one_process_with_two_devices(tmp_path, algorithm, updates,
                                                              minibatches):
    """Parameters, metrics and the gathered rollout statistics of every member equal the
    2-device process's, bit for bit (the slow cases: 2 updates, 2 minibatches, and IPPO;
    the default case covers MAPPO's one update)."""
    members, reference = run_group(tmp_path, algorithm, updates, minibatches, lambda: (
        group_updates(algorithm, 2, updates, minibatches)))
    assert reference["metrics/episode/count"] > 0
    for member in members:
        # gloo's event loop, found and given the lowest priority by `join`
        assert member.pop("gloo_loop_niceness").tolist() == [distributed.GLOO_LOOP_NICENESS]
        assert_same(reference, member)


def test_a_killed_member_stops_the_group_within_seconds(tmp_path):
    """Member 1 is SIGKILLed once the group is up: member 0's next collective fails (gloo's
    connection closed; else JAX's heartbeat timeout, 5 s here, ends it) and it exits within
    seconds instead of waiting for ever (the Ray group's restart: tests/test_ray_driver.py,
    -m slow)."""
    import time

    address = free_address()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(WORKER.parent.parent), os.environ.get("PYTHONPATH", "")])}
    procs = [subprocess.Popen([sys.executable, str(WORKER), "die", address, "2", str(i), "0",
                               "0", "-"], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(2)]
    try:
        t0 = time.monotonic()
        out = procs[0].communicate(timeout=60)[0]
        took = time.monotonic() - t0
        procs[1].wait(timeout=10)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert procs[1].returncode == -9
    assert procs[0].returncode != 0, out[-2000:]
    assert took < 45, took  # start-up (imports, join, one compile) and the stop
    assert "collective failed" in out or "heartbeat" in out, out[-2000:]


class FakeMember:
    """An actor handle that records the calls it is sent."""

    def __init__(self, index: int, log: list):
        self.index, self.log, self._actor_id = index, log, f"actor-{index}"

    def __getattr__(self, method: str):
        member = self

        class Remote:
            @staticmethod
            def remote(*args, **kwargs):
                member.log.append((member.index, method, args))
                return f"ref-{member.index}-{method}"

        return Remote


def test_a_learner_group_sends_collective_calls_to_every_member():
    """The Ray handle of a learner group (workers/learner_group.py): what changes the train
    state or runs the update goes to every member with the same arguments; reads, scoring and
    readiness go to learner 0, whose ref the driver waits on (the 2-learner Ray run:
    tests/test_ray_driver.py, -m slow)."""
    from workers.learner_group import COLLECTIVE, LearnerGroup

    log: list = []
    group = LearnerGroup([FakeMember(i, log) for i in range(3)], None, "127.0.0.1:1")
    assert group.train.remote("levels", "key") == "ref-0-train"
    assert log == [(i, "train", ("levels", "key")) for i in range(3)]
    assert group.others == ["ref-1-train", "ref-2-train"]
    log.clear()
    for method in ("params", "train_state", "score_levels", "ready", "version"):
        assert getattr(group, method).remote(1) == f"ref-0-{method}"
    assert [entry[0] for entry in log] == [0] * 5
    assert COLLECTIVE == {"init", "train", "train_scored", "set_train_state"}
    assert group._actor_id == "actor-0"  # a death is named by learner 0's id


def test_learner_group_settings_are_checked():
    from test_ued_train import ued_config

    from ued.config import ConfigError

    with pytest.raises(ConfigError, match="ray.learners: must be >= 1"):
        ued_config("robust_plr", **{"ray.enabled": "true", "ray.learners": 0})
    with pytest.raises(ConfigError, match=r"ray.learners: 3 learners .* \(6\)"):
        ued_config("robust_plr", **{"ray.enabled": "true", "ray.learners": 3})
    assert ued_config("robust_plr", **{"ray.enabled": "true", "ray.learners": 2}).ray.learners == 2


def test_a_learner_group_restart_counts_the_steps_since_the_checkpoint(tmp_path):
    """`Restarts` (the Ray driver's restart after a lost learner): the next session resumes
    from the newest checkpoint, the steps done since it are lost and counted, and the call's
    `max_updates` still ends where it would have (the Ray run: tests/test_ray_driver.py,
    -m slow)."""
    import io

    import jax
    import jax.numpy as jnp

    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR
    from workers.learner_group import Restarts

    with Checkpoints(tmp_path / CHECKPOINT_DIR) as checkpoints:
        checkpoints.save(4, {"w": jnp.zeros(2)}, jax.random.key(0))
    restarts, out = Restarts(2), io.StringIO()
    assert restarts.left() and restarts.fields() == {"learner_restarts": 0, "steps_lost": 0}
    # A session from step 2 asked for 6 more (to 8), stopped after finishing step 7.
    assert restarts.restart(tmp_path, 2, 7, 6, RuntimeError("learner died"), out) == 4
    assert restarts.restart(tmp_path, 4, 5, None, RuntimeError("learner died"), out) is None
    assert restarts.fields() == {"learner_restarts": 2, "steps_lost": 4}
    assert not restarts.left()
    assert "restart 1 of 2 (ray.learner_restarts) after learner died: the run continues from " \
           "its checkpoint at step 4; 3 steps lost (3 in all)" in out.getvalue()


def test_only_a_lost_learner_restarts_the_run(tmp_path):
    """`ray.learner_restarts` answers a stop for the lost learner (or a group member, which
    stops the group: its learner 0 dies) alone; a stop for another actor (Ray restarted it in
    place until its budget was spent) ends the run. Sessions stood in for; the Ray run:
    tests/test_ray_driver.py, -m slow."""
    import io
    from types import SimpleNamespace

    import jax
    import jax.numpy as jnp
    from test_ued_train import ued_config

    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR
    from workers.driver import RunStopped
    from workers.ray_driver import RayDriver

    with Checkpoints(tmp_path / CHECKPOINT_DIR) as checkpoints:
        checkpoints.save(2, {"w": jnp.zeros(2)}, jax.random.key(0))
    config = ued_config("dr", **{"ray.enabled": "true", "ray.learner_restarts": 3})

    class Stops(RayDriver):
        def __init__(self, lost: list[str]):
            super().__init__()
            self.lost, self.sessions = lost, 0

        def session(self, config, run_dir, **_):
            self.sessions += 1
            self.runner = SimpleNamespace(start=0, reached=3)
            if self.lost:
                raise RunStopped(f"{self.lost[0]} died", lost=self.lost.pop(0))
            return run_dir

    learner = Stops(["learner", "learner"])
    assert learner.run(config, tmp_path, stream=io.StringIO()) == tmp_path
    assert learner.sessions == 3
    explorer = Stops(["explorer-0"])
    with pytest.raises(RunStopped, match="explorer-0 died"):
        explorer.run(config, tmp_path, stream=io.StringIO())
    assert explorer.sessions == 1


def test_members_on_one_machine_share_its_cores():
    """`share_cores`: member r of n on one machine keeps the r-th slice of the CPUs it may
    use (before JAX starts, so XLA sizes its thread pools to it); one member keeps all. In a
    child process: the pinning is the process's own."""
    code = ("import os; from ued.learners.distributed import share_cores; "
            "cpus = sorted(os.sched_getaffinity(0)); per = len(cpus) // 2; "
            "assert share_cores(0, 1) == cpus; "
            "mine = share_cores(1, 2); "
            "assert mine == (cpus[per:2 * per] if per else cpus), mine; "
            "assert sorted(os.sched_getaffinity(0)) == mine")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
