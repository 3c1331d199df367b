"""Cheap per-unit random words: one threefry word per call, spread over many by a hash.

`jax.random` draws every word with threefry, which on CPU runs as a rolled loop of small
kernels: drawing a few words per unit per env per step cost a fifth of a scripted-opponent
step. Here one 32-bit threefry word seeds a counter-based stream, word i = fmix32(seed + i *
golden ratio) (MurmurHash3's finaliser: every input bit flips each output bit with probability
about one half), which XLA fuses into the consumer. Quality is ample for sampling actions and
exploration coin flips; it is not meant for anything cryptographic.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

_GOLDEN = 0x9E3779B9


def fmix32(h: jax.Array) -> jax.Array:
    """MurmurHash3's 32-bit finaliser (a bijection on uint32 with full avalanche)."""
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * jnp.uint32(0xC2B2AE35)
    return h ^ (h >> 16)


def random_words(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """uint32 words of `shape` from `key`: one threefry word, hashed with a counter."""
    seed = jax.random.bits(key, (), jnp.uint32)
    count = math.prod(shape)
    counter = jnp.arange(count, dtype=jnp.uint32).reshape(shape)
    return fmix32(seed + counter * jnp.uint32(_GOLDEN))


def to_unit_float(words: jax.Array, bits: int = 24) -> jax.Array:
    """The top `bits` bits of uint32 words as floats in [0, 1)."""
    return (words >> (32 - bits)).astype(jnp.float32) * (1.0 / (1 << bits))
