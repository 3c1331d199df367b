"""Kernel-time summary of a JAX profiler trace on the CPU, without the TensorBoard plugin.

    XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true python my_script.py  # calls
        jax.profiler.start_trace(DIR) ... jax.profiler.stop_trace()
    python tools/xplane_summary.py DIR [--top 30] [--by-kernel]

With `--xla_cpu_enable_xprof_traceme` XLA:CPU records one event per executed kernel (fusion,
dot, copy, ...) on the thread that ran it. This reads the `*.xplane.pb` that `jax.profiler`
writes (protobuf wire format, decoded by hand: XSpace.planes -> XPlane.lines -> XLine.events,
names from XPlane.event_metadata) and prints the total time and count per kernel kind
(`fusion.12` and `fusion.7` are one kind, `fusion`) or, with `--by-kernel`, per kernel. It
also prints how busy XLA's threads were: their summed kernel time against the wall time from
the first kernel to the end of the last. How to take a trace: docs/benchmarks.md, "How to
profile"; the profiles of docs/learners.md ("Performance") were summarised with it.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
from collections.abc import Iterator
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


def kernel_events(xspace: bytes) -> Iterator[tuple[str, str, int, int]]:
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


_NOT_KERNELS = ("ThunkExecutor", "ThreadpoolListener", "end: ")


def summarise(trace_dir: str | Path, by_kernel: bool = False
              ) -> tuple[list[tuple[str, float, int]], float, float]:
    """([(kernel, total ms, count)] slowest first, summed kernel ms, wall ms from the first
    kernel's start to the last one's end) of the newest `*.xplane.pb` under `trace_dir`."""
    files = sorted(Path(trace_dir).rglob("*.xplane.pb"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb under {trace_dir}: was the trace written "
                                f"with jax.profiler.start_trace/stop_trace?")
    total: collections.Counter[str] = collections.Counter()
    count: collections.Counter[str] = collections.Counter()
    first, last = float("inf"), 0.0
    for thread, name, start, duration in kernel_events(files[-1].read_bytes()):
        # Kernels run on XLA's threads ("tf_XLAEigen/..." workers, and "tf_XLAPjRtCpuClient/..."
        # for small programs); the host thread's spans (named after the process) and the
        # executor's own spans wrap them.
        if not thread.startswith("tf_XLA") or name.startswith(_NOT_KERNELS):
            continue
        kind = name if by_kernel else re.sub(r"(\.\d+)+$", "", name)
        total[kind] += duration
        count[kind] += 1
        first, last = min(first, start), max(last, start + duration)
    rows = [(k, v / 1e9, count[k]) for k, v in total.most_common()]
    wall = (last - first) / 1e9 if total else 0.0
    return rows, sum(total.values()) / 1e9, wall


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trace_dir", help="the folder given to jax.profiler.start_trace")
    parser.add_argument("--top", type=int, default=30, help="rows to print (default 30)")
    parser.add_argument("--by-kernel", action="store_true",
                        help="one row per kernel instead of per kernel kind")
    args = parser.parse_args(argv)
    try:
        rows, busy, wall = summarise(args.trace_dir, args.by_kernel)
    except (FileNotFoundError, ValueError) as err:
        print(f"xplane_summary: {err}", file=sys.stderr)
        return 2
    if not rows:
        print("no XLA:CPU kernel events: set XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true "
              "before JAX starts", file=sys.stderr)
        return 2
    print(f"{'ms':>10} {'count':>9}  kernel")
    for name, ms, n in rows[:args.top]:
        print(f"{ms:10.1f} {n:9d}  {name}")
    print(f"kernel time {busy:.1f} ms over {wall:.1f} ms from the first kernel to the last")
    return 0


if __name__ == "__main__":
    sys.exit(main())
