"""The learner and curriculum registry (`ued.registry`): entries say what a method needs
without building it. `tabx runs check` reads the registry and builds no learner, train state
or curriculum; a curriculum registered from outside the package (tests/ued/example_curriculum.py,
the worked example of CONTRIBUTING.md) is found by name by config validation and training.
"""

from __future__ import annotations

import io
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from test_learners_helpers import tiny_config

from tabx_ued.cli import main
from ued.config import ConfigError
from ued.registry import (
    CURRICULA,
    LEARNERS,
    curriculum_entry,
    learner_class,
    register_curriculum,
)
from ued.run_folder import create_run_dir, open_checkpoints
from workers.driver import Driver
from workers.train import train


def test_every_entry_names_its_class():
    for name in LEARNERS:
        assert learner_class(name).name == name
    for name, entry in CURRICULA.items():
        assert entry.build(tiny_config(**{"ued.method": name}).ued).name == name


def forbid_building(monkeypatch) -> None:
    """Every way to build a learner, a train state or a curriculum raises."""
    import ued.experiment
    import ued.learners
    from ued.curricula import Curriculum
    from ued.learners.ppo import PPOLearner

    def refuse(*args, **kwargs):
        raise AssertionError("tabx runs check built a learner, train state or curriculum")

    monkeypatch.setattr(PPOLearner, "__init__", refuse)
    monkeypatch.setattr(PPOLearner, "init", refuse)
    monkeypatch.setattr(Curriculum, "__init__", refuse)
    monkeypatch.setattr(ued.learners, "make_learner", refuse)
    monkeypatch.setattr(ued.experiment, "learner_for", refuse)


@pytest.mark.parametrize("method", ["none", "robust_plr"])
def test_runs_check_builds_no_learner(method, tmp_path, monkeypatch, capsys):
    config = tiny_config(**{"ued.method": method})
    run_dir = create_run_dir(config, tmp_path / "run")
    state = {"params": {"w": jnp.ones((3, 2))}, "step": jnp.asarray(2)}
    with open_checkpoints(run_dir, config) as checkpoints:
        checkpoints.save(2, state, jax.random.key(1))
    forbid_building(monkeypatch)
    code = main(["runs", "check", str(run_dir)])
    out = capsys.readouterr().out
    if method == "none":
        assert code == 0 and "step 2: intact" in out, out
    else:  # the registry says Robust PLR keeps a buffer: its snapshot is missing
        assert code == 1 and "state-2.json: missing" in out, out
        assert curriculum_entry(method).load().uses_buffer


@pytest.fixture
def toy():
    import example_curriculum

    register_curriculum(example_curriculum.ENTRY)
    yield example_curriculum
    CURRICULA.pop(example_curriculum.ENTRY.name, None)


class CurriculumOnly(Driver):
    """A driver that builds a UED run's step logic and stops: what `train` hands it."""

    def run(self, config, run_dir: Path, **kwargs) -> Path:
        from workers.ued_step import UEDRun

        self.run_logic = UEDRun(config, service=None, explorer=None)
        return run_dir


def test_a_registered_curriculum_is_found_by_name(toy, tmp_path):
    config = tiny_config(**{"ued.method": "alternating_replay"})
    assert config.ued.method == "alternating_replay"
    driver = CurriculumOnly()
    train(config, run_dir=tmp_path / "run", driver=driver, stream=io.StringIO())
    curriculum = driver.run_logic.curriculum
    assert isinstance(curriculum, toy.AlternatingReplay)
    assert curriculum_entry("alternating_replay").load().uses_buffer


def test_an_unregistered_method_is_a_config_error():
    with pytest.raises(ConfigError, match="ued.method: must be one of none, dr, plr, "
                                          "robust_plr, accel, sfl or an import path "
                                          "module:Class, got 'alternating_rep'"):
        tiny_config(**{"ued.method": "alternating_rep"})
