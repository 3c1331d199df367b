"""`tabx.observe_kernel`: the observation's assembly by the native CPU kernel gives the bits of
its XLA version, for any team size, zone width and batch shape, under vmap, split over two
devices (each device assembling its own envs, nothing gathered) and under differentiation;
without a compiler, or with TABX_NATIVE=0, the XLA version runs instead."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.sharding import NamedSharding, PartitionSpec

from tabx.native_lib import build_library, native_available
from tabx.observe_kernel import assemble_observation, assemble_xla

native = jax.jit(assemble_observation)
reference = jax.jit(assemble_xla)


def operands(seed: int, n: int, zone_width: int, batch: tuple[int, ...]) -> tuple:
    rng = np.random.default_rng(seed)
    floats = rng.normal(0.0, 3.0, (*batch, n, 14)).astype(np.float32)
    floats[rng.random(floats.shape) < 0.1] = -0.0  # signed zeros must survive the copy
    return (floats,
            rng.uniform(-60, 60, (*batch, n, 2)).astype(np.float32),
            (1.0 / rng.uniform(10, 100, (*batch, 2))).astype(np.float32),
            rng.integers(0, 2, (*batch, n)).astype(np.int32),
            rng.random((*batch, n, n)) < 0.6,
            rng.random((*batch, n, n)) < 0.4,
            rng.normal(0.0, 1.0, (*batch, n, zone_width)).astype(np.float32))


def same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def test_the_native_kernel_is_built_and_compiled_into_cpu_programs():
    assert native_available()
    text = native.lower(*operands(0, 3, 6, (4,))).compile().as_text()
    assert 'custom_call_target="tabx_assemble_observation"' in text


@given(st.integers(0, 2**31), st.integers(1, 9), st.sampled_from([0, 6, 36]),
       st.sampled_from([(), (1,), (5,), (2, 3)]))
@settings(max_examples=25, deadline=None)
def test_native_equals_xla_bit_for_bit(seed, n, zone_width, batch):
    args = operands(seed, n, zone_width, batch)
    out = native(*args)
    assert out.shape == (*batch, n, 14 + 16 * (n - 1) + zone_width)
    assert same_bits(out, reference(*args))


def test_layout_of_one_row():
    own, position, inv_half, team, seen, attackable, zones = operands(1, 3, 6, ())
    seen[0] = [False, True, False]  # viewer 0 sees unit 1, not unit 2
    out = np.asarray(native(own, position, inv_half, team, seen, attackable, zones))
    row = out[0]
    np.testing.assert_array_equal(row[:14], own[0])
    block = row[14:30]  # unit 1, first in viewer 0's cyclic order
    np.testing.assert_array_equal(block[[0, 1]], own[1, [0, 1]])
    np.testing.assert_array_equal(block[2:4], (position[1] - position[0]) * inv_half)
    np.testing.assert_array_equal(block[4:13], own[1, 4:13])
    assert block[13] == float(team[0] == team[1]) and block[14] == float(attackable[0, 1])
    assert block[15] == own[1, 13]
    assert not row[30:46].any()  # unit 2, unseen
    np.testing.assert_array_equal(row[46:], zones[0])


def test_vmap_with_shared_operands_and_nested_vmap():
    own, position, inv_half, team, seen, attackable, zones = operands(2, 4, 6, (3, 2))
    shared = jax.vmap(jax.vmap(assemble_observation, in_axes=(0, 0, None, None, 0, 0, 0)),
                      in_axes=(0, 0, None, None, 0, 0, 0))
    args = (own, position, inv_half[0, 0], team[0, 0], seen, attackable, zones)
    expected = reference(own, position, np.broadcast_to(inv_half[0, 0], (3, 2, 2)),
                         np.broadcast_to(team[0, 0], (3, 2, 4)), seen, attackable, zones)
    assert same_bits(jax.jit(shared)(*args), expected)


def test_a_batch_split_over_two_devices_stays_split():
    mesh = jax.sharding.Mesh(np.array(jax.local_devices()[:2]), ("envs",))
    args = [jax.device_put(x, NamedSharding(mesh, PartitionSpec("envs")))
            for x in operands(3, 5, 6, (8,))]
    compiled = native.lower(*args).compile()
    text = compiled.as_text()
    assert "all-gather(" not in text and "f32[4,5,84]" in text  # 4 envs per device
    out = compiled(*args)
    assert len(out.sharding.device_set) == 2
    assert same_bits(out, reference(*operands(3, 5, 6, (8,))))


def test_gradients_flow_through_the_xla_version():
    own, position, inv_half, team, seen, attackable, zones = operands(4, 3, 6, (2,))

    def loss(fn, position):
        return jnp.sum(fn(own, position, inv_half, team, seen, attackable, zones) ** 2)

    grad_native = jax.grad(lambda p: loss(assemble_observation, p))(position)
    grad_xla = jax.grad(lambda p: loss(assemble_xla, p))(position)
    np.testing.assert_allclose(grad_native, grad_xla, rtol=1e-6)
    assert np.abs(grad_native).sum() > 0


def test_the_library_is_cached_and_rebuilt_only_when_missing(tmp_path):
    first = build_library(tmp_path)
    stamp = first.stat().st_mtime_ns
    assert build_library(tmp_path) == first and first.stat().st_mtime_ns == stamp
    first.unlink()
    assert build_library(tmp_path).is_file()


_PROBE = textwrap.dedent("""
    import warnings, jax, numpy as np
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from tabx.native_lib import native_available
        from tabx.observe_kernel import assemble_observation, assemble_xla
        args = [np.zeros((2, 3, 14), np.float32), np.ones((2, 3, 2), np.float32),
                np.ones((2, 2), np.float32), np.zeros((2, 3), np.int32),
                np.ones((2, 3, 3), bool), np.zeros((2, 3, 3), bool), np.ones((2, 3, 6), np.float32)]
        text = jax.jit(assemble_observation).lower(*args).compile().as_text()
        same = np.array_equal(jax.jit(assemble_observation)(*args), jax.jit(assemble_xla)(*args))
    print("custom_call" in text, native_available(), same,
          any("native CPU kernels unavailable" in str(w.message) for w in caught))
""")


def _probe(tmp_path, **env) -> str:
    environ = {**os.environ, "TABX_CACHE_DIR": str(tmp_path), **env}
    result = subprocess.run([sys.executable, "-c", _PROBE], env=environ, capture_output=True,
                            text=True, timeout=300, check=True)
    return result.stdout.split("\n")[-2]


def test_without_a_compiler_or_when_turned_off_the_xla_version_runs(tmp_path):
    # custom call compiled in, native available, same values, warned
    assert _probe(tmp_path / "off", TABX_NATIVE="0") == "False False True False"
    assert _probe(tmp_path / "nocxx", CXX="/bin/false") == "False False True True"


def test_a_damaged_cached_library_is_rebuilt(tmp_path):
    library = build_library(tmp_path)
    library.write_bytes(b"not a shared library")
    assert _probe(tmp_path) == "True True True False"
