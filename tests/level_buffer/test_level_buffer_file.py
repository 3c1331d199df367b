"""Buffer files: exact round trip (rng state included), template-free loading, and refusal of
truncated, corrupted, mismatched or newer files with a clear BufferFileError."""

from __future__ import annotations

import os

import msgpack
import numpy as np
import pytest

from level_buffer import SLOT_FIELDS, BufferFileError, LevelBuffer, Source
from level_buffer.fileformat import FORMAT_VERSION, MAGIC


def template() -> dict:
    return {"units": {"pos": np.zeros((3, 2), np.float32), "hp": np.zeros(3, np.float32),
                      "alive": np.zeros(3, bool)},
            "kind": np.zeros((), np.int64), "arena": np.zeros(2, np.float64)}


def batch(rng: np.random.Generator, n: int) -> dict:
    return {"units": {"pos": rng.random((n, 3, 2)).astype(np.float32),
                      "hp": rng.integers(1, 5, (n, 3)).astype(np.float32),
                      "alive": rng.random((n, 3)) < 0.5},
            "kind": rng.integers(0, 2**40, n), "arena": rng.random((n, 2))}


def filled(capacity=16, seed=0, n_batches=4, **kw) -> LevelBuffer:
    rng = np.random.default_rng(seed)
    buf = LevelBuffer(template(), capacity=capacity, seed=seed, **kw)
    for i in range(n_batches):
        res = buf.insert_batch(batch(rng, 6), rng.random(6), max_returns=rng.random(6),
                               policy_versions=i, sources=rng.integers(0, 4, 6))
        live = [i for i in res.ids.tolist() if i in buf][:2]
        if len(live) == 2:  # re-insert two: duplicates
            buf.insert_batch(buf.get(live), [0.5, 0.6])
        replay = buf.sample(5)
        buf.update_batch(replay.ids, rng.random(5), max_returns=rng.random(5))
    return buf


def assert_same(a: LevelBuffer, b: LevelBuffer) -> None:
    assert (a.size, a.clock, a.next_id, a.config, a.stats) == (b.size, b.clock, b.next_id,
                                                              b.config, b.stats)
    for name in SLOT_FIELDS:
        np.testing.assert_array_equal(a.column(name), b.column(name))
        assert a.column(name).dtype == b.column(name).dtype
    for path in a.spec.paths:
        np.testing.assert_array_equal(a.leaf(path), b.leaf(path))
        assert a.leaf(path).dtype == b.leaf(path).dtype
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


def test_round_trip_is_exact_and_continues_identically(tmp_path):
    buf = filled()
    path = buf.save(tmp_path / "run" / "buffer.msgpack")
    loaded = LevelBuffer.load(path, template())
    assert_same(buf, loaded)
    # The resumed buffer behaves exactly like the one that was never saved.
    rng_a, rng_b = np.random.default_rng(9), np.random.default_rng(9)
    for _ in range(3):
        assert buf.sample_replay_decision() == loaded.sample_replay_decision()
        ra, rb = buf.sample(7), loaded.sample(7)
        np.testing.assert_array_equal(ra.ids, rb.ids)
        np.testing.assert_array_equal(ra.levels["units"]["pos"], rb.levels["units"]["pos"])
        ia = buf.insert_batch(batch(rng_a, 5), rng_a.random(5))
        ib = loaded.insert_batch(batch(rng_b, 5), rng_b.random(5))
        np.testing.assert_array_equal(ia.ids, ib.ids)
    assert_same(buf, loaded)
    assert [p.name for p in path.parent.iterdir()] == ["buffer.msgpack"]  # no temp files left


def test_round_trip_near_duplicates_and_topk(tmp_path):
    buf = filled(near_duplicates=True, near_duplicate_atol=0.01, prioritization="topk",
                 topk_k=3)
    loaded = LevelBuffer.from_bytes(buf.to_bytes(), template())
    assert_same(buf, loaded)
    some = loaded.get(loaded.ids[:1])
    assert loaded.insert_batch(some, [2.0]).status[0] == 2  # duplicate index was rebuilt


def test_empty_buffer_round_trip():
    buf = LevelBuffer(template(), capacity=3, seed=5)
    assert_same(buf, LevelBuffer.from_bytes(buf.to_bytes()))


def test_load_without_template_gives_dicts_by_key_path(tmp_path):
    buf = filled()
    path = buf.save(tmp_path / "b.msgpack")
    loaded = LevelBuffer.load(path)
    assert loaded.spec.paths == ("arena", "kind", "units.alive", "units.hp", "units.pos")
    level = loaded.get_level(int(loaded.ids[0]))
    assert set(level) == set(loaded.spec.paths)
    original = buf.get_level(int(buf.ids[0]))
    np.testing.assert_array_equal(level["units.pos"], original["units"]["pos"])
    assert level["kind"].dtype == np.int64  # host dtypes survive (no jax 32-bit demotion)
    # Template-free buffers still work: insert dicts keyed by path.
    more = loaded.get(loaded.ids[:2])
    assert set(more) == set(loaded.spec.paths)
    assert (loaded.insert_batch(more, [9.0, 9.0]).status == 2).all()


def test_overwrite_keeps_old_file_until_replaced(tmp_path):
    path = tmp_path / "b.msgpack"
    filled(seed=1).save(path)
    buf = filled(seed=2)
    buf.save(path)
    assert_same(buf, LevelBuffer.load(path, template()))


def test_every_truncation_is_refused(tmp_path):
    data = filled(capacity=4, n_batches=1).to_bytes()
    for cut in range(len(data)):
        with pytest.raises(BufferFileError):
            LevelBuffer.from_bytes(data[:cut], name="cut.msgpack")
    with pytest.raises(BufferFileError, match="trunc.msgpack: .*truncated"):
        path = tmp_path / "trunc.msgpack"
        path.write_bytes(data[: len(data) // 2])
        LevelBuffer.load(path)


def test_every_flipped_byte_is_refused():
    data = filled(capacity=4, n_batches=1).to_bytes()
    for pos in range(len(data)):
        bad = bytearray(data)
        bad[pos] ^= 0xFF
        with pytest.raises(BufferFileError):
            LevelBuffer.from_bytes(bytes(bad), name="flip.msgpack")


def test_corrupted_payload_names_file_and_checksum(tmp_path):
    data = bytearray(filled().to_bytes())
    data[len(data) // 2] ^= 0x01
    path = tmp_path / "corrupt.msgpack"
    path.write_bytes(bytes(data))
    with pytest.raises(BufferFileError) as info:
        LevelBuffer.load(path, template())
    assert str(path) in str(info.value) and "checksum" in str(info.value)
    assert isinstance(info.value, ValueError) and info.value.path == str(path)


def test_structure_mismatch_is_refused(tmp_path):
    path = filled().save(tmp_path / "b.msgpack")
    wrong_shape = template()
    wrong_shape["units"]["hp"] = np.zeros(4, np.float32)
    with pytest.raises(BufferFileError, match=r"b.msgpack: .*'units.hp'.*shape \(3,\)"):
        LevelBuffer.load(path, wrong_shape)
    wrong_dtype = template()
    wrong_dtype["arena"] = np.zeros(2, np.float32)
    with pytest.raises(BufferFileError, match="'arena'.*float64"):
        LevelBuffer.load(path, wrong_dtype)
    missing = template()
    del missing["kind"]
    with pytest.raises(BufferFileError, match=r"file leaves not in the template: \['kind'\]"):
        LevelBuffer.load(path, missing)
    extra = template()
    extra["new"] = np.zeros(1)
    with pytest.raises(BufferFileError, match="missing from the file: \\['new'\\]"):
        LevelBuffer.load(path, extra)


def _rewrap(data: bytes, **changes) -> bytes:
    outer = msgpack.unpackb(data, raw=False)
    outer.update(changes)
    return msgpack.packb(outer, use_bin_type=True)


def test_other_files_are_refused(tmp_path):
    data = filled().to_bytes()
    with pytest.raises(BufferFileError, match="newer version"):
        LevelBuffer.from_bytes(_rewrap(data, format_version=FORMAT_VERSION + 1))
    with pytest.raises(BufferFileError, match="wrong magic"):
        LevelBuffer.from_bytes(_rewrap(data, magic="something-else"))
    with pytest.raises(BufferFileError, match="wrong magic"):
        LevelBuffer.from_bytes(msgpack.packb([1, 2, 3]))
    with pytest.raises(BufferFileError, match="not a readable"):
        LevelBuffer.from_bytes(b"")
    with pytest.raises(BufferFileError, match="cannot read"):
        LevelBuffer.load(tmp_path / "missing.msgpack")
    assert MAGIC in data.decode("latin-1")


def test_inconsistent_contents_with_valid_checksum_are_refused():
    """A file rewritten by a buggy tool (valid checksum, bad content) is still refused."""
    import hashlib

    buf = filled()
    data = buf.to_bytes()
    outer = msgpack.unpackb(data, raw=False)
    header = msgpack.unpackb(outer["header"], raw=False)
    header["clock"] = 0  # timestamps now lie in the future
    hb = msgpack.packb(header, use_bin_type=True)
    outer.update(header=hb, sha256=hashlib.sha256(hb + outer["payload"]).hexdigest())
    with pytest.raises(BufferFileError, match="beyond the clock"):
        LevelBuffer.from_bytes(msgpack.packb(outer, use_bin_type=True))


def test_full_4000_buffer_save_load_is_fast(tmp_path):
    import time

    from tabx_bench.level_buffer import random_levels, toy_level

    rng = np.random.default_rng(0)
    buf = LevelBuffer(toy_level(), capacity=4000)
    for _ in range(8):
        buf.insert_batch(random_levels(rng, 500, toy_level()), rng.random(500),
                         sources=Source.RANDOM)
    assert buf.size == 4000
    path = tmp_path / "big.msgpack"
    t0 = time.perf_counter()
    buf.save(path)
    t1 = time.perf_counter()
    loaded = LevelBuffer.load(path, toy_level())
    t2 = time.perf_counter()
    assert_same(buf, loaded)
    # Measured ~30 ms each; a loose bound so a busy CI machine does not flake.
    assert t1 - t0 < 1.0 and t2 - t1 < 1.0, (t1 - t0, t2 - t1)
    assert os.path.getsize(path) < 8 * 2**20
