"""The Ray driver's asynchronous schedule on one machine: it bounds staleness and commits every
issued batch exactly once, with chaos kills, a SIGKILLed Explorer or Evaluator, and over a long
run whose object refs stay flat and which `tabx runs` can inspect while it runs.

One Ray (3 logical CPUs) serves the module, as in test_ray_driver.py (the deterministic
schedule), which runs beside this one in the other test process.
"""

from __future__ import annotations

import io
import json
import os

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402
import ray  # noqa: E402
from test_ray_driver import duel_suite, ray_config  # noqa: E402

from level_buffer import LevelBuffer  # noqa: E402
from ued.run_folder import LEVELS_DIR  # noqa: E402
from workers.ray.driver import RAY_RECORD  # noqa: E402
from workers.train import train  # noqa: E402

# Every test here runs on the module's local Ray (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("local_ray")


def test_asynchronous_mode_bounds_staleness_and_commits_every_batch_once(tmp_path):
    # Half the steps train on replayed levels while the Explorer scores new ones ahead, and no
    # lag is allowed: any score whose policy moved on before it came back must be re-scored.
    # Chaos kills the Explorer or the service every 0.2 s besides: nothing may change that.
    config = ray_config("robust_plr", **{"ray.max_policy_lag": 0, "ray.max_inflight": 2,
                                         "ued.replay_prob": 0.5, "ued.buffer_size": 32,
                                         "ued.min_fill_ratio": 0.25, "ray.explorers": 1,
                                         "ray.chaos_kill_every_s": 0.2,
                                         "ray.chaos_roles": "service,explorer"})
    out = io.StringIO()
    run_dir = train(config, run_dir=tmp_path / "async", stream=out, max_updates=8)
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["mode"] == "asynchronous"
    assert record["chaos_kills"] >= 2 and "(ray.chaos_kill_every_s=0.2)" in out.getvalue()
    # (A kill is seen as a death only where a call found the actor down.)
    assert sum(record["restarts"].values()) <= record["chaos_kills"], out.getvalue()[-3000:]
    assert set(record["staleness"]) <= {"0"}  # nothing older than max_policy_lag committed
    assert record["ledger"] == {"committed": 8}  # every issued batch committed
    new = record["branches"]["new"]
    assert record["committed_batches"] == new and new >= 2
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-8.msgpack")
    # Each committed batch offered its 4 levels once: no batch lost, none counted twice.
    assert buffer.stats["insert_attempts"] == 4 * new
    versions = buffer.column("policy_version")
    assert versions.min() >= 0 and versions.max() <= record["branches"]["replay"]
    assert "explorers 1" in out.getvalue() and "trained" in out.getvalue()


@pytest.mark.parametrize("explorers", [0, 2])
def test_accel_runs_to_the_end_while_commits_evict_replayed_parents(tmp_path, explorers):
    # A buffer of one batch (4 levels) that ACCEL fills again every few steps, Explorer
    # results committed at the start of every step and in the drain before each checkpoint:
    # between a replay step and its mutate step, inserts evict the replayed parents. The
    # children are made from the replayed levels themselves, so every step runs, and every
    # snapshot taken between the two steps keeps the parents.
    config = ray_config("accel", **{"ray.explorers": explorers, "ray.max_inflight": 2,
                                    "ray.max_policy_lag": 100, "ued.buffer_size": 4,
                                    "ued.min_fill_ratio": 0.25, "ued.replay_prob": 0.6,
                                    "run.checkpoint_every": 3,
                                    "learner.total_timesteps": 30 * 64})
    run_dir = train(config, run_dir=tmp_path / "accel", stream=io.StringIO(), max_updates=30)
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["mode"] == "asynchronous" and record["ledger"] == {"committed": 30}, record
    assert record["branches"]["mutate"] >= 5
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-30.msgpack")
    assert buffer.stats["insert_attempts"] >= 4 * 10  # the buffer was filled many times over
    assert (buffer.column("source") == 1).any() or buffer.stats["rejected"] > 0
    from workers.resume import check_run_folder

    checks = check_run_folder(run_dir)
    assert all(check.intact and check.note is None for check in checks), checks


def test_an_explorer_killed_mid_batch_restarts_and_its_batches_are_reissued(tmp_path,
                                                                              monkeypatch):
    # SIGKILL the Explorer's own process right after the third batch went to it: that batch
    # (and any other in flight) dies with it, must be re-issued with the current policy to
    # the restarted Explorer, and committed exactly once.
    import signal

    from workers.ray.async_schedule import AsyncRun

    killed: list[int] = []
    submitted = {"n": 0}
    original = AsyncRun._submit

    def submit_then_kill(self, batch):
        actor = self.scorers[batch.explorer]
        if submitted["n"] == 0:
            killed.append(ray.get(actor.pid.remote()))  # before any batch: answers at once
        original(self, batch)
        submitted["n"] += 1
        if submitted["n"] == 3:
            os.kill(killed[0], signal.SIGKILL)

    monkeypatch.setattr(AsyncRun, "_submit", submit_then_kill)
    config = ray_config("robust_plr", **{"ray.explorers": 1, "ray.max_inflight": 2,
                                         "ued.replay_prob": 0.5, "ued.buffer_size": 32,
                                         "ued.min_fill_ratio": 0.25})
    out = io.StringIO()
    run_dir = train(config, run_dir=tmp_path / "killed", stream=out, max_updates=10)
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["restarts"] == {"explorer-0": 1}, out.getvalue()[-2000:]
    assert record["reissued"] >= 1
    assert "ray: explorer-0 died" in out.getvalue() and "re-issued" in out.getvalue()
    assert record["ledger"] == {"committed": 10}  # nothing lost
    new = record["branches"]["new"]
    assert record["committed_batches"] == new
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-10.msgpack")
    assert buffer.stats["insert_attempts"] == 4 * new  # nothing counted twice
    with pytest.raises(ProcessLookupError):
        os.kill(killed[0], 0)  # the process really died



def test_an_evaluator_killed_mid_evaluation_runs_it_again_on_its_restart(tmp_path,
                                                                          monkeypatch):
    import signal

    from ued.tensorboard import read_scalars
    from workers.ray.async_schedule import AsyncRun

    suite = duel_suite(tmp_path)
    killed = []
    original = AsyncRun.submit_evaluation

    def submit_then_kill(self, done):
        pid = ray.get(self.workers.evaluator.pid.remote()) if not killed else None
        original(self, done)
        if pid is not None:  # the first evaluation is in flight (it compiles): kill it
            os.kill(pid, signal.SIGKILL)
            killed.append(done)

    monkeypatch.setattr(AsyncRun, "submit_evaluation", submit_then_kill)
    config = ray_config("robust_plr", **{"ray.explorers": 1, "ued.eval_suites": f"[{suite}]",
                                         "ued.eval_every": 2})
    out = io.StringIO()
    run_dir = train(config, run_dir=tmp_path / "eval-killed", stream=out, max_updates=6)
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert killed == [2] and record["status"] == "finished"
    assert record["restarts"] == {"evaluator": 1}, out.getvalue()[-2000:]
    # The killed evaluation, and any sent before the death was seen, ran again; none lost.
    assert record["evaluations_rerun"] >= 1 and record["evaluations_lost"] == 0
    assert "ray: evaluator died" in out.getvalue()
    assert "duels.yaml after step 2 runs again on its restart" in out.getvalue()
    # Every evaluation was logged, the killed one from the restarted Evaluator.
    logged = read_scalars(run_dir / "events")["eval/duels/mean_win_rate"]
    assert sorted(step for step, _ in logged) == [2 * 64, 4 * 64, 6 * 64]



def test_a_long_run_holds_no_more_object_refs_at_its_end_and_can_be_inspected_while_it_runs(
        tmp_path):
    # 40 asynchronous steps: refs of levels, scores and parameters are released once used,
    # so the driver's reference table (and the objects it pins) stays flat. After step 3 a
    # user asks from another process, as `tabx runs buffer|status RUN` does, what it holds.
    from tabx_ued.cli import main

    run_dir = tmp_path / "long"
    seen, inspected = {}, {}

    def count(done, train_state, values):
        seen[done] = values["ray/driver_refs"]
        if done == 3:  # the run is going: ask from outside, as a user would
            for what in ("buffer", "status"):
                inspected[what] = subprocess.run(
                    [sys.executable, "-m", "tabx_ued", "runs", what, str(run_dir)],
                    capture_output=True, text=True, timeout=120)

    config = ray_config("robust_plr", **{"ray.explorers": 1, "ued.replay_prob": 0.5,
                                         "ued.buffer_size": 32, "ued.min_fill_ratio": 0.25,
                                         "learner.total_timesteps": 40 * 64,
                                         "run.log_every": 1})
    train(config, run_dir=run_dir, stream=io.StringIO(), max_updates=40, callback=count)
    early = max(seen[s] for s in range(5, 15))
    late = max(seen[s] for s in range(30, 41))
    assert 0 < late <= early + 2, seen

    buffer = inspected["buffer"]
    assert buffer.returncode == 0, buffer.stderr[-2000:]
    assert f"{run_dir} (live): " in buffer.stdout and " / 32 levels" in buffer.stdout
    assert "policy versions:" in buffer.stdout  # the summary of tabx buffer inspect
    status = inspected["status"]
    assert status.returncode == 0, status.stderr[-2000:]
    assert f"{run_dir}: running; asynchronous schedule; step 3 of 40" in status.stdout
    assert "explorer-0" in status.stdout and "learner" in status.stdout
    assert "env steps/s over the last " in status.stdout and ", explored " in status.stdout
    # Over: the record says so, and the live buffer points to the snapshots.
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["status"] == "finished" and record["steps"] == [0, 40]
    assert main(["runs", "buffer", str(run_dir)]) == 2
    assert main(["runs", "status", str(tmp_path / "nowhere")]) == 2

