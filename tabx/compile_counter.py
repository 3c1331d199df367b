"""Count JAX traces and XLA compilations while a block runs (benchmarks and no-recompile tests).

    with CompileCounter() as cc:
        run()
    assert cc.compiles == 0, cc.traced      # the names of the functions that were traced

Uses JAX's own monitoring events, so it sees every compilation in the process, eager
operations included. A program loaded from a persistent compilation cache counts as a
compilation too (JAX times the load as one) and also in `cache_hits`. The listeners are
registered once per process; counters nest. `compile_seconds()` is the process's running
total, for clocks that leave compilation out of a rate.
"""

from __future__ import annotations

import threading

import jax

_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_COMPILE = "/jax/core/compile/backend_compile_duration"
_LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_CACHE_HIT = "/jax/compilation_cache/cache_hits"
_LISTENING: list[CompileCounter] = []
_LOCK = threading.Lock()
_REGISTERED = [False]
_TOTAL_SECONDS = [0.0]


def _on_duration(event: str, duration: float, **kwargs: object) -> None:
    if event not in (_TRACE, _COMPILE, _LOWER):
        return
    with _LOCK:
        _TOTAL_SECONDS[0] += duration
        for counter in _LISTENING:
            if event == _TRACE:
                counter.traces += 1
                counter.traced.append(str(kwargs.get("fun_name", "?")))
            elif event == _COMPILE:
                counter.compiles += 1
            counter.seconds += duration


def _on_event(event: str, **kwargs: object) -> None:
    if event != _CACHE_HIT:
        return
    with _LOCK:
        for counter in _LISTENING:
            counter.cache_hits += 1


def _register() -> None:
    """Listen to JAX's events (once per process; call with `_LOCK` held)."""
    if not _REGISTERED[0]:
        jax.monitoring.register_event_duration_secs_listener(_on_duration)
        jax.monitoring.register_event_listener(_on_event)
        _REGISTERED[0] = True


def compile_seconds() -> float:
    """Seconds this process has spent tracing, lowering and compiling (programs loaded from a
    persistent cache included) since the first call here or the first `CompileCounter`: the
    difference of two calls is the compilation time between them."""
    with _LOCK:
        _register()
        return _TOTAL_SECONDS[0]


class CompileCounter:
    """Counts XLA compilations (`compiles`), traces (`traces`, with the traced functions'
    names in `traced`), programs loaded from a persistent compilation cache (`cache_hits`)
    and the total seconds (trace, lowering and backend compile) while active."""

    def __init__(self) -> None:
        self.compiles = 0
        self.traces = 0
        self.traced: list[str] = []
        self.seconds = 0.0
        self.cache_hits = 0

    def __enter__(self) -> CompileCounter:
        with _LOCK:
            _register()
            _LISTENING.append(self)
        return self

    def __exit__(self, *exc: object) -> None:
        with _LOCK:
            _LISTENING.remove(self)


__all__ = ["CompileCounter", "compile_seconds"]
