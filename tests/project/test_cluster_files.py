"""The Ray cluster launcher files (`cluster.yaml`, `cluster-local.yaml`) against Ray's own
launcher schema, offline: a mistyped key or a wrong type fails here, not at `ray up`.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
LAUNCHER_FILES = ["cluster.yaml", "cluster-local.yaml"]


@pytest.fixture(scope="module")
def schema():
    import ray.autoscaler

    path = Path(ray.autoscaler.__file__).parent / "ray-schema.json"
    return json.loads(path.read_text())


def load(name: str) -> dict:
    return yaml.safe_load((ROOT / name).read_text())


@pytest.mark.parametrize("name", LAUNCHER_FILES)
def test_launcher_file_is_valid_for_ray(schema, name):
    config = load(name)
    jsonschema.validate(config, schema)
    # What every node needs to join and run actors: the token, the project, token auth on.
    assert config["file_mounts"]["~/.ray/auth_token"] == "~/.ray/auth_token"
    assert config["file_mounts"]["~/tabx-ued"] == "."
    assert any("[ray]" in command for command in config["setup_commands"])
    starts = config["head_start_ray_commands"] + config["worker_start_ray_commands"]
    assert all("RAY_AUTH_MODE=token" in c for c in starts if "ray start" in c)


def test_local_launcher_file_carries_the_fixes_for_shared_machines():
    config = load("cluster-local.yaml")
    assert any("RAY_enable_autoscaler_v2=0" in c for c in config["head_start_ray_commands"])
    workers = config["worker_start_ray_commands"]
    assert not any(c.strip().startswith("ray stop") for c in workers)
    assert all("--node-ip-address" in c for c in workers if "ray start" in c)


def test_cloud_launcher_file_has_a_gpu_head_and_cpu_explorers():
    config = load("cluster.yaml")
    types = config["available_node_types"]
    assert types[config["head_node_type"]]["resources"].get("GPU", 0) >= 1
    assert any(t["resources"].get("GPU", 0) == 0 and t["resources"]["CPU"] >= 1
               for t in types.values())


@pytest.mark.parametrize("mistake", [
    lambda c: c.update(max_worker=2),  # a mistyped key
    lambda c: c.update(idle_timeout_minutes="ten"),  # a wrong type
    lambda c: c["auth"].update(ssh_usr="me"),  # a mistyped key in a section
    lambda c: c.pop("provider"),  # a required section missing
])
def test_a_mistake_in_a_launcher_file_is_caught(schema, mistake):
    config = copy.deepcopy(load("cluster-local.yaml"))
    mistake(config)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(config, schema)
