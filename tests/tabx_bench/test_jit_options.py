"""`tabx.jit_options`: which compiler options simulator and learner programs get, that a
program compiled with them computes what plain `jax.jit` computes, and what the benchmark rollout
carries as its observation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tabx import jit_options
from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.params import EnvConfig
from tabx.random_levels import random_levels
from tabx_bench.simulator import make_rollout
from tabx_bench.suite import host_batch

SMALL = EnvConfig(max_allies=3, max_enemies=3, max_zones=2)


@pytest.fixture(scope="module")
def levels():
    return jax.device_put(host_batch(random_levels(1, seed=5, config=SMALL, min_units=2,
                                                   max_units=3)[0], 4))


def test_cpu_simulator_programs_use_the_older_fusion_emitters_and_fast_min_max():
    assert jax.default_backend() == "cpu"
    assert jit_options.simulator_compiler_options() == {"xla_cpu_use_fusion_emitters": False,
                                                        "xla_cpu_enable_fast_min_max": True}


def test_default_compiler_on_request_or_on_unmeasured_jaxlib(monkeypatch):
    monkeypatch.setenv("TABX_DEFAULT_COMPILER", "1")
    assert jit_options.simulator_compiler_options() is None
    monkeypatch.delenv("TABX_DEFAULT_COMPILER")
    monkeypatch.setattr("tabx.xla_flags._KNOWN_JAXLIB_PREFIXES", ("99.",))
    assert jit_options.simulator_compiler_options() is None


def test_bfloat16_learner_programs_get_ynnpack_products_on_cpu(monkeypatch):
    assert jit_options.learner_compiler_options("bfloat16") == {
        "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}
    assert jit_options.learner_compiler_options("float32") is None
    x = jax.random.normal(jax.random.key(0), (48, 128)).astype(jnp.bfloat16)
    w = jax.random.normal(jax.random.key(1), (128, 384)).astype(jnp.bfloat16)

    def product(x, w):
        return jnp.dot(x, w, preferred_element_type=jnp.float32)

    tuned, plain = jit_options.learner_jit(product, "bfloat16"), jax.jit(product)
    assert "__ynn_fusion" in tuned.lower(x, w).compile().as_text()
    assert "__ynn_fusion" not in plain.lower(x, w).compile().as_text()  # off elsewhere
    # bfloat16 x bfloat16 products are exact in float32; the two kernels add the 128 of each
    # entry in another order: sqrt(128) x 2**-24 x sum|terms| (about 80 here) is 5e-5.
    np.testing.assert_allclose(tuned(x, w), plain(x, w), rtol=1e-5, atol=1e-4)
    monkeypatch.setenv("TABX_DEFAULT_COMPILER", "1")
    assert jit_options.learner_compiler_options("bfloat16") is None


@pytest.mark.parametrize("enemy", ["random", "heuristic:medium"])
def test_simulator_jit_computes_what_plain_jit_computes(levels, monkeypatch, enemy):
    """Same rollout (observations, states, sums) bit for bit with and without the options,
    random and scripted enemies."""
    env = TabxEnv(SMALL)
    controllers = (Controller("random"), Controller.parse(enemy))
    levels = with_tiers(levels, controllers)
    tuned = make_rollout(env, 24, controllers=controllers)(levels, jax.random.key(1))
    monkeypatch.setattr("tabx_bench.simulator.simulator_jit", jax.jit)
    plain = make_rollout(env, 24, controllers=controllers)(levels, jax.random.key(1))
    tuned, plain = jax.tree.leaves(tuned)[1:], jax.tree.leaves(plain)[1:]  # leaf 0: the key
    assert len(tuned) == len(plain)
    for a, b in zip(tuned, plain, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_rollout_carries_the_observation_of_the_last_state_acted_on(levels):
    """Step k starts by observing the state it acts on: after k steps the carried observation
    is that of the state after k - 1 steps (same keys: the key is carried and split)."""
    env = TabxEnv(SMALL)
    key = jax.random.key(2)
    _, states_before, _, _ = make_rollout(env, 6)(levels, key)
    _, _, obs, _ = make_rollout(env, 7)(levels, key)
    expected = jax.jit(jax.vmap(env.observe))(states_before, levels)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(expected))
    assert np.abs(np.asarray(obs)).sum() > 0
    _, _, no_obs, _ = make_rollout(env, 3, with_obs=False)(levels, key)
    assert no_obs.shape == (4, 0)
