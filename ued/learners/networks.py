"""Recurrent networks of the PPO learners, as pure functions over parameter dicts.

One trunk serves every network (`layers.py` of the reference; docs/differences.md):

    x -> Dense(H) -> LayerNorm -> ReLU -> GRU(H) -> Dense(H) -> LayerNorm -> ReLU -> Dense(out)

with orthogonal initialisation (scale sqrt 2 for the embedding, 2 after the GRU as the
reference, 0.01 for policy logits, 1.0 for values), LayerNorm epsilon 1e-6 and zero biases.
The GRU is flax's `GRUCell` equation with the three gates fused into one matmul per input:

    r = sigmoid(Wi_r x + bi_r + Wh_r h + bh_r)      z = sigmoid(Wi_z x + bi_z + Wh_z h + bh_z)
    n = tanh(Wi_n x + bi_n + r * (Wh_n h + bh_n))    h' = (1 - z) n + z h

`step` runs one time step (the rollout); `sequence` runs whole sequences for training, one
rematerialised scan step per time step (see its docstring), resetting the hidden state to zeros
where `starts` is True (the observation opens an episode).

Every function takes the matmul input `dtype` (float32 or bfloat16; the learner's
`learner.matmul_dtype`). With bfloat16 the layers' matrix products round their inputs (the
activations, the weights, and in the backward pass the output gradients) to bfloat16 and
accumulate in float32, as JAX's default precision does on TPUs; everything else (LayerNorm,
the GRU gates, weight gradients, the parameters and the optimiser) stays float32. On a CPU with
AMX, XLA:CPU's YNNPACK dot kernels run these products about 3x faster than float32 ones
(`learner_jit`, docs/learners_internals.md "Matmul precision").
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

Params = dict
LN_EPS = 1e-6
# Time steps per iteration of the training scans: a loop iteration has a fixed cost on XLA:CPU
# that is large next to one step of a 96-row minibatch; 4 steps per iteration made a whole
# update about 1.4x faster than 1, for 3 s more compilation (MAPPO's update compiled in 9.5 s
# with 1, 12.6 s with 4); 8 and 16 were no faster and compile longer still. Smaller networks
# (rows x hidden units per step, summed over the networks of the scan, below UNROLL_MIN_SIZE)
# are not unrolled: on the 2-core VM, MAPPO split over two devices (48 actor + 16 critic rows
# per device) ran no faster unrolled 2 or 4 times (6.5-6.7 s per update either way) and its
# first update took 19-20 s instead of 16.7 s.
SEQUENCE_UNROLL = 4
UNROLL_MIN_SIZE = 96 * 128


# --- initialisation --------------------------------------------------------------------------


def _orthogonal(key: jax.Array, shape: tuple[int, int], scale: float) -> jax.Array:
    return jax.nn.initializers.orthogonal(scale)(key, shape, jnp.float32)


def dense_init(key: jax.Array, n_in: int, n_out: int, scale: float) -> Params:
    return {"w": _orthogonal(key, (n_in, n_out), scale), "b": jnp.zeros(n_out, jnp.float32)}


def layer_norm_init(n: int) -> Params:
    return {"scale": jnp.ones(n, jnp.float32), "bias": jnp.zeros(n, jnp.float32)}


def gru_init(key: jax.Array, n_in: int, hidden: int) -> Params:
    """Fused GRU weights: input (n_in, 3H) LeCun normal, recurrent (H, 3H) orthogonal per gate
    (flax GRUCell's initialisers); gate order r, z, n."""
    k_in, *k_h = jax.random.split(key, 4)
    wi = jax.nn.initializers.lecun_normal()(k_in, (n_in, 3 * hidden), jnp.float32)
    wh = jnp.concatenate([_orthogonal(k, (hidden, hidden), 1.0) for k in k_h], axis=1)
    return {"wi": wi, "bi": jnp.zeros(3 * hidden, jnp.float32),
            "wh": wh, "bh": jnp.zeros(3 * hidden, jnp.float32)}


def trunk_init(key: jax.Array, n_in: int, hidden: int, head_scales: tuple[float, ...]
               ) -> Params:
    """Parameters of one recurrent network. `head_scales` gives one output column per entry
    (its orthogonal init scale), e.g. 8 x 0.01 for policy logits, (1.0,) for a value."""
    k_embed, k_gru, k_hidden, *k_heads = jax.random.split(key, 3 + len(set(head_scales)))
    columns = []
    for k, scale in zip(k_heads, sorted(set(head_scales), key=head_scales.index), strict=True):
        width = sum(1 for s in head_scales if s == scale)
        columns.append(_orthogonal(k, (hidden, width), scale))
    return {
        "embed": dense_init(k_embed, n_in, hidden, math.sqrt(2.0)),
        "ln_embed": layer_norm_init(hidden),
        "gru": gru_init(k_gru, hidden, hidden),
        "hidden": dense_init(k_hidden, hidden, hidden, 2.0),
        "ln_hidden": layer_norm_init(hidden),
        "out": {"w": jnp.concatenate(columns, axis=1),
                "b": jnp.zeros(len(head_scales), jnp.float32)},
    }


# --- forward pieces --------------------------------------------------------------------------


def _product(a: jax.Array, b: jax.Array, dtype: jnp.dtype) -> jax.Array:
    """a @ b with both inputs rounded to `dtype`, accumulated and returned in float32."""
    return jnp.dot(a.astype(dtype), b.astype(dtype), preferred_element_type=jnp.float32)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _matmul(x: jax.Array, w: jax.Array, w_t: jax.Array | None, dtype: jnp.dtype
            ) -> jax.Array:
    return _product(x, w, dtype)


def _matmul_fwd(x, w, w_t, dtype):
    return _product(x, w, dtype), (x, w, w_t)


def _matmul_bwd(dtype, res, g):
    x, w, w_t = res
    dx = _product(g, jnp.transpose(w) if w_t is None else w_t, dtype)
    # The weight gradient from float32 inputs: it sums over every row of the minibatch, and
    # XLA:CPU runs this transposed-operand product no faster in bfloat16.
    dw = jnp.einsum("...i,...o->io", x, g)
    return dx, dw, None


_matmul.defvjp(_matmul_fwd, _matmul_bwd)


def linear(x: jax.Array, w: jax.Array, w_t: jax.Array | None = None,
           dtype: jnp.dtype = jnp.float32) -> jax.Array:
    """x @ w, its inputs rounded to the matmul `dtype` (float32: exactly x @ w). With `w_t`
    (w transposed, laid out row-major once per gradient step by `with_transposes`), the input
    gradient is g @ w_t rather than a product against w's rows: XLA:CPU runs that
    transposed-operand product 1.3-3x slower on small minibatches."""
    if w_t is None and jnp.dtype(dtype) == jnp.float32:
        return x @ w
    return _matmul(x, w, w_t, jnp.dtype(dtype))


def with_transposes(p: Params, dtype: jnp.dtype = jnp.float32) -> Params:
    """`p` with row-major transposes (no gradient, in the matmul `dtype`) of the weights whose
    input gradient the backward pass needs: the GRU's and the layers after it (the
    embedding's input, the observation, needs none)."""
    t = lambda w: jax.lax.stop_gradient(jnp.transpose(w)).astype(dtype)
    return {**p, "gru": {**p["gru"], "wi_t": t(p["gru"]["wi"]), "wh_t": t(p["gru"]["wh"])},
            "hidden": {**p["hidden"], "w_t": t(p["hidden"]["w"])},
            "out": {**p["out"], "w_t": t(p["out"]["w"])}}


def dense(p: Params, x: jax.Array, dtype: jnp.dtype = jnp.float32) -> jax.Array:
    return linear(x, p["w"], p.get("w_t"), dtype) + p["b"]


def _row_mean(x: jax.Array) -> jax.Array:
    """Mean over the last axis as a matrix-vector product. XLA:CPU splits a plain 128-wide
    row reduction into an unfused reduce-window and a reduce (two more kernels per LayerNorm
    statistic, forward and backward, every time step); the product is one kernel, and made
    whole PPO updates 2-4% faster (MAPPO and IPPO on crossfire, `tabx bench train`)."""
    n = x.shape[-1]
    return x @ jnp.full((n, 1), 1.0 / n, x.dtype)


def layer_norm(p: Params, x: jax.Array) -> jax.Array:
    """LayerNorm over the last axis (epsilon 1e-6, learned scale and bias)."""
    return _layer_norm(x, p["scale"], p["bias"])


def _normalised(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    mean = _row_mean(x)
    centred = x - mean
    rstd = jax.lax.rsqrt(_row_mean(centred * centred) + LN_EPS)
    return centred * rstd, rstd


@jax.custom_vjp
def _layer_norm(x: jax.Array, scale: jax.Array, bias: jax.Array) -> jax.Array:
    return _normalised(x)[0] * scale + bias


def _layer_norm_fwd(x, scale, bias):
    y, rstd = _normalised(x)
    return y * scale + bias, (y, rstd, scale)


def _layer_norm_bwd(res, g):
    """dx = rstd (dy - mean(dy) - y mean(dy y)) with dy = g scale, the row means as
    matrix-vector products: autodiff of the forward made two row reductions of the
    broadcast statistics, each an unfused reduce-window and a reduce on XLA:CPU (IPPO updates
    3-5 % faster this way; docs/learners_internals.md, "Performance")."""
    y, rstd, scale = res
    rows = tuple(range(g.ndim - 1))
    dy = g * scale
    dx = rstd * (dy - _row_mean(dy) - y * _row_mean(dy * y))
    return dx, jnp.sum(g * y, rows), jnp.sum(g, rows)


_layer_norm.defvjp(_layer_norm_fwd, _layer_norm_bwd)


def encode(p: Params, x: jax.Array, dtype: jnp.dtype = jnp.float32) -> jax.Array:
    """(..., n_in) -> (..., 3H): embedding and the GRU's input projection (no recurrence)."""
    e = jax.nn.relu(layer_norm(p["ln_embed"], dense(p["embed"], x, dtype)))
    gi = linear(e, p["gru"]["wi"], p["gru"].get("wi_t"), dtype) + p["gru"]["bi"]
    return checkpoint_name(gi, "gru_gi")


def decode(p: Params, h: jax.Array, dtype: jnp.dtype = jnp.float32) -> jax.Array:
    """(..., H) GRU output -> (..., out): the layers after the GRU."""
    hidden = jax.nn.relu(layer_norm(p["ln_hidden"], dense(p["hidden"], h, dtype)))
    return dense(p["out"], hidden, dtype)


def _gates(gi: jax.Array, gh: jax.Array, h: jax.Array
           ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """(new h, r, z, n) from the input and recurrent projections (biases included).
    `lax.split` rather than slices: its gradient is one concatenate, not a pad per gate."""
    sizes = (h.shape[-1],) * 3
    gi_r, gi_z, gi_n = jax.lax.split(gi, sizes, axis=-1)
    gh_r, gh_z, gh_n = jax.lax.split(gh, sizes, axis=-1)
    r = jax.nn.sigmoid(gi_r + gh_r)
    z = jax.nn.sigmoid(gi_z + gh_z)
    n = jnp.tanh(gi_n + r * gh_n)
    return (1.0 - z) * n + z * h, r, z, n


def gru_cell(p: Params, gi: jax.Array, h: jax.Array, dtype: jnp.dtype = jnp.float32
             ) -> jax.Array:
    """One GRU step from the encoded input `gi` (..., 3H) and hidden `h` (..., H)."""
    gh = checkpoint_name(linear(h, p["wh"], p.get("wh_t"), dtype) + p["bh"], "gru_gh")
    return _gates(gi, gh, h)[0]


def step(p: Params, x: jax.Array, h: jax.Array, dtype: jnp.dtype = jnp.float32
         ) -> tuple[jax.Array, jax.Array]:
    """One time step of the whole network: (new hidden, output). Used by the rollout."""
    h = gru_cell(p["gru"], encode(p, x, dtype), h, dtype)
    return h, decode(p, h, dtype)


# --- whole sequences (training) --------------------------------------------------------------


def sequences(params: tuple[Params, ...], xs: tuple[jax.Array, ...],
              starts: tuple[jax.Array, ...], h0s: tuple[jax.Array, ...],
              dtype: jnp.dtype = jnp.float32) -> tuple[jax.Array, ...]:
    """Several networks over sequences of the same length in one scan: outputs (T, B_i, out_i)
    of network i over inputs `xs[i]` (T, B_i, n_in_i) from hidden `h0s[i]` (B_i, H_i),
    resetting its hidden state to zeros before every step where `starts[i]` (T, B_i).

    One scan step runs every network for one time step, under `jax.checkpoint`: the forward
    pass keeps the hidden states and the GRU's two projections (`gru_gi`, `gru_gh`: the
    largest matmuls) of each step, and the backward pass recomputes the step's other
    activations (in cache) instead of reading them back from memory. On a CPU this trades
    more matmul work for much less memory traffic (saving every activation was 15-25 %
    slower, saving none 3-5 % slower than saving the two projections, measured on two
    devices); running the networks of MAPPO (actor and critic) in the same step halves the
    loop iterations and lets their independent matmuls run side by side. The backward pass
    multiplies by weights transposed once per call (`with_transposes`). `dtype`: the matmul
    inputs' (see the module doc)."""
    params = tuple(with_transposes(p, dtype) for p in params)

    def body(hs, inputs):
        outs, new_hs = [], []
        for p, h, (x_t, start_t) in zip(params, hs, inputs, strict=True):
            h, out = step(p, x_t, jnp.where(start_t[:, None], 0.0, h), dtype)
            new_hs.append(h)
            outs.append(out)
        return tuple(new_hs), tuple(outs)

    saved = jax.checkpoint_policies.save_only_these_names("gru_gi", "gru_gh")
    body = jax.checkpoint(body, prevent_cse=False, policy=saved)
    size = sum(h.shape[0] * h.shape[-1] for h in h0s)
    unroll = SEQUENCE_UNROLL if size >= UNROLL_MIN_SIZE else 1
    return jax.lax.scan(body, tuple(h0s), tuple(zip(xs, starts, strict=True)),
                        unroll=unroll)[1]


def sequence(p: Params, x: jax.Array, starts: jax.Array, h0: jax.Array,
             dtype: jnp.dtype = jnp.float32) -> jax.Array:
    """Outputs (T, B, out) of one network over inputs `x` (T, B, n_in) from hidden `h0`
    (B, H), resetting the hidden state where `starts` (T, B); see `sequences`."""
    return sequences((p,), (x,), (starts,), (h0,), dtype)[0]


__all__ = ["decode", "encode", "gru_cell", "sequence", "sequences", "step", "trunk_init"]
