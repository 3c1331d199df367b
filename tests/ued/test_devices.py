"""`tabx.devices`: how a batch of envs is split over local devices, and that a rollout split over
two devices computes what it computes on one: the same states bit for bit, observations to the
last bit of float32 (the tests run with two CPU devices, tests/conftest.py)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tabx.controllers import Controller, with_tiers
from tabx.devices import env_devices, env_sharding
from tabx.env import TabxEnv
from tabx.params import EnvConfig
from tabx.random_levels import random_levels
from tabx_bench.simulator import make_rollout, run_one
from tabx_bench.suite import host_batch
from tabx_ued.cli import main

SMALL = EnvConfig(max_allies=3, max_enemies=3, max_zones=2)


def test_two_cpu_devices_in_the_tests():
    assert len(jax.local_devices()) == 2


@given(st.integers(1, 10_000))
@settings(max_examples=50, deadline=None)
def test_default_split_is_the_most_devices_that_divide_the_envs(num_envs):
    devices = env_devices(num_envs)
    assert num_envs % len(devices) == 0
    assert len(devices) == (2 if num_envs % 2 == 0 else 1)
    assert env_devices(num_envs, 1) == (jax.local_devices()[0],)


def test_asked_for_devices_must_exist_and_divide_the_envs():
    assert len(env_devices(8, 2)) == 2
    with pytest.raises(ValueError, match="7 envs do not split evenly over 2 devices"):
        env_devices(7, 2)
    with pytest.raises(ValueError, match="3 devices asked for, 2 available"):
        env_devices(6, 3)
    with pytest.raises(ValueError, match="devices must be 0"):
        env_devices(6, -1)


@pytest.mark.parametrize("enemy", ["random", "heuristic:medium"])
def test_a_rollout_split_over_two_devices_equals_one_device(enemy):
    controllers = (Controller("random"), Controller.parse(enemy))
    level = random_levels(1, seed=3, config=SMALL, min_units=2, max_units=3)[0]
    host = host_batch(with_tiers(level, controllers), 8)
    rollout = make_rollout(TabxEnv(SMALL), 20, controllers=controllers)
    key = jax.random.key(4)
    split = rollout(jax.device_put(host, env_sharding(env_devices(8, 2))), key)
    whole = rollout(jax.device_put(host, env_sharding(env_devices(8, 1))), key)
    assert len(split[2].sharding.device_set) == 2 and len(whole[2].sharding.device_set) == 1
    _, states_split, obs_split, total_split = split
    _, states_whole, obs_whole, total_whole = whole
    for a, b in zip(jax.tree.leaves(states_split), jax.tree.leaves(states_whole), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(total_split), np.asarray(total_whole))
    # XLA compiles the split program's observation fusions apart; a value may round differently.
    np.testing.assert_allclose(np.asarray(obs_split), np.asarray(obs_whole), rtol=1e-6, atol=1e-7)
    assert np.abs(np.asarray(obs_split)).sum() > 0  # observations were computed


def test_bench_records_the_devices_and_refuses_a_bad_split(capsys):
    assert run_one(2, 1, 4, steps=2, repeats=1).devices == 2
    assert run_one(2, 1, 4, steps=2, repeats=1, devices=1).devices == 1
    assert main(["bench", "env", "--team-sizes", "2", "--num-envs", "3", "--devices", "2"]) == 2
    err = capsys.readouterr().err
    assert "--devices: 3 envs do not split evenly over 2 devices" in err
    assert "Traceback" not in err
