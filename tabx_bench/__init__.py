"""Benchmarks of TABX-UED: the simulator's throughput, compile time and scaling
(`tabx_bench.simulator`, `tabx_bench.suite`), the per-stage profile of a simulator step with its
XLA profile and HLO text readers (`tabx_bench.stage_profile`, `.step_stages`, `.xplane`,
`.hlo_text`), the side by side comparison with SMAX (`tabx_bench.peers`), training throughput
(`tabx_bench.train`) and a UED run on the local driver and on Ray (`tabx_bench.ued`); the
`tabx bench` command is `tabx_bench.cli`.

It sits between the workers and the command line: `tabx` <- `level_buffer` <- `ued` <-
`workers` <- `tabx_bench` <- `tabx_ued` (docs/architecture.md). See docs/benchmarks.md.
"""
