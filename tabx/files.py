"""Safe file writing: every file the project writes goes through `atomic_write_*`, so a crash or
a full disk never leaves a half-written scenario, buffer or config behind (temp file in the same
folder, fsync, rename, fsync of the folder).

The rename only ever lands on a missing or regular file. A symlink keeps its link: its target is
replaced. One of this process's open files by name (`/dev/stdout`, `/dev/fd/3`, `>(cmd)`) is
written to at its place in the stream, after what Python has buffered for it; a character
device, pipe or socket by name (`/dev/null`, a FIFO) is written through, as any tool writes to
it; a directory or block device is refused. Errors on those paths are `OutputError`s, one line
naming the path."""

from __future__ import annotations

import json
import os
import re
import stat
import sys
import tempfile
from pathlib import Path
from typing import Any

from tabx.errors import UserError

# A name for one of this process's open files: /dev/stdout, /dev/fd/N, /proc/self/fd/N.
_OPEN_FILE = re.compile(r"/dev/(stdout|stderr)|/dev/fd/(\d+)|/proc/(self|\d+)/fd/(\d+)")
_STD_FDS = {"stdout": 1, "stderr": 2}


class OutputError(UserError):
    """An output path that cannot take the file (a directory, a block device, a full device)."""


def not_a_file(path: str | os.PathLike) -> str | None:
    """None where `path` is a regular file (through any links), else what it is, for a
    message: "missing", "a broken symbolic link", "a folder", "a character device", ..."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a broken symbolic link" if os.path.islink(path) else "missing"
    except OSError as err:
        return f"unreadable ({err.strerror or err})"
    if stat.S_ISREG(mode):
        return None
    for test, kind in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return f"{kind}, not a file" + (" (through a symbolic link)"
                                            if os.path.islink(path) else "")
    return "not a regular file"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically; the old file (if any) stays intact until the rename.

    Special files are written through (see the module docstring); returns `path`."""
    path = Path(path)
    fd = _open_file(path)
    if fd is not None:
        _write_fd(path, fd, data)
        return path
    try:
        mode = os.stat(path).st_mode  # follows symlinks: what a write would land on
    except FileNotFoundError:
        mode = None
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from None
    if mode is not None and not stat.S_ISREG(mode):
        if stat.S_ISCHR(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode):
            _write_through(path, data)
            return path
        kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
        raise OutputError(f"cannot write {path}: it is {kind}")
    # A link's target is replaced; the link stays a link.
    _replace(Path(os.path.realpath(path)) if path.is_symlink() else path, data)
    return path


def _open_file(path: Path) -> int | None:
    """The descriptor `path` names, following its links (`/dev/stdout` -> /proc/self/fd/1),
    when it is one of this process's open files; None otherwise."""
    for _ in range(40):  # the kernel's own limit on a chain of links
        found = _OPEN_FILE.fullmatch(str(path))
        if found:
            std, fd, pid, proc_fd = found.groups()
            if pid is not None and pid not in ("self", str(os.getpid())):
                return None
            number = _STD_FDS[std] if std else int(fd if fd is not None else proc_fd)
            try:
                os.fstat(number)
            except OSError:
                return None
            return number
        if not path.is_symlink():
            return None
        path = path.parent / os.readlink(path)
    return None


def _write_fd(path: Path, fd: int, data: bytes) -> None:
    """Write at the stream's place: what Python buffered for it first, then `data`."""
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None and stream.fileno() == fd:
                stream.flush()
        except (AttributeError, OSError, ValueError):  # replaced or closed streams
            pass
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from None


def _write_through(path: Path, data: bytes) -> None:
    """A plain open and write, for outputs a rename must not replace."""
    try:
        with open(path, "wb") as f:
            f.write(data)
            f.flush()
    except OSError as err:
        raise OutputError(f"cannot write {path}: {err.strerror or err}") from None


def _replace(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates the file 0600; give it the mode a plain open() would (umask applied).
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent) + "\n")


__all__ = ["OutputError", "atomic_write_bytes", "atomic_write_json", "atomic_write_text",
           "not_a_file"]
