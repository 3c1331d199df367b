"""SIGKILL a UED training process at the worst moments, then resume it: the continued run ends
with the same parameters and the same level buffer, bit for bit, as a run never interrupted.

The process is killed by the kernel (no cleanup, no `finally`), from inside, at a chosen point:
during a training step between checkpoints; right after orbax made the temporary folder of a
checkpoint (the step's level snapshot is on disk, its checkpoint is not); and after every
array of the checkpoint is written but before orbax renames the folder into place.
"""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from test_ued_train import ued_config

from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.run_folder import CHECKPOINT_DIR, LEVELS_DIR
from workers.train import train
from workers.ued_step import UEDRun

ROOT = Path(__file__).resolve().parents[2]
# The folders of the helpers it imports (test_ued_train here, test_learners_helpers in ued/).
TESTS = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1] / "ued")]
STEPS = 6
KILL_STEP = 4  # the checkpoint being written when the process dies (one exists at 2)
CONFIG = {"run.checkpoint_every": 2, "run.keep_checkpoints": 3}

# Runs in a fresh interpreter: trains STEPS steps and SIGKILLs itself at the point `where`.
KILLED_RUN = textwrap.dedent("""
    import os, signal, sys
    sys.path[:0] = {tests!r}
    from orbax.checkpoint._src.path import atomicity
    from test_ued_train import ued_config
    from workers.ued_step import UEDRun
    from workers.train import train

    where, step = {where!r}, {step}

    def die():
        sys.stdout.flush()
        os.kill(os.getpid(), signal.SIGKILL)

    if where == "training":  # inside the step after the checkpoint before `step`
        original_step = UEDRun.step
        def step_then_die(self, learner, index, key):
            if index == step - 1:
                die()
            return original_step(self, learner, index, key)
        UEDRun.step = step_then_die
    else:
        cls = atomicity.AtomicRenameTemporaryPath
        original = getattr(cls, where)
        async def patched(self, *args, **kwargs):
            if where == "finalize" and self.get_final().name == str(step):
                die()  # every array written, the folder not yet renamed into place
            result = await original(self, *args, **kwargs)
            if where == "create" and self.get_final().name == str(step):
                die()  # the temporary folder made, nothing in it yet
            return result
        setattr(cls, where, patched)
    train(ued_config("robust_plr", **{config!r}), run_dir={run_dir!r}, max_updates={steps},
          progress=False)
    print("not killed")
""")


def final_params(run_dir: Path):
    config = ued_config("robust_plr", **CONFIG)
    template = UEDRun.local(config)[1].init(jax.random.key(0))
    with Checkpoints(run_dir / CHECKPOINT_DIR, create=False) as checkpoints:
        state, _, restored = checkpoints.restore(template, STEPS)
    assert restored == STEPS
    return jax.tree.map(np.asarray, state.params)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("runs") / "whole"
    train(ued_config("robust_plr", **CONFIG), run_dir=run_dir, stream=io.StringIO(),
          max_updates=STEPS)
    return run_dir


@pytest.mark.parametrize("where", [
    "finalize",
    pytest.param("create", marks=pytest.mark.slow),
    pytest.param("training", marks=pytest.mark.slow),
])
def test_killed_run_resumes_to_the_uninterrupted_result(where, uninterrupted, tmp_path, capsys):
    run_dir = tmp_path / "run"
    script = KILLED_RUN.format(tests=TESTS, where=where, step=KILL_STEP, config=CONFIG,
                               run_dir=str(run_dir), steps=STEPS)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TF_CPP_MIN_LOG_LEVEL": "3"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=env, timeout=900)
    assert done.returncode == -signal.SIGKILL, (done.stdout, done.stderr[-3000:])

    # What the kill left: checkpoint 2, and no committed checkpoint 4.
    checkpoints = run_dir / CHECKPOINT_DIR
    assert (checkpoints / "2").is_dir() and not (checkpoints / str(KILL_STEP)).exists()
    snapshot = run_dir / LEVELS_DIR / f"buffer-{KILL_STEP}.msgpack"
    assert snapshot.exists() == (where != "training")  # the snapshot is written first
    if where != "training":
        assert [p.name for p in checkpoints.iterdir() if p.name.startswith(f"{KILL_STEP}.")]

    # `tabx runs check` sees one intact step; resume continues from it to the end.
    assert main(["runs", "check", str(run_dir)]) == 0
    assert "newest intact step: 2" in capsys.readouterr().out
    assert main(["train", "--resume", str(run_dir), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and "damaged" not in err, err

    assert all(np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(final_params(uninterrupted)), jax.tree.leaves(final_params(run_dir)),
        strict=True))
    for name in (f"buffer-{STEPS}.msgpack", f"state-{STEPS}.json"):
        assert (run_dir / LEVELS_DIR / name).read_bytes() == (
            uninterrupted / LEVELS_DIR / name).read_bytes(), name
    # The snapshot and the half-written checkpoint of the step that never got its checkpoint
    # were set aside, not deleted; checkpoints/ holds only whole checkpoints.
    if where != "training":
        aside = run_dir / "set-aside"
        assert list(aside.rglob(f"buffer-{KILL_STEP}.msgpack"))
        assert list(aside.glob(f"*/{CHECKPOINT_DIR}/{KILL_STEP}.orbax-checkpoint-tmp*"))
    assert all(p.name.isdigit() for p in checkpoints.iterdir()), list(checkpoints.iterdir())
