"""The simulator's native CPU kernels (tabx/native/*.cc): compiled once per machine with the
system's C++ compiler, cached on disk, loaded with ctypes and registered as XLA FFI targets.

Why a build at first use rather than at install: the kernels include XLA's FFI headers, which
ship with the installed jaxlib (`jax.ffi.include_dir()`), so the library is built against the
jaxlib that runs it, and `pip install` stays a plain Python install. The build takes a few
seconds, once: the library is cached under `$TABX_CACHE_DIR/native` (default
`~/.cache/tabx/native`) in a folder named by a hash of the source, the compiler command and the
jaxlib version, written atomically (temp file, rename), so processes that build at the same time
do not see each other's half-written files.

Without a working compiler, or with `TABX_NATIVE=0`, nothing is built and every kernel's caller
uses its XLA version (same results); a failed build says so once, as a warning. Only the CPU
platform uses these kernels: other platforms compile the XLA version.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shlex
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path

SOURCE_DIR = Path(__file__).parent / "native"
LIBRARY_NAME = "libtabx_native.so"
# No fast math and no FMA contraction: the kernels must round exactly as XLA:CPU does.
CXX_FLAGS = ("-std=c++17", "-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math",
             "-w")
# source file -> XLA FFI target name -> exported handler symbol
TARGETS = {"observe.cc": {"tabx_assemble_observation": "TabxAssembleObservation"}}

_lock = threading.Lock()
_state: dict[str, object] = {}


class NativeBuildError(RuntimeError):
    """The native library could not be built or loaded."""


NATIVE_OFF = ("0", "false", "no", "off")
NATIVE_ON = ("", "1", "true", "yes", "on")


def native_enabled() -> bool:
    """False when the user turned the native kernels off (`TABX_NATIVE=0`). Any other value
    than those of NATIVE_OFF and NATIVE_ON is named in one warning line (once) and leaves
    them on."""
    value = os.environ.get("TABX_NATIVE", "1").strip().lower()
    if value not in NATIVE_OFF + NATIVE_ON and not _state.get(f"warned {value}"):
        _state[f"warned {value}"] = True
        print(f"warning: TABX_NATIVE={os.environ['TABX_NATIVE']!r:.40}: expected 1 or 0 "
              "(on or off); the native kernels stay on", file=sys.stderr)
    return value not in NATIVE_OFF


def cache_dir() -> Path:
    base = os.environ.get("TABX_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "tabx")
    return Path(base) / "native"


def _compiler() -> list[str]:
    return shlex.split(os.environ.get("CXX", "c++"))


def _include_dir() -> str:
    import jax

    return jax.ffi.include_dir()


def _build_key(sources: list[Path]) -> str:
    from importlib.metadata import version

    digest = hashlib.sha256()
    for source in sources:
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    digest.update(" ".join(_compiler() + list(CXX_FLAGS)).encode())
    digest.update(version("jaxlib").encode())
    return digest.hexdigest()[:16]


def build_library(out_dir: Path | None = None) -> Path:
    """Compile tabx/native/*.cc into one shared library (or find it cached); its path."""
    sources = sorted(SOURCE_DIR / name for name in TARGETS)
    folder = (out_dir or cache_dir()) / _build_key(sources)
    library = folder / LIBRARY_NAME
    if library.is_file():
        return library
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".build-", suffix=".so", dir=folder)
    os.close(fd)
    command = [*_compiler(), *CXX_FLAGS, "-isystem", _include_dir(),
               *map(str, sources), "-o", tmp]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as err:
        Path(tmp).unlink(missing_ok=True)
        raise NativeBuildError(f"could not run the C++ compiler ({shlex.join(command)}): "
                               f"{err}") from err
    if result.returncode != 0:
        Path(tmp).unlink(missing_ok=True)
        raise NativeBuildError(f"the C++ compiler failed ({shlex.join(command)}):\n"
                               f"{result.stderr.strip()[-2000:]}")
    with open(tmp, "rb") as handle:
        os.fsync(handle.fileno())
    os.replace(tmp, library)
    return library


def _register(library: Path) -> None:
    import jax

    lib = ctypes.cdll.LoadLibrary(str(library))
    for targets in TARGETS.values():
        for target, symbol in targets.items():
            jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)),
                                        platform="cpu")
    _state["lib"] = lib  # keep the library loaded for the life of the process


def native_available() -> bool:
    """The native kernels are built, loaded and registered for the CPU (built on first call;
    False, with one warning, if that fails, or when `TABX_NATIVE=0`)."""
    if not native_enabled():
        return False
    with _lock:
        if "ok" not in _state:
            try:
                library = build_library()
                try:
                    _register(library)
                except OSError:  # a damaged cached library: build it again, once
                    library.unlink(missing_ok=True)
                    _register(build_library())
                _state["ok"] = True
            except (NativeBuildError, OSError, AttributeError) as err:
                _state["ok"] = False
                warnings.warn(f"tabx: native CPU kernels unavailable, using the XLA versions "
                              f"(same results, slower observations): {err}", stacklevel=2)
        return bool(_state["ok"])


__all__ = ["CXX_FLAGS", "NativeBuildError", "build_library", "cache_dir", "native_available",
           "native_enabled"]
