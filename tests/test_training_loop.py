"""The one training loop (`workers.training_loop`) with a stand-in runner whose step is a draw
from its key: what is due after which step, and a resumed run continuing the key chain and
state of an uninterrupted one. No learner is compiled."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from test_learners_helpers import tiny_config

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
