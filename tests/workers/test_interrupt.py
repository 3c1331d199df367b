"""Ctrl-C and resume as a run's record sees them: SIGINT lets the step under way finish, writes
its checkpoint and then stops (`workers.training_loop.Interrupt`); a resumed run's TensorBoard
files hold one point per step (`SummaryWriter`'s purge_step drops the redone steps' old ones)."""

from __future__ import annotations

import io
import os
import signal

import jax.numpy as jnp
import pytest
from test_learners_helpers import tiny_config

from ued.checkpoint import Checkpoints
from ued.run_folder import CHECKPOINT_DIR, EVENTS_DIR
from ued.tensorboard import SummaryWriter, read_scalars
from workers.training_loop import Runner, train_loop


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


class StubRunner(Runner):
    """A run whose steps compute nothing: the loop's own behaviour, without compiling."""

    def init(self, key):
        self.state = {"w": jnp.zeros(2)}

    def template(self):
        return self.state

    def restore(self, run_dir, train_state, start):
        self.state = train_state

    def headline(self, run_dir, start):
        return "a stub"

    def step(self, index, key, *, last, checkpoint_due):
        self.state = {"w": self.state["w"] + 1}
        return True

    def host_metrics(self):
        return {"loss/total": float(self.state["w"][0])}

    def log(self, metrics, report):
        report.show(metrics, self.state)

    def checkpoint(self, done, run_dir):
        return self.state, done


@pytest.fixture
def python_sigint_handler():
    """Python's own SIGINT handler, as `tabx train` has it: a test that ran earlier in this
    process (one that started Ray, say) may have left another in place."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_writes_a_checkpoint_of_the_step_under_way(tmp_path, python_sigint_handler):
    config = tiny_config(**{"run.checkpoint_every": 100, "run.log_every": 1})

    def interrupt(step, state, metrics):
        if step == 2:
            os.kill(os.getpid(), signal.SIGINT)

    out = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        train_loop(StubRunner(config), tmp_path, resume=False, max_updates=5, progress=True,
                   stream=out, callback=interrupt)
    assert "interrupted: checkpoint of step 2 written" in out.getvalue()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back
    with Checkpoints(tmp_path / CHECKPOINT_DIR) as checkpoints:
        assert checkpoints.latest() == 2
    # The resume redoes nothing here, but writes its purge mark: one point per step.
    train_loop(StubRunner(config), tmp_path, resume=True, max_updates=2, progress=False,
               stream=out, callback=None)
    steps = [step for step, _ in read_scalars(tmp_path / EVENTS_DIR)["loss/total"]]
    assert steps == sorted(set(steps)) and len(steps) == 4
