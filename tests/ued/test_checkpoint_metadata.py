"""Checkpoints say what produced them: orbax custom metadata (config hash, update, policy
version, package versions), shown by `tabx runs show`; a checkpoint saved without metadata
still resumes, and shows as "no metadata"."""

from __future__ import annotations

import jax
import pytest
from test_learners_helpers import tiny_config

import tabx
from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.experiment import learner_for
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE, checkpoint_metadata, config_hash


def test_metadata_round_trips_and_old_checkpoints_read_empty(tmp_path):
    config = tiny_config()
    state = learner_for(config).init(jax.random.key(0))
    meta = checkpoint_metadata(config, 3, policy_version=2)
    with Checkpoints(tmp_path) as checkpoints:
        checkpoints.save(1, state, jax.random.key(1))  # as written before metadata existed
        checkpoints.save(3, state, jax.random.key(1), meta)
        assert checkpoints.metadata(1) == {}
        assert checkpoints.metadata(3) == meta
    assert meta["config_sha256"] == config_hash(config) != config_hash(tiny_config(seed=7))
    assert (meta["update"], meta["policy_version"]) == (3, 2)
    assert meta["tabx_ued"] == tabx.__version__ and meta["jax"] == jax.__version__


def make_run(tmp_path):
    """A run folder whose one checkpoint (update 1) was saved without metadata."""
    config = tiny_config()
    run = tmp_path / "run"
    run.mkdir()
    (run / CONFIG_FILE).write_text(config.to_yaml())
    with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
        checkpoints.save(1, learner_for(config).init(jax.random.key(0)), jax.random.key(1))
    return config, run


def test_runs_show_prints_each_checkpoints_metadata(tmp_path, capsys, caplog):
    config, run = make_run(tmp_path)
    assert main(["runs", "show", str(run)]) == 0
    out = capsys.readouterr().out
    assert "checkpoint 1: no metadata" in out and config_hash(config)[:12] in out
    state = learner_for(config).init(jax.random.key(0))
    with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
        checkpoints.save(2, state, jax.random.key(1), checkpoint_metadata(config, 2, 2))
        checkpoints.save(3, state, jax.random.key(1),
                         checkpoint_metadata(tiny_config(seed=9), 3, 2))
    assert main(["runs", "show", str(run)]) == 0
    out = capsys.readouterr().out
    assert "checkpoint 1: no metadata" in out
    assert (f"checkpoint 2: update 2, policy version 2, config sha256 "
            f"{config_hash(config)[:12]} (= config.yaml); tabx-ued {tabx.__version__}, "
            f"jax {jax.__version__}") in out
    assert "checkpoint 3: update 3, policy version 2" in out and "differs from config" in out
    # orbax's "could not be restored" warnings about reading metadata alone stay quiet
    assert not [r for r in caplog.records if "could not be restored" in r.getMessage()]
    assert main(["runs", "show", str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err


@pytest.mark.slow
def test_a_checkpoint_without_metadata_resumes(tmp_path, capsys):
    config, run = make_run(tmp_path)
    assert main(["train", "--resume", str(run), "--max-updates", "1", "--quiet"]) == 0
    with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
        assert checkpoints.all() == [1, 2]
        assert checkpoints.metadata(1) == {}
        assert checkpoints.metadata(2) == checkpoint_metadata(config, 2, policy_version=2)
