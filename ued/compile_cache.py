"""JAX's persistent compilation cache for training and evaluation runs.

A learner's update takes 10-12 s to compile on a 2-core CPU (MAPPO on crossfire), and the run
pays it again whenever it starts: `--resume` after a crash or a pre-emption, the same config
with another seed, `tabx eval` of a run. With the cache on, the compiled executable is stored
on disk (under 1 MB for that update) and a later process with the same program loads it
instead: MAPPO's first update went from 23.4 s to 12.7 s (docs/learners.md, "Compilation
cache"). The cached executable is the one XLA compiled, so results are the same bit for bit.

`tabx train` turns it on unless the config says `run.compile_cache: false`; `tabx eval` always.
The folder is `$TABX_COMPILE_CACHE_DIR` (default `~/.cache/tabx/xla`), `off` disables it for
every command. Nothing is evicted (JAX's size limit needs the `filelock` package, which we do
not depend on for this): the folder grows by about 1 MB per distinct program (a config, a
jaxlib version) and can be deleted at any time. Benchmarks (`tabx bench`) never turn it on:
they measure cold compiles.

JAX writes cache entries in place, not atomically: an entry cut short (a process killed while
writing it) makes later runs warn "Error reading persistent compilation cache entry" and compile
as if there were no cache (tested: nothing worse happens). Deleting the folder clears it.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import jax

ENV_VAR = "TABX_COMPILE_CACHE_DIR"
DEFAULT_DIR = "~/.cache/tabx/xla"
# Programs that compile faster than this are not worth a disk write and a read.
MIN_COMPILE_SECONDS = 1.0


def cache_dir() -> Path | None:
    """The cache folder for this process, or None where `$TABX_COMPILE_CACHE_DIR` is `off`."""
    value = os.environ.get(ENV_VAR, "").strip()
    if value.lower() == "off":
        return None
    return Path(value or DEFAULT_DIR).expanduser()


def enable(enabled: bool = True) -> Path | None:
    """Turn the persistent cache on for this process (before anything large compiles); returns
    its folder, or None when it stays off (disabled, or the folder cannot be created or
    written: a warning, not an error, since the cache only saves time)."""
    if not enabled:
        return None
    configured = jax.config.jax_compilation_cache_dir
    if configured:  # the user's own JAX setting wins
        return Path(configured)
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
        # A folder that exists but cannot be written would fail each write, quietly.
        fd, probe = tempfile.mkstemp(dir=path, prefix=".tabx-write-check-")
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        print(f"warning: compilation cache off: cannot write into {path} ({err.strerror}); "
              f"set {ENV_VAR} to a writable folder or to 'off'", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return path


__all__ = ["DEFAULT_DIR", "ENV_VAR", "cache_dir", "enable"]
