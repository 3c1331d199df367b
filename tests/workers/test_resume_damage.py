"""Resume survives damaged files: a truncated checkpoint data file, a truncated `_METADATA`
or a damaged buffer snapshot of the newest step sends `--resume` to the newest intact step,
in one line naming the file; the newer files are set aside, not deleted; the continued run
equals the uninterrupted one; `tabx runs check` reports every step; nothing intact: one clear
error and no traceback.
"""

from __future__ import annotations

import io
import shutil

import jax
import numpy as np
import pytest
from test_ued_train import ued_config

from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.config import ConfigError
from ued.run_folder import CHECKPOINT_DIR, LEVELS_DIR
from workers.resume import SET_ASIDE_DIR
from workers.train import train
from workers.ued_step import UEDRun

STEPS = 6
CONFIG = {"run.checkpoint_every": 2, "run.keep_checkpoints": 3}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A 6-step Robust PLR run with checkpoints and snapshots at steps 2, 4 and 6."""
    run_dir = tmp_path_factory.mktemp("runs") / "run"
    train(ued_config("robust_plr", **CONFIG), run_dir=run_dir, stream=io.StringIO(),
          max_updates=STEPS)
    return run_dir


def final_params(run_dir, step):
    config = ued_config("robust_plr", **CONFIG)
    template = UEDRun.local(config)[1].init(jax.random.key(0))
    with Checkpoints(run_dir / CHECKPOINT_DIR) as checkpoints:
        state, _, restored = checkpoints.restore(template, step)
    assert restored == step
    return jax.tree.map(np.asarray, state.params)


def largest_data_file(run_dir, step):
    files = [p for p in (run_dir / CHECKPOINT_DIR / str(step)).rglob("*") if p.is_file()]
    return max(files, key=lambda p: p.stat().st_size)


def truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


DAMAGES = {
    "checkpoint data": (lambda run: truncate(largest_data_file(run, STEPS)), "cannot be restored"),
    "checkpoint _METADATA": (lambda run: truncate(run / CHECKPOINT_DIR / str(STEPS) / "default"
                                                  / "_METADATA"), "cannot be restored"),
    "buffer snapshot": (lambda run: truncate(run / LEVELS_DIR / f"buffer-{STEPS}.msgpack"),
                        f"buffer-{STEPS}.msgpack"),
    "missing state": (lambda run: (run / LEVELS_DIR / f"state-{STEPS}.json").unlink(),
                      f"state-{STEPS}.json: missing"),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_resume_falls_back_to_the_newest_intact_step(tmp_path, finished, damage):
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    expected = final_params(finished, STEPS)
    harm, message = DAMAGES[damage]
    harm(run_dir)

    assert main(["runs", "check", str(run_dir)]) == 1  # a damaged step: non-zero

    out = io.StringIO()
    train(run_dir=run_dir, resume=True, stream=out, max_updates=2)
    text = out.getvalue()
    assert f"resume: step {STEPS} is damaged: " in text and message in text, text
    assert "resume: from step 4; " in text and "newer files moved to" in text
    # The damaged step's files are kept, set aside; the run went on from 4 to 6 again.
    aside = list((run_dir / SET_ASIDE_DIR).iterdir())
    assert len(aside) == 1 and (aside[0] / CHECKPOINT_DIR / str(STEPS)).is_dir()
    assert all(np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(expected), jax.tree.leaves(final_params(run_dir, STEPS)), strict=True))
    assert (run_dir / LEVELS_DIR / f"buffer-{STEPS}.msgpack").read_bytes() == (
        finished / LEVELS_DIR / f"buffer-{STEPS}.msgpack").read_bytes()
    assert main(["runs", "check", str(run_dir)]) == 0


def test_nothing_intact_is_one_clear_error(tmp_path, finished, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    for step in (2, 4, 6):
        truncate(run_dir / LEVELS_DIR / f"buffer-{step}.msgpack")
    with pytest.raises(ConfigError, match="no intact checkpoint to resume from"):
        train(run_dir=run_dir, resume=True, stream=io.StringIO(), max_updates=1)
    assert main(["train", "--resume", str(run_dir), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no intact checkpoint to resume from (steps 2, 4, 6)" in err
    assert "Traceback" not in err
    assert not (run_dir / SET_ASIDE_DIR).exists()  # nothing moved when nothing resumed


def test_runs_check_reports_every_step(tmp_path, finished, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    assert main(["runs", "check", str(run_dir)]) == 0
    out = capsys.readouterr().out
    assert all(f"step {s}: intact" in out for s in (2, 4, 6)), out
    truncate(run_dir / LEVELS_DIR / "buffer-4.msgpack")
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert main(["runs", "check", str(run_dir)]) == 1
    out = capsys.readouterr().out
    assert "step 4: damaged: snapshot: " in out and "buffer-4.msgpack" in out
    assert "newest intact step: 6" in out
    assert before == {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert main(["runs", "check", str(tmp_path / "nowhere")]) == 2
