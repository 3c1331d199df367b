"""XLA:CPU tuning applied when `tabx` is imported, before JAX starts its backend.

On jaxlib 0.10 the CPU compiler routes small reductions through its experimental YNN fusion,
which is 1.5-2x slower for the (envs, units, units) reductions of this simulator (measured in
docs/benchmarks.md). We turn it off by adding one flag to XLA_FLAGS, only when the user has
not set that flag, only for jaxlib versions known to accept it (an unknown XLA flag aborts the
process), and never when TABX_KEEP_XLA_FLAGS=1. It has no effect once JAX's backend exists.
"""

from __future__ import annotations

import os

_FLAG = "--xla_cpu_experimental_ynn_fusion_type="
_KNOWN_JAXLIB_PREFIXES = ("0.10.",)


def jaxlib_is_measured() -> bool:
    """The installed jaxlib is one our XLA:CPU settings were measured on (and known to accept:
    an unknown XLA option is an error). Also used by `tabx.jit_options`."""
    try:
        from importlib.metadata import version

        jaxlib_version = version("jaxlib")
    except Exception:  # noqa: BLE001 - no metadata: assume not
        return False
    return jaxlib_version.startswith(_KNOWN_JAXLIB_PREFIXES)


def apply() -> bool:
    """Add the flag if allowed; return True if XLA_FLAGS was changed."""
    if os.environ.get("TABX_KEEP_XLA_FLAGS") == "1":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_experimental_ynn_fusion_type" in flags:
        return False
    if not jaxlib_is_measured():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}".strip()
    return True
