"""The level service's commit log: a restart (the constructor again, same arguments) restores
every acknowledged commit and applies none twice; a torn last record is cut off; another
session's log is set aside, not replayed. Runs in this process (Ray is not needed: a restart
is the constructor running again over the same folder).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_ued_train import ued_config

from level_buffer.commit_log import CommitLog, CommitLogError, read
from workers.ray.actors import LevelServiceActor
from workers.ray.durable_service import LOG_NAME

# --- the log file --------------------------------------------------------------------------

arrays = st.builds(
    lambda dtype, shape, seed: np.asarray(np.random.default_rng(seed).normal(size=shape),
                                          dtype=dtype),
    st.sampled_from(["float32", "float64", "int8", "int64", "bool", "uint16"]),
    st.lists(st.integers(0, 3), max_size=3).map(tuple), st.integers(0, 2**31))
values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**62, 2**62) | st.floats(allow_nan=False)
    | st.text(max_size=8) | arrays,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                  max_size=3),
    max_leaves=8)


def same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and np.array_equal(a, b))
    if isinstance(a, list | tuple):
        return isinstance(b, list) and len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return a == b and type(a) is type(b)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(records=st.lists(values, max_size=6), cut=st.integers(0, 10**6))
def test_log_reads_back_its_records_and_any_truncation_keeps_a_prefix(tmp_path, records, cut):
    path = tmp_path / "a.log"
    log = CommitLog.create(path, base=3)
    header_bytes = path.stat().st_size
    for record in records:
        log.append(record)
    log.close()
    contents = read(path)
    assert contents.header == {"base": 3} and not contents.torn
    assert len(contents.records) == len(records)
    assert all(same(a, b) for a, b in zip(records, contents.records, strict=True))
    data = path.read_bytes()
    cut = cut % (len(data) + 1)
    path.write_bytes(data[:cut])
    try:
        kept = read(path)
    except CommitLogError:  # the header itself was cut
        assert cut < header_bytes
        return
    n = len(kept.records)
    assert all(same(a, b) for a, b in zip(records[:n], kept.records, strict=True))
    assert kept.torn == (cut > kept.intact_bytes)
    reopened, _ = CommitLog.reopen(path)  # appending after a torn tail cuts it off first
    reopened.append("next")
    reopened.close()
    assert same(read(path).records, [*records[:n], "next"])


def test_a_flipped_byte_ends_the_log_there_and_a_file_of_another_kind_is_refused(tmp_path):
    path = tmp_path / "a.log"
    log = CommitLog.create(path)
    for i in range(3):
        log.append({"i": i})
    log.close()
    data = bytearray(path.read_bytes())
    data[-3] ^= 0xFF  # inside the last record
    path.write_bytes(bytes(data))
    assert [r["i"] for r in read(path).records] == [0, 1] and read(path).torn
    other = tmp_path / "b.log"
    other.write_bytes(b"\x05\x00\x00\x00" + b"\x00" * 4 + b"hello")
    with pytest.raises(CommitLogError, match="b.log"):
        read(other)


# --- the service ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def config():
    return ued_config("accel", **{"ued.buffer_size": 16, "ued.min_fill_ratio": 0.25})


def work(service, key, steps: int, start: int = 0) -> list:
    """A run's worth of state-changing calls (numbered, as the driver sends them); returns
    what they answered."""
    out = []
    for step in range(start, start + steps):
        k = jax.random.fold_in(key, step)
        if service.sample_replay_decision():
            replay = service.replay(4)
            service.update(replay.ids, np.linspace(0, 1, 4) + step, np.ones(4), step)
            out.append(replay.ids.tolist())
            children = service.mutate(k, replay.levels)
            out.append(service.insert(children, np.full(4, 0.5 + step), np.ones(4), step, 1,
                                      replay.ids).status.tolist())
        else:
            levels = service.fresh(k, 4)
            out.append(service.insert(levels, np.arange(4.0) * step, np.ones(4), step,
                                      0).status.tolist())
    return out


def test_a_restarted_service_has_every_commit_and_continues_as_if_it_had_not_died(tmp_path,
                                                                                    config):
    folder = tmp_path / "levels"
    key = jax.random.key(3)
    alive = LevelServiceActor(config, str(folder), "run-a")
    work(alive, key, 5)
    alive.save(str(folder), 5, {"step": 5})  # a snapshot; the log starts again after it
    work(alive, key, 4, start=5)
    assert sorted(p.name for p in folder.glob("commits-*")) == [LOG_NAME.format(5)]

    restarted = LevelServiceActor(config, str(folder), "run-a")  # what Ray's restart does
    assert restarted.restored == (5, len(read(folder / LOG_NAME.format(5)).records))
    assert restarted.seq == alive.seq
    assert restarted.buffer.to_bytes() == alive.buffer.to_bytes()
    assert work(restarted, key, 6, start=9) == work(alive, key, 6, start=9)
    assert restarted.buffer.to_bytes() == alive.buffer.to_bytes()


def test_a_call_sent_again_after_a_restart_is_answered_not_applied_twice(tmp_path, config):
    folder = tmp_path / "levels"
    service = LevelServiceActor(config, str(folder), "run-a")
    levels = service.fresh(jax.random.key(0), 4)
    first = service.apply(1, "insert", levels, np.arange(4.0), np.ones(4), 0, 0)
    attempts = service.buffer.stats["insert_attempts"]
    restarted = LevelServiceActor(config, str(folder), "run-a")
    again = restarted.apply(1, "insert", levels, np.arange(4.0), np.ones(4), 0, 0)
    assert again.ids.tolist() == first.ids.tolist()
    assert restarted.buffer.stats["insert_attempts"] == attempts == 4
    with pytest.raises(RuntimeError, match="call 1 is update"):
        restarted.apply(1, "update", first.ids, np.zeros(4), np.ones(4), 0)
    with pytest.raises(RuntimeError, match="missing"):
        restarted.apply(5, "replay", 2)


def test_a_group_commit_applies_its_calls_in_order_with_one_fsync(tmp_path, config,
                                                                   monkeypatch):
    # Three numbered inserts in one call (their levels passed flat, as Ray resolves them): one
    # fsync for the group; a restart has all three; the group sent again is answered from the
    # first application, one already applied call inside it too.
    from workers.ray.durable_service import Slot

    folder = tmp_path / "levels"
    service = LevelServiceActor(config, str(folder), "run-a")
    syncs = []
    sync = CommitLog.sync
    monkeypatch.setattr(CommitLog, "sync", lambda self: (syncs.append(1), sync(self)))
    batches = [service.fresh(jax.random.key(i), 4) for i in range(3)]
    first = service.apply(1, "insert", batches[0], np.arange(4.0), np.ones(4), 0, 0)
    assert len(syncs) == 1
    calls = [(seq, "insert", (Slot(i), np.arange(4.0) + seq, np.ones(4), 0, 0), {})
             for i, seq in enumerate((1, 2, 3))]
    results = service.apply_many(calls, *batches)
    assert len(syncs) == 2 and service.seq == 3
    assert results[0].ids.tolist() == first.ids.tolist()  # call 1: answered, not applied again
    assert service.buffer.stats["insert_attempts"] == 12
    restarted = LevelServiceActor(config, str(folder), "run-a")
    assert restarted.seq == 3 and restarted.buffer.stats["insert_attempts"] == 12
    again = restarted.apply_many(calls, *batches)
    assert [r.ids.tolist() for r in again] == [r.ids.tolist() for r in results]
    assert restarted.buffer.stats["insert_attempts"] == 12


def test_a_torn_last_record_is_an_unacknowledged_call_and_is_cut_off(tmp_path, config):
    folder = tmp_path / "levels"
    service = LevelServiceActor(config, str(folder), "run-a")
    work(service, jax.random.key(1), 3)
    before = service.buffer.to_bytes()
    levels = service.fresh(jax.random.key(9), 4)
    service.insert(levels, np.full(4, 9.0), np.ones(4), 3, 0)
    path = folder / LOG_NAME.format(0)
    path.write_bytes(path.read_bytes()[:-5])  # killed in the middle of the last append
    restarted = LevelServiceActor(config, str(folder), "run-a")
    assert restarted.buffer.to_bytes() == before and restarted.seq == service.seq - 1
    assert not read(path).torn  # cut off before appending again


def test_another_sessions_log_is_set_aside_not_replayed(tmp_path, config):
    folder = tmp_path / "levels"
    old = LevelServiceActor(config, str(folder), "run-a")
    work(old, jax.random.key(1), 3)
    resumed = LevelServiceActor(config, str(folder), "run-b")  # a new session of the run
    assert resumed.restored is None and len(resumed.buffer) == 0
    aside = list((tmp_path / "set-aside").rglob(LOG_NAME.format(0)))
    assert len(aside) == 1 and read(aside[0]).header["session"] == "run-a"
    assert read(folder / LOG_NAME.format(0)).header["session"] == "run-b"
