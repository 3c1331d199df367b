"""`tabx sweep`: sweep files, trials scheduled with Ray Tune on a local Ray, the report.

The default suite runs one end-to-end sweep (a 2 x 2 grid of tiny plain MARL runs and a bad
trial, on a Ray started in this process) and the sweep file's checks; killing and resuming a
sweep, the two-node cluster and a lost node are `-m slow`.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_learners_helpers import tiny_config

from ued.config import ConfigError
from workers.sweep.spec import read_sweep_spec

ROOT = Path(__file__).resolve().parents[3]


def write_spec(folder: Path, text: str, base: dict | None = None) -> Path:
    (folder / "base.yaml").write_text(tiny_config(**(base or {})).to_yaml())
    path = folder / "sweep.yaml"
    path.write_text(text)
    return path


# --- the sweep file ----------------------------------------------------------------------------


def test_grid_points_templates_and_names(tmp_path):
    spec = read_sweep_spec(write_spec(tmp_path, """
name: demo
base: base.yaml
set: {run.log_every: 2}
grid:
  - learner.lr: [0.001, 0.002]
    variant:
      small: {hidden_dim: 8, run.name: "small-{seed}"}
      wide: {hidden_dim: 32}
    seed: [0, 1]
points:
  - {name: long, learner.total_timesteps: 512}
resources: {cpus: 2, explorers: 1}
"""))
    assert len(spec.trials) == 2 * 2 * 2 + 1
    first = spec.trials[0]
    assert first.name == "lr0.001-small-seed0"
    assert first.label_map == {"learner.lr": "0.001", "variant": "small", "seed": "0"}
    assert (first.config.learner.lr, first.config.learner.hidden_dim, first.config.seed,
            first.config.run.log_every, first.config.run.name) == (0.001, 8, 0, 2, "small-0")
    assert spec.trial("long").config.learner.total_timesteps == 512
    assert spec.axes == ("learner.lr", "variant", "seed", "learner.total_timesteps")
    assert spec.resources.bundles() == [{"CPU": 2.0}, {"CPU": 1.0}]
    roles = spec.report_axes()
    assert roles.seed_axis == "seed" and roles.line_axis is None
    assert spec.folder() == Path("sweeps/demo")


@pytest.mark.parametrize("text,message", [
    ("base: base.yaml\ngrid: {seed: [0]}\nbogus: 1\n", "unknown key 'bogus'"),
    ("base: base.yaml\ngrid: {ued.metod: [dr]}\n", "grid.ued.metod: unknown config key"),
    ("base: base.yaml\ngrid: {seed: []}\n", "grid.seed: expected a non-empty list"),
    ("base: base.yaml\ngrid: {learner.gamma: [0.9, 2]}\n",
     "grid, trial gamma2: .*learner.gamma: must be in"),
    ("base: base.yaml\ngrid: {seed: [0]}\nset: {run.name: '{nope}'}\n",
     r"grid.run.name: \{nope\} names no axis"),
    ("base: base.yaml\ngrid: {seed: [0]}\nresources: {gpu: 1}\n", "resources.gpu: unknown"),
    ("grid: {seed: [0]}\n", "base: missing"),
    ("base: base.yaml\npoints: [{seed: 1}, {seed: 1}]\n", "two trials are named 'seed1'"),
    ("base: base.yaml\ngrid: {metod: [dr, plr]}\n",
     "trials dr and plr have the same config; does the named axis 'metod' set anything"),
])
def test_a_bad_sweep_file_is_one_error_naming_file_and_field(tmp_path, text, message):
    path = write_spec(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        read_sweep_spec(path)
    assert str(info.value).startswith(str(path))


def test_the_shipped_sweeps_read(tmp_path):
    shipped = sorted((ROOT / "configs" / "sweeps").glob("*.yaml"))
    assert {"paper_ued", "paper_ued_cpu", "paper_ablation_cpu", "paper_marl_cpu"} <= {
        path.stem for path in shipped}
    for path in shipped:
        spec = read_sweep_spec(path)
        assert spec.trials and spec.report_axes().seed_axis is not None, path.name
    paper = read_sweep_spec(ROOT / "configs" / "sweeps" / "paper_ued.yaml")
    # 5 methods x {unit, zone} x 4 scenarios, and the health/speed/damage ablations, x 5 seeds
    assert len(paper.trials) == 5 * (2 + 3) * 4 * 5
    assert {t.config.learner.total_timesteps for t in paper.trials} == {50_000_000}
    marl = read_sweep_spec(ROOT / "configs" / "sweeps" / "paper_marl_cpu.yaml")
    # MAPPO and IPPO x 4 challenges, 3 seeds in each trial's program
    assert len(marl.trials) == 2 * 4 and {t.config.seeds for t in marl.trials} == {(0, 1, 2)}
    ablation = read_sweep_spec(ROOT / "configs" / "sweeps" / "paper_ablation_cpu.yaml")
    # one attribute free at a time, at the UED study's CPU budget, x 3 seeds
    assert len(ablation.trials) == 3 * 3
    assert {t.config.levels.free for t in ablation.trials} == {
        ("health",), ("speed",), ("damage",)}
    assert {t.config.learner.total_timesteps for t in ablation.trials} == {819_200}


# --- running a sweep ---------------------------------------------------------------------------


def test_a_grid_runs_as_run_folders_a_bad_trial_fails_alone_and_the_report(tmp_path):
    """A 2 x 2 grid and a trial whose scenario does not exist, on a Ray started here: four
    ordinary run folders, one failed trial with its error, a report that names the missing
    trial unless --partial."""
    from tabx_ued.cli import main
    from workers.sweep.folder import SweepFolder
    from workers.sweep.report import write_report
    from workers.sweep.tune import run_sweep

    spec = read_sweep_spec(write_spec(tmp_path, f"""
name: grid
base: base.yaml
dir: {tmp_path / 'sweeps'}
grid:
  seed: [0, 1]
  run.log_every: [1, 2]
points:
  - {{name: bad, env.scenario: no_such_scenario}}
"""))
    log = tmp_path / "table.txt"
    with open(log, "w") as stream:
        outcome = run_sweep(spec, num_cpus=2, stream=stream, reuse_processes=True)
    table = log.read_text()
    assert sorted(outcome.finished) == sorted(t.name for t in spec.trials if t.name != "bad")
    assert list(outcome.failed) == ["bad"] and "no_such_scenario" in outcome.failed["bad"]
    assert "bad" in table and "failed" in table and "steps/s" in table
    folder = SweepFolder(outcome.folder)
    for trial in outcome.finished:
        run = folder.run_dir(trial)
        assert (run / "config.yaml").is_file() and (run / "checkpoints").is_dir()
        record = folder.record(trial)
        assert record.state == "finished" and record.sessions == 1 and record.seconds > 0
    with pytest.raises(ConfigError, match=r"1 of 5 trials are not finished: bad \(failed: "):
        write_report(outcome.folder)
    code = main(["sweep", "report", str(outcome.folder), "--partial"])
    assert code == 0
    report = folder.path / "report"
    assert {p.name for p in report.iterdir()} >= {"report.md", "results.csv", "trials.csv",
                                                  "curves-all.png"}
    rows = (report / "results.csv").read_text().splitlines()
    assert rows[0].startswith("run.log_every,env.scenario,table,suite,opponent,seeds,mean")
    # one cell per run.log_every (the training win rate over 2 seeds) and its `mean` row
    assert len(rows) == 5 and all(",train,,,2," in row for row in rows[1:])


def _records(folder: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in (folder / "trials").glob("*.json")}


@pytest.mark.slow
def test_a_killed_sweep_resumes_and_finishes_each_trial_once(tmp_path):
    """The sweep process SIGKILLed while one trial is finished and others are part-way; `tabx
    sweep SPEC --resume` finishes the others from their checkpoints and runs no finished trial
    again. (The default test above covers a sweep run in one go.)"""
    path = write_spec(tmp_path, f"""
name: killed
base: base.yaml
dir: {tmp_path / 'sweeps'}
grid:
  seed: [0, 1, 2]
  run.log_every: [1]
max_concurrent: 2
""", base={"learner.total_timesteps": 64 * 40, "run.checkpoint_every": 2})
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "tabx_ued", "sweep", str(path), "--table-every", "1"]
    folder = tmp_path / "sweeps" / "killed"
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        states = [r["state"] for r in _records(folder).values()] if folder.exists() else []
        if "finished" in states and "running" in states:
            break
        time.sleep(0.5)
    else:
        process.kill()
        pytest.fail("no trial finished in time")
    process.send_signal(signal.SIGKILL)
    process.wait()
    before = _records(folder)
    done = subprocess.run([*command, "--resume"], env=env, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    after = _records(folder)
    assert all(r["state"] == "finished" for r in after.values()) and len(after) == 3
    for name, record in before.items():
        if record["state"] == "finished":
            assert after[name]["sessions"] == record["sessions"] == 1, name  # not run again
        else:
            assert after[name]["sessions"] == record["sessions"] + 1, name
    assert "finished before" in done.stderr
    from workers.sweep.report import write_report

    assert write_report(folder).markdown.is_file()


@pytest.mark.slow
def test_address_joins_a_two_node_cluster_and_trials_run_on_both_nodes(tmp_path):
    """`--address` joins a running cluster (two nodes on 127.0.0.1, one CPU each): the two
    trials run at once, one on each node. (The default test above covers a local Ray.)"""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        path = write_spec(tmp_path, f"""
name: twonodes
base: base.yaml
dir: {tmp_path / 'sweeps'}
grid: {{seed: [0, 1]}}
""")
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        done = subprocess.run([sys.executable, "-m", "tabx_ued", "sweep", str(path),
                               "--address", cluster.address], env=env, capture_output=True,
                              text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-3000:]
        records = _records(tmp_path / "sweeps" / "twonodes")
        nodes = {node for r in records.values() for node in r["nodes"]}
        assert len(records) == 2 and len(nodes) == 2
    finally:
        cluster.shutdown()


@pytest.mark.slow
def test_a_lost_nodes_trial_is_rescheduled_and_resumes_its_run_folder(tmp_path):
    """The node running a trial is removed mid-trial (a cluster on 127.0.0.1: a head with no
    CPUs for trials and two one-CPU nodes): Tune's retry runs it on the other node, where it
    resumes its run folder from the last checkpoint, and it finishes once. (The default test
    above covers a trial that runs in one go; the SIGKILLed-sweep test covers resuming.)"""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    workers = [cluster.add_node(num_cpus=1) for _ in range(2)]
    cluster.wait_for_nodes()
    folder = tmp_path / "sweeps" / "lostnode"
    try:
        path = write_spec(tmp_path, f"""
name: lostnode
base: base.yaml
dir: {tmp_path / 'sweeps'}
grid: {{seed: [0]}}
""", base={"learner.total_timesteps": 64 * 60, "run.checkpoint_every": 2})
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        process = subprocess.Popen(
            [sys.executable, "-m", "tabx_ued", "sweep", str(path), "--address",
             cluster.address, "--table-every", "1"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 600
        record: dict = {}
        while time.monotonic() < deadline:  # a checkpoint written, the trial still running
            record = _records(folder).get("seed0", {}) if folder.exists() else {}
            if record.get("state") == "running" and 64 * 6 <= record.get("steps", 0) < 64 * 50:
                break
            time.sleep(0.2)
        else:
            process.kill()
            pytest.fail(f"the trial did not get part-way in time: {record}")
        [lost] = [w for w in workers if w.node_id == record["nodes"][0]]
        cluster.remove_node(lost, allow_graceful=False)
        _, err = process.communicate(timeout=900)
        assert process.returncode == 0, err[-3000:]
        after = _records(folder)["seed0"]
        assert after["state"] == "finished" and after["sessions"] == 2, after
        assert len(after["nodes"]) == 2 and after["nodes"][0] == lost.node_id
        log = (folder / "trials" / "seed0.log").read_text()
        assert log.count(": new run ") == 1 and log.count(": resume ") == 1, log
    finally:
        cluster.shutdown()
