"""Safe file writing: every file the project writes goes through `atomic_write_*`, so a crash or
a full disk never leaves a half-written scenario, buffer or config behind (temp file in the same
folder, fsync, rename, fsync of the folder).

The rename only ever lands on a missing or regular file. A symlink keeps its link: its target is
replaced. A character device, pipe or socket (`/dev/stdout`, `/dev/null`, a FIFO, `>(cmd)`) is
written through, as any tool writes to it; a directory or block device is refused. Errors on that
path are `OutputError`s, one line naming the path."""

from __future__ import annotations

import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any

from tabx.errors import UserError


class OutputError(UserError):
    """An output path that cannot take the file (a directory, a block device, a full device)."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically; the old file (if any) stays intact until the rename.

    Special files are written through (see the module docstring); returns `path`."""
    path = Path(path)
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
    target = path
    if path.is_symlink():
        real = Path(os.path.realpath(path))
        if real.parts[1:2] == ("proc",):
            # /dev/stdout and /dev/fd/N resolve through /proc to an open file: replacing that
            # path would swap the file under the process holding it; write into it instead.
            _write_through(path, data)
            return path
        target = real  # replace the link's target; the link stays a link
    _replace(target, data)
    return path


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


__all__ = ["OutputError", "atomic_write_bytes", "atomic_write_json", "atomic_write_text"]
