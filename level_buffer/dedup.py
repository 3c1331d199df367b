"""Vectorised duplicate look-up for the level buffer.

Comparing a batch of 128 levels leaf by leaf against 4000 stored ones would touch ~10^8
elements, so every slot keeps small *keys* and only pairs whose keys agree are compared in full:

* exact duplicates: a 64-bit hash of the level's canonical bytes (every leaf, -0.0 folded into
  +0.0). Two levels are exact duplicates when those bytes are equal.
* near duplicates (optional): a hash of the int/bool leaves, and K projections w·f of the float
  leaves f with |w|_1 = 1. If max|f_a - f_b| <= atol then |w·f_a - w·f_b| <= atol, so the
  projections are a pre-filter with no false negatives; candidates are then checked exactly
  (int/bool leaves equal, every float element within atol).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from level_buffer.tree import LevelSpec

NUM_PROJECTIONS = 4
_KEY_SEED = 0x7AB5  # fixed: keys must not depend on (or consume) the buffer's sampling rng


class BatchKeys(NamedTuple):
    hash: np.ndarray  # uint64 (B,)
    rows: np.ndarray  # uint8 (B, nbytes), canonical bytes of every leaf
    int_hash: np.ndarray | None  # uint64 (B,), int/bool leaves only (near mode)
    int_rows: np.ndarray | None
    floats: np.ndarray | None  # float64 (B, F) (near mode)
    proj: np.ndarray | None  # float64 (B, K) (near mode)


def _canonical_rows(leaves: list[np.ndarray], n: int) -> np.ndarray:
    """(n, nbytes) uint8: the bytes of each level, with -0.0 turned into +0.0."""
    parts = []
    for leaf in leaves:
        x = leaf.reshape(n, math.prod(leaf.shape[1:]))
        if x.dtype.kind == "f":
            x = x + x.dtype.type(0.0)  # IEEE: -0.0 + 0.0 == +0.0, so equal values hash equal
        parts.append(np.ascontiguousarray(x).view(np.uint8))  # (n, k * itemsize)
    return np.concatenate(parts, axis=1) if parts else np.zeros((n, 0), np.uint8)


class DuplicateIndex:
    """Per-slot duplicate keys of a buffer, and batch-vs-buffer / within-batch matching."""

    def __init__(self, spec: LevelSpec, capacity: int, near_atol: float | None) -> None:
        self.near_atol = near_atol
        self._is_float = [d.kind == "f" for d in spec.dtypes]
        rng = np.random.default_rng(_KEY_SEED)
        nbytes = sum(int(np.prod(s)) * d.itemsize for s, d in zip(spec.shapes, spec.dtypes,
                                                                   strict=True))
        int_nbytes = sum(int(np.prod(s)) * d.itemsize for s, d, f in zip(
            spec.shapes, spec.dtypes, self._is_float, strict=True) if not f)
        self._mult = rng.integers(1, 2**63, size=(nbytes + 7) // 8 + 1, dtype=np.uint64) | 1
        self._int_mult = rng.integers(1, 2**63, size=(int_nbytes + 7) // 8 + 1,
                                      dtype=np.uint64) | 1
        self.hash = np.zeros(capacity, np.uint64)
        if near_atol is not None:
            nfloat = sum(int(np.prod(s)) for s, f in zip(spec.shapes, self._is_float,
                                                         strict=True) if f)
            w = rng.standard_normal((nfloat, NUM_PROJECTIONS))
            self._proj_w = w / np.maximum(np.abs(w).sum(axis=0, keepdims=True), 1e-300)
            self.int_hash = np.zeros(capacity, np.uint64)
            self.proj = np.zeros((capacity, NUM_PROJECTIONS))
            self.fscale = np.zeros(capacity)

    @staticmethod
    def _hash(rows: np.ndarray, mult: np.ndarray) -> np.ndarray:
        n, nb = rows.shape
        padded = np.zeros((n, mult.shape[0] * 8), np.uint8)
        padded[:, :nb] = rows
        words = padded.view(np.uint64)
        # Wrapping multiply-add of the 8-byte words: a cheap hash; equality is verified anyway.
        return (words * mult).sum(axis=1, dtype=np.uint64) ^ np.uint64(nb)

    def keys(self, leaves: list[np.ndarray], n: int) -> BatchKeys:
        rows = _canonical_rows(leaves, n)
        if self.near_atol is None:
            return BatchKeys(self._hash(rows, self._mult), rows, None, None, None, None)
        int_leaves = [x for x, f in zip(leaves, self._is_float, strict=True) if not f]
        int_rows = _canonical_rows(int_leaves, n)
        float_parts = [x.reshape(n, math.prod(x.shape[1:])).astype(np.float64)
                       for x, f in zip(leaves, self._is_float, strict=True) if f]
        floats = np.concatenate(float_parts, axis=1) if float_parts else np.zeros((n, 0))
        return BatchKeys(self._hash(rows, self._mult), rows, self._hash(int_rows, self._int_mult),
                         int_rows, floats, floats @ self._proj_w)

    def store(self, slot: int, keys: BatchKeys, b: int) -> None:
        self.hash[slot] = keys.hash[b]
        if self.near_atol is not None:
            self.int_hash[slot] = keys.int_hash[b]
            self.proj[slot] = keys.proj[b]
            self.fscale[slot] = np.abs(keys.floats[b]).max(initial=0.0)

    def rebuild(self, leaves: list[np.ndarray], size: int) -> None:
        """Recompute the keys of slots [0, size) (after a load)."""
        if size == 0:
            return
        keys = self.keys([x[:size] for x in leaves], size)
        self.hash[:size] = keys.hash
        if self.near_atol is not None:
            self.int_hash[:size] = keys.int_hash
            self.proj[:size] = keys.proj
            self.fscale[:size] = np.abs(keys.floats).max(axis=1, initial=0.0)

    # --- matching ----------------------------------------------------------------------------

    def _candidates(self, keys: BatchKeys, other: BatchKeys | None, size: int) -> np.ndarray:
        """(B, M) bool: pairs whose keys agree (M = size stored slots, or B batch items)."""
        if self.near_atol is None:
            other_hash = self.hash[:size] if other is None else other.hash
            return keys.hash[:, None] == other_hash[None, :]
        if other is None:
            ih, proj, scale = self.int_hash[:size], self.proj[:size], self.fscale[:size]
        else:
            ih, proj = other.int_hash, other.proj
            scale = np.abs(other.floats).max(axis=1, initial=0.0)
        cand = keys.int_hash[:, None] == ih[None, :]
        # Rounding slack of the float64 dot products; generous, since candidates are verified.
        big = max(float(scale.max(initial=0.0)),
                  float(np.abs(keys.floats).max(initial=0.0)))
        tol = self.near_atol + 1e-9 * (1.0 + big)
        for k in range(NUM_PROJECTIONS):
            cand &= np.abs(keys.proj[:, k, None] - proj[None, :, k]) <= tol
        return cand

    def _verify(self, keys: BatchKeys, b: np.ndarray, other: BatchKeys, o: np.ndarray
                ) -> np.ndarray:
        if self.near_atol is None:
            return (keys.rows[b] == other.rows[o]).all(axis=1)
        same_int = (keys.int_rows[b] == other.int_rows[o]).all(axis=1)
        close = (np.abs(keys.floats[b] - other.floats[o]) <= self.near_atol).all(axis=1)
        return same_int & close

    def match_stored(self, keys: BatchKeys, leaves: list[np.ndarray], size: int
                     ) -> list[list[int]]:
        """For each batch item, the stored slots (ascending) holding a duplicate of it."""
        n = keys.hash.shape[0]
        out: list[list[int]] = [[] for _ in range(n)]
        if size == 0:
            return out
        b_idx, s_idx = np.nonzero(self._candidates(keys, None, size))
        if b_idx.size == 0:
            return out
        slots = np.unique(s_idx)
        stored = self.keys([x[slots] for x in leaves], slots.size)
        ok = self._verify(keys, b_idx, stored, np.searchsorted(slots, s_idx))
        for b, s in zip(b_idx[ok].tolist(), s_idx[ok].tolist(), strict=True):
            out[b].append(s)  # np.nonzero is row-major, so slots come out ascending
        return out

    def match_within(self, keys: BatchKeys) -> list[list[int]]:
        """For each batch item b, the earlier items a < b that are duplicates of it."""
        n = keys.hash.shape[0]
        out: list[list[int]] = [[] for _ in range(n)]
        cand = np.tril(self._candidates(keys, keys, 0), k=-1)
        b_idx, a_idx = np.nonzero(cand)
        if b_idx.size:
            ok = self._verify(keys, b_idx, keys, a_idx)
            for b, a in zip(b_idx[ok].tolist(), a_idx[ok].tolist(), strict=True):
                out[b].append(a)
        return out
