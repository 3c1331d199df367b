"""CPU tuning for training: keep freed memory in the process instead of returning it to the OS.

An update of 128 envs x 512 steps allocates buffers of hundreds of megabytes per call (the
rollout, the minibatch activations); glibc serves each with a fresh `mmap` and unmaps it on
free, so every update pays the page faults of touching that memory again, which on a virtual
machine costs as much as the computation around it. `tune_allocator` (glibc only; a no-op
elsewhere) turns off mmap for large blocks and the trimming of the heap, so the memory of one
update is reused by the next. It changes no result, only where memory comes from; it is
called by `tabx train`, `tabx eval` and `tabx bench train`. Set TABX_KEEP_MALLOC=1 to skip it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_done = False


def tune_allocator() -> bool:
    """Apply the glibc settings once per process; True if they were applied."""
    global _done
    if _done or os.environ.get("TABX_KEEP_MALLOC") == "1" or not sys.platform.startswith(
            "linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    _done = ok
    return ok


__all__ = ["tune_allocator"]
