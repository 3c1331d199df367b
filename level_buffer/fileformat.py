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

`read_file` reads a file only when it is a regular file whose size is what its outer map
declares, and whose payload is no bigger than a buffer of its header's capacity can be: a FIFO,
a device (`/dev/zero`) or a huge sparse file is refused after reading at most the header
(MAX_HEADER_BYTES), never read whole.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from typing import IO, Any

import msgpack
import numpy as np

from level_buffer.config import BufferConfig
from level_buffer.state import SLOT_FIELDS, STAT_NAMES, BufferState
from level_buffer.tree import LevelSpec

MAGIC = "tabx-level-buffer"
FORMAT_VERSION = 1
BIT_GENERATORS = ("PCG64", "PCG64DXSM", "Philox", "SFC64", "MT19937")
# The header holds names, shapes, the config and the RNG state: a few kB. A bigger one is
# refused before it is read.
MAX_HEADER_BYTES = 1 << 20
# Room for the payload's own msgpack framing (map, array and bin headers, field names).
_PAYLOAD_FRAMING = 1024


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


def _file_kind(mode: int) -> str:
    for test, kind in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a regular file"


def read_file(path: str | os.PathLike) -> bytes:
    """The bytes of a level-buffer file, read only after its layout says they fit.

    BufferFileError(path, ...) for a missing or non-regular file (checked before it is opened,
    so a FIFO never blocks), a size other than its outer map declares (truncated or padded),
    a header over MAX_HEADER_BYTES, or a payload bigger than a buffer of the header's
    capacity and leaves can be."""
    try:
        mode = os.stat(path).st_mode
    except OSError as err:
        raise BufferFileError(path, f"cannot read: {err.strerror or err}") from err
    if not stat.S_ISREG(mode):
        raise BufferFileError(path, f"cannot read: {_file_kind(mode)}, not a level-buffer file")
    try:
        # O_NONBLOCK: should the path become a FIFO after the check, open does not wait.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as err:
        raise BufferFileError(path, f"cannot read: {err.strerror or err}") from err
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise BufferFileError(path, f"cannot read: {_file_kind(info.st_mode)}, not a "
                                  f"level-buffer file")
        size = info.st_size
        try:
            bins, values = _outer_layout(f, size)
        except ValueError as err:
            raise BufferFileError(path, f"not a readable level-buffer file (truncated or "
                                  f"corrupted msgpack: {err})") from None
        _check_payload_size(f, bins, values, path)
        f.seek(0)
        data = f.read(size)
    if len(data) != size:
        raise BufferFileError(path, f"cannot read: the file changed while it was read "
                              f"({len(data)} of {size} bytes)")
    return data


def _take(f: IO[bytes], n: int) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise ValueError("truncated")
    return data


def _length(f: IO[bytes], width: int) -> int:
    return int.from_bytes(_take(f, width), "big")


def _outer_layout(f: IO[bytes], size: int
                  ) -> tuple[dict[str, tuple[int, int]], dict[str, Any]]:
    """({key: (offset, length)} of the outer map's bin values, {key: value} of the others),
    found by reading the map's framing and seeking past every bin; ValueError unless the map
    ends exactly at `size`."""
    if size == 0:
        raise ValueError("the file is empty")
    first = _take(f, 1)[0]
    if 0x80 <= first <= 0x8F:
        entries = first & 0x0F
    elif first in (0xDE, 0xDF):
        entries = _length(f, 2 if first == 0xDE else 4)
    else:
        raise ValueError(f"expected a map, found type byte 0x{first:02x}")
    if entries > 16:
        raise ValueError(f"an outer map of {entries} entries")
    bins: dict[str, tuple[int, int]] = {}
    values: dict[str, Any] = {}
    for _ in range(entries):
        key = _small_value(f)
        if not isinstance(key, str):
            raise ValueError("an outer map key that is not a string")
        byte = _take(f, 1)[0]
        if byte in (0xC4, 0xC5, 0xC6):  # bin 8/16/32: skipped, not read
            length = _length(f, {0xC4: 1, 0xC5: 2, 0xC6: 4}[byte])
            offset = f.tell()
            if offset + length > size:
                raise ValueError(f"{key!r} declares {length} bytes; the file is {size} bytes")
            bins[key] = (offset, length)
            f.seek(offset + length)
        else:
            f.seek(-1, os.SEEK_CUR)
            values[key] = _small_value(f)
    end = f.tell()
    if end != size:
        raise ValueError(f"the map ends at byte {end} of {size}: extra data")
    return bins, values


def _small_value(f: IO[bytes]) -> Any:
    """One scalar or short string of the outer map (magic, version, digest, keys)."""
    byte = _take(f, 1)[0]
    if byte <= 0x7F or byte >= 0xE0:  # positive and negative fixint
        return byte if byte <= 0x7F else byte - 0x100
    if 0xA0 <= byte <= 0xBF or byte in (0xD9, 0xDA):  # fixstr, str 8, str 16
        length = byte & 0x1F if byte <= 0xBF else _length(f, 1 if byte == 0xD9 else 2)
        return _take(f, length).decode("utf-8", "replace")
    widths = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8, 0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}
    if byte in widths:
        return _length(f, widths[byte])
    if byte in (0xC0, 0xC2, 0xC3):  # nil, false, true
        return None
    raise ValueError(f"unexpected type byte 0x{byte:02x} in the outer map")


def _check_payload_size(f: IO[bytes], bins: dict[str, tuple[int, int]],
                        values: dict[str, Any], path: str | os.PathLike) -> None:
    """Refuse a payload bigger than a buffer of the header's capacity and leaves can be,
    reading only the header. A header that gives no bound is damaged: the checksum (computed
    in pieces, never holding the payload) or the header's own problem says how."""
    if "header" not in bins or "payload" not in bins or values.get("magic") != MAGIC:
        return  # not a level-buffer file: `read_header` says so without the payload
    offset, length = bins["header"]
    if length > MAX_HEADER_BYTES:
        raise BufferFileError(path, f"not a level-buffer file: a header of {length} bytes (at "
                              f"most {MAX_HEADER_BYTES})")
    f.seek(offset)
    try:
        header = msgpack.unpackb(f.read(length), raw=False)
        capacity = _get(header, "capacity", int, "header")
        leaves = _get(header, "leaves", list, "header")
        fields = _get(header, "slot_fields", list, "header")
        per_level = sum(int(np.prod(leaf["shape"], dtype=np.int64))
                        * np.dtype(str(leaf["dtype"])).itemsize for leaf in leaves)
        per_level += sum(np.dtype(str(field["dtype"])).itemsize for field in fields)
        # a bin header per leaf and per field, and the fields' names
        framing = _PAYLOAD_FRAMING + 16 * (len(leaves) + len(fields))
        framing += sum(len(str(field["name"])) for field in fields)
    except Exception as err:  # noqa: BLE001 (msgpack and numpy raise many kinds)
        digest = hashlib.sha256()
        for start, length in (bins["header"], bins["payload"]):
            f.seek(start)
            while length > 0:
                chunk = f.read(min(length, 1 << 20))
                if not chunk:
                    break
                digest.update(chunk)
                length -= len(chunk)
        if digest.hexdigest() != values.get("sha256"):
            raise BufferFileError(path, "checksum mismatch: the file is corrupted") from None
        raise BufferFileError(path, f"header: {err}") from None
    bound = max(capacity, 0) * per_level + framing
    if bins["payload"][1] > bound:
        raise BufferFileError(path, f"not a level-buffer file: a payload of "
                              f"{bins['payload'][1]} bytes, more than a buffer of capacity "
                              f"{capacity} holds (at most {bound})")


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
