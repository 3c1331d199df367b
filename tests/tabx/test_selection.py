"""Packed-key row argmin (tabx.selection) against numpy, and file modes of atomic writes."""

from __future__ import annotations

import os
import stat

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tabx.files import atomic_write_text
from tabx.selection import index_one_hot, pick_row, row_argmin


@st.composite
def rows(draw):
    n = draw(st.sampled_from([1, 3, 8, 20, 33]))  # few shapes: each one compiles
    m = 6
    # Values on a coarse grid (exact ties are common) or spread over many magnitudes.
    values = draw(arrays(np.float32, (m, n), elements=st.one_of(
        st.sampled_from([0.0, 1.0, 2.5, 1e6]),
        st.floats(0, 1e7, width=32, allow_nan=False, allow_infinity=False))))
    valid = draw(arrays(np.bool_, (m, n)))
    return values, valid


_row_argmin = jax.jit(row_argmin)


@settings(max_examples=40, deadline=None)
@given(rows())
def test_row_argmin_matches_numpy_up_to_near_ties(data):
    values, valid = data
    index, one_hot, any_valid = (np.asarray(x) for x in _row_argmin(jnp.asarray(values),
                                                                    jnp.asarray(valid)))
    np.testing.assert_array_equal(any_valid, valid.any(-1))
    assert np.all(one_hot.sum(-1) == 1)  # exactly one column, valid rows or not
    masked = np.where(valid, values, np.inf)
    best = masked.min(-1)
    for r in np.flatnonzero(valid.any(-1)):
        i = index[r]
        assert valid[r, i] and one_hot[r, i]
        # The chosen value is the minimum up to the packed precision (2^-17 relative, and a
        # few ulps of the smallest denormals absolute).
        assert values[r, i] <= best[r] * (1 + 2.0**-17) + 1e-30
        if np.count_nonzero(masked[r] == best[r]) == 1 and np.all(
                (masked[r] == best[r]) | (masked[r] > best[r] * (1 + 2.0**-16) + 1e-30)):
            assert i == np.argmin(masked[r])
    # The index's own one-hot (what selections read) is row_argmin's, invalid rows included.
    np.testing.assert_array_equal(np.asarray(index_one_hot(jnp.asarray(index), values.shape[1])),
                                  one_hot)


def test_pick_row_selects_values_vectors_and_flags():
    matrix = jnp.arange(12.0).reshape(3, 4)
    one_hot = jnp.eye(4, dtype=bool)[jnp.array([2, 0, 3])]
    np.testing.assert_array_equal(pick_row(matrix, one_hot), [2.0, 4.0, 11.0])
    vectors = jnp.stack([matrix, -matrix], -1)
    np.testing.assert_array_equal(pick_row(vectors, one_hot), [[2, -2], [4, -4], [11, -11]])
    np.testing.assert_array_equal(pick_row(matrix > 4, one_hot), [False, False, True])


def test_atomic_writes_get_normal_file_permissions(tmp_path):
    path = atomic_write_text(tmp_path / "x.txt", "hi")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask
