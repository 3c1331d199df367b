"""XLA:CPU kernel events from a JAX profiler trace (`*.xplane.pb`), without TensorBoard.

With `XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true` (set before JAX starts its backend)
XLA:CPU records one event per executed kernel (fusion, dot, copy, ...) on the thread that ran
it, named after the HLO instruction the kernel computes (`fusion.12`, `dot.3`). This module
reads the `*.xplane.pb` that `jax.profiler.start_trace/stop_trace` writes (protobuf wire format,
decoded by hand: XSpace.planes -> XPlane.lines -> XLine.events, names from
XPlane.event_metadata) and returns those kernel events with their *exclusive* time: a kernel
that wraps others on its thread (a `while` running part of its body inline) counts only the
time none of them ran, so summed kernel time never counts a microsecond twice.

Used by `tabx bench profile` (tabx_bench/stage_profile.py) and tools/xplane_summary.py.
"""

from __future__ import annotations

import collections
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path


def _varint(data: bytes, i: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        byte = data[i]
        i += 1
        result |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return result, i


def fields(data: bytes) -> Iterator[tuple[int, int | bytes]]:
    """(field number, value) of one protobuf message: ints for varints, bytes otherwise."""
    i, n = 0, len(data)
    while i < n:
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 2:
            length, i = _varint(data, i)
            value, i = data[i:i + length], i + length
        elif wire == 1:
            value, i = data[i:i + 8], i + 8
        elif wire == 5:
            value, i = data[i:i + 4], i + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire} at byte {i}")
        yield number, value


def trace_events(xspace: bytes) -> Iterator[tuple[str, str, int, int]]:
    """(thread name, event name, start ps, duration ps) of every event of every plane."""
    for number, plane in fields(xspace):
        if number != 1:  # XSpace.planes
            continue
        names: dict[int, str] = {}
        lines = []
        for f, value in fields(plane):
            if f == 3:  # XPlane.lines
                lines.append(value)
            elif f == 4:  # XPlane.event_metadata: map<int64, XEventMetadata>
                key, meta = 0, b""
                for g, v in fields(value):
                    key, meta = (v, meta) if g == 1 else (key, v if g == 2 else meta)
                names[key] = next((v.decode(errors="replace") for g, v in fields(meta)
                                   if g == 2), "?")
        for line in lines:
            thread, events, start = "", [], 0
            for f, value in fields(line):
                if f == 2:  # XLine.name
                    thread = value.decode(errors="replace")
                elif f == 3:  # XLine.timestamp_ns
                    start = value * 1000
                elif f == 4:  # XLine.events
                    events.append(value)
            for event in events:
                meta_id = offset = duration = 0
                for g, v in fields(event):
                    if g == 1:
                        meta_id = v
                    elif g == 2:
                        offset = v
                    elif g == 3:
                        duration = v
                yield thread, names.get(meta_id, "?"), start + offset, duration


# The short "end: X" marker each kernel leaves: not a kernel. Nor are spans named like C++
# methods: the executor's and the thread pool's spans that wrap kernels
# (`ThunkExecutor::Execute`) and the pieces of work a kernel hands to other threads
# (`Transpose::ExecuteChunk`).
_NOT_KERNELS = ("end: ",)


@dataclass(frozen=True)
class KernelEvent:
    thread: str
    name: str  # the HLO instruction the kernel computes
    start_ps: int
    duration_ps: int  # inclusive
    exclusive_ps: int  # less the kernels nested inside it on the same thread


def kernel_spans(xspace: bytes) -> list[KernelEvent]:
    """The XLA:CPU kernel events of a trace, sorted by start, with their exclusive time."""
    by_thread: dict[str, list[tuple[str, int, int]]] = collections.defaultdict(list)
    for thread, name, start, duration in trace_events(xspace):
        # Kernels run on XLA's threads ("tf_XLAEigen/..." workers, and "tf_XLAPjRtCpuClient/..."
        # for small programs); the host thread's spans (named after the process) and the
        # executor's own spans wrap them.
        if thread.startswith("tf_XLA") and not name.startswith(_NOT_KERNELS) and "::" not in name:
            by_thread[thread].append((name, start, duration))
    spans: list[KernelEvent] = []
    for thread, events in by_thread.items():
        events.sort(key=lambda e: (e[1], -e[2]))
        spans.extend(KernelEvent(thread, name, start, duration, exclusive)
                     for (name, start, duration), exclusive
                     in zip(events, exclusive_times(events), strict=True))
    spans.sort(key=lambda e: e.start_ps)
    return spans


def exclusive_times(events: list[tuple[str, int, int]]) -> list[int]:
    """The time of each (name, start, duration) event of one thread, sorted by start (longest
    first on ties), that none of the events nested inside it covers."""
    nested = [0] * len(events)
    open_spans: list[int] = []  # indices of the spans enclosing the current event
    for i, (_, start, duration) in enumerate(events):
        while open_spans and sum(events[open_spans[-1]][1:]) <= start:
            open_spans.pop()
        if open_spans:
            nested[open_spans[-1]] += duration
        open_spans.append(i)
    return [max(duration - inner, 0) for (_, _, duration), inner in zip(events, nested,
                                                                          strict=True)]


def newest_trace(trace_dir: str | Path) -> Path:
    """The newest `*.xplane.pb` under `trace_dir` (FileNotFoundError if there is none)."""
    files = sorted(Path(trace_dir).rglob("*.xplane.pb"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb under {trace_dir}: was the trace written "
                                f"with jax.profiler.start_trace/stop_trace?")
    return files[-1]


def summarise(trace_dir: str | Path, by_kernel: bool = False
              ) -> tuple[list[tuple[str, float, int]], float, float]:
    """([(kernel, total ms, count)] slowest first, summed kernel ms, wall ms from the first
    kernel's start to the last one's end) of the newest `*.xplane.pb` under `trace_dir`.
    Kernel kinds (default) group `fusion.12` and `fusion.7` as `fusion`; times are exclusive."""
    total: collections.Counter[str] = collections.Counter()
    count: collections.Counter[str] = collections.Counter()
    first, last = float("inf"), 0.0
    for event in kernel_spans(newest_trace(trace_dir).read_bytes()):
        kind = event.name if by_kernel else re.sub(r"(\.\d+)+$", "", event.name)
        total[kind] += event.exclusive_ps
        count[kind] += 1
        first = min(first, event.start_ps)
        last = max(last, event.start_ps + event.duration_ps)
    rows = [(k, v / 1e9, count[k]) for k, v in total.most_common()]
    wall = (last - first) / 1e9 if total else 0.0
    return rows, sum(total.values()) / 1e9, wall


__all__ = ["KernelEvent", "exclusive_times", "fields", "kernel_spans", "newest_trace", "summarise",
           "trace_events"]
