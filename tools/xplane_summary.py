"""Kernel-time summary of a JAX profiler trace on the CPU, without the TensorBoard plugin.

    XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true python my_script.py  # calls
        jax.profiler.start_trace(DIR) ... jax.profiler.stop_trace()
    python tools/xplane_summary.py DIR [--top 30] [--by-kernel]

Prints the total (exclusive) time and count per kernel kind (`fusion.12` and `fusion.7` are one
kind, `fusion`) or, with `--by-kernel`, per kernel, and how busy XLA's threads were: their summed
kernel time against the wall time from the first kernel to the end of the last. The trace is
read by `tabx_bench.xplane`; `tabx bench profile` goes further and splits a simulator step's kernel
time by stage. How to take a trace: docs/performance.md, "How to profile".
"""

from __future__ import annotations

import argparse
import sys

from tabx_bench.xplane import fields, kernel_spans, summarise


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


__all__ = ["fields", "kernel_spans", "main", "summarise"]  # re-exported for callers

if __name__ == "__main__":
    sys.exit(main())
