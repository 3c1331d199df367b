"""Ctrl-C and resume as a run's record sees them: SIGINT lets the step under way finish, writes
its checkpoint and then stops (`workers.training_loop.Interrupt`); a resumed run's TensorBoard
files hold one point per step (`SummaryWriter`'s purge_step drops the redone steps' old ones)."""

from __future__ import annotations

import io
import os
import signal

import pytest
from test_learners_helpers import tiny_config

from ued.checkpoint import Checkpoints
from ued.run_folder import CHECKPOINT_DIR, EVENTS_DIR
from ued.tensorboard import SummaryWriter, read_scalars
from workers.train import train


def test_a_resumed_writer_purges_the_redone_steps(tmp_path):
    with SummaryWriter(tmp_path) as writer:
        for step in (10, 20, 30, 40):
            writer.scalars({"a": step, "b": -step}, step)
    with SummaryWriter(tmp_path, purge_step=21) as writer:  # resumed after step 20
        for step in (30, 40, 50):
            writer.scalars({"a": step + 1}, step)
    scalars = read_scalars(tmp_path)
    assert scalars["a"] == [(10, 10), (20, 20), (30, 31), (40, 41), (50, 51)]
    assert scalars["b"] == [(10, -10), (20, -20)]


def test_ctrl_c_writes_a_checkpoint_of_the_step_under_way(tmp_path):
    config = tiny_config(**{"run.checkpoint_every": 100, "run.log_every": 1})

    def interrupt(step, state, metrics):
        if step == 1:
            os.kill(os.getpid(), signal.SIGINT)

    out = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        train(config, run_dir=tmp_path / "run", stream=out, callback=interrupt, max_updates=3)
    assert "interrupted: checkpoint of step 1 written" in out.getvalue()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back
    with Checkpoints(tmp_path / "run" / CHECKPOINT_DIR) as checkpoints:
        assert checkpoints.latest() == 1
    steps = [step for step, _ in read_scalars(tmp_path / "run" / EVENTS_DIR)["loss/total"]]
    assert len(steps) == 1  # the step it stopped after, and no other
