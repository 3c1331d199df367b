"""Fast row-wise argmin for small matrices on CPU, as an index *and* a one-hot mask.

`jnp.argmin` lowers to a variadic (value, index) reduction that XLA on CPU runs slowly, and
using its index to gather from (N, N) matrices adds gathers, slower still under vmap. Here the
index is packed into the low bits of the value: non-negative float32 values compare like their
int32 bit patterns, so clearing the low `ceil(log2 n)` mantissa bits and writing the column
index there turns the argmin into one plain integer min-reduction, and equality with the row's
minimum gives an exact one-hot mask (the packed keys of a row are all distinct). Selecting with
the mask (`pick_row`) replaces gathers.

The price: values closer than about 2^-(23 - bits) relative (1e-5 for 20 columns) count as
ties, and ties go to the lowest index, as with argmin.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp


def row_argmin(values: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(index (...,), one_hot (..., n) bool, any_valid (...,)) of the smallest valid entry of
    each row of `values` (..., n), non-negative floats. Rows without a valid entry get index
    and one-hot of an arbitrary column: mask their use with `any_valid`."""
    n = values.shape[-1]
    bits = max(1, math.ceil(math.log2(n)))
    column = jnp.arange(n, dtype=jnp.int32)
    pattern = jax.lax.bitcast_convert_type(jnp.maximum(values, 0.0).astype(jnp.float32),
                                           jnp.int32)
    # Invalid entries: the largest key (still distinct per column, so the one-hot is exact).
    key = jnp.where(valid, (pattern & ~((1 << bits) - 1)) | column, jnp.int32(0x7FFFFFFF) - n
                    + 1 + column)
    smallest = jnp.min(key, axis=-1)
    one_hot = key == smallest[..., None]
    any_valid = jnp.any(valid, axis=-1)
    index = jnp.where(any_valid, smallest & ((1 << bits) - 1), 0)
    return index, one_hot, any_valid


def index_one_hot(index: jax.Array, n: int) -> jax.Array:
    """(..., n) bool one-hot rows of integer `index` (...,). Selections (`pick_row`) should read
    these rather than `row_argmin`'s own one-hot, which compares each key with its row's
    minimum: XLA fuses that comparison, the minimum and the whole key computation into every
    element of the selection; an index compare is one operation per element."""
    return index[..., None] == jnp.arange(n)


def pick_row(matrix: jax.Array, one_hot: jax.Array) -> jax.Array:
    """matrix[i, index[i]] for a one-hot (..., n) mask; matrix is (..., n) or (..., n, k)."""
    if matrix.dtype == jnp.bool_:
        return jnp.any(one_hot & matrix, axis=-1)
    if matrix.ndim == one_hot.ndim:
        return jnp.sum(jnp.where(one_hot, matrix, jnp.zeros((), matrix.dtype)), axis=-1)
    return jnp.sum(jnp.where(one_hot[..., None], matrix, jnp.zeros((), matrix.dtype)), axis=-2)


def materialise(x: jax.Array) -> jax.Array:
    """x (..., k) float, computed once. XLA on CPU drops optimization barriers before fusing
    and duplicates cheap producers into every consumer fusion (each (N, N) output of a step
    re-deriving the whole pairwise geometry, say). A matrix product is never fused with its
    operands, so multiplying by the identity makes XLA compute x once; under vmap the identity
    is unbatched, so this is one plain matrix product over the whole batch. Exact for finite
    floats (HIGHEST precision; each output is one product with 1 plus zeros)."""
    identity = jnp.eye(x.shape[-1], dtype=x.dtype)
    return jnp.matmul(x, identity, precision=jax.lax.Precision.HIGHEST)
