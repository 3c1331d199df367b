"""The Ray driver on real multi-process clusters on 127.0.0.1: a two-node cluster
(`ray.cluster_utils.Cluster`) with an Explorer on each node, and a cluster started with the
`ray` command line that `tabx train --ray --address` joins.

Each test starts its cluster, runs a short asynchronous ACCEL or Robust PLR job (the UED tests'
tiny config), checks where the actors ran, the level buffer and the `ray/*` metrics, and shuts
the cluster down (bounded in time; never `ray stop`, which would stop every Ray on the machine).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import ray
from ray.cluster_utils import Cluster
from test_ued_train import ued_config

from level_buffer import LevelBuffer
from ued.run_folder import EVENTS_DIR, LEVELS_DIR
from ued.tensorboard import read_scalars
from workers.ray.driver import RAY_RECORD
from workers.train import train

STEPS = 6


def check_run(run_dir: Path, steps: int) -> dict:
    """The run folder of a finished asynchronous run: its record, buffer and metrics agree."""
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["mode"] == "asynchronous" and record["steps"] == [0, steps]
    assert record["ledger"] == {"committed": steps}
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / f"buffer-{steps}.msgpack")
    assert len(buffer) > 0
    scored = record["branches"]["new"] + record["branches"]["mutate"]
    assert record["committed_batches"] == scored
    assert buffer.stats["insert_attempts"] == 4 * scored
    assert buffer.column("policy_version").max() <= record["branches"]["replay"]
    scalars = read_scalars(run_dir / EVENTS_DIR)
    assert scalars["ray/committed_batches"][-1][1] == scored
    assert scalars["ray/explored_steps_per_s"][-1][1] > 0
    return record


@pytest.mark.slow  # the lost-node test below also runs an Explorer on a second node
def test_two_node_cluster_places_an_explorer_on_each_node(tmp_path):
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 2, "include_dashboard": False, "object_store_memory": 96 * 2**20})
    try:
        cluster.add_node(num_cpus=2, object_store_memory=96 * 2**20)
        cluster.wait_for_nodes(timeout=60)
        ray.init(address=cluster.address, logging_level="ERROR")
        nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"]}
        assert len(nodes) == 2
        config = ued_config("accel", **{"ray.enabled": "true", "ray.explorers": 2})
        out = io.StringIO()
        run_dir = train(config, run_dir=tmp_path / "two-nodes", stream=out, max_updates=STEPS)
        record = check_run(run_dir, STEPS)
        placement = record["placement"]
        assert set(placement.values()) <= nodes
        assert {placement["explorer-0"], placement["explorer-1"]} == nodes  # one per node
        assert "explorers 2" in out.getvalue()
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_a_lost_node_moves_its_explorer_and_the_run_finishes(tmp_path):
    # The learner and the service sit on the head (Ray keeps early actors on the driver's
    # node); an Explorer on the worker node. Removing that node mid-run must restart its
    # Explorer on the head (which has a CPU to spare), re-issue what it held, and finish with
    # every batch committed once.
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 3, "include_dashboard": False, "object_store_memory": 96 * 2**20})
    try:
        worker = cluster.add_node(num_cpus=2, object_store_memory=96 * 2**20)
        cluster.wait_for_nodes(timeout=60)
        ray.init(address=cluster.address, logging_level="ERROR")
        run_dir = tmp_path / "lost-node"
        removed = {}

        def remove_worker(done, train_state, values):
            if done == 2:
                placement = json.loads((run_dir / RAY_RECORD).read_text())["placement"]
                removed["placement"] = placement
                assert placement["learner"] != worker.node_id, placement  # precondition
                assert placement["service"] != worker.node_id, placement
                cluster.remove_node(worker)
                removed["at"] = done

        config = ued_config("accel", **{"ray.enabled": "true", "ray.explorers": 2,
                                        "run.log_every": 1})
        out = io.StringIO()
        train(config, run_dir=run_dir, stream=out, max_updates=8, callback=remove_worker)
        assert removed["at"] == 2
        assert worker.node_id in removed["placement"].values()  # an Explorer was there
        record = check_run(run_dir, 8)
        assert record["status"] == "finished"
        moved = [name for name, node in removed["placement"].items() if node == worker.node_id]
        head = removed["placement"]["learner"]
        assert moved and all(record["placement_end"][name] == head for name in moved), record
    finally:
        ray.shutdown()
        cluster.shutdown()


@pytest.mark.slow  # tests/workers/ray/test_learner_group.py covers the same update by default
def test_two_learners_on_two_nodes_train_as_one_learner_with_two_devices(tmp_path):
    """`ray.learners: 2` on a two-node cluster: one learner per node (the group's placement
    group spreads CPU learners), one JAX process group over both; IPPO + ACCEL, deterministic,
    equals the local run with 2 devices bit for bit."""
    import jax
    import numpy as np

    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR
    from workers.ued_step import UEDRun

    base = {"algorithm": "ippo"}
    local = train(ued_config("accel", **base), run_dir=tmp_path / "local", stream=io.StringIO(),
                  max_updates=3)
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 2, "include_dashboard": False, "object_store_memory": 96 * 2**20})
    try:
        cluster.add_node(num_cpus=1, object_store_memory=96 * 2**20)
        cluster.wait_for_nodes(timeout=60)
        ray.init(address=cluster.address, logging_level="ERROR")
        nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"]}
        config = ued_config("accel", **base, **{
            "ray.enabled": "true", "ray.deterministic": "true", "ray.explorers": 0,
            "ray.learners": 2})
        remote = train(config, run_dir=tmp_path / "two-nodes", stream=io.StringIO(),
                       max_updates=3)
        record = json.loads((remote / RAY_RECORD).read_text())
        assert set(record["learner_nodes"]) == nodes  # one learner per node
    finally:
        ray.shutdown()
        cluster.shutdown()
    template = UEDRun.local(ued_config("accel", **base))[1].init(jax.random.key(0))
    states = []
    for run_dir in (local, remote):
        with Checkpoints(run_dir / CHECKPOINT_DIR) as checkpoints:
            states.append(checkpoints.restore(template))
    (state_a, _, step_a), (state_b, _, step_b) = states
    assert step_a == step_b == 3
    for a, b in zip(jax.tree.leaves(state_a), jax.tree.leaves(state_b), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ray_command() -> str:
    beside = Path(sys.executable).parent / "ray"
    found = str(beside) if beside.exists() else shutil.which("ray")
    assert found, "the ray command line is not installed (pip install -e '.[ray]')"
    return found


def stop_session(process: subprocess.Popen, grace_s: float = 10.0) -> None:
    """Stop a `ray start --block` and everything it started (its own process group)."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(process.pid, signal.SIGKILL)  # what SIGTERM left (raylet, GCS)
    except ProcessLookupError:
        pass
    process.wait(timeout=grace_s)


@pytest.fixture
def cli_cluster(tmp_path):
    """A one-node Ray cluster started with `ray start --head`, checking a token of its own (a
    fresh machine has no ~/.ray/auth_token, and the user's must not be touched); yields its
    address and the environment a process joining it needs."""
    import secrets

    port = free_port()
    log = open(tmp_path / "ray-head.log", "w")  # noqa: SIM115 (closed below)
    token = tmp_path / "auth_token"
    token.write_text(secrets.token_hex(32))  # the form `ray get-auth-token --generate` writes
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)}
    env.pop("RAY_AUTH_TOKEN", None)
    head = subprocess.Popen(
        [ray_command(), "start", "--head", f"--port={port}", "--num-cpus=2",
         "--include-dashboard=false", "--disable-usage-stats", "--block"],
        stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        while "Ray runtime started" not in (tmp_path / "ray-head.log").read_text():
            assert head.poll() is None, (tmp_path / "ray-head.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "ray start --head did not start in 90 s"
            time.sleep(0.5)
        yield f"127.0.0.1:{port}", env
    finally:
        stop_session(head)
        log.close()
        forget_address(f"127.0.0.1:{port}")


def forget_address(address: str) -> None:
    """Remove the address `ray start` left in /tmp/ray/ray_current_cluster (as `ray stop`
    does), where it is this head's: a later plain `ray.init()` would try to join it."""
    from ray._common.utils import get_ray_address_file

    path = get_ray_address_file(None)
    if os.path.exists(path) and open(path).read().strip() == address:
        os.unlink(path)


def test_tabx_train_joins_a_cluster_started_with_the_ray_command(tmp_path, cli_cluster):
    config_file = tmp_path / "tiny.yaml"
    config_file.write_text(ued_config("robust_plr", **{"ray.explorers": 1}).to_yaml())
    run_dir = tmp_path / "joined"
    address, env = cli_cluster  # the CLI cluster checks its token
    done = subprocess.run(
        [sys.executable, "-m", "tabx_ued", "train", str(config_file), "--ray", "--address",
         address, "--run-dir", str(run_dir), "--max-updates", str(STEPS)],
        capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith(str(run_dir))
    assert "on Ray (asynchronous, 1 explorers" in done.stderr
    record = check_run(run_dir, STEPS)
    assert set(record["placement"]) == {"service", "learner", "explorer-0"}


def test_joining_an_address_where_no_cluster_runs_is_a_clear_error(tmp_path, capsys):
    # In the test process (`main` is what `python -m tabx_ued` runs): the address is refused
    # before Ray starts, so a process of its own would only add its imports.
    from tabx_ued.cli import main

    config_file = tmp_path / "tiny.yaml"
    config_file.write_text(ued_config("robust_plr").to_yaml())
    code = main(["train", str(config_file), "--ray", "--address", f"127.0.0.1:{free_port()}",
                 "--run-dir", str(tmp_path / "never")])
    err = capsys.readouterr().err
    assert code == 2, err[-3000:]
    assert "ray.address: no Ray head answers at 127.0.0.1:" in err
    assert not ray.is_initialized()  # refused before Ray started
    assert not (tmp_path / "never").exists()  # no run folder for a run that never started


def test_joining_an_address_where_a_web_server_listens_fails_at_once(tmp_path, capsys):
    # A socket that answers is not yet a Ray head: a plain HTTP server is refused in one line,
    # within seconds, before a run folder exists (Ray itself would retry it for minutes).
    import http.server
    import threading

    from tabx_ued.cli import main

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    config_file = tmp_path / "tiny.yaml"
    config_file.write_text(ued_config("robust_plr").to_yaml())
    try:
        t0 = time.perf_counter()
        code = main(["train", str(config_file), "--ray", "--address",
                     f"127.0.0.1:{server.server_address[1]}", "--run-dir",
                     str(tmp_path / "never")])
        elapsed = time.perf_counter() - t0
    finally:
        server.shutdown()
        server.server_close()
    err = capsys.readouterr().err
    assert code == 2, err
    assert elapsed < 10
    lines = [line for line in err.splitlines() if line.startswith("tabx")]  # not the server's
    assert len(lines) == 1 and "is not a Ray head" in lines[0], err
    assert not (tmp_path / "never").exists()
