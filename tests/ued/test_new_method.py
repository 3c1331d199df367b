"""A UED method from outside the package, used by import path (examples/uniform_replay.py, a
Robust PLR that replays uniformly): it validates like a built-in method, draws its replays by
its own rule, and runs on every driver with what must agree agreeing (`workers.ray.method_check`:
the deterministic Ray schedule equal to the local driver bit for bit, the continuous schedule
committing every batch once). A method's own settings section (examples/novelty_pvl.py's
`novelty:`) validates like a built-in section, survives the run folder's config.yaml and reaches
the curriculum in every process that builds it. And no driver, schedule or command looks at a
curriculum's class or name: they go by its hooks.
"""

from __future__ import annotations

import ast
import functools
import math
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_ued_train import ued_config

from ued.config import ConfigError, config_from_dict, load_config
from ued.curricula.robust_plr import RobustPLR
from ued.registry import build_curriculum, curriculum_class, curriculum_for
from ued.run_folder import CONFIG_FILE, read_run_config

ROOT = Path(__file__).resolve().parents[2]
UNIFORM = "examples.uniform_replay:UniformReplay"  # importable from the repository root
NOVELTY = "examples.novelty_pvl:NoveltyPVL"


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


@pytest.mark.parametrize("overrides, message", [
    ({"novelty.bonus_wieght": 1.0}, "unknown key 'novelty.bonus_wieght'; did you mean "
                                    "'novelty.bonus_weight'?"),
    ({"novelty.bonus_weight": "big"}, "novelty.bonus_weight: expected a number, got 'big'"),
    ({"novelty.bonus_weight": -1}, "novelty.bonus_weight: must be >= 0, got -1.0"),
])
def test_a_methods_own_settings_validate_as_built_in_ones_do(overrides, message):
    with pytest.raises(ConfigError) as err:
        ued_config(NOVELTY, **overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_its_section_in_a_file_validates_and_belongs_to_it_alone():
    data = ued_config(NOVELTY).to_dict()
    assert data["novelty"] == {"bonus_weight": 0.5}  # the defaults, written out
    with pytest.raises(ConfigError, match=r"^config: unknown key 'novelty\.bonus_wieght'; did "
                                          r"you mean 'novelty\.bonus_weight'\?"):
        config_from_dict({**data, "novelty": {"bonus_wieght": 1.0}})
    for method in ("robust_plr", UNIFORM):  # a method that reads no such section
        with pytest.raises(ConfigError, match=r"^config: unknown key 'novelty' \("):
            config_from_dict({**data, "ued": {**data["ued"], "method": method}})
        with pytest.raises(ConfigError, match=r"unknown key 'novelty\.bonus_weight'$"):
            ued_config(method, **{"novelty.bonus_weight": 1.0})
    assert "novelty" not in ued_config("robust_plr").to_dict()


def test_its_settings_round_trip_through_the_run_folders_config(tmp_path):
    """config.yaml, as `tabx train` writes it and a resume, `tabx runs` and a sweep trial read
    it, holds the section and reads back to the same config."""
    config = ued_config(NOVELTY, **{"novelty.bonus_weight": 2.0})
    assert config.curriculum_settings().bonus_weight == 2.0
    (tmp_path / CONFIG_FILE).write_text(config.to_yaml())
    assert "\nnovelty:\n  bonus_weight: 2.0\n" in config.to_yaml()
    assert load_config(tmp_path / CONFIG_FILE) == config
    assert read_run_config(tmp_path) == config
    assert read_run_config(tmp_path).to_yaml() == config.to_yaml()
    again = load_config(tmp_path / CONFIG_FILE, ["novelty.bonus_weight=3"])
    assert again.curriculum_settings().bonus_weight == 3.0
    with pytest.raises(ConfigError, match=r"unknown key 'novelty'"):  # the section stays
        load_config(tmp_path / CONFIG_FILE, ["ued.method=robust_plr"])
    # The settings are plain values: a Ray actor or a trial unpickles the config before it
    # imports the method's module.
    assert pickle.loads(pickle.dumps(config)).method_settings == (("bonus_weight", 2.0),)


def test_its_settings_reach_the_curriculum_where_levels_are_scored():
    """The level service (an actor on Ray: `level_service_for`) and the run's curriculum get
    the config's `novelty.bonus_weight`, and new levels' scores scale with it."""
    import jax

    from workers.ued_step import UEDRun, level_service_for

    bonus = {}
    for weight in (0.0, 0.5, 2.0):
        config = ued_config(NOVELTY, **{"novelty.bonus_weight": weight})
        run, learner = UEDRun.local(config)
        service = level_service_for(config, learner)
        assert run.curriculum.settings.bonus_weight == weight
        assert service.curriculum.settings.bonus_weight == weight
        for seed in (0, 1):
            service.insert(service.fresh(jax.random.key(seed), 4), np.zeros(4), np.zeros(4), 0)
        bonus[weight] = np.asarray(service.buffer.scores[4:])
    np.testing.assert_array_equal(bonus[0.0], 0.0)
    assert (bonus[0.5] > 0).all()
    np.testing.assert_allclose(bonus[2.0], 4 * bonus[0.5])


@dataclass(frozen=True)
class Weight:
    weight: float = 1.0


class ClaimsUED(RobustPLR):
    """A method whose settings section would be the `ued:` section."""

    name = "claims_ued"
    settings_section = "ued"
    settings_type = Weight


class ClaimsMyIPPO(ClaimsUED):
    """A method whose settings section is the one examples/ippo_variant.py's learner reads."""

    settings_section = "my_ippo"


class NoDataclass(ClaimsUED):
    settings_section = "no_dataclass"
    settings_type = dict


def test_a_section_that_is_not_a_new_key_of_its_own_is_one_error():
    here = Path(__file__).stem
    cases = {
        f"{here}:ClaimsUED": (),
        f"{here}:NoDataclass": (),
        f"{here}:ClaimsMyIPPO": ("algorithm=examples.ippo_variant:MyIPPO",),
    }
    messages = {
        f"{here}:ClaimsUED": r"ued\.method: .*:ClaimsUED names its settings section 'ued' .*must "
                             r"be a new top-level key, its type a dataclass",
        f"{here}:NoDataclass": r"ued\.method: .*:NoDataclass names its settings section .*its "
                               r"type a dataclass",
        f"{here}:ClaimsMyIPPO": r"ued\.method: .*:ClaimsMyIPPO reads the section 'my_ippo', "
                                r"which algorithm examples\.ippo_variant:MyIPPO reads too",
    }
    for method, more in cases.items():
        data = {**ued_config("robust_plr").to_dict(), **dict(o.split("=") for o in more)}
        data["ued"] = {**data["ued"], "method": method}
        with pytest.raises(ConfigError, match=messages[method]) as err:
            config_from_dict(data)
        assert "\n" not in str(err.value)


def test_the_built_in_methods_take_no_settings():
    config = ued_config("robust_plr")
    assert config.curriculum_settings() is None and "method_settings" not in config.to_dict()
    for method in ("dr", "plr", "robust_plr", "accel", "sfl"):
        assert curriculum_class(method).settings_section is None
        with pytest.raises(ValueError, match="takes no settings"):
            build_curriculum(curriculum_class(method), config.ued, Weight())


def test_a_sweep_varies_a_methods_own_settings_and_checks_them_per_trial(tmp_path):
    """A sweep's grid may name a by-path method's own settings: each trial's config carries its
    value, and a misspelt field is one error naming the trial and the field."""
    from workers.sweep.spec import read_sweep_spec

    (tmp_path / "base.yaml").write_text(ued_config(NOVELTY).to_yaml())
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text("base: base.yaml\ngrid:\n  novelty.bonus_weight: [0.0, 2.0]\n"
                     "  seed: [0, 1]\n")
    spec = read_sweep_spec(sweep)
    weights = sorted(t.config.curriculum_settings().bonus_weight for t in spec.trials)
    assert weights == [0.0, 0.0, 2.0, 2.0]
    sweep.write_text("base: base.yaml\ngrid:\n  novelty.bonus_wieght: [0.0, 2.0]\n")
    with pytest.raises(ConfigError, match=r"unknown key 'novelty\.bonus_wieght'; did you mean"):
        read_sweep_spec(sweep)
    sweep.write_text("base: base.yaml\nset: {ued.method: robust_plr}\n"
                     "grid:\n  novelty.bonus_weight: [1.0]\n")
    with pytest.raises(ConfigError, match=r"unknown key 'novelty"):  # not robust_plr's
        read_sweep_spec(sweep)


@functools.cache
def novelty_data() -> dict:
    return ued_config(NOVELTY).to_dict()


@given(value=st.one_of(st.none(), st.booleans(), st.integers(), st.floats(),
                       st.text(max_size=12), st.lists(st.floats(), max_size=2)))
@settings(max_examples=60, deadline=None)
def test_any_bonus_weight_is_taken_as_a_number_or_is_one_error_naming_it(value):
    """A value that is a finite number >= 0 (or a string of one) is taken as that number; any
    other is refused by one line naming `novelty.bonus_weight`."""
    try:
        number = float(value) if not isinstance(value, bool | list | type(None)) else None
    except (ValueError, OverflowError):
        number = None
    data = {**novelty_data(), "novelty": {"bonus_weight": value}}
    if number is not None and math.isfinite(number) and number >= 0:
        assert config_from_dict(data).curriculum_settings().bonus_weight == number
        return
    with pytest.raises(ConfigError) as err:
        config_from_dict(data)
    assert str(err.value).startswith("config: novelty.bonus_weight: ")
    assert "\n" not in str(err.value)


@pytest.mark.usefixtures("local_ray")
def test_the_example_method_runs_on_every_driver_and_they_agree(tmp_path):
    from workers.ray.method_check import check_method

    check = check_method(ued_config(UNIFORM, **{"ued.replay_prob": 0.6}), tmp_path, steps=4)
    assert check.continuous_record["branches"]["replay"] >= 1


def test_the_ray_level_service_rebuilds_the_method_with_its_own_settings():
    """The Ray level service (built here, in this process, as Ray builds the actor: from a
    pickled copy of the config) scores with the config's `novelty.bonus_weight`."""
    from workers.ray.actors import LevelServiceActor

    config = ued_config(NOVELTY, **{"novelty.bonus_weight": 2.0})
    actor = LevelServiceActor(pickle.loads(pickle.dumps(config)))
    assert actor.curriculum.settings.bonus_weight == 2.0


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
