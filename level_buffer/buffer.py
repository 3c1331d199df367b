"""`LevelBuffer`: the scored, prioritised level buffer of PLR, Robust PLR and ACCEL, on the host.

Storage is struct-of-arrays: one numpy array per level leaf with leading axis = capacity, and
one array per slot field (score, timestamp, max return, replay count, source, parent id, level
id, policy version, lineage depth). Slots [0, size) are filled; a slot is only ever overwritten
by an eviction, never emptied.

Semantics follow JaxUED's `LevelSampler` (see docs/level_buffer.md):
* a sampling clock (JaxUED's `episode_count`) ticks once per replay draw and once per insert
  attempt; a slot's staleness is `clock - timestamp`, where timestamp is the tick at which it
  was last inserted, sampled or refreshed as a duplicate;
* replay draws are sequential and with replacement: each draw re-weights with the staleness
  left by the previous one;
* insert goes to the next free slot, or when full to the slot with the lowest replay weight,
  and only if the new score is strictly higher than that slot's; a -inf score (no finished
  episode) is therefore never inserted;
* with the duplicate check, a level equal to a stored one refreshes that slot (score, extras,
  timestamp) instead of being inserted.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from level_buffer import weights as W
from level_buffer.config import BufferConfig, Source
from level_buffer.dedup import DuplicateIndex
from level_buffer.fileformat import decode, encode, make_rng, read_file
from level_buffer.state import SLOT_FIELDS, STAT_NAMES, BufferState
from level_buffer.tree import LevelSpec, named_leaves

REJECTED, INSERTED, DUPLICATE = 0, 1, 2  # InsertResult.status


class InsertResult(NamedTuple):
    """Per level of an insert batch: the id it got (its new id, the id of the stored duplicate
    it refreshed, or -1 when rejected), that slot (-1 when rejected), and a status (REJECTED 0,
    INSERTED 1, DUPLICATE 2). A level of the batch can be evicted again by a later one of the
    same batch; `id in buffer` tells."""

    ids: np.ndarray
    slots: np.ndarray
    status: np.ndarray


class Replay(NamedTuple):
    """A batch of replayed levels with the slot data a learner needs to rescore them."""

    ids: np.ndarray  # int64 (n,) stable level ids: pass these to update_batch
    slots: np.ndarray  # int64 (n,) slot indices at sampling time
    levels: Any  # the levels, leading axis n (a pytree like the template, or a dict by path)
    scores: np.ndarray  # float64 (n,) scores before replay
    max_returns: np.ndarray  # float64 (n,) best return seen so far (MaxMC's R_max)
    depths: np.ndarray  # int64 (n,) lineage depth (a mutation's child has depth + 1)


def _check_scores(scores: Any, n: int, what: str) -> np.ndarray:
    s = np.asarray(scores, np.float64).reshape(-1)
    if s.shape[0] != n:
        raise ValueError(f"{what}: got {s.shape[0]} scores for {n} levels")
    bad = np.isnan(s) | (s == np.inf)
    if bad.any():
        raise ValueError(f"{what}: score {s[bad][0]} at position {int(np.argmax(bad))} is not "
                         "allowed (finite or -inf only)")
    return s


def _broadcast_int(value: Any, n: int, what: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "biu":
        raise ValueError(f"{what} must be integers, got dtype {arr.dtype}")
    try:
        return np.broadcast_to(arr.astype(np.int64), (n,)).copy()
    except ValueError:
        raise ValueError(f"{what}: shape {arr.shape} does not fit a batch of {n}") from None


class LevelBuffer:
    """A PLR level buffer over levels shaped like `template_level` (any pytree of arrays)."""

    def __init__(self, template_level: Any, config: BufferConfig | None = None, *,
                 seed: int | None = 0, **overrides: Any) -> None:
        """`config` (default `BufferConfig()`) with any field overridden by keyword, e.g.
        `LevelBuffer(level, capacity=100, prioritization="topk")`; `seed` seeds the numpy
        Generator used for replay decisions and draws."""
        config = config if config is not None else BufferConfig()
        if overrides:
            config = dataclasses.replace(config, **overrides)
        self._setup(LevelSpec.from_template(template_level), config,
                    np.random.default_rng(seed))

    def _setup(self, spec: LevelSpec, config: BufferConfig, rng: np.random.Generator) -> None:
        self.spec = spec
        self.config = config
        self.rng = rng
        cap = config.capacity
        self._levels = [np.zeros((cap, *shape), dtype)
                        for shape, dtype in zip(spec.shapes, spec.dtypes, strict=True)]
        self._slots = {name: np.full(cap, fill, dtype) for name, (dtype, fill) in
                       SLOT_FIELDS.items()}
        self.size = 0
        self.clock = 0
        self.next_id = 0
        self.stats = dict.fromkeys(STAT_NAMES, 0)
        self._slot_of: dict[int, int] = {}
        self._dedup = DuplicateIndex(
            spec, cap, config.near_duplicate_atol if config.near_duplicates else None)

    # --- read access -------------------------------------------------------------------------

    @property
    def capacity(self) -> int:
        return self.config.capacity

    def __len__(self) -> int:
        return self.size

    def __contains__(self, level_id: object) -> bool:
        return isinstance(level_id, (int, np.integer)) and int(level_id) in self._slot_of

    def column(self, name: str) -> np.ndarray:
        """A copy of one slot field over the filled slots, e.g. `column("score")`."""
        if name not in SLOT_FIELDS:
            raise KeyError(f"unknown slot field {name!r}; expected one of {list(SLOT_FIELDS)}")
        return self._slots[name][: self.size].copy()

    @property
    def ids(self) -> np.ndarray:
        return self.column("level_id")

    @property
    def scores(self) -> np.ndarray:
        return self.column("score")

    def staleness(self) -> np.ndarray:
        return self.clock - self._slots["timestamp"][: self.size]

    def leaf(self, path: str) -> np.ndarray:
        """A copy of one level leaf over the filled slots, shape (size, *leaf shape)."""
        if path not in self.spec.paths:
            raise KeyError(f"unknown level field {path!r}; expected one of {list(self.spec.paths)}")
        return self._levels[self.spec.paths.index(path)][: self.size].copy()

    def slot_of(self, level_id: int) -> int:
        """The slot holding `level_id`, or -1 if it is not (or no longer) in the buffer."""
        return self._slot_of.get(int(level_id), -1)

    def _slots_for(self, ids: Any) -> np.ndarray:
        ids = np.asarray(ids, np.int64).reshape(-1)
        slots = np.array([self._slot_of.get(i, -1) for i in ids.tolist()], np.int64)
        if (slots < 0).any():
            missing = ids[slots < 0][:5].tolist()
            raise KeyError(f"level ids {missing} are not in the buffer")
        return slots

    def get(self, ids: Sequence[int] | np.ndarray) -> Any:
        """The levels with these ids, stacked (leading axis len(ids)); KeyError if one is gone."""
        slots = self._slots_for(ids)
        return self.spec.unflatten([x[slots] for x in self._levels])

    def get_level(self, level_id: int) -> Any:
        """One level (no leading axis)."""
        slot = self._slots_for([level_id])[0]
        return self.spec.unflatten([x[slot].copy() for x in self._levels])

    def record(self, level_id: int) -> dict[str, Any]:
        """The slot fields of one level as Python scalars (source as its name)."""
        slot = int(self._slots_for([level_id])[0])
        out: dict[str, Any] = {name: self._slots[name][slot].item() for name in SLOT_FIELDS}
        out["source"] = Source(out["source"]).name.lower()
        out["staleness"] = self.clock - out["timestamp"]
        out["slot"] = slot
        return out

    def top(self, k: int) -> np.ndarray:
        """Ids of the k best-scoring levels, best first (ties: lower slot first)."""
        order = W.score_order(self._slots["score"][: self.size])[: max(k, 0)]
        return self._slots["level_id"][order].copy()

    def find(self, level: Any) -> int:
        """Id of a stored level equal to `level` under the buffer's duplicate rule, or -1."""
        leaves, _ = self.spec.flatten_batch(
            self.spec.unflatten([np.asarray(x)[None] for x in self._leaves_of(level)]), "level")
        keys = self._dedup.keys(leaves, 1)
        found = self._dedup.match_stored(keys, self._levels, self.size)[0]
        return int(self._slots["level_id"][found[0]]) if found else -1

    def _leaves_of(self, level: Any) -> list[Any]:
        named = named_leaves(level)
        if set(named) != set(self.spec.paths):
            raise ValueError("level does not match the buffer's level structure")
        return [named[p] for p in self.spec.paths]

    # --- weights -----------------------------------------------------------------------------

    def score_weights(self) -> np.ndarray:
        """P_score over the filled slots (length size)."""
        return W.score_weights(self._slots["score"][: self.size], self.config)

    def staleness_weights(self) -> np.ndarray:
        return W.staleness_weights(self._slots["timestamp"][: self.size], self.clock)

    def weights(self) -> np.ndarray:
        """The replay distribution over the filled slots (length size, sums to 1)."""
        return W.replay_weights(self._slots["score"][: self.size],
                                self._slots["timestamp"][: self.size], self.clock, self.config)

    def _score_weights_from_order(self, order: np.ndarray) -> np.ndarray:
        return W.score_weights(self._slots["score"][: self.size], self.config, order)

    # --- replay ------------------------------------------------------------------------------

    def sample_replay_decision(self) -> bool:
        """True for a replay step: the buffer is filled to at least minimum_fill_ratio and a
        uniform draw falls below replay_prob. Always consumes one draw, so the rng stream does
        not depend on the fill level."""
        u = self.rng.random()
        filled = self.size / self.capacity >= self.config.minimum_fill_ratio
        return bool(filled and u < self.config.replay_prob)

    def sample(self, n: int) -> Replay:
        """Draw n levels from the replay distribution, one after the other, with replacement;
        each draw stamps its slot with the next clock tick (staleness 0) and counts a replay."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty level buffer")
        if n < 0:
            raise ValueError(f"sample size must be >= 0, got {n}")
        size, rho = self.size, self.config.staleness_coeff
        scores = self._slots["score"][:size]
        ts = self._slots["timestamp"][:size]
        # Scores do not change while sampling, so P_score is computed once.
        score_part = (1.0 - rho) * self._score_weights_from_order(W.score_order(scores))
        slots = np.empty(n, np.int64)
        for i in range(n):
            cdf = np.cumsum(score_part + rho * W.staleness_weights(ts, self.clock))
            u = self.rng.random()
            # Slots of weight 0 have an empty interval in the cdf, so "right" never picks them.
            slot = min(int(np.searchsorted(cdf, u * cdf[-1], side="right")), size - 1)
            self.clock += 1
            ts[slot] = self.clock
            self._slots["replay_count"][slot] += 1
            slots[i] = slot
        self.stats["sampled"] += n
        return Replay(self._slots["level_id"][slots].copy(), slots,
                      self.spec.unflatten([x[slots] for x in self._levels]),
                      self._slots["score"][slots].copy(), self._slots["max_return"][slots].copy(),
                      self._slots["depth"][slots].copy())

    def update_batch(self, ids: Sequence[int] | np.ndarray, scores: Any, *,
                     max_returns: Any = None, policy_versions: Any = None) -> np.ndarray:
        """New scores for replayed levels, by id, in order (a repeated id: the last one wins).
        `max_returns` raise the stored best return (never lower it); `policy_versions` record
        which policy produced the score. Ids no longer in the buffer (evicted since they were
        sampled) are skipped; returns a bool mask of the ids that were found."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        n = ids.shape[0]
        scores = _check_scores(scores, n, "update_batch")
        mr = None if max_returns is None else np.broadcast_to(
            np.asarray(max_returns, np.float64), (n,))
        pv = None if policy_versions is None else _broadcast_int(policy_versions, n,
                                                                 "policy_versions")
        found = np.zeros(n, bool)
        for i, level_id in enumerate(ids.tolist()):
            slot = self._slot_of.get(level_id, -1)
            if slot < 0:
                continue
            found[i] = True
            self._slots["score"][slot] = scores[i]
            if mr is not None:
                self._slots["max_return"][slot] = max(self._slots["max_return"][slot], mr[i])
            if pv is not None:
                self._slots["policy_version"][slot] = pv[i]
        self.stats["updated"] += int(found.sum())
        return found

    def update(self, level_id: int, score: float, **kwargs: Any) -> bool:
        return bool(self.update_batch([level_id], [score], **kwargs)[0])

    # --- insert ------------------------------------------------------------------------------

    def insert(self, level: Any, score: float, **kwargs: Any) -> InsertResult:
        """Insert one level (no leading axis); see insert_batch."""
        batch = self.spec.unflatten([np.asarray(x)[None] for x in self._leaves_of(level)])
        return self.insert_batch(batch, [score], **kwargs)

    def insert_batch(self, levels: Any, scores: Any, *, sources: Any = Source.RANDOM,
                     parent_ids: Any = -1, policy_versions: Any = -1, max_returns: Any = None,
                     depths: Any = None) -> InsertResult:
        """Try to insert a batch of levels (leading axis B), one after the other.

        Each attempt ticks the clock. A duplicate (if the check is on) refreshes the stored
        slot: score and policy version replaced, max return raised, timestamp = clock. Otherwise
        the level goes to the next free slot, or when full to the slot of lowest replay weight,
        if and only if its score is strictly higher than that slot's (free slots hold -inf).
        `depths` default to the parent's depth + 1 when the parent is still stored, 1 for an
        unknown parent and 0 without one. Everything is validated before the buffer changes.
        """
        leaves, n = self.spec.flatten_batch(levels, "insert_batch levels")
        scores = _check_scores(scores, n, "insert_batch")
        src = _broadcast_int(sources, n, "sources")
        valid_sources = [int(s) for s in Source]
        if not np.isin(src, valid_sources).all():
            raise ValueError(f"sources must be among {[s.name for s in Source]} "
                             f"({valid_sources}), got {sorted(set(src.tolist()))}")
        parents = _broadcast_int(parent_ids, n, "parent_ids")
        pvs = _broadcast_int(policy_versions, n, "policy_versions")
        mrs = np.full(n, -np.inf) if max_returns is None else np.broadcast_to(
            np.asarray(max_returns, np.float64), (n,)).copy()
        dps = None if depths is None else _broadcast_int(depths, n, "depths")

        keys = self._dedup.keys(leaves, n)
        if self.config.duplicate_check:
            stored_matches = self._dedup.match_stored(keys, self._levels, self.size)
            batch_matches = self._dedup.match_within(keys)
        placed = np.full(n, -1, np.int64)
        out_ids = np.full(n, -1, np.int64)
        holder: dict[int, int] = {}  # slot -> batch index written into it by this call
        status = np.zeros(n, np.int8)
        s = self._slots
        order: np.ndarray | None = None  # score order of a full buffer, kept up to date
        neg_sorted: np.ndarray | None = None
        score_part: tuple[np.ndarray | None, Any] = (None, None)  # (order, its weighted P_score)

        def reorder(slot: int, old: float, new: float) -> None:
            nonlocal order, neg_sorted
            if order is None:
                return
            lo = np.searchsorted(neg_sorted, -old, "left")
            hi = np.searchsorted(neg_sorted, -old, "right")
            pos = lo + np.searchsorted(order[lo:hi], slot)
            order, neg_sorted = np.delete(order, pos), np.delete(neg_sorted, pos)
            lo = np.searchsorted(neg_sorted, -new, "left")
            hi = np.searchsorted(neg_sorted, -new, "right")
            pos = lo + np.searchsorted(order[lo:hi], slot)
            order, neg_sorted = np.insert(order, pos, slot), np.insert(neg_sorted, pos, -new)

        for b in range(n):
            score = float(scores[b])
            dup = -1
            if self.config.duplicate_check:
                cands = [t for t in stored_matches[b] if t not in holder]
                cands += [int(placed[a]) for a in batch_matches[b]
                          if placed[a] >= 0 and holder.get(int(placed[a])) == a]
                dup = min(cands) if cands else -1
            self.stats["insert_attempts"] += 1
            if dup >= 0:
                old = float(s["score"][dup])
                s["score"][dup] = score
                s["max_return"][dup] = max(s["max_return"][dup], mrs[b])
                s["policy_version"][dup] = pvs[b]
                self.clock += 1
                s["timestamp"][dup] = self.clock
                reorder(dup, old, score)
                placed[b], status[b] = dup, DUPLICATE
                out_ids[b] = s["level_id"][dup]
                self.stats["duplicates"] += 1
                continue
            if self.size < self.capacity:
                slot = self.size
            else:
                if order is None:
                    order = W.score_order(s["score"])
                    neg_sorted = -s["score"][order]
                rho = self.config.staleness_coeff
                if score_part[0] is not order:  # P_score changes only with the order
                    score_part = (order, (1.0 - rho) * self._score_weights_from_order(order))
                w = score_part[1] + rho * W.staleness_weights(s["timestamp"], self.clock)
                slot = int(np.argmin(w))
            self.clock += 1
            if not s["score"][slot] < score:
                self.stats["rejected"] += 1
                continue
            old = float(s["score"][slot])
            if self.size == self.capacity:
                del self._slot_of[int(s["level_id"][slot])]
                self.stats["evicted"] += 1
            else:
                self.size += 1
            for dst, src_leaf in zip(self._levels, leaves, strict=True):
                dst[slot] = src_leaf[b]
            parent = int(parents[b])
            if dps is not None:
                depth = int(dps[b])
            elif parent >= 0:
                pslot = self._slot_of.get(parent, -1)
                depth = int(s["depth"][pslot]) + 1 if pslot >= 0 else 1
            else:
                depth = 0
            s["score"][slot] = score
            s["timestamp"][slot] = self.clock
            s["max_return"][slot] = mrs[b]
            s["replay_count"][slot] = 0
            s["source"][slot] = src[b]
            s["parent_id"][slot] = parent
            s["level_id"][slot] = self.next_id
            s["policy_version"][slot] = pvs[b]
            s["depth"][slot] = depth
            self._slot_of[self.next_id] = slot
            out_ids[b] = self.next_id
            self.next_id += 1
            self._dedup.store(slot, keys, b)
            reorder(slot, old, score)
            holder[slot] = b
            placed[b], status[b] = slot, INSERTED
            self.stats["inserted"] += 1
        return InsertResult(out_ids, placed, status)

    # --- persistence -------------------------------------------------------------------------

    def state(self) -> BufferState:
        """A snapshot (copies) of everything that defines the buffer."""
        n = self.size
        return BufferState(self.spec, self.config, n, self.clock, self.next_id, dict(self.stats),
                           json.loads(json.dumps(self.rng.bit_generator.state)),
                           [x[:n].copy() for x in self._levels],
                           {k: v[:n].copy() for k, v in self._slots.items()})

    @classmethod
    def from_state(cls, state: BufferState) -> LevelBuffer:
        """A buffer from a (validated) snapshot; see level_buffer.fileformat for validation."""
        buf = cls.__new__(cls)
        buf._setup(state.spec, state.config, make_rng(state.rng_state))
        n = state.size
        for dst, src in zip(buf._levels, state.levels, strict=True):
            dst[:n] = src
        for k, v in state.slots.items():
            buf._slots[k][:n] = v
        buf.size, buf.clock, buf.next_id = n, state.clock, state.next_id
        buf.stats.update(state.stats)
        buf._slot_of = {int(i): slot for slot, i in enumerate(buf._slots["level_id"][:n])}
        buf._dedup.rebuild(buf._levels, n)
        return buf

    def to_bytes(self) -> bytes:
        return encode(self.state())

    @classmethod
    def from_bytes(cls, data: bytes, template_level: Any = None, name: str = "<bytes>"
                   ) -> LevelBuffer:
        return cls.from_state(decode(data, name, template_level))

    def save(self, path: str | os.PathLike) -> Path:
        """Write the buffer atomically (temp file, fsync, rename): a crash never leaves a
        half-written file, and the previous file stays intact until the rename."""
        from tabx.files import atomic_write_bytes

        return atomic_write_bytes(path, self.to_bytes())

    @classmethod
    def load(cls, path: str | os.PathLike, template_level: Any = None) -> LevelBuffer:
        """Read a buffer file. With a template, levels come back as pytrees like it (and the
        file must hold exactly its leaves, shapes and dtypes, except leaves added to the level
        type after the file was written, which its class's `FILE_DEFAULTS` fill); without
        one, as dicts keyed by key path ("units.health"). Raises BufferFileError naming the
        file for a missing, truncated, corrupted or mismatched file; nothing is
        half-loaded."""
        return cls.from_bytes(read_file(path), template_level, str(path))
