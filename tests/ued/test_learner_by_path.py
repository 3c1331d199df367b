"""A learner given by import path (`algorithm: module:Class`), registered nowhere: the worked
example examples/ippo_variant.py trains from its folder on the command line, its own settings
section validates as a built-in section does, a bad path is one config error naming the key,
and the run's other processes (Ray actors, sweep trials) find the module (`import_env`).
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_learners_helpers import tiny_config

from tabx_ued.cli import main
from ued import registry
from ued.checkpoint import Checkpoints
from ued.config import ConfigError, config_from_dict
from ued.experiment import learner_for
from ued.learners.ppo import value_loss
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE, read_run_config
from workers.train import train

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
VARIANT = "ippo_variant:MyIPPO"


@pytest.fixture
def in_examples(monkeypatch):
    """The current folder is examples/, as for a researcher running their module from its
    folder; sys.path and the registry's folders are restored afterwards."""
    monkeypatch.chdir(EXAMPLES)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(registry, "_ROOTS", {})
    monkeypatch.delenv(registry.IMPORT_PATH_ENV, raising=False)


def test_the_example_trains_from_its_folder_by_path(in_examples, tmp_path, capsys):
    yaml_path = tmp_path / "tiny.yaml"
    yaml_path.write_text(tiny_config().to_yaml())
    runs = tmp_path / "runs"
    code = main(["train", str(yaml_path), f"algorithm={VARIANT}", "my_ippo.value_clip=0.5",
                 "learner.total_timesteps=128", f"run.dir={runs}", "--quiet"])
    assert code == 0, capsys.readouterr().err
    (run_dir,) = runs.iterdir()
    assert run_dir.name.startswith("MyIPPO_")  # the class's name, not the path, in the folder
    text = (run_dir / CONFIG_FILE).read_text()
    assert f"algorithm: {VARIANT}" in text and "my_ippo:\n  value_clip: 0.5" in text
    config = read_run_config(run_dir)  # as a resume reads it
    assert config.learner_settings().value_clip == 0.5
    assert sorted(p.name for p in (run_dir / CHECKPOINT_DIR).iterdir()
                  if p.name.isdigit()) == ["1", "2"]
    learner = learner_for(config)
    assert type(learner).__name__ == "MyIPPO" and learner.settings.value_clip == 0.5


def test_the_example_clips_the_value_at_its_own_range(in_examples):
    """The variant's value loss is IPPO's with `value_clip` in place of `clip_eps`."""
    config = tiny_config(algorithm=VARIANT, **{"my_ippo.value_clip": 0.5})
    learner = learner_for(config)
    rng = np.random.default_rng(0)
    values, old, targets = (jnp.asarray(rng.normal(size=(4, 2, 2)), jnp.float32)
                            for _ in range(3))
    valid = jnp.ones((4, 2, 2), bool)
    batch, count = {"value": old, "targets": targets}, jnp.asarray(16)
    loss, _ = learner.critic_loss(values, batch, valid, count, None)
    assert float(loss) == float(value_loss(values, old, targets, valid, 0.5, True, count))
    assert float(loss) != float(value_loss(values, old, targets, valid,
                                           config.learner.clip_eps, True, count))


@pytest.mark.parametrize("overrides, message", [
    ({"my_ippo.value_clp": 0.1}, "unknown key 'my_ippo.value_clp'; did you mean "
                                 "'my_ippo.value_clip'?"),
    ({"my_ippo.value_clip": -1}, "my_ippo.value_clip: must be > 0, got -1.0"),
    ({"my_ippo.value_clip": "wide"}, "my_ippo.value_clip: expected a number, got 'wide'"),
    ({"qlearning.buffer_size": 100}, "qlearning.buffer_size: a setting of the Q-learners "
                                     f"(iql, vdn, qmix); {VARIANT} does not use it"),
    ({"learner.rnd_lr": 0.1}, f"RND settings go with algorithm mappo_rnd, not {VARIANT}"),
])
def test_its_settings_validate_as_built_in_ones_do(in_examples, overrides, message):
    with pytest.raises(ConfigError) as err:
        tiny_config(algorithm=VARIANT, **overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_its_section_in_a_file_validates_and_belongs_to_it_alone(in_examples):
    data = tiny_config(algorithm=VARIANT).to_dict()
    assert data["my_ippo"] == {"value_clip": 0.2}  # the defaults, written out
    with pytest.raises(ConfigError, match=r"unknown key 'my_ippo\.value_clp'; did you mean "
                                          r"'my_ippo\.value_clip'"):
        config_from_dict({**data, "my_ippo": {"value_clp": 0.1}})
    with pytest.raises(ConfigError, match=r"unknown key 'my_ippo'"):  # not ippo's
        config_from_dict({**data, "algorithm": "ippo"})


def test_a_bad_path_is_one_config_error_naming_the_key(in_examples, tmp_path, monkeypatch):
    (tmp_path / "broken.py").write_text("def oops(:\n")
    (tmp_path / "needs.py").write_text("import no_such_dependency\n")
    monkeypatch.chdir(tmp_path)
    cases = {
        "no_such_module:Learner": "algorithm: no module 'no_such_module'",
        "ippo_variant:Nope": "algorithm: ippo_variant (",
        "ippo_variant:ValueClip": "algorithm: ippo_variant:ValueClip is not a learner class",
        "ippo_variant:1Bad": "algorithm: expected a class as module:Class",
        "ippo variant": "algorithm: must be one of mappo, ippo, mappo_rnd, iql, vdn, qmix or a "
                        "learner class given as module:Class, got 'ippo variant'",
        "broken:Learner": "algorithm: importing broken failed: SyntaxError",
        "needs:Learner": "algorithm: importing needs failed: No module named "
                         "'no_such_dependency'",
    }
    monkeypatch.syspath_prepend(str(EXAMPLES))
    for algorithm, message in cases.items():
        with pytest.raises(ConfigError) as err:
            tiny_config(algorithm=algorithm)
        assert message in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_another_process_imports_the_class_from_the_folders_it_is_handed(in_examples):
    """An actor or trial process starts elsewhere, its sys.path without examples/: the
    variable `import_env` gives it (workers.ray.start.actor_env, workers.sweep.tune.worker_env)
    is where it finds the module."""
    from workers.ray.start import actor_env

    assert registry.import_env() == {}
    tiny_config(algorithm=VARIANT)  # the driver validates the config: the import
    env = registry.import_env()
    assert env == {registry.IMPORT_PATH_ENV: str(EXAMPLES)}
    assert actor_env(False)[registry.IMPORT_PATH_ENV] == str(EXAMPLES)
    code = ("from ued.registry import learner_class; "
            f"print(learner_class({VARIANT!r}).name)")
    base = {k: v for k, v in os.environ.items() if k != registry.IMPORT_PATH_ENV}
    base["PYTHONPATH"] = str(ROOT)
    found = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                           text=True, env={**base, **env}, timeout=300)
    assert found.returncode == 0 and found.stdout.strip() == "my_ippo", found.stderr[-2000:]
    lost = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, env=base, timeout=300)
    assert lost.returncode == 1 and "no module 'ippo_variant'" in lost.stderr


def test_ray_actors_build_the_learner_the_local_driver_builds(local_ray, in_examples, tmp_path):
    """A deterministic Ray run of the example (DR) equals the local driver's, parameter for
    parameter: its actors, whose processes started before the driver entered examples/, imported
    the class from the folder the driver handed them and read the same `my_ippo.value_clip`."""
    from test_ued_train import ued_config

    overrides = {"algorithm": VARIANT, "my_ippo.value_clip": 0.5}
    config = ued_config("dr", **overrides)
    local = train(config, run_dir=tmp_path / "local", stream=io.StringIO(), max_updates=2)
    remote = train(ued_config("dr", **overrides, **{"ray.enabled": "true",
                                                    "ray.deterministic": "true",
                                                    "ray.explorers": 0}),
                   run_dir=tmp_path / "ray", stream=io.StringIO(), max_updates=2)
    template = learner_for(config).init(jax.random.key(0))
    states = []
    for run in (local, remote):
        with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
            states.append(checkpoints.restore(template))
    (a, _, step_a), (b, _, step_b) = states
    assert step_a == step_b == 2
    for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params), strict=True):
        assert np.array_equal(x, y)
