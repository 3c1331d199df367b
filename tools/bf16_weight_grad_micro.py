"""Micro-benchmark: ways to compute a GRU weight gradient over a whole training sequence.

    python tools/bf16_weight_grad_micro.py

The recurrent weight gradient of one IPPO minibatch is the sum over T = 512 steps of
h_t^T @ dg_t (B = 96 rows, H = 128, 3H = 384). The learners compute it step by step inside
the backward scan, in float32. This times that against one product over the stacked steps, in
float32 and in bfloat16 with float32 accumulation (AMX on this CPU), with and without the
casts and transposes that produce the operands. Written for issue #7 and not a `tabx bench`:
the laid-out bf16 product is 5x faster than the per-step dots, but producing its operands from
a backward scan costs more than that on XLA:CPU, so the learners keep per-step float32 dots
(docs/learners.md, "Performance", session 5).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

T, B, H = 512, 96, 128


def best_ms(fn, *args, repeats: int = 5) -> float:
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return 1000 * min(times)


@jax.jit
def per_step_f32(hs: jax.Array, dg: jax.Array) -> jax.Array:
    def body(acc, step):
        h, d = step
        return acc + h.T @ d, None

    return jax.lax.scan(body, jnp.zeros((H, 3 * H)), (hs, dg), unroll=4)[0]


@jax.jit
def stacked_f32(hs: jax.Array, dg: jax.Array) -> jax.Array:
    return jnp.einsum("tbh,tbg->hg", hs, dg)


@jax.jit
def stacked_bf16_with_casts(hs: jax.Array, dg: jax.Array) -> jax.Array:
    return jax.lax.dot_general(hs.reshape(-1, H).astype(jnp.bfloat16),
                               dg.reshape(-1, 3 * H).astype(jnp.bfloat16),
                               (((0,), (0,)), ((), ())), preferred_element_type=jnp.float32)


@jax.jit
def stacked_bf16_laid_out(hs_t: jax.Array, dg: jax.Array) -> jax.Array:
    """Operands already (H, T*B) and (T*B, 3H) in bfloat16: a plain product."""
    return jnp.dot(hs_t, dg, preferred_element_type=jnp.float32)


def main() -> None:
    k_h, k_g = jax.random.split(jax.random.key(0))
    hs = jax.random.normal(k_h, (T, B, H))
    dg = jax.random.normal(k_g, (T, B, 3 * H))
    hs_t = hs.reshape(-1, H).T.astype(jnp.bfloat16)
    dg_b = dg.reshape(-1, 3 * H).astype(jnp.bfloat16)
    flops = 2 * T * B * H * 3 * H
    for name, fn, args in [("per-step float32", per_step_f32, (hs, dg)),
                           ("stacked float32", stacked_f32, (hs, dg)),
                           ("stacked bf16, casts incl.", stacked_bf16_with_casts, (hs, dg)),
                           ("stacked bf16, laid out", stacked_bf16_laid_out, (hs_t, dg_b))]:
        ms = best_ms(fn, *args)
        print(f"{name:28s} {ms:7.2f} ms  {flops / ms / 1e6:6.1f} GFLOP/s")
    ref = np.asarray(per_step_f32(hs, dg))
    got = np.asarray(stacked_bf16_laid_out(hs_t, dg_b))
    print(f"bf16 relative error {float(np.abs(got - ref).max() / np.abs(ref).max()):.1e}")


if __name__ == "__main__":
    main()
