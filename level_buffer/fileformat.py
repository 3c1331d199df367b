"""The level-buffer file format (version 1): one msgpack map

    {"magic": "tabx-level-buffer", "format_version": 1,
     "header": <bin: msgpack map>, "payload": <bin: msgpack map>,
     "sha256": <hex sha256 of header bytes + payload bytes>}

The header holds the level leaves (key path, shape, dtype), the slot fields (name, dtype),
size, capacity, clock, next id, counters, the BufferConfig, the numpy Generator state (JSON,
since PCG64 state integers exceed 64 bits) and the payload's length. The payload holds the raw
little-endian bytes of every level leaf and slot field, filled slots only:
{"levels": [bin per leaf, header order], "slots": {name: bin}}.

`decode` checks magic, version, checksum, every length, dtype and shape, and the buffer's own
invariants before anything is built, so a bad file raises `BufferFileError` and is never
half-loaded. A template may fill leaves that the file predates (`tree.file_defaults`).
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any

import msgpack
import numpy as np

from level_buffer.config import BufferConfig
from level_buffer.state import SLOT_FIELDS, STAT_NAMES, BufferState
from level_buffer.tree import LevelSpec

MAGIC = "tabx-level-buffer"
FORMAT_VERSION = 1
BIT_GENERATORS = ("PCG64", "PCG64DXSM", "Philox", "SFC64", "MT19937")


class BufferFileError(ValueError):
    """A level-buffer file that cannot be used: missing, truncated, corrupted, from a newer
    format, or not matching the template. `str()` names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def make_rng(state: dict[str, Any]) -> np.random.Generator:
    """A numpy Generator restored from `bit_generator.state` (as stored in a file)."""
    name = state.get("bit_generator") if isinstance(state, dict) else None
    if name not in BIT_GENERATORS:
        raise ValueError(f"unsupported bit generator {name!r}; expected one of {BIT_GENERATORS}")
    bit_gen = getattr(np.random, name)()
    bit_gen.state = state
    return np.random.Generator(bit_gen)


def _le(arr: np.ndarray) -> bytes:
    """Raw little-endian bytes (the file format is little-endian on every host)."""
    return np.ascontiguousarray(arr, arr.dtype.newbyteorder("<")).tobytes()


def encode(state: BufferState) -> bytes:
    """The file bytes of a `BufferState`."""
    payload = msgpack.packb({
        "levels": [_le(x) for x in state.levels],
        "slots": {name: _le(state.slots[name]) for name in SLOT_FIELDS},
    }, use_bin_type=True)
    spec = state.spec
    leaves = [{"path": p, "shape": list(s), "dtype": d.newbyteorder("<").str}
              for p, s, d in zip(spec.paths, spec.shapes, spec.dtypes, strict=True)]
    header = msgpack.packb({
        "leaves": leaves,
        "slot_fields": [{"name": k, "dtype": d.newbyteorder("<").str}
                        for k, (d, _) in SLOT_FIELDS.items()],
        "size": state.size,
        "capacity": state.config.capacity,
        "clock": state.clock,
        "next_id": state.next_id,
        "stats": state.stats,
        "config": state.config.to_dict(),
        "rng_state": json.dumps(state.rng_state),
        "payload_bytes": len(payload),
    }, use_bin_type=True)
    return msgpack.packb({
        "magic": MAGIC,
        "format_version": FORMAT_VERSION,
        "header": header,
        "payload": payload,
        "sha256": hashlib.sha256(header + payload).hexdigest(),
    }, use_bin_type=True)


def _get(mapping: Any, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if not isinstance(mapping, dict) or key not in mapping:
        raise ValueError(f"{where} has no {key!r} entry")
    value = mapping[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"{where} entry {key!r} has the wrong type {type(value).__name__}")
    return value


def _array(data: Any, dtype: np.dtype, shape: tuple[int, ...], what: str) -> np.ndarray:
    if not isinstance(data, bytes):
        raise ValueError(f"{what}: expected raw bytes")
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(data) != expected:
        raise ValueError(f"{what}: {len(data)} bytes, expected {expected} for shape {shape} "
                         f"dtype {dtype}")
    return np.frombuffer(data, dtype.newbyteorder("<")).astype(dtype).reshape(shape)


def read_header(data: bytes, name: str) -> tuple[dict[str, Any], bytes]:
    """Check magic, version and checksum; the decoded header and the raw payload."""
    try:
        outer = msgpack.unpackb(data, raw=False)
    except Exception as err:  # msgpack raises several types for truncated or garbled input
        raise BufferFileError(name, f"not a readable level-buffer file (truncated or "
                              f"corrupted msgpack: {err})") from err
    try:
        if not isinstance(outer, dict) or outer.get("magic") != MAGIC:
            raise ValueError("not a level-buffer file (wrong magic)")
        version = _get(outer, "format_version", int, "file")
        if version != FORMAT_VERSION:
            newer = " (written by a newer version)" if version > FORMAT_VERSION else ""
            raise ValueError(f"unsupported format version {version}{newer}; this reader "
                             f"supports version {FORMAT_VERSION}")
        header_bytes = _get(outer, "header", bytes, "file")
        payload = _get(outer, "payload", bytes, "file")
        digest = _get(outer, "sha256", str, "file")
        if hashlib.sha256(header_bytes + payload).hexdigest() != digest:
            raise ValueError("checksum mismatch: the file is corrupted")
        header = msgpack.unpackb(header_bytes, raw=False)
        if not isinstance(header, dict):
            raise ValueError("header is not a map")
        if _get(header, "payload_bytes", int, "header") != len(payload):
            raise ValueError("payload length does not match the header")
    except BufferFileError:
        raise
    except Exception as err:
        raise BufferFileError(name, str(err)) from err
    return header, payload


def decode(data: bytes, name: str, template_level: Any = None) -> Any:
    """A validated `BufferState` from file bytes; BufferFileError(name, ...) on any problem."""
    header, payload_bytes = read_header(data, name)
    try:
        spec = LevelSpec.from_header(_get(header, "leaves", list, "header"))
        filled: dict[str, Any] = {}  # leaves newer than the file, at their old meaning
        if template_level is not None:
            try:
                spec, filled = spec.with_template(template_level)
            except ValueError as err:
                raise ValueError(f"does not match the template level: {err}") from err
        config = BufferConfig.from_dict(_get(header, "config", dict, "header"))
        size = _get(header, "size", int, "header")
        capacity = _get(header, "capacity", int, "header")
        clock = _get(header, "clock", int, "header")
        next_id = _get(header, "next_id", int, "header")
        if capacity != config.capacity or not 0 <= size <= capacity:
            raise ValueError(f"size {size} / capacity {capacity} inconsistent with the config")
        stats = {k: int(v) for k, v in _get(header, "stats", dict, "header").items()
                 if k in STAT_NAMES}
        fields = {str(f["name"]): np.dtype(str(f["dtype"]))
                  for f in _get(header, "slot_fields", list, "header")}
        if set(fields) != set(SLOT_FIELDS):
            raise ValueError(f"slot fields {sorted(fields)} differ from {sorted(SLOT_FIELDS)}")
        rng_state = json.loads(_get(header, "rng_state", str, "header"))
        make_rng(rng_state)  # validate now, not after the buffer is half built

        payload = msgpack.unpackb(payload_bytes, raw=False)
        raw_levels = _get(payload, "levels", list, "payload")
        stored = len(spec.paths) - len(filled)
        if len(raw_levels) != stored:
            raise ValueError(f"payload has {len(raw_levels)} level leaves, header {stored}")
        levels = [_array(b, d, (size, *s), f"level leaf {p!r}")
                  for b, p, s, d in zip(raw_levels, spec.paths, spec.shapes, spec.dtypes,
                                        strict=False)]
        levels += [np.full((size, *s), filled[p], d)
                   for p, s, d in zip(spec.paths[stored:], spec.shapes[stored:],
                                      spec.dtypes[stored:], strict=True)]
        raw_slots = _get(payload, "slots", dict, "payload")
        slots = {}
        for k, (dtype, _) in SLOT_FIELDS.items():
            arr = _array(raw_slots.get(k), fields[k], (size,), f"slot field {k!r}")
            slots[k] = arr.astype(dtype)
        ids = slots["level_id"]
        if np.unique(ids).size != size or (size and (ids.min() < 0 or ids.max() >= next_id)):
            raise ValueError("level ids are not unique, negative or beyond next_id")
        if size and (slots["timestamp"].max() > clock):
            raise ValueError("a timestamp lies beyond the clock")
        if np.isnan(slots["score"]).any():
            raise ValueError("a score is NaN")
    except BufferFileError:
        raise
    except Exception as err:
        raise BufferFileError(name, str(err)) from err
    # The template's treedef orders the output; the file's leaf order is kept for storage.
    return BufferState(spec, config, size, clock, next_id, {**dict.fromkeys(STAT_NAMES, 0),
                                                             **stats},
                       rng_state, levels, slots)
