"""The one training loop (`workers.training_loop`) with a stand-in runner whose step is a draw
from its key: what is due after which step, and a resumed run continuing the key chain and
state of an uninterrupted one. No learner is compiled."""

from __future__ import annotations

import io
import os
import re
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_learners_helpers import tiny_config

from workers.driver import Driver
from workers.training_loop import Output, Report, Runner, train_loop


class Counting(Runner):
    """A train state {"x": sum of the steps' draws}; every hook call logged in `calls`."""

    def __init__(self, config):
        super().__init__(config)
        self.calls: list[tuple[str, int]] = []
        self.state: Any = None

    @property
    def eval_every(self) -> int:
        return 3

    def init(self, key):
        self.state = {"x": jax.random.uniform(key)}

    def template(self):
        return self.state

    def restore(self, run_dir: Path, train_state, start: int) -> None:
        self.state = train_state
        self.calls.append(("restore", start))

    def headline(self, run_dir: Path, start: int) -> str:
        return f"counting in {run_dir}"

    def step(self, index: int, key, *, last: bool, checkpoint_due: bool) -> bool:
        self.state = {"x": self.state["x"] + jax.random.uniform(key)}
        self.calls.append(("step", index))
        return True

    def host_metrics(self) -> dict[str, Any]:
        return {"x": float(self.state["x"])}

    def log(self, metrics: dict[str, Any], report: Report) -> None:
        self.calls.append(("log", report.done))
        report.show({**metrics, **report.timing}, self.state)

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if due:
            self.calls.append(("evaluate", done))

    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        self.calls.append(("checkpoint", done))
        return self.state, done


def config():
    return tiny_config(**{"learner.total_timesteps": 5 * 64, "run.log_every": 2,
                          "run.checkpoint_every": 2, "run.keep_checkpoints": 5})


def test_log_evaluate_and_checkpoint_when_due(tmp_path):
    runner, out, seen = Counting(config()), io.StringIO(), []
    train_loop(runner, tmp_path, resume=False, max_updates=None, progress=True, stream=out,
               callback=lambda done, state, metrics: seen.append(done))
    after = {}
    for what, n in runner.calls:
        after.setdefault(n if what == "step" else n - 1, []).append(what)
    assert after == {0: ["step", "log"], 1: ["step", "log", "checkpoint"],
                     2: ["step", "evaluate"], 3: ["step", "log", "checkpoint"],
                     4: ["step", "log", "evaluate", "checkpoint"]}
    assert seen == [1, 2, 4, 5]  # the first step, every run.log_every, the last
    assert out.getvalue().startswith(f"training counting in {tmp_path}\n")


def test_a_resumed_run_continues_the_key_chain(tmp_path):
    whole = Counting(config())
    train_loop(whole, tmp_path / "whole", resume=False, max_updates=None, progress=False,
               stream=io.StringIO(), callback=None)
    part = tmp_path / "part"
    train_loop(Counting(config()), part, resume=False, max_updates=3, progress=False,
               stream=io.StringIO(), callback=None)
    resumed = Counting(config())
    train_loop(resumed, part, resume=True, max_updates=None, progress=False,
               stream=io.StringIO(), callback=None)
    assert resumed.calls[0] == ("restore", 3)  # step 3: the last of the first call
    assert [n for what, n in resumed.calls if what == "step"] == [3, 4]
    np.testing.assert_array_equal(jnp.asarray(resumed.state["x"]), whole.state["x"])


class Diverging(Counting):
    """Counting whose state turns NaN at step `at` (0-based), with a `loss` metric."""

    def __init__(self, config, at: int, log_loss: bool = True):
        super().__init__(config)
        self.at, self.log_loss = at, log_loss

    def step(self, index: int, key, *, last: bool, checkpoint_due: bool) -> bool:
        super().step(index, key, last=last, checkpoint_due=checkpoint_due)
        if index >= self.at:
            self.state = {"x": self.state["x"] * jnp.nan}
        return True

    def host_metrics(self) -> dict[str, Any]:
        x = float(self.state["x"])
        return {"x": x, "loss/total": x} if self.log_loss else {"x": x}


def test_a_nonfinite_loss_stops_the_run_before_it_is_saved(tmp_path):
    """A NaN loss stops the run at that update with one line naming the last good checkpoint;
    with no loss logged, the parameters' check keeps the NaN state out of the checkpoints."""
    from ued.run_folder import open_checkpoints
    from workers.training_loop import TrainingDiverged

    for log_loss, stopped_at in ((True, 4), (False, 4)):
        run_dir = tmp_path / f"loss-{log_loss}"
        runner = Diverging(config(), at=2, log_loss=log_loss)  # step 3 (done) is the first NaN
        try:
            train_loop(runner, run_dir, resume=False, max_updates=None, progress=False,
                       stream=io.StringIO(), callback=None)
        except TrainingDiverged as err:
            message = str(err)
        else:
            raise AssertionError("a NaN run finished")
        assert "\n" not in message
        assert f"diverged at update {stopped_at}" in message
        assert "step 2" in message and "checkpoints/2" in message, message
        with open_checkpoints(run_dir, runner.config) as checkpoints:
            assert checkpoints.all() == [2]  # the NaN state of step 4 was never saved


class CountingDriver(Driver):
    """The local driver's part of `train`, with the Counting stand-in for a learner."""

    def run(self, config, run_dir, *, resume=False, max_updates=None, progress=True,
            stream=None, callback=None):
        return train_loop(Counting(config), run_dir, resume=resume, max_updates=max_updates,
                          progress=progress, stream=stream or io.StringIO(), callback=callback)


def finished_run(tmp_path: Path) -> Path:
    from workers.train import train

    return train(config(), run_dir=tmp_path / "run", driver=CountingDriver(), progress=False)


def test_resuming_a_finished_run_checks_its_last_checkpoint(tmp_path):
    """A finished run whose last checkpoint is intact is "already complete"; a damaged last
    step is resumed from the step before (and finished again); with every checkpoint damaged,
    one line says none can be resumed, as `tabx runs check` does."""
    from ued.config import ConfigError
    from workers.train import train

    run_dir = finished_run(tmp_path)
    out = io.StringIO()
    train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=out)
    assert "already complete (5 of 5 updates)" in out.getvalue()

    for data in (run_dir / "checkpoints/5").rglob("*"):
        if data.is_file() and data.stat().st_size > 64 and "ocdbt" in str(data):
            data.write_bytes(data.read_bytes()[:32])
    out = io.StringIO()
    train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=out)
    assert "already complete" not in out.getvalue()
    assert "resume: step 5 is damaged" in out.getvalue() and "from step 4" in out.getvalue()

    for step in (2, 4, 5):
        for data in (run_dir / f"checkpoints/{step}").rglob("*"):
            if data.is_file() and data.stat().st_size > 64 and "ocdbt" in str(data):
                data.write_bytes(data.read_bytes()[:32])
    try:
        train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=io.StringIO())
    except ConfigError as err:
        assert "no intact checkpoint to resume from" in str(err)
    else:
        raise AssertionError("resumed a run whose every checkpoint is damaged")


def test_a_second_writer_of_a_run_folder_is_refused(tmp_path):
    """While one process holds a run folder, `--resume` of it is one ConfigError that changes
    nothing; the lock adds no file, ends with its holder (also one killed with SIGKILL) and
    never blocks after it."""
    import subprocess
    import sys

    from ued.config import ConfigError
    from ued.run_folder import lock_run_dir
    from workers.train import train

    run_dir = finished_run(tmp_path)
    before = sorted(p.name for p in run_dir.iterdir())
    with lock_run_dir(run_dir):
        try:
            train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=io.StringIO())
        except ConfigError as err:
            assert "another process is training this run" in str(err)
        else:
            raise AssertionError("two writers of one run folder")
        # A sweep's trial holds the lock itself and tells train so.
        out = io.StringIO()
        train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=out, locked=True)
        assert "already complete" in out.getvalue()
    assert sorted(p.name for p in run_dir.iterdir()) == before
    holder = subprocess.Popen(
        # The same kernel lock as lock_run_dir's, without importing the project (seconds).
        [sys.executable, "-c", "import fcntl, os, time\n"
         f"fd = os.open({str(run_dir)!r}, os.O_RDONLY | os.O_DIRECTORY)\n"
         "fcntl.flock(fd, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        try:
            with lock_run_dir(run_dir):
                raise AssertionError("a held run folder was locked twice")
        except ConfigError:
            pass
        # A waiting lock (a sweep's trial) takes the folder once its holder is gone.
        import threading

        threading.Timer(1.0, holder.kill).start()  # SIGKILL: no cleanup runs in the holder
        with lock_run_dir(run_dir, wait_s=30):
            assert holder.wait(timeout=10) is not None
    finally:
        holder.kill()
        holder.wait(timeout=10)
    out = io.StringIO()
    train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=out)
    assert "already complete" in out.getvalue()


class Heavy(Counting):
    """Counting with 1.2 MB of random parameters beside its sum: two checkpoints fill 2 MB."""

    def init(self, key):
        self.state = {"x": jax.random.uniform(key),
                      "w": jax.random.uniform(jax.random.key(1), (300_000,))}

    def step(self, index: int, key, *, last: bool, checkpoint_due: bool) -> bool:
        self.state = {**self.state, "x": self.state["x"] + jax.random.uniform(key)}
        return True


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs (root only: skipped elsewhere)."""
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs",
                                            str(mount)], capture_output=True).returncode:
        pytest.skip("mounting a small tmpfs needs root")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_during_a_checkpoint_is_one_line(small_disk, capfd):
    """The checkpoint of step 4 does not fit: one CheckpointError naming the folder, the free
    space and the space needed; nothing else on stderr; checkpoint 2 restores."""
    from ued.checkpoint import CheckpointError
    from ued.run_folder import open_checkpoints

    run_dir = small_disk / "run"
    runner = Heavy(config())
    with pytest.raises(CheckpointError) as caught:
        train_loop(runner, run_dir, resume=False, max_updates=None, progress=False,
                   stream=io.StringIO(), callback=None)
    message = str(caught.value)
    assert "\n" not in message and f"{run_dir}/checkpoints/4: cannot be saved: no space" in message
    assert re.search(r"\d+\.\d MB free; the checkpoint needs about 1\.2 MB\); checkpoint 2 is "
                     r"intact", message), message
    _, err = capfd.readouterr()
    assert "Traceback" not in err and "ERROR" not in err, err[-2000:]
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["2"]
    with open_checkpoints(run_dir, runner.config) as checkpoints:
        state, _, step = checkpoints.restore(runner.template(), 2)
    assert step == 2 and state["w"].shape == (300_000,)


def test_a_read_only_run_folder_is_refused_before_any_work(tmp_path):
    """`--resume` of a run folder that cannot be written (a read-only mount as root, else its
    permissions), and a new run under a parent that cannot be written: one ConfigError each,
    and nothing changes."""
    import subprocess

    from ued.config import ConfigError
    from workers.train import train

    run_dir = finished_run(tmp_path)
    for data in (run_dir / "checkpoints/5").rglob("*"):  # so that resume would train
        if data.is_file() and data.stat().st_size > 64 and "ocdbt" in str(data):
            data.write_bytes(data.read_bytes()[:32])
    before = sorted(str(p) for p in run_dir.rglob("*"))
    if os.geteuid() == 0:
        mounted = subprocess.run(["mount", "--bind", "-o", "ro", str(run_dir), str(run_dir)],
                                 capture_output=True).returncode == 0
        if not mounted:
            pytest.skip("no read-only bind mount here")
        undo = ["umount", "-l", str(run_dir)]
    else:
        run_dir.chmod(0o555)
        undo = ["chmod", "755", str(run_dir)]
    try:
        with pytest.raises(ConfigError, match=r"not writable \(Read-only file system|"
                                              r"not writable \(Permission denied"):
            train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=io.StringIO())
        with pytest.raises(ConfigError, match=r"cannot make the run folder"):
            train(config(), run_dir=run_dir / "new", driver=CountingDriver(), progress=False)
    finally:
        subprocess.run(undo, check=False)
    assert sorted(str(p) for p in run_dir.rglob("*")) == before


def test_a_resumed_run_compares_its_config_with_its_checkpoint(tmp_path):
    """config.yaml cut to a shorter valid value: `--resume` refuses it in one line, naming
    the file; the same file restored resumes."""
    from ued.config import ConfigError
    from ued.run_folder import CONFIG_FILE
    from workers.train import train

    run_dir = train(config(), run_dir=tmp_path / "run", driver=CountingDriver(), progress=False,
                    max_updates=2)
    path = run_dir / CONFIG_FILE
    text = path.read_text()
    assert "total_timesteps: 320\n" in text
    path.write_text(text.replace("total_timesteps: 320\n", "total_timesteps: 32\n"))
    with pytest.raises(ConfigError, match=r"config\.yaml: differs from the config checkpoint 2 "
                                          r"was trained with"):
        train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=io.StringIO())
    path.write_text(text)
    train(run_dir=run_dir, resume=True, driver=CountingDriver(), stream=io.StringIO())
