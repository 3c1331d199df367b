"""A UED method from outside the package, used by import path (examples/uniform_replay.py, a
Robust PLR that replays uniformly): it validates like a built-in method, draws its replays by
its own rule, and runs on every driver with what must agree agreeing (`workers.ray.method_check`:
the deterministic Ray schedule equal to the local driver bit for bit, the continuous schedule
committing every batch once). And no driver, schedule or command looks at a curriculum's class
or name: they go by its hooks.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path

import numpy as np
import pytest
from test_ued_train import ued_config

from ued.config import ConfigError
from ued.registry import curriculum_for

ROOT = Path(__file__).resolve().parents[2]
UNIFORM = "examples.uniform_replay:UniformReplay"  # importable from the repository root


@pytest.fixture(autouse=True)
def from_the_repository_root(monkeypatch):
    monkeypatch.chdir(ROOT)  # where `examples` is importable, in this process and in Ray's


def test_a_method_by_import_path_validates_and_draws_replays_by_its_own_rule():
    config = ued_config(UNIFORM, **{"ued.prioritization": "rank"})
    curriculum = curriculum_for(config.ued)
    assert curriculum.name == "uniform_replay" and curriculum.uses_buffer
    settings = curriculum.buffer_config(config.ued)
    assert settings.prioritization == "uniform" and settings.staleness_coeff == 0.0
    # Its level service's buffer replays every stored level alike, whatever the scores.
    from workers.ued_step import UEDRun

    run, _ = UEDRun.local(config)
    service = run.service
    import jax

    levels = service.fresh(jax.random.key(0), 4)
    service.insert(levels, np.array([0.1, 5.0, 0.2, 9.0]), np.zeros(4), 0)
    np.testing.assert_allclose(service.buffer.weights(), np.full(4, 0.25))
    with pytest.raises(ConfigError, match=r"ued.method: no module 'no_such_module'"):
        ued_config("no_such_module:Method")
    with pytest.raises(ConfigError, match=r"ued.method: examples.uniform_replay \(.*"
                                          r"uniform_replay.py\) has no 'Nope'"):
        ued_config("examples.uniform_replay:Nope")
    with pytest.raises(ConfigError, match=r"ued.method: 'numpy:ndarray' is not a "
                                          r"ued.curricula.Curriculum subclass"):
        ued_config("numpy:ndarray")


def test_a_method_that_changes_scoring_ranks_new_levels_by_pvl_and_novelty():
    import jax

    from workers.ued_step import UEDRun

    config = ued_config("examples.novelty_pvl:NoveltyPVL", **{"ued.score": "max_mc"})
    run, _ = UEDRun.local(config)
    assert run.score == "pvl"  # its own regret estimate, whatever ued.score says
    service = run.service
    first = service.fresh(jax.random.key(0), 4)
    service.insert(first, np.zeros(4), np.zeros(4), 0)
    np.testing.assert_array_equal(service.buffer.scores, np.zeros(4))  # nothing to be new to
    second = service.fresh(jax.random.key(1), 4)
    service.insert(second, np.zeros(4), np.zeros(4), 0)
    assert len(service.buffer) == 8
    assert (service.buffer.scores[4:] > 0).all()  # the novelty bonus of unlike levels


@pytest.mark.usefixtures("local_ray")
def test_the_example_method_runs_on_every_driver_and_they_agree(tmp_path):
    from workers.ray.method_check import check_method

    check = check_method(ued_config(UNIFORM, **{"ued.replay_prob": 0.6}), tmp_path, steps=4)
    assert check.continuous_record["branches"]["replay"] >= 1


CURRICULUM_CLASSES = {"Curriculum", "DomainRandomization", "PLR", "RobustPLR", "ACCEL", "SFL",
                      "UniformReplay"}
METHOD_NAMES = {"dr", "plr", "robust_plr", "accel", "sfl", "uniform_replay"}


def test_no_driver_schedule_or_command_tests_a_curriculums_class_or_name():
    found = []
    for package in ("workers", "tabx_ued", "tabx_bench"):
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                        and node.func.id in ("isinstance", "issubclass", "type")):
                    names = {n.id for arg in node.args[1:] for n in ast.walk(arg)
                             if isinstance(n, ast.Name)}
                    if names & CURRICULUM_CLASSES:
                        found.append(f"{where}: {node.func.id} of a curriculum class")
                if isinstance(node, ast.Compare):
                    constants = {n.value for n in ast.walk(node)
                                 if isinstance(n, ast.Constant) and isinstance(n.value, str)}
                    if constants & METHOD_NAMES:
                        found.append(f"{where}: compares with a method's name")
                if isinstance(node, ast.ImportFrom) and node.module and (
                        node.module.startswith("ued.curricula")):
                    concrete = {a.name for a in node.names} & (CURRICULUM_CLASSES - {"Curriculum"})
                    if concrete:
                        found.append(f"{where}: imports {sorted(concrete)}")
    assert not found, "\n".join(found)


def test_the_example_is_one_short_file():
    text = (ROOT / "examples" / "uniform_replay.py").read_text()
    assert len(text.splitlines()) < 60
    assert os.path.isfile(ROOT / "examples" / "new_method_vs_baselines.yaml")
