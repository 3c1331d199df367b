"""`simulator_jit`: `jax.jit` with the XLA options that suit simulator-only programs.

On XLA:CPU (jaxlib 0.10) the newer MLIR fusion emitters take about twice as long to compile
the simulator's step as the older loop emitters, and the compiled step runs about as fast
either way (docs/benchmarks.md, "Compile options for simulator programs (session 5)"): the
reconfiguration rollout (10v10 + 6 zones, observations) compiles in 2.2 s instead of 4.3-5.1 s.
Compile time is what a researcher pays on every new `EnvConfig`, so programs that only run the
simulator (benchmarks, `tabx rollout`, tournaments, the editor's preview) are compiled with
`xla_cpu_use_fusion_emitters=False`.

Learner programs keep XLA's defaults: their network updates ran 15-25 % slower with the older
emitters (`tabx bench train`), which outweighs their faster compile.

The option is a CPU compiler option: on any other backend, and on jaxlib versions it was not
measured on (an unknown option is an error), `simulator_jit` is plain `jax.jit`. Set
TABX_DEFAULT_COMPILER=1 to compile simulator programs with XLA's defaults too.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import jax

from tabx import _xla_flags

SIMULATOR_CPU_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}


def simulator_compiler_options() -> dict[str, Any] | None:
    """The compiler options for a simulator-only program on the default backend (None: XLA's
    defaults)."""
    if os.environ.get("TABX_DEFAULT_COMPILER") == "1":
        return None
    if not _xla_flags.jaxlib_is_measured():
        return None
    if jax.default_backend() != "cpu":
        return None
    return dict(SIMULATOR_CPU_OPTIONS)


def simulator_jit(fn: Callable, **jit_kwargs: Any) -> Any:
    """`jax.jit(fn, **jit_kwargs)` compiled with `simulator_compiler_options()`. For programs
    without neural networks; a learner's update keeps `jax.jit`."""
    return jax.jit(fn, compiler_options=simulator_compiler_options(), **jit_kwargs)


__all__ = ["SIMULATOR_CPU_OPTIONS", "simulator_compiler_options", "simulator_jit"]
