"""The Ray driver on one machine: its deterministic mode equals the local driver (parameters and
level-buffer files, Robust PLR, ACCEL and SFL) through chaos kills, a killed level service and a
resume on other Explorers; its refusals and placement; and the local mode never imports Ray.
The asynchronous schedule's runs are in test_ray_async.py, `tabx bench ued` in
tests/tabx_bench/test_ray_bench.py (other modules, so that the two test processes share the Ray
tests).

One Ray (3 logical CPUs) serves the module; runs use the UED tests' tiny config (2 archers v 1
farmer, 4 envs x 16 steps), so each run costs its actors' start-up and compilation, seconds.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import ray  # noqa: E402
from test_ued_train import ued_config  # noqa: E402

from level_buffer import LevelBuffer  # noqa: E402
from level_buffer.commit_log import read  # noqa: E402
from ued.checkpoint import Checkpoints  # noqa: E402
from ued.config import ConfigError  # noqa: E402
from ued.run_folder import CHECKPOINT_DIR, LEVELS_DIR  # noqa: E402
from workers.ray.driver import RAY_RECORD  # noqa: E402
from workers.ray.durable_service import LOG_NAME  # noqa: E402
from workers.ray.start import RAY_NAMESPACE  # noqa: E402
from workers.train import train  # noqa: E402
from workers.ued_step import UEDRun  # noqa: E402

STEPS = 6


# Every test here runs on the module's local Ray (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("local_ray")


# The deterministic ACCEL tests compare their Ray runs with this one local run (7 steps,
# checkpoints and level snapshots after steps 4 and 7): one reference run for the module.
ACCEL_STEPS = 7
ACCEL_CONFIG = {"run.checkpoint_every": 4}


@pytest.fixture(scope="module")
def local_accel(tmp_path_factory):
    """The local driver's uninterrupted ACCEL run (read only: tests compare with it)."""
    return train(ued_config("accel", **ACCEL_CONFIG), run_dir=tmp_path_factory.mktemp(
        "local-accel") / "local", stream=io.StringIO(), max_updates=ACCEL_STEPS)


def ray_config(method: str, **overrides):
    return ued_config(method, **{"ray.enabled": "true", **overrides})


def final_state(run_dir, config):
    template = UEDRun.local(config)[1].init(jax.random.key(0))
    with Checkpoints(run_dir / CHECKPOINT_DIR) as checkpoints:
        state, key, step = checkpoints.restore(template)
    return state, jax.random.key_data(key), step


def trees_equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b),
                                                    strict=True))


# With `-m slow`: the default run has ACCEL's deterministic equality (replay, mutation, fresh
# levels) on 2 Explorers in the chaos test below, which asserts all of this with kills besides.
@pytest.mark.slow
@pytest.mark.parametrize("method", ["robust_plr", "accel", "sfl"])
def test_deterministic_mode_equals_the_local_driver(tmp_path, method):
    local = train(ued_config(method), run_dir=tmp_path / "local", stream=io.StringIO(),
                  max_updates=STEPS)
    remote = train(ray_config(method, **{"ray.deterministic": "true", "ray.explorers": 2}),
                   run_dir=tmp_path / "ray", stream=io.StringIO(), max_updates=STEPS)
    state_a, key_a, step_a = final_state(local, ued_config(method))
    state_b, key_b, step_b = final_state(remote, ued_config(method))
    assert step_a == step_b == STEPS
    assert trees_equal(state_a.params, state_b.params)
    assert trees_equal(state_a.opt_state, state_b.opt_state)
    assert np.array_equal(key_a, key_b)
    snapshots = sorted(p.name for p in (local / LEVELS_DIR).iterdir())
    remote_files = sorted(p.name for p in (remote / LEVELS_DIR).iterdir())
    # The same snapshots, and the service's commit log since the last one (empty).
    assert remote_files == sorted([*snapshots, LOG_NAME.format(STEPS)])
    assert read(remote / LEVELS_DIR / LOG_NAME.format(STEPS)).records == []
    assert any(name.endswith(".msgpack") for name in snapshots)  # a buffer or SFL's set
    for name in snapshots:  # buffer, SFL's learnable set, curriculum state: byte for byte
        assert (local / LEVELS_DIR / name).read_bytes() == (remote / LEVELS_DIR / name
                                                            ).read_bytes(), name
    record = json.loads((remote / RAY_RECORD).read_text())
    assert record["mode"] == "deterministic" and set(record["placement"]) == {
        "service", "learner", "explorer-0", "explorer-1"}


def test_zero_explorers_score_on_the_learner(tmp_path):
    config = ray_config("accel", **{"ray.explorers": 0})
    run_dir = train(config, run_dir=tmp_path / "zero", stream=io.StringIO(), max_updates=5)
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert set(record["placement"]) == {"service", "learner"}
    assert record["committed_batches"] == record["branches"]["new"] + record["branches"][
        "mutate"]


def test_ray_settings_are_checked():
    with pytest.raises(ConfigError, match="ray.enabled: the Ray driver runs UED runs"):
        ued_config("none", **{"ray.enabled": "true"})
    with pytest.raises(ConfigError, match=r"ray.max_inflight: must be in \[1, 64\]"):
        ray_config("dr", **{"ray.max_inflight": 0})
    with pytest.raises(ConfigError, match="ray.learner_gpus"):
        ray_config("dr", **{"ray.learner_gpus": -2})
    with pytest.raises(ConfigError, match="ray.actor_restarts: must be -1"):
        ray_config("dr", **{"ray.actor_restarts": -3})
    with pytest.raises(ConfigError, match="ray.chaos_kill_every: must be >= 0"):
        ray_config("dr", **{"ray.chaos_kill_every": -1})
    with pytest.raises(ConfigError, match="ray.chaos_kill_every_s: must be >= 0"):
        ray_config("dr", **{"ray.chaos_kill_every_s": -1})
    with pytest.raises(ConfigError, match="ray.chaos_roles: must be a comma-separated list"):
        ray_config("dr", **{"ray.chaos_roles": "explorer,learner"})
    with pytest.raises(ConfigError, match="ray.schedule: must be one of sequential, continuous"):
        ray_config("dr", **{"ray.schedule": "eager"})
    with pytest.raises(ConfigError, match="ray.schedule: continuous scoring runs beside"):
        ray_config("dr", **{"ray.schedule": "continuous", "ray.deterministic": "true"})


def test_a_run_that_cannot_be_placed_is_refused(tmp_path):
    # 5 Explorers and a learner on a 3-CPU Ray would wait for ever: say so instead.
    with pytest.raises(ConfigError, match="reserve 6 CPUs, but this Ray has 3"):
        train(ray_config("robust_plr", **{"ray.explorers": 5}), run_dir=tmp_path / "big",
              stream=io.StringIO(), max_updates=1)


def test_a_learner_gpu_on_a_cpu_only_ray_fails_after_the_placement_timeout(tmp_path):
    # The module's Ray has no GPU: a learner that asks for one is refused in one line naming
    # the resource, after ray.placement_timeout_s, not left pending for ever.
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"the cluster has 0 GPU of the 1 the run reserves "
                                          r"\(learner 1\)"):
        train(ray_config("dr", **{"ray.learner_gpus": 1, "ray.placement_timeout_s": 1}),
              run_dir=tmp_path / "gpu", stream=io.StringIO(), max_updates=1)
    assert time.perf_counter() - t0 < 15



def test_a_learner_group_that_cannot_be_placed_fails_after_the_placement_timeout(tmp_path):
    # `ray.learners: 2` asking for a GPU each on this CPU-only Ray: refused in one line naming
    # both members. The group's placement group itself also waits at most the timeout (the
    # cluster may hold enough in all while other jobs reserve it), and is then released.
    from workers.ray.learner_group import start_group

    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"the cluster has 0 GPU of the 2 the run reserves "
                                          r"\(learner 1, learner-1 1\)"):
        train(ray_config("dr", **{"ray.learners": 2, "ray.learner_gpus": 1,
                                  "ray.placement_timeout_s": 0.5}),
              run_dir=tmp_path / "gpus", stream=io.StringIO(), max_updates=1)
    with pytest.raises(ConfigError, match=r"ray.placement_timeout_s: after \d+ s the learner "
                                          r"group \(2 learners x 1 GPU\) is not placed: the "
                                          r"cluster has 0 GPU free of 0"):
        start_group(ray, 2, 1.0, lambda *_: pytest.fail("no member starts"), timeout_s=0.3)
    assert time.perf_counter() - t0 < 10
    assert all(pg["state"] == "REMOVED" for pg in ray.util.placement_group_table().values())

def test_live_explorers_are_the_ones_answering():
    from workers.ray.actor_manager import ActorManager
    from workers.ray.stats import live_actors

    @ray.remote(num_cpus=0)
    class Stub:
        def ready(self):
            return True

    actors = ActorManager(ray)
    stubs = [Stub.remote() for _ in range(2)]
    ray.get([s.ready.remote() for s in stubs])
    for i, stub in enumerate(stubs):
        actors.add(f"explorer-{i}", stub, restarts=True)
    assert live_actors(ray, actors, ["explorer-0", "explorer-1"]) == 2
    ray.kill(stubs[1])
    deadline = time.perf_counter() + 10
    while live_actors(ray, actors, ["explorer-0", "explorer-1"]) != 1:
        assert time.perf_counter() < deadline, "a killed actor still counted live"
        time.sleep(0.1)


def test_the_local_mode_never_imports_ray():
    code = ("import sys; import workers.train, tabx_ued.cli; "
            "assert 'ray' not in sys.modules, 'ray imported'")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def duel_suite(folder):
    """A two-entry suite on the evaluation tests' duels, whose outcome does not depend on the
    policy (the weak allies lose, the weak enemies lose): win rates 0 then 1."""
    from test_eval_suites import weak_level

    from tabx.scenarios import level_to_scenario, save_scenario

    for weak in ("ally", "enemy"):
        save_scenario(folder / f"weak_{weak}.json",
                      level_to_scenario(weak_level(weak), name=f"weak_{weak}"))
    suite = folder / "duels.yaml"
    suite.write_text("name: duels\nepisodes: 2\nentries:\n"
                     f"  - scenario: {folder / 'weak_ally.json'}\n    opponent: random\n"
                     f"  - scenario: {folder / 'weak_enemy.json'}\n    opponent: idle\n")
    return suite


def test_eval_suite_on_a_ray_actor_gives_the_local_table(tmp_path, capsys):
    from tabx_ued.cli import main

    suite = duel_suite(tmp_path)
    run = train(ued_config("dr"), run_dir=tmp_path / "run", stream=io.StringIO(),
                max_updates=1)
    outputs = {}
    for name, extra in (("local", []), ("ray", ["--ray"])):
        out_json = tmp_path / f"{name}.json"
        assert main(["eval", str(run), "--suite", str(suite), "--seed", "5", "--json",
                     str(out_json), *extra]) == 0
        outputs[name] = json.loads(out_json.read_text())
    assert "ray: evaluating duels on a CPU actor" in capsys.readouterr().err
    assert [e["win_rate"] for e in outputs["ray"]["entries"]] == [0.0, 1.0]
    assert outputs["ray"] == outputs["local"]  # the same Evaluator, seed and parameters

    for argv, message in ((["eval", str(run), "--ray"], "--ray plays an evaluation suite"),
                          (["eval", str(run), "--suite", str(suite), "--address", "auto"],
                           "--address joins a Ray cluster: give --ray too")):
        assert main(argv) == 2
        assert message in capsys.readouterr().err


def test_chaos_kills_leave_the_deterministic_run_equal_to_the_local_one(tmp_path,
                                                                       local_accel):
    # Every 2 steps chaos kills the next of service, explorer-0, explorer-1 (Ray's kill, as a
    # user's cluster would see it), and the service's own process is SIGKILLed after step 5:
    # the run still equals the local driver's, byte for byte. With snapshots every 4 steps the
    # service comes back from the session's start and its log (after step 2) and from the
    # snapshot of step 4 and its log (after step 5).
    method = "accel"
    local = local_accel
    out = io.StringIO()
    run_dir = tmp_path / "chaos"
    remote = train(ray_config(method, **{"ray.deterministic": "true", "ray.explorers": 2,
                                         "ray.chaos_kill_every": 2,
                                         "ray.chaos_roles": "explorer,service",
                                         **ACCEL_CONFIG}),
                   run_dir=run_dir, stream=out, max_updates=ACCEL_STEPS,
                   callback=kill_service_at(run_dir, {5}))
    record = json.loads((remote / RAY_RECORD).read_text())
    assert record["mode"] == "deterministic" and set(record["placement"]) == {
        "service", "learner", "explorer-0", "explorer-1"}
    assert record["chaos_kills"] == 3  # after steps 2, 4 and 6, not the last
    for victim, step in (("service", 2), ("explorer-0", 4), ("explorer-1", 6)):
        assert (f"ray: chaos: killed {victim} after step {step} (ray.chaos_kill_every=2)"
                in out.getvalue())
    # (Ray's kill is seen as a death only where a call found the service down; SIGKILL is.)
    assert 1 <= record["restarts"].get("service", 0) <= 2, out.getvalue()[-2000:]
    assert "ray: service died" in out.getvalue()
    state_a, key_a, _ = final_state(local, ued_config(method))
    state_b, key_b, _ = final_state(remote, ued_config(method))
    assert trees_equal(state_a.params, state_b.params) and np.array_equal(key_a, key_b)
    snapshots = sorted(p.name for p in (local / LEVELS_DIR).iterdir())
    assert any(name.endswith(".msgpack") for name in snapshots)  # the buffer's
    # The same snapshots, and the service's commit log since the last one (empty).
    last = ACCEL_STEPS
    assert sorted(p.name for p in (remote / LEVELS_DIR).iterdir()) == sorted(
        [*snapshots, LOG_NAME.format(last)])
    assert read(remote / LEVELS_DIR / LOG_NAME.format(last)).records == []
    for name in snapshots:  # buffer and curriculum state: byte for byte
        assert (local / LEVELS_DIR / name).read_bytes() == (remote / LEVELS_DIR / name
                                                            ).read_bytes(), name


def test_a_ray_run_resumed_with_other_explorers_equals_an_uninterrupted_local_run(
        tmp_path, local_accel):
    # 3 steps on 2 Explorers, then 4 more on 1 (as `tabx train --resume RUN --ray
    # ray.explorers=1` does), deterministic: the local driver's 7 steps, byte for byte.
    import dataclasses

    method = "accel"
    local = local_accel
    config = ray_config(method, **{"ray.deterministic": "true", "ray.explorers": 2,
                                   **ACCEL_CONFIG})
    remote = train(config, run_dir=tmp_path / "ray", stream=io.StringIO(), max_updates=3)
    fewer = dataclasses.replace(config.ray, explorers=1)
    train(run_dir=remote, resume=True, ray=fewer, stream=io.StringIO(), max_updates=4)
    record = json.loads((remote / RAY_RECORD).read_text())
    assert record["steps"] == [3, ACCEL_STEPS] and set(record["placement"]) == {
        "service", "learner", "explorer-0"}
    state_a, key_a, step_a = final_state(local, ued_config(method))
    state_b, key_b, step_b = final_state(remote, ued_config(method))
    assert step_a == step_b == ACCEL_STEPS
    assert trees_equal(state_a.params, state_b.params) and np.array_equal(key_a, key_b)
    assert (local / LEVELS_DIR / f"buffer-{ACCEL_STEPS}.msgpack").read_bytes() == (
        remote / LEVELS_DIR / f"buffer-{ACCEL_STEPS}.msgpack").read_bytes()


def kill_service_at(run_dir, steps):
    """A progress callback that SIGKILLs the level service's own process after these steps."""
    import signal

    def kill(done, train_state, values):
        if done in steps:
            name = json.loads((run_dir / RAY_RECORD).read_text())["actors"]["service"]
            service = ray.get_actor(name, namespace=RAY_NAMESPACE)
            os.kill(ray.get(service.pid.remote()), signal.SIGKILL)
    return kill


# With `-m slow`: the chaos test above SIGKILLs the service after step 5 (snapshot and log)
# and kills it after step 2 (the session's start and its log), with the same equality.
@pytest.mark.slow
def test_a_killed_service_restarts_with_every_commit_and_the_run_equals_the_local_one(
        tmp_path, local_accel):
    # Deterministic: killed after step 3 (it restores from the start of the session and its
    # log) and after step 5 (from the snapshot of step 4 and its log). Parameters, key and
    # every snapshot equal the local driver's uninterrupted run: no commit lost or repeated.
    method, steps = "accel", ACCEL_STEPS
    local = local_accel
    run_dir = tmp_path / "ray"
    config = ray_config(method, **{"ray.deterministic": "true", "ray.explorers": 1,
                                   **ACCEL_CONFIG})
    out = io.StringIO()
    train(config, run_dir=run_dir, stream=out, max_updates=steps,
          callback=kill_service_at(run_dir, {3, 5}))
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["restarts"] == {"service": 2}, out.getvalue()[-2000:]
    assert out.getvalue().count("ray: service died") == 2
    state_a, key_a, _ = final_state(local, ued_config(method))
    state_b, key_b, _ = final_state(run_dir, ued_config(method))
    assert trees_equal(state_a.params, state_b.params) and np.array_equal(key_a, key_b)
    for name in sorted(p.name for p in (local / LEVELS_DIR).iterdir()):
        assert (local / LEVELS_DIR / name).read_bytes() == (run_dir / LEVELS_DIR / name
                                                            ).read_bytes(), name


# With `-m slow`: test_ray_async.py's chaos test kills the service every 0.2 s and asserts
# this.
@pytest.mark.slow
def test_a_killed_service_loses_no_committed_batch_in_the_asynchronous_mode(tmp_path):
    # Explorer batches in flight when the service dies lose their levels with it: they are
    # asked for again and committed once; every commit acknowledged before the death stays.
    run_dir = tmp_path / "async"
    config = ray_config("robust_plr", **{"ray.explorers": 1, "ray.max_inflight": 2,
                                         "ued.replay_prob": 0.5, "ued.buffer_size": 32,
                                         "ued.min_fill_ratio": 0.25})
    out = io.StringIO()
    train(config, run_dir=run_dir, stream=out, max_updates=10,
          callback=kill_service_at(run_dir, {3, 7}))
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["restarts"] == {"service": 2}, out.getvalue()[-2000:]
    assert record["ledger"] == {"committed": 10}
    new = record["branches"]["new"]
    assert record["committed_batches"] == new
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-10.msgpack")
    assert buffer.stats["insert_attempts"] == 4 * new  # none lost, none counted twice


# With `-m slow`: test_ray_schedule.py's continuous tests (stand-in Ray) check that every
# issued batch is committed once and stale ones are scored again, without kills.
@pytest.mark.slow
def test_continuous_scoring_commits_every_batch_once_when_explorers_and_the_service_die(
        tmp_path, monkeypatch):
    # ACCEL on the continuous schedule: the Explorer is SIGKILLed right after its third batch
    # went to it, the service after steps 3 and 6. Batches in flight are re-issued, levels
    # lost with the service asked for again, numbered calls sent again in order: every
    # issued batch is committed exactly once, and the buffer saw each batch's levels once.
    import signal

    from workers.ray.async_schedule import AsyncRun

    killed: list[int] = []
    submitted = {"n": 0}
    original = AsyncRun._submit

    def submit_then_kill(self, batch):
        actor = self.scorers[batch.explorer]
        if submitted["n"] == 0:
            killed.append(ray.get(actor.pid.remote()))
        original(self, batch)
        submitted["n"] += 1
        if submitted["n"] == 3:
            os.kill(killed[0], signal.SIGKILL)

    monkeypatch.setattr(AsyncRun, "_submit", submit_then_kill)
    run_dir = tmp_path / "continuous"
    config = ray_config("accel", **{"ray.explorers": 1, "ray.max_inflight": 2,
                                    "ray.schedule": "continuous", "ued.buffer_size": 32,
                                    "ued.min_fill_ratio": 0.25})
    out = io.StringIO()
    train(config, run_dir=run_dir, stream=out, max_updates=8,
          callback=kill_service_at(run_dir, {3, 6}))
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["mode"] == "continuous"
    assert record["restarts"] == {"explorer-0": 1, "service": 2}, out.getvalue()[-3000:]
    assert record["ledger"] == {"committed": 8} and record["branches"]["replay"] == 8
    committed = record["committed_batches"]
    assert record["explorer_batches"] == {"committed": committed} and committed >= 2
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-8.msgpack")
    assert buffer.stats["insert_attempts"] == 4 * committed  # none lost, none counted twice


def test_the_simulated_control_plane_keeps_8_explorers_near_their_ideal_rate():
    # `tabx bench ued --simulate` at a small size: 8 stand-in Explorers of 0.2 s batches (ideal
    # 40 batches/s) on the real driver, level service and commit log; a generous bound (the
    # machine is shared), the measured numbers are in docs/benchmarks.md.
    from tabx_bench.ued_sim import simulate

    config = ray_config("robust_plr")
    result = simulate(ray, config, 8, batch_s=0.2, learner_s=0.2, seconds=2.0)
    assert result.committed_per_s >= 0.5 * result.ideal_per_s, result
    assert result.learner_steps >= 3 and result.service_fsyncs < result.service_calls


# With `-m slow`: test_learner_group.py runs the same update in 2 processes by default,
# and test_a_learner_group_sends_collective_calls_to_every_member its Ray handle.
@pytest.mark.slow
def test_two_learner_processes_train_as_one_learner_with_two_devices_and_resume_on_one(
        tmp_path):
    """`ray.learners: 2` (one JAX process group, gloo collectives; `learner.num_devices`
    automatic: 1 device each for their 2 envs) trains as one learner with 2 devices, bit for
    bit; its checkpoint (saved once, from learner 0) resumes on 1 learner (2 devices) and
    continues as the uninterrupted run. Robust PLR, deterministic; learner 0 also scores."""
    import dataclasses

    local = train(ued_config("robust_plr"), run_dir=tmp_path / "local", stream=io.StringIO(),
                  max_updates=3)
    config = ray_config("robust_plr", **{"ray.deterministic": "true", "ray.explorers": 0,
                                         "ray.learners": 2})
    remote = train(config, run_dir=tmp_path / "group", stream=io.StringIO(), max_updates=2)
    record = json.loads((remote / RAY_RECORD).read_text())
    assert record["learners"] == 2 and len(record["learner_nodes"]) == 2
    one = dataclasses.replace(config.ray, learners=1)
    train(run_dir=remote, resume=True, ray=one, stream=io.StringIO(), max_updates=1)
    record = json.loads((remote / RAY_RECORD).read_text())
    assert record["learners"] == 1 and record["steps"] == [2, 3]
    state_a, key_a, step_a = final_state(local, ued_config("robust_plr"))
    state_b, key_b, step_b = final_state(remote, ued_config("robust_plr"))
    assert step_a == step_b == 3
    assert trees_equal(state_a.params, state_b.params)
    assert trees_equal(state_a.opt_state, state_b.opt_state)
    assert np.array_equal(key_a, key_b)


def kill_learner_after(run_dir, steps: list[int]):
    """A callback that kills the run's learner actor (Ray's kill, as its node's loss or the
    memory monitor would) after each step of `steps` in turn, one per session: the learner
    of the session running then (`ray.json` names it)."""
    def kill(done, train_state, values):
        if steps and done == steps[0]:
            name = json.loads((run_dir / RAY_RECORD).read_text())["actors"]["learner"]
            ray.kill(ray.get_actor(name, namespace=RAY_NAMESPACE))
            steps.pop(0)

    return kill


def test_a_lost_learner_restarts_the_run_from_its_newest_checkpoint_by_default(
        tmp_path, local_accel):
    """The learner killed after step 1, before the first checkpoint (step 4): the run starts
    again from step 0 and says so; killed again after step 5: it continues from the checkpoint
    of step 4, 1 step lost. `ray.learner_restarts` is left at its default (2). Deterministic
    ACCEL on 1 Explorer: the run still ends as the uninterrupted local one, bit for bit."""
    run_dir, out = tmp_path / "restarted", io.StringIO()
    kills = [1, 5]
    train(ray_config("accel", **{"ray.deterministic": "true", "ray.explorers": 1,
                                 **ACCEL_CONFIG}),
          run_dir=run_dir, stream=out, max_updates=ACCEL_STEPS,
          callback=kill_learner_after(run_dir, kills))
    text = out.getvalue()
    assert kills == [], text[-3000:]
    assert ("restart 1 of 2 (ray.learner_restarts): the run has no checkpoint yet: it starts "
            "again from step 0; 1 steps lost (1 in all)") in text, text[-3000:]
    assert f"resume: {run_dir} has no checkpoint yet: the run starts again from step 0" in text
    assert ("restart 2 of 2 (ray.learner_restarts): the run continues from its checkpoint at "
            "step 4; 1 steps lost (2 in all)") in text
    assert text.count("ray: learner died (") == 2  # each restart line names the learner
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["status"] == "finished" and record["steps"] == [4, ACCEL_STEPS]
    assert record["learner_restarts"] == 2 and record["steps_lost"] == 2
    state_a, key_a, _ = final_state(local_accel, ued_config("accel"))
    state_b, key_b, step_b = final_state(run_dir, ued_config("accel"))
    assert step_b == ACCEL_STEPS
    assert trees_equal(state_a.params, state_b.params) and np.array_equal(key_a, key_b)


def test_a_lost_learner_with_no_restart_left_stops_saying_what_resume_will_do(tmp_path):
    """`ray.learner_restarts: 0`, the learner killed after step 1 of a run whose first
    checkpoint would be step 4: the stop names the learner, the spent budget, and that a
    resume starts from step 0 (there is no checkpoint); `ray.json` says stopped."""
    from workers.driver import RunStopped

    run_dir, out = tmp_path / "stopped", io.StringIO()
    with pytest.raises(RunStopped) as stopped:
        train(ray_config("robust_plr", **{"ray.learner_restarts": 0, "ray.explorers": 0,
                                          "run.checkpoint_every": 4}),
              run_dir=run_dir, stream=out, max_updates=3,
              callback=kill_learner_after(run_dir, [1]))
    message = str(stopped.value)
    assert message.startswith(f"{run_dir}: learner died ("), message
    assert message.endswith(f"; ray.learner_restarts (0) spent; no checkpoint yet: tabx train "
                            f"--resume {run_dir} starts it again from step 0"), message
    assert out.getvalue().splitlines()[-1] == "ray: the run stops: " + message.split(": ", 1)[1]
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["status"] == "stopped" and record["error"].startswith("learner died (")


# With `-m slow`: test_learner_group.py's killed-member test covers the group's stop, and
# test_a_learner_group_restart_counts_the_steps_since_the_checkpoint the restart's count.
@pytest.mark.slow
def test_a_killed_learner_stops_its_group_and_the_run_restarts_from_its_checkpoint(tmp_path):
    """`ray.learners: 2`, learner 1 SIGKILLed after step 3 (checkpoints every 2 steps): the
    next update fails on learner 0 too (its collective loses a member), the run continues by
    itself from the checkpoint of step 2 (`ray.learner_restarts: 1`), step 3 is lost and
    played again, and the deterministic run ends as the uninterrupted local one."""
    import signal

    overrides = {"run.checkpoint_every": 2, "run.log_every": 1}
    local = train(ued_config("robust_plr", **overrides), run_dir=tmp_path / "local",
                  stream=io.StringIO(), max_updates=4)
    run_dir = tmp_path / "group"

    def kill_learner_1(done, train_state, values):
        if done == 3 and not killed:
            name = json.loads((run_dir / RAY_RECORD).read_text())["actors"]["learner"]
            member = ray.get_actor(f"{name}-1", namespace=RAY_NAMESPACE)
            os.kill(ray.get(member.pid.remote()), signal.SIGKILL)
            killed.append(done)

    killed: list[int] = []
    config = ray_config("robust_plr", **overrides, **{
        "ray.deterministic": "true", "ray.explorers": 0, "ray.learners": 2,
        "ray.learner_restarts": 1})
    out = io.StringIO()
    train(config, run_dir=run_dir, stream=out, max_updates=4, callback=kill_learner_1)
    assert killed == [3]
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["learner_restarts"] == 1 and record["steps_lost"] == 1, out.getvalue()[-3000:]
    assert record["status"] == "finished" and record["steps"] == [2, 4]
    assert "continues from its checkpoint at step 2; 1 steps lost" in out.getvalue()
    state_a, key_a, step_a = final_state(local, ued_config("robust_plr"))
    state_b, key_b, step_b = final_state(run_dir, ued_config("robust_plr"))
    assert step_a == step_b == 4
    assert trees_equal(state_a.params, state_b.params) and np.array_equal(key_a, key_b)
