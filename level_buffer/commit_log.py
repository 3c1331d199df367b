"""An append-only log of records, durable one record at a time: what the level service writes
between snapshots so that a restart loses no acknowledged commit.

File layout: a sequence of frames, each

    <u32 little-endian payload length> <u32 little-endian CRC-32 of the payload> <payload>

where the payload is msgpack. The first frame is the header map
`{"magic": "tabx-commit-log", "version": 1, **fields}` (the writer's own fields: for the level
service, the snapshot step the log continues and the session that wrote it). Every later frame
is one record. Numpy arrays travel as msgpack extension type 1 (dtype, shape, raw bytes) and
come back as arrays of the same dtype and shape; tuples come back as lists.

`append` returns once the frame is on disk (flush + fsync): a record that `append` acknowledged
survives a SIGKILL of the writer. A group commit appends several records with `sync=False` and
makes them durable with one `sync` before any of them is acknowledged. A crash in the middle
of an append leaves a torn last frame; `read` stops at the first frame that is short or fails
its CRC and reports how many bytes it kept, and `CommitLog.reopen` truncates the file there
before appending again.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

MAGIC = "tabx-commit-log"
VERSION = 1
_FRAME = struct.Struct("<II")
_NDARRAY = 1  # msgpack extension type of a numpy array
MAX_RECORD_BYTES = 1 << 31  # a length beyond this is damage, not a record


class CommitLogError(ValueError):
    """A commit log that cannot be used (no header, not a commit log, a newer version).
    `str()` names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path, self.problem = str(path), problem
        super().__init__(f"{self.path}: {problem}")


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise TypeError("object arrays cannot be logged")
        little = obj.astype(obj.dtype.newbyteorder("<"), copy=False)
        return msgpack.ExtType(_NDARRAY, msgpack.packb(
            [little.dtype.str, list(obj.shape), little.tobytes(order="C")], use_bin_type=True))
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot log a {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != _NDARRAY:
        return msgpack.ExtType(code, data)
    dtype, shape, raw = msgpack.unpackb(data, raw=False)
    return np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape).copy()


def pack(value: Any) -> bytes:
    """msgpack bytes of `value` (numpy arrays and scalars allowed)."""
    return msgpack.packb(value, default=_default, use_bin_type=True)


def unpack(data: bytes) -> Any:
    return msgpack.unpackb(data, ext_hook=_ext_hook, raw=False, strict_map_key=False)


def frame(payload: bytes) -> bytes:
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


@dataclass(frozen=True)
class LogContents:
    """What `read` found: the header fields, the intact records in order, the bytes they span,
    and the file's size (larger than `intact_bytes` where the tail is torn or damaged)."""

    header: dict[str, Any]
    records: list[Any]
    intact_bytes: int
    file_bytes: int

    @property
    def torn(self) -> bool:
        return self.file_bytes > self.intact_bytes


def _frames(data: bytes) -> Iterator[tuple[bytes, int]]:
    """(payload, end offset) of each intact frame, stopping at the first damaged one."""
    offset = 0
    while offset + _FRAME.size <= len(data):
        length, crc = _FRAME.unpack_from(data, offset)
        start, end = offset + _FRAME.size, offset + _FRAME.size + length
        if length > MAX_RECORD_BYTES or end > len(data):
            return
        payload = data[start:end]
        if zlib.crc32(payload) != crc:
            return
        yield payload, end
        offset = end


def read(path: str | os.PathLike) -> LogContents:
    """The header and the intact records of the log at `path` (CommitLogError where the file
    has no intact header or is not a commit log)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise CommitLogError(path, f"unreadable ({err.strerror or err})") from None
    frames = _frames(data)
    first = next(frames, None)
    if first is None:
        raise CommitLogError(path, "no intact header frame (empty, truncated or damaged)")
    try:
        header = unpack(first[0])
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as err:
        raise CommitLogError(path, f"header does not decode ({err})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise CommitLogError(path, f"not a commit log (expected magic {MAGIC!r})")
    if header.get("version") != VERSION:
        raise CommitLogError(path, f"commit-log version {header.get('version')!r}; this "
                                   f"version of tabx-ued reads version {VERSION}")
    records, end = [], first[1]
    for payload, frame_end in frames:
        try:
            records.append(unpack(payload))
        except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
            break  # a frame whose CRC matches but does not decode: treat as the damaged tail
        end = frame_end
    fields = {k: v for k, v in header.items() if k not in ("magic", "version")}
    return LogContents(fields, records, end, len(data))


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


class CommitLog:
    """An open log to append records to (`create` a new one, `reopen` an existing one)."""

    def __init__(self, path: Path, handle: Any, records: int):
        self.path, self._handle, self.records = path, handle, records

    @classmethod
    def create(cls, path: str | os.PathLike, **header: Any) -> CommitLog:
        """A new, empty log at `path` with these header fields (written durably: the file and
        its directory entry are fsynced). An existing file there is replaced."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "wb") as f:
            f.write(frame(pack({"magic": MAGIC, "version": VERSION, **header})))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
        return cls(path, open(path, "ab"), 0)

    @classmethod
    def reopen(cls, path: str | os.PathLike) -> tuple[CommitLog, LogContents]:
        """The log at `path` opened for appending after its last intact record (a torn tail is
        cut off first), and what it holds."""
        path = Path(path)
        contents = read(path)
        if contents.torn:
            with open(path, "r+b") as f:
                f.truncate(contents.intact_bytes)
                f.flush()
                os.fsync(f.fileno())
        return cls(path, open(path, "ab"), len(contents.records)), contents

    def append(self, record: Any, sync: bool = True) -> None:
        """Write one record; returns when it is on disk. `sync=False`: written but not yet
        durable, until the next `sync` (group commit: one fsync for several records)."""
        self._handle.write(frame(pack(record)))
        self.records += 1
        if sync:
            self.sync()

    def sync(self) -> None:
        """Make every record written so far durable (flush + fsync)."""
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def close(self) -> None:
        if not self._handle.closed:
            self._handle.close()


__all__ = ["MAGIC", "VERSION", "CommitLog", "CommitLogError", "LogContents", "pack", "read",
           "unpack"]
