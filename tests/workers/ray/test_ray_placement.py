"""Placement and start-up of the Ray driver, without starting Ray: how a run's actors fit a Ray
started on this machine (decided, or refused, before the run folder exists), the bounded wait
for a cluster's resources with a one-line error naming the missing one, Explorers kept off a
GPU learner's nodes, and `RAY_ADDRESS` read as Ray's own tools read it. A real Ray refusing a
GPU learner is in tests/workers/ray/test_ray_driver.py."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time

import pytest
from test_ued_train import ued_config

from ued.config import ConfigError, RaySection
from workers.ray import driver as ray_driver
from workers.ray.start import (
    explorer_selector,
    join_address,
    local_plan,
    requests,
    wait_for_resources,
)
from workers.ray.stats import RateWindow
from workers.train import train


def test_explorers_share_the_cores_of_a_small_machine():
    # README's `--ray ray.explorers=2` on 2 cores: the CPU learner has one, the Explorers
    # share the other, and the run says so.
    plan = local_plan(RaySection(enabled=True, explorers=2), cpus=2, gpus_here=0)
    assert (plan.cpus, plan.gpus, plan.explorer_cpus) == (2, 0.0, 0.5)
    assert "2 Explorers share 1 CPU (0.5 each)" in plan.note
    assert "ray.num_cpus=3" in plan.note
    roomy = local_plan(RaySection(enabled=True, explorers=2, num_cpus=4), cpus=2, gpus_here=0)
    assert (roomy.explorer_cpus, roomy.note) == (1.0, "")
    gpu = local_plan(RaySection(enabled=True, explorers=2), cpus=2, gpus_here=1)
    assert (gpu.gpus, gpu.explorer_cpus, gpu.note) == (1.0, 1.0, "")
    with pytest.raises(ConfigError, match="ray.explorers: 9 Explorers and a CPU learner do not"):
        local_plan(RaySection(enabled=True, explorers=9), cpus=2, gpus_here=0)


def test_refusals_come_before_the_run_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(ray_driver, "local_resources", lambda: (2, 0))
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    t0 = time.perf_counter()
    for overrides, match in (({"ray.learner_gpus": 1}, "ray.learner_gpus: the learner asks "
                                                      "for 1 GPU but this machine has 0"),
                             ({"ray.explorers": 9}, "ray.explorers: 9 Explorers")):
        with pytest.raises(ConfigError, match=match):
            train(ued_config("dr", **{"ray.enabled": "true", **overrides}),
                  run_dir=tmp_path / "never", stream=io.StringIO())
    assert not (tmp_path / "never").exists()
    assert time.perf_counter() - t0 < 10


class FakeRay:
    def __init__(self, resources, nodes=()):
        self.resources, self._nodes = resources, list(nodes)

    def cluster_resources(self):
        return self.resources

    def nodes(self):
        return self._nodes


def test_a_missing_resource_is_named_after_a_bounded_wait():
    needs = requests(RaySection(enabled=True, explorers=2), gpus=1.0, explorer_cpus=1.0)
    stream = io.StringIO()
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"ray.placement_timeout_s: after 0 s the cluster has "
                                          r"0 GPU of the 1 the run reserves \(learner 1\)"):
        wait_for_resources(FakeRay({"CPU": 8.0}), needs, timeout_s=0.3, stream=stream,
                           poll_s=0.1)
    assert time.perf_counter() - t0 < 2
    assert "waiting up to 0.3 s for 1 GPU (learner 1)" in stream.getvalue()
    wait_for_resources(FakeRay({"CPU": 2.0, "GPU": 1.0}), needs, 0.3, stream)  # fits


def node(node_id, cpus, gpus=0):
    return {"NodeID": node_id, "Alive": True, "Resources": {"CPU": cpus, "GPU": gpus}}


def test_explorers_keep_off_a_gpu_learners_nodes_unless_asked():
    out = io.StringIO()
    cluster = FakeRay({}, [node("head", 8, gpus=1), node("w1", 16), node("w2", 16)])
    assert explorer_selector(cluster, 1.0, False, out) == {"ray.io/node-id": "!in(head)"}
    assert explorer_selector(cluster, 1.0, True, out) is None  # asked to share
    assert explorer_selector(cluster, 0.0, False, out) is None  # a CPU learner
    lone = FakeRay({}, [node("head", 8, gpus=1)])
    assert explorer_selector(lone, 1.0, False, out) is None  # one GPU machine: share, say so
    assert "no CPU-only node" in out.getvalue()


def test_ray_address_is_joined_where_no_address_is_given(monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert join_address(RaySection(enabled=True)) == "10.0.0.1:6379"
    assert join_address(RaySection(enabled=True, address="auto")) == "auto"
    monkeypatch.delenv("RAY_ADDRESS")
    assert join_address(RaySection(enabled=True)) == ""


def test_the_driver_process_keeps_jax_off_accelerators(tmp_path):
    # `tabx train --ray` on a GPU head: the driver's JAX is CPU-only before it starts (here a
    # run refused up front: the setting is made first, whatever follows).
    config_file = tmp_path / "tiny.yaml"
    config_file.write_text(ued_config("dr").to_yaml())
    code = ("import sys, jax; from tabx_ued.cli import main; "
            f"rc = main(['train', {str(config_file)!r}, '--ray', 'ray.explorers=99', "
            f"'--run-dir', {str(tmp_path / 'never')!r}]); "
            "assert rc == 2, rc; assert jax.config.jax_platforms == 'cpu', "
            "jax.config.jax_platforms; print(jax.devices()[0].platform)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "JAX_PLATFORMS": ""})
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "cpu"
    assert not (tmp_path / "never").exists()


def test_rates_are_averaged_over_a_stated_window():
    now = [0.0]
    window = RateWindow(window_s=10.0, clock=lambda: now[0], start=(0,))
    now[0] = 1.0
    assert window.add(15_000) == (15_000.0,)  # one burst: all it has
    for t in range(2, 31):
        now[0] = float(t)
        (rate,) = window.add(15_000 + 500 * (t - 1))
    assert rate == pytest.approx(500.0) and window.span_s == pytest.approx(10.0, abs=1)


def test_runs_status_says_which_steps_its_rates_count():
    """`tabx runs status`: the trained and the explored env steps/s, each named (the
    continuous schedule trains at every step while its Explorers explore many times more); a
    record of an older driver (one rate, the loop's steps) is named for what it counts."""
    from workers.ray.live import status_text

    record = {"status": "finished", "mode": "continuous", "steps": [0, 40],
              "trained_steps_per_s": 451.2, "explored_steps_per_s": 12_034.0,
              "rate_window_s": 60.0, "buffer_size": 128}
    lines = status_text("RUN", record).splitlines()
    assert "env steps/s over the last 60 s: trained 451, explored 12,034; buffer: 128" in lines
    older = {"status": "finished", "steps": [0, 4], "env_steps_per_s": 451.2,
             "rate_window_s": 60.0, "buffer_size": 128}
    assert ("env steps/s of the loop's steps, trained or explored over the last 60 s: 451; "
            "buffer: 128") in status_text("RUN", older).splitlines()
