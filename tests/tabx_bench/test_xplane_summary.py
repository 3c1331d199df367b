"""tools/xplane_summary.py reads a real JAX profiler trace of XLA:CPU kernels."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tools"))

import xplane_summary  # noqa: E402

TRACE_SCRIPT = """
import sys, jax, jax.numpy as jnp
f = jax.jit(lambda x: jnp.tanh(x @ x) + 1.0)
x = jnp.ones((64, 64))
f(x).block_until_ready()
jax.profiler.start_trace(sys.argv[1])
for _ in range(5):
    f(x).block_until_ready()
jax.profiler.stop_trace()
"""


def test_summary_of_a_real_trace_names_the_kernels(tmp_path, capsys):
    env = dict(os.environ, XLA_FLAGS="--xla_cpu_enable_xprof_traceme=true",
               JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", TRACE_SCRIPT, str(tmp_path)], check=True, env=env,
                   timeout=120)
    rows, busy, wall = xplane_summary.summarise(tmp_path)
    kinds = {name: n for name, _, n in rows}
    # Every kernel of the program (the matmul, the fused tanh + add) ran once per call, and
    # no wrapper span (the executor's, the Python thread's) is counted as a kernel.
    assert kinds and all(n == 5 for n in kinds.values()), kinds
    assert any("fusion" in k or "dot" in k for k in kinds), kinds
    assert 0 < busy and 0 < wall
    assert xplane_summary.main([str(tmp_path), "--top", "3"]) == 0
    out = capsys.readouterr().out
    assert "kernel time" in out and len(out.splitlines()) <= 5


def test_missing_trace_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="no \\*.xplane.pb"):
        xplane_summary.summarise(tmp_path)
    assert xplane_summary.main([str(tmp_path)]) == 2
    assert "xplane_summary:" in capsys.readouterr().err


def test_fields_decodes_varints_and_nested_messages():
    # field 1 varint 300, field 2 bytes b"ab" (a nested message would be bytes too)
    message = bytes([0x08, 0xAC, 0x02, 0x12, 0x02]) + b"ab"
    assert list(xplane_summary.fields(message)) == [(1, 300), (2, b"ab")]
    with pytest.raises(ValueError, match="wire type"):
        list(xplane_summary.fields(bytes([0x0B])))  # wire type 3 (groups) is not supported
