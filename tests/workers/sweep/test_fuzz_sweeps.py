"""`tabx sweep` and `tabx sweep report` fed bad sweep files, bad options and damaged sweep
folders, as tests/tabx_ued/test_fuzz_inputs.py feeds the other commands: one `tabx sweep: error:`
line naming the input, a non-zero exit, no traceback, and nothing written where nothing may be (no
sweep folder for a refused sweep, the damaged folder unchanged). Also: a grid counted before any
trial is built, the command line's overrides recorded and reused by `--resume`, and a SIGKILLed
sweep leaving no process behind.

Only the last case starts Ray (a subprocess sweep); the others are refused before Ray starts, or
read a sweep folder whose one trial trained in this process.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_fuzz_inputs import assert_one_error, run_cli, tree
from test_learners_helpers import tiny_config

from ued.config import ConfigError
from workers.sweep.folder import SweepFolder, TrialRecord
from workers.sweep.spec import read_sweep_spec

ROOT = Path(__file__).resolve().parents[3]


def write_spec(folder: Path, text: str) -> Path:
    (folder / "base.yaml").write_text(tiny_config().to_yaml())
    path = folder / "sweep.yaml"
    path.write_text(text)
    return path


# --- the sweep file ----------------------------------------------------------------------------

LONG = "x" * 260
SPECS = {
    # 10^8 trials: refused from the axes' lengths, before any trial is built.
    "a huge grid": ("grid:\n" + "".join(f"  a{i}: [{', '.join(map(str, range(10)))}]\n"
                                        for i in range(8)),
                    r"100,000,000 trials \(grid: 10 x 10 x 10 x 10 x 10 x 10 x 10 x 10; 0 "
                    r"points\) is more than max_trials \(1,000\); .*max_trials: 100000000"),
    "max_trials not a count": ("grid: {seed: [0]}\nmax_trials: -1\n",
                               r"max_trials: expected an integer >= 1"),
    "a trial name over 200 bytes": (f"grid: {{variant: {{{LONG}: {{seed: 1}}}}}}\n",
                                    r"grid: a trial's name: the folder name 'xxx.*is 260 "
                                    r"bytes; at most 200"),
    "a point name over 200 bytes": (f"points: [{{name: {LONG}, seed: 1}}]\n",
                                    r"points\[0\]\.name: the folder name .* at most 200"),
    "the sweep named ..": ("name: ..\ngrid: {seed: [0]}\n",
                           r"name: expected a folder name \(.*not \. or \.\.\), got '\.\.'"),
    "a point named .": ("points: [{name: ., seed: 1}]\n", r"points\[0\]\.name: expected a folder"),
    "a point named ..": ("points: [{name: .., seed: 1}]\n",
                         r"points\[0\]\.name: expected a folder"),
    "cpus NaN": ("grid: {seed: [0]}\nresources: {cpus: .nan}\n",
                 r"resources\.cpus: expected a finite number >= 0, got nan"),
    "cpus infinite": ("grid: {seed: [0]}\nresources: {cpus: .inf}\n",
                      r"resources\.cpus: expected a finite number >= 0, got inf"),
    "gpus NaN": ("grid: {seed: [0]}\nresources: {gpus: .nan}\n",
                 r"resources\.gpus: expected a finite number >= 0, got nan"),
    "explorers 10^8": ("grid: {seed: [0]}\nresources: {explorers: 100000000}\n",
                       r"resources\.explorers: expected an integer in \[0, 1024\]"),
    "ray settings without ray": ("grid: {seed: [0]}\nset: {ray.learners: 4}\n",
                                 r"ray\.learners: a setting of runs on Ray"),
}


@pytest.mark.parametrize("case", list(SPECS))
def test_a_bad_sweep_file_is_one_line_and_no_folder(case, tmp_path, capsys):
    body, pattern = SPECS[case]
    path = write_spec(tmp_path, f"base: base.yaml\ndir: {tmp_path / 'sweeps'}\n{body}")
    before = tree(tmp_path)
    t0 = time.monotonic()
    argv = ["sweep", str(path)]
    assert_one_error(*run_cli(capsys, argv), argv, str(path), pattern)
    assert time.monotonic() - t0 < 30, "the file was not refused before its trials were built"
    assert tree(tmp_path) == before


def test_max_trials_lets_a_bigger_grid_through(tmp_path):
    path = write_spec(tmp_path, "base: base.yaml\nmax_trials: 2\ngrid: {seed: [0, 1, 2]}\n")
    with pytest.raises(ConfigError, match="3 trials .* is more than max_trials \\(2\\)"):
        read_sweep_spec(path)
    path.write_text(path.read_text().replace("max_trials: 2", "max_trials: 3"))
    assert len(read_sweep_spec(path).trials) == 3


# --- the command's options ---------------------------------------------------------------------

OPTIONS = {
    ("--cpus", "nan"): r"--cpus: expected a finite number >= 0, got nan",
    ("--cpus", "inf"): r"--cpus: expected a finite number >= 0, got inf",
    ("--gpus", "nan"): r"--gpus: expected a finite number >= 0, got nan",
    ("--cpus", "0"): r"--cpus, --gpus: a trial needs some CPUs",
    ("--num-cpus", "-1"): r"--num-cpus: expected an integer >= 1",
    ("--address", ""): r"--address: empty",
    # No node of the Ray started here can hold a trial: Tune would keep it pending for ever.
    ("--cpus", "1000000"): r"resources: a trial holds 1e\+06 CPU, but the Ray started here has "
                           r"\d+: no trial could start; give --num-cpus, or fewer CPUs",
    ("--gpus", "64"): r"resources: a trial holds 64 GPU, but the Ray started here has \d+",
}


@pytest.mark.parametrize("option", list(OPTIONS), ids=lambda o: " ".join(o))
def test_a_bad_option_is_one_line_before_the_sweep_folder(option, tmp_path, capsys):
    path = write_spec(tmp_path, f"base: base.yaml\ndir: {tmp_path / 'sweeps'}\n"
                                "grid: {seed: [0]}\n")
    before = tree(tmp_path)
    argv = ["sweep", str(path), *option]
    assert_one_error(*run_cli(capsys, argv), argv, option[0].split()[0].lstrip("-")[:3],
                     OPTIONS[option])
    assert tree(tmp_path) == before


def test_a_sweep_folder_that_cannot_be_made_is_one_line(tmp_path, capsys):
    path = write_spec(tmp_path, "base: base.yaml\ndir: /proc/nope\ngrid: {seed: [0]}\n")
    argv = ["sweep", str(path)]
    assert_one_error(*run_cli(capsys, argv), argv, "/proc/nope/sweep",
                     r"cannot make the sweep folder \(.*\); give another dir")


def test_a_cluster_that_cannot_hold_a_trial_is_warned_about(tmp_path):
    """On a cluster nodes may join (an autoscaler), so trials no node can hold are a warning,
    not a refusal: a trial of 4 CPUs on nodes of 2, or 4 Explorers beside it on a cluster of
    6 CPUs in all (a stand-in for Ray's node list)."""
    import types

    from workers.sweep.tune import warn_unfit_cluster

    path = write_spec(tmp_path, "base: base.yaml\ngrid: {seed: [0]}\n"
                                "resources: {cpus: 4, explorers: 4}\n")
    spec = read_sweep_spec(path)

    def warned(*nodes: dict) -> str:
        ray = types.SimpleNamespace(nodes=lambda: [{"Alive": True, "Resources": n}
                                                   for n in nodes])
        stream = io.StringIO()
        warn_unfit_cluster(ray, spec, stream)
        return stream.getvalue()

    assert "no node of the cluster can hold a trial (4 CPU on one node)" in warned(
        {"CPU": 2.0}, {"CPU": 2.0})
    assert "a trial holds 8 CPU but the cluster has 6 CPU;" in warned(
        {"CPU": 4.0}, {"CPU": 2.0})
    assert warned({"CPU": 4.0}, {"CPU": 4.0}) == ""


# --- a sweep folder of one finished trial ------------------------------------------------------


@pytest.fixture(scope="module")
def finished_sweep(tmp_path_factory) -> tuple[Path, Path]:
    """(sweep file, sweep folder): one trial, `seed0`, trained to its end with the command
    line override `run.log_every=2`, and its record saying so."""
    from workers.train import train

    root = tmp_path_factory.mktemp("sweep")
    path = write_spec(root, f"name: one\nbase: base.yaml\ndir: {root / 'sweeps'}\n"
                            "grid: {seed: [0]}\n")
    spec = read_sweep_spec(path, ["run.log_every=2"])
    folder = SweepFolder(spec.folder())
    folder.write(spec, resume=False)
    (trial,) = spec.trials
    train(trial.config, run_dir=folder.run_dir(trial.name), stream=io.StringIO())
    folder.write_record(trial.name, TrialRecord(
        state="finished", sessions=1, seconds=3.0, steps=256, total_steps=256))
    return path, folder.path


def test_resume_reuses_the_overrides_the_sweep_started_with(finished_sweep, tmp_path, capsys):
    """`tabx sweep SPEC run.log_every=2`, then `tabx sweep SPEC --resume`: the overrides are
    the sweep folder's (sweep.json), so every trial keeps its config (here: all finished, so
    nothing starts); other overrides are refused, naming the ones it started with."""
    spec_path, source = finished_sweep
    sweep = tmp_path / "sweeps" / "one"
    shutil.copytree(source, sweep)
    argv = ["sweep", str(spec_path), "--resume", "--dir", str(tmp_path / "sweeps")]
    code, out, err = run_cli(capsys, argv)
    assert code == 0, err
    assert "resuming with the overrides it started with: run.log_every=2" in err
    assert "1 of 1 trials finished" in out
    assert json.loads((sweep / "sweep.json").read_text())["overrides"] == ["run.log_every=2"]
    argv = [*argv, "run.log_every=3"]
    assert_one_error(*run_cli(capsys, argv), argv, str(sweep),
                     r"started with the overrides run\.log_every=2, not run\.log_every=3; "
                     r"resume without overrides")


def _edit_json(path: Path, edit) -> None:
    path.write_text(json.dumps(edit(json.loads(path.read_text()))))


def _trial0(body: dict, **changes) -> dict:
    return {**body, "trials": [{**body["trials"][0], **changes}]}


FOLDER_DAMAGE = {
    "sweep.json a list": ("sweep.json", lambda b: [b], r"sweep\.json: expected a JSON object"),
    "sweep.json without trials": ("sweep.json", lambda b: {k: v for k, v in b.items()
                                                          if k != "trials"},
                                  r"sweep\.json: trials: expected a list, got None"),
    "a trial without labels": ("sweep.json", lambda b: {**b, "trials": [
        {k: v for k, v in b["trials"][0].items() if k != "labels"}]},
        r"sweep\.json: trials\[0\]\.labels: missing"),
    "report a list": ("sweep.json", lambda b: {**b, "report": [1]},
                      r"sweep\.json: report: expected a mapping"),
    "axes a number": ("sweep.json", lambda b: {**b, "axes": 3}, r"sweep\.json: axes: expected"),
    "a trial name that leaves the folder": ("sweep.json", lambda b: _trial0(b, name="../../x"),
                                            r"sweep\.json: trials\[0\]\.name: expected a "
                                            r"folder name"),
    "labels of numbers": ("sweep.json", lambda b: _trial0(b, labels={"seed": 0}),
                          r"trials\[0\]\.labels: expected a mapping of axis to label"),
    "overrides a string": ("sweep.json", lambda b: {**b, "overrides": "seed=1"},
                           r"sweep\.json: overrides: expected a list of KEY=VALUE"),
    "record seconds a string": ("trials/seed0.json", lambda r: {**r, "seconds": "abc"},
                                r"seed0\.json: seconds: expected a number >= 0, got 'abc'"),
    "record a list": ("trials/seed0.json", lambda r: [r],
                      r"seed0\.json: the record: expected a JSON object"),
    "record steps null": ("trials/seed0.json", lambda r: {**r, "steps": None},
                          r"seed0\.json: steps: expected an integer >= 0, got None"),
    "record of an unknown state": ("trials/seed0.json", lambda r: {**r, "state": "done"},
                                   r"seed0\.json: state: expected one of pending"),
}


@pytest.mark.parametrize("case", list(FOLDER_DAMAGE))
def test_a_damaged_sweep_folder_is_one_line_in_report_and_resume(case, finished_sweep,
                                                                 tmp_path, capsys):
    spec_path, source = finished_sweep
    sweep = tmp_path / "sweeps" / "one"
    shutil.copytree(source, sweep)
    rel, edit, pattern = FOLDER_DAMAGE[case]
    _edit_json(sweep / rel, edit)
    before = tree(tmp_path)
    for argv in (["sweep", "report", str(sweep)],
                 ["sweep", "report", str(sweep), "--partial"],
                 ["sweep", str(spec_path), "--resume", "--dir", str(tmp_path / "sweeps")]):
        assert_one_error(*run_cli(capsys, argv), argv, str(sweep / rel), pattern)
        assert tree(tmp_path) == before, argv


@pytest.mark.parametrize("out", ["a file", "a folder in a file", "/proc/nope"])
def test_a_report_output_that_cannot_be_a_folder_is_one_line(out, finished_sweep, tmp_path,
                                                             capsys):
    _, sweep = finished_sweep
    (tmp_path / "file").write_text("x")
    target = {"a file": str(tmp_path / "file"), "a folder in a file": str(tmp_path / "file/x"),
              "/proc/nope": "/proc/nope/report"}[out]
    before = tree(sweep)
    argv = ["sweep", "report", str(sweep), "--out", target]
    assert_one_error(*run_cli(capsys, argv), argv, target, r"--out: ")
    assert tree(sweep) == before
    assert (tmp_path / "file").read_text() == "x"


# --- nothing outlives the command --------------------------------------------------------------


def test_a_killed_sweep_leaves_no_process_behind(tmp_path):
    """`tabx sweep` SIGKILLed while its trial trains: every process it started (its Ray's GCS,
    raylet, dashboard and runtime-env agents, the trial's worker) ends. The test tells them by
    their descent from the sweep's process, recorded while it ran (a pid and its start time):
    another Ray on this machine is neither counted nor touched."""
    from workers.process_guard import alive, descendants, process_table

    path = write_spec(tmp_path, f"name: killed\nbase: base.yaml\ndir: {tmp_path / 'sweeps'}\n"
                                "grid: {seed: [0]}\n"
                                "set: {learner.total_timesteps: 6400000}\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen([sys.executable, "-m", "tabx_ued", "sweep", str(path),
                                "--num-cpus", "1", "--table-every", "1"], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    seen: set[tuple[int, int]] = set()

    def names(processes) -> list[str]:
        out = []
        for pid, _ in processes:
            try:
                out.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(
                    b"\0", b" ").decode(errors="replace")[:100])
            except OSError:
                pass
        return out

    # Ray is up when its agents are, and the trial's process has started.
    wanted = ("raylet", "ray::DashboardAgent", "ray::RuntimeEnvAgent", "ray::ImplicitFunc")
    deadline = time.monotonic() + 300
    try:
        while time.monotonic() < deadline and process.poll() is None:
            seen |= descendants({process.pid}, process_table())
            running = names(alive(seen))
            if all(any(w in c for c in running) for w in wanted):
                break
            time.sleep(0.2)
        else:
            pytest.fail(f"the trial did not start: {process.stderr.read().decode()[-2000:]}"
                        if process.poll() is not None else f"not all started: {running}")
        process.send_signal(signal.SIGKILL)
        process.wait()
        deadline = time.monotonic() + 60
        while alive(seen) and time.monotonic() < deadline:
            time.sleep(0.5)
        left = names(alive(seen))
        assert not left, f"left running after the sweep was killed: {left}"
    finally:
        if process.poll() is None:
            process.kill()
        for pid, _ in alive(seen):  # only processes this test's sweep started
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
