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
    seconds instead of waiting for ever (the Ray group's restart: test_ray_driver.py,
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
    """The Ray handle of a learner group (workers/ray/learner_group.py): what changes the train
    state or runs the update goes to every member with the same arguments; reads, scoring and
    readiness go to learner 0, whose ref the driver waits on (the 2-learner Ray run:
    tests/workers/ray/test_ray_driver.py, -m slow)."""
    from workers.ray.learner_group import COLLECTIVE, LearnerGroup

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


def test_a_restart_counts_the_steps_since_the_checkpoint():
    """`Restarts` (the Ray driver's restart after a lost learner): the next session resumes
    from the newest intact checkpoint (step 0 where there is none), the steps done since it
    are lost and counted, and the call's `max_updates` still ends where it would have; the
    line says what died, which restart it is and where the run continues (the Ray runs:
    tests/workers/ray/test_ray_driver.py)."""
    import io

    from workers.ray.learner_group import Restarts

    restarts, out = Restarts(3), io.StringIO()
    assert restarts.left() and restarts.fields() == {"learner_restarts": 0, "steps_lost": 0}
    # A session from step 2 asked for 6 more (to 8), stopped after finishing step 7.
    assert restarts.restart("learner died (killed)", 4, (2, 7), 6, out) == 4
    assert restarts.restart("learner died (killed)", 4, (4, 5), None, out) is None
    # Before the first checkpoint: from step 0, every step done is lost.
    assert restarts.restart("learner died (killed)", None, (0, 1), 3, out) == 3
    assert restarts.fields() == {"learner_restarts": 3, "steps_lost": 5}
    assert not restarts.left()
    first, _, third = out.getvalue().splitlines()
    assert first == ("ray: learner died (killed): restart 1 of 3 (ray.learner_restarts): the "
                     "run continues from its checkpoint at step 4; 3 steps lost (3 in all)")
    assert third == ("ray: learner died (killed): restart 3 of 3 (ray.learner_restarts): the "
                     "run has no checkpoint yet: it starts again from step 0; 1 steps lost "
                     "(5 in all)")


def test_a_lost_learner_restarts_the_run_by_default_and_the_stop_says_what_resume_does(
        tmp_path, monkeypatch):
    """A stop for the lost learner (or a group member, which stops the group) starts the run
    again, `ray.learner_restarts` times (2 by default); so does any actor lost while the
    actors started (nothing restarted it); a stop for another actor mid-run (Ray restarted
    it in place until its budget was spent) ends the run. The last stop names what died, that
    the budget is spent, and what `--resume` will do. Sessions and the run folder's newest
    intact checkpoint stood in for; the Ray runs: tests/workers/ray/test_ray_driver.py."""
    import io
    from types import SimpleNamespace

    from test_ued_train import ued_config

    from workers.driver import RunStopped
    from workers.ray import driver as ray_driver
    from workers.ray.driver import RayDriver

    config = ued_config("dr", **{"ray.enabled": "true"})
    assert config.ray.learner_restarts == 2
    monkeypatch.setattr(ray_driver, "resume_point", lambda run_dir, config: (2, 1))
    monkeypatch.setattr(ray_driver, "what_resume_does", lambda run_dir, config: (
        f"tabx train --resume {run_dir} continues it from its checkpoint at step 2"))

    class Stops(RayDriver):
        def __init__(self, lost: list[tuple[str, bool]]):
            super().__init__()
            self.lost, self.sessions = lost, 0

        def session(self, config, run_dir, **_):
            self.sessions += 1
            if self.lost:
                name, started = self.lost.pop(0)
                self.runner = SimpleNamespace(start=0, reached=3) if started else None
                raise RunStopped(f"{name} died (killed)", lost=name)
            return run_dir

    # Twice the learner: restarted twice, and the run ends.
    learner = Stops([("learner", True), ("learner", True)])
    assert learner.run(config, tmp_path, stream=io.StringIO()) == tmp_path
    assert learner.sessions == 3
    # An Explorer lost while the actors started: nothing restarted it, so the run starts again.
    at_start = Stops([("explorer-0", False)])
    assert at_start.run(config, tmp_path, stream=io.StringIO()) == tmp_path
    assert at_start.sessions == 2
    # An Explorer's stop mid-run ends it, with what --resume will do.
    explorer = Stops([("explorer-0", True)])
    with pytest.raises(RunStopped, match=f"^{tmp_path}: explorer-0 died \\(killed\\); tabx "
                                         f"train --resume {tmp_path} continues it from its "
                                         f"checkpoint at step 2$"):
        explorer.run(config, tmp_path, stream=io.StringIO())
    assert explorer.sessions == 1
    # A third loss of the learner: the budget is spent, and the stop line says so.
    out = io.StringIO()
    spent = Stops([("learner", True)] * 3)
    with pytest.raises(RunStopped, match="ray.learner_restarts \\(2\\) spent"):
        spent.run(config, tmp_path, stream=out)
    assert spent.sessions == 3
    assert out.getvalue().splitlines()[-1] == (
        f"ray: the run stops: learner died (killed); ray.learner_restarts (2) spent; tabx train "
        f"--resume {tmp_path} continues it from its checkpoint at step 2")


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
