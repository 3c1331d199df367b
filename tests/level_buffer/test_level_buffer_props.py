"""Property tests: random operation sequences on a LevelBuffer agree step by step with a naive
reference model of JaxUED's LevelSampler semantics, and keep the invariants (size <= capacity,
unique never-reused ids, no level lost except by the eviction rule). Save/load round trips are
mixed into the sequences, so resumed buffers must continue exactly."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from level_buffer import INSERTED, BufferConfig, LevelBuffer

POOL = [0.0, -0.0, 1.0, 2.0, 3.0, 4.5, 7.0]  # -0.0 and 0.0 are the same level


def toy(values) -> dict:
    v = np.asarray(values, np.float32)
    return {"hp": np.stack([v, v + 1], axis=1), "tag": (np.abs(v) > 2).astype(np.int32),
            "on": v > 1}


class Model:
    """The JaxUED LevelSampler rules, written as plainly as possible (lists and loops)."""

    def __init__(self, cfg: BufferConfig, seed: int) -> None:
        self.cfg, self.rng = cfg, np.random.default_rng(seed)
        self.slots: list[dict] = []
        self.clock = self.next_id = 0

    def weights(self) -> np.ndarray:
        n, cfg = len(self.slots), self.cfg
        best_first = sorted(range(n), key=lambda i: (-self.slots[i]["score"], i))
        sw = np.zeros(n)
        if cfg.prioritization == "rank":
            for rank, i in enumerate(best_first, 1):
                sw[i] = (1.0 / rank) ** (1.0 / cfg.temperature)
        else:
            top = best_first[: cfg.topk_k]
            scores = [self.slots[i]["score"] for i in top]
            m = max(scores)
            for i, s in zip(top, scores, strict=True):
                sw[i] = 1.0 if m == -math.inf else math.exp(s - m)
        sw /= sw.sum()
        stale = np.array([self.clock - s["ts"] for s in self.slots], float)
        stw = stale / stale.sum() if stale.sum() > 0 else np.full(n, 1.0 / n)
        return (1 - cfg.staleness_coeff) * sw + cfg.staleness_coeff * stw

    def decide(self) -> bool:
        u = self.rng.random()
        return len(self.slots) / self.cfg.capacity >= self.cfg.minimum_fill_ratio and \
            u < self.cfg.replay_prob

    def sample(self, n: int) -> list[int]:
        out = []
        for _ in range(n):
            cdf = np.cumsum(self.weights())
            u = self.rng.random()
            i = min(int(np.searchsorted(cdf, u * cdf[-1], side="right")), len(self.slots) - 1)
            self.clock += 1
            self.slots[i]["ts"] = self.clock
            self.slots[i]["replays"] += 1
            out.append(self.slots[i]["id"])
        return out

    def insert(self, value: float, score: float) -> int:
        if self.cfg.duplicate_check:
            for s in self.slots:
                if s["value"] == value:  # -0.0 == 0.0
                    s["score"] = score
                    self.clock += 1
                    s["ts"] = self.clock
                    return s["id"]
        if len(self.slots) < self.cfg.capacity:
            idx = len(self.slots)
            current = -math.inf
        else:
            idx = int(np.argmin(self.weights()))
            current = self.slots[idx]["score"]
        self.clock += 1
        if not current < score:
            return -1
        slot = {"value": value, "score": score, "ts": self.clock, "replays": 0,
                "id": self.next_id, "max_return": -math.inf}
        self.next_id += 1
        if idx == len(self.slots):
            self.slots.append(slot)
        else:
            self.slots[idx] = slot
        return slot["id"]

    def update(self, level_id: int, score: float, max_return: float) -> bool:
        for s in self.slots:
            if s["id"] == level_id:
                s["score"] = score
                s["max_return"] = max(s["max_return"], max_return)
                return True
        return False


configs = st.builds(
    BufferConfig, capacity=st.integers(1, 5),
    replay_prob=st.sampled_from([0.0, 0.5, 1.0]),
    staleness_coeff=st.sampled_from([0.0, 0.3, 1.0]),
    minimum_fill_ratio=st.sampled_from([0.0, 0.5, 1.0]),
    prioritization=st.sampled_from(["rank", "topk"]),
    temperature=st.sampled_from([0.3, 1.0]), topk_k=st.integers(1, 3),
    duplicate_check=st.booleans())
scores = st.one_of(st.sampled_from([-math.inf, 0.0, 0.5, 1.0]),
                   st.floats(-5, 5, allow_nan=False))
ops = st.lists(st.one_of(
    st.tuples(st.just("insert"), st.lists(st.tuples(st.integers(0, len(POOL) - 1), scores),
                                          max_size=6)),
    st.tuples(st.just("sample"), st.integers(1, 5)),
    st.tuples(st.just("update"), st.lists(st.tuples(st.integers(-1, 12), scores,
                                                    st.floats(-3, 3)), max_size=4)),
    st.tuples(st.just("decide"), st.none()),
    st.tuples(st.just("reload"), st.none()),
), max_size=14)


def check_same(buf: LevelBuffer, model: Model) -> None:
    assert buf.size == len(model.slots) <= buf.capacity
    assert buf.clock == model.clock and buf.next_id == model.next_id
    ids = buf.ids
    assert ids.tolist() == [s["id"] for s in model.slots]
    assert len(set(ids.tolist())) == len(ids) and (ids < buf.next_id).all()
    assert buf.scores.tolist() == [s["score"] for s in model.slots]
    assert buf.column("timestamp").tolist() == [s["ts"] for s in model.slots]
    assert buf.column("replay_count").tolist() == [s["replays"] for s in model.slots]
    assert buf.column("max_return").tolist() == [s["max_return"] for s in model.slots]
    np.testing.assert_array_equal(buf.leaf("hp")[:, 0],
                                  np.array([s["value"] for s in model.slots], np.float32))
    if buf.size:
        np.testing.assert_allclose(buf.weights(), model.weights(), rtol=1e-9, atol=1e-12)


@settings(max_examples=80, deadline=None)
@given(cfg=configs, seed=st.integers(0, 2**16), sequence=ops)
def test_random_operations_match_the_reference(cfg, seed, sequence):
    template = {k: v[0] for k, v in toy([0.0]).items()}
    buf, model = LevelBuffer(template, cfg, seed=seed), Model(cfg, seed)
    for op, arg in sequence:
        if op == "insert":
            values = [POOL[i] for i in (a for a, _ in arg)]
            live_before = set(buf.ids.tolist())
            res = buf.insert_batch(toy(values), [s for _, s in arg])
            expected = [model.insert(v, s) for v, (_, s) in zip(values, arg, strict=True)]
            assert res.ids.tolist() == expected
            # a level leaves the buffer only from a slot that an insert of this batch took
            taken = set(res.slots[res.status == INSERTED].tolist())
            for gone in live_before - set(buf.ids.tolist()):
                assert buf.slot_of(gone) == -1
            for slot in range(buf.size):
                if int(buf.ids[slot]) not in live_before:
                    assert slot in taken
            assert len(live_before - set(buf.ids.tolist())) <= len(taken)
        elif op == "sample":
            if buf.size == 0:
                continue
            replay = buf.sample(arg)
            assert replay.ids.tolist() == model.sample(arg)
        elif op == "update":
            ids = [i for i, _, _ in arg]
            found = buf.update_batch(ids, [s for _, s, _ in arg],
                                     max_returns=[m for _, _, m in arg])
            assert found.tolist() == [model.update(i, s, m) for i, s, m in arg]
        elif op == "decide":
            assert buf.sample_replay_decision() == model.decide()
        else:
            buf = LevelBuffer.from_bytes(buf.to_bytes(), template)
        check_same(buf, model)
