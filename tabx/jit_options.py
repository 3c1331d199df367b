"""`simulator_jit` and `learner_jit`: `jax.jit` with the XLA options that suit simulator-only
programs and learner programs.

On XLA:CPU (jaxlib 0.10) the newer MLIR fusion emitters take about twice as long to compile
the simulator's step as the older loop emitters, and the compiled step runs about as fast
either way (docs/performance.md, "Compile options for simulator programs"): the
reconfiguration rollout (10v10 + 6 zones, observations) compiles in 2.2 s instead of 4.3-5.1 s.
Compile time is what a researcher pays on every new `EnvConfig`, so programs that only run the
simulator (benchmarks, `tabx rollout`, tournaments, the editor's preview) are compiled with
`xla_cpu_use_fusion_emitters=False`. They also get `xla_cpu_enable_fast_min_max`: min and max
compiled as a compare and a select, without the checks that propagate a NaN operand. The
simulator's values are finite by construction (safe denominators, clamped health; padding never
makes NaN), and the 3v3 step ran up to 7 % faster (docs/performance.md). Learner
programs keep NaN-propagating min/max: a diverging network should show its NaNs.

Learner programs (updates, scoring, evaluation) keep the newer emitters: their network updates
ran 15-25 % slower with the older ones (`tabx bench train`), which outweighs their faster
compile. When their networks multiply in bfloat16 (`learner.matmul_dtype`, the default) they get
XLA:CPU's YNNPACK kernels for their matrix products (`xla_cpu_experimental_ynn_fusion_type`,
which `tabx.xla_flags` turns off process-wide because its reductions are slow for the
simulator): these use the CPU's AMX units for bfloat16 inputs, about 3x faster than XLA's own
dot kernels on the learners' small products. In float32 they were 2-4 % slower on whole updates,
so float32 learners keep XLA's defaults (docs/learners_internals.md, "Matmul precision").

The options are CPU compiler options: on any other backend, and on jaxlib versions they were
not measured on (an unknown option is an error), both are plain `jax.jit`. Set
TABX_DEFAULT_COMPILER=1 to compile every program with XLA's defaults (and the process-wide
flags).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import jax

from tabx import xla_flags

SIMULATOR_CPU_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False,
                                         "xla_cpu_enable_fast_min_max": True}
LEARNER_CPU_OPTIONS: dict[str, Any] = {
    "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}


def _cpu_options(options: dict[str, Any]) -> dict[str, Any] | None:
    if os.environ.get("TABX_DEFAULT_COMPILER") == "1":
        return None
    if not xla_flags.jaxlib_is_measured():
        return None
    if jax.default_backend() != "cpu":
        return None
    return dict(options)


def simulator_compiler_options() -> dict[str, Any] | None:
    """The compiler options for a simulator-only program on the default backend (None: XLA's
    defaults)."""
    return _cpu_options(SIMULATOR_CPU_OPTIONS)


def learner_compiler_options(matmul_dtype: str) -> dict[str, Any] | None:
    """The compiler options for a learner program whose networks multiply in `matmul_dtype`
    ("bfloat16" or "float32"), on the default backend (None: XLA's defaults)."""
    if matmul_dtype != "bfloat16":
        return None
    return _cpu_options(LEARNER_CPU_OPTIONS)


def simulator_jit(fn: Callable, **jit_kwargs: Any) -> Any:
    """`jax.jit(fn, **jit_kwargs)` compiled with `simulator_compiler_options()`. For programs
    without neural networks; a learner's update keeps `jax.jit`."""
    return jax.jit(fn, compiler_options=simulator_compiler_options(), **jit_kwargs)


def learner_jit(fn: Callable, matmul_dtype: str, **jit_kwargs: Any) -> Any:
    """`jax.jit(fn, **jit_kwargs)` compiled with `learner_compiler_options(matmul_dtype)`: for
    programs that run the learners' networks (update, scoring, evaluation)."""
    return jax.jit(fn, compiler_options=learner_compiler_options(matmul_dtype), **jit_kwargs)


__all__ = ["LEARNER_CPU_OPTIONS", "SIMULATOR_CPU_OPTIONS", "learner_compiler_options",
           "learner_jit", "simulator_compiler_options", "simulator_jit"]
