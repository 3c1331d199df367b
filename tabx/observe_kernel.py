"""The observation's assembly as one JAX primitive: the other units' blocks in each viewer's
cyclic order, masked by what it sees, between its own features and its zone features.

On the CPU it runs the native kernel tabx/native/observe.cc (built once per machine,
`tabx.native_lib`); everywhere else, and on the CPU when that kernel is unavailable or
`TABX_NATIVE=0`, the XLA version below. Both give the same bits (tests/tabx/test_observe_kernel.py).

Why a kernel: XLA:CPU writes the cyclic order as 2N slices and a concatenate per step, each a
small kernel copying a few floats per env; at 5v5 they were over half of a random-action step
(docs/performance.md). The primitive takes any leading batch dimensions (vmap moves them to the
front), tells the partitioner that those dimensions may be split over devices (a batch split
over devices stays split: each device assembles its own envs), and differentiates through the
XLA version.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp

from tabx.native_lib import native_available

try:  # JAX's primitive machinery; on a JAX without it, observations use the XLA version
    from jax.extend.core import Primitive
    from jax.interpreters import ad, batching, mlir

    ShapedArray = getattr(jax.core, "ShapedArray", None)
    if ShapedArray is None:  # pragma: no cover - newer JAX keeps it internal
        from jax._src.core import ShapedArray
except ImportError:  # pragma: no cover - depends on the JAX version
    Primitive = None

TARGET = "tabx_assemble_observation"
OWN_FEATURES = 14
OTHER_FEATURES = 16
# Rank of each operand for one env: own (N, 14), position (N, 2), inv_half (2,), team (N,),
# seen (N, N), attackable (N, N), zones (N, ZF).
_CORE_RANKS = (2, 2, 1, 1, 2, 2, 2)


def _assemble_one(own, position, inv_half, team, seen, attackable, zones):
    n = own.shape[0]
    rel = (position[None, :, :] - position[:, None, :]) * inv_half  # (viewer, other, 2)
    is_ally = (team[None, :] == team[:, None]).astype(jnp.float32)

    def per_other(features: jax.Array) -> jax.Array:  # (N, k) of the other unit -> (N, N, k)
        return jnp.broadcast_to(features[None], (n, *features.shape))

    pair = jnp.concatenate([per_other(own[:, :2]), rel, per_other(own[:, 4:13]),
                            is_ally[..., None], attackable.astype(jnp.float32)[..., None],
                            per_other(own[:, 13:])], axis=-1)  # (viewer, other, 16)
    pair = jnp.where(seen[..., None], pair, 0.0)
    # Viewer i's row is [own i | pair[i, i+1:] | pair[i, :i] | zones i]: contiguous pieces in
    # one concatenate (XLA:CPU copies those in runs; a gather was slower).
    pieces = []
    for i in range(n):  # static: the layout, not the data, depends on i
        pieces += [own[i], pair[i, i + 1:].reshape(-1), pair[i, :i].reshape(-1), zones[i]]
    return jnp.concatenate(pieces).reshape(n, -1)


def assemble_xla(own, position, inv_half, team, seen, attackable, zones) -> jax.Array:
    """The XLA version, for operands with any (equal) leading batch dimensions."""
    fn = _assemble_one
    for _ in range(own.ndim - 2):
        fn = jax.vmap(fn)
    return fn(own, position, inv_half, team, seen, attackable, zones)


def _abstract_eval(own, position, inv_half, team, seen, attackable, zones):
    n = own.shape[-2]
    size = OWN_FEATURES + OTHER_FEATURES * (n - 1) + zones.shape[-1]
    return ShapedArray((*own.shape[:-1], size), jnp.float32)


def _batch(args, dims):
    def mapped(d) -> bool:  # unmapped: None, or batching.NotMapped on some JAX versions
        return d is not None and not isinstance(d, getattr(batching, "NotMapped", ()))

    size = next(a.shape[d] for a, d in zip(args, dims, strict=True) if mapped(d))
    moved = [jnp.moveaxis(a, d, 0) if mapped(d) else jnp.broadcast_to(a, (size, *a.shape))
             for a, d in zip(args, dims, strict=True)]
    return assemble_p.bind(*moved), 0


def _jvp(primals, tangents):
    tangents = tuple(ad.instantiate_zeros(t) for t in tangents)
    _, tangent_out = jax.jvp(assemble_xla, tuple(primals), tangents)
    return assemble_p.bind(*primals), tangent_out


def _sharding_attributes(ctx, num_batch: int) -> dict:
    """Leading batch dimensions may be split over devices, for both partitioners: GSPMD reads
    the frontend attribute (with the target registered as batch partitionable), Shardy a rule
    `... a b, ... -> ... x y`."""
    attributes = {"mhlo.frontend_attributes": mlir.ir_attribute({"num_batch_dims":
                                                                 str(num_batch)})}
    if num_batch and jax.config.jax_use_shardy_partitioner:
        try:  # JAX-internal helpers (as jax.lax.linalg's kernels use them)
            from jax._src.custom_partitioning_sharding_rule import (
                sdy_sharding_rule_to_mlir,
                str_to_sdy_sharding_rule,
            )
        except ImportError:  # pragma: no cover - a batch split over devices is then gathered
            return attributes

        letters = iter("abcdefghijklmnopqrstuvwxyz")

        def spec(rank: int) -> str:
            return "... " + " ".join(next(letters) for _ in range(rank))

        rule = str_to_sdy_sharding_rule(
            f"{', '.join(spec(r) for r in _CORE_RANKS)} -> {spec(2)}")
        attributes["sdy.sharding_rule"] = sdy_sharding_rule_to_mlir(
            rule, [mlir.aval_to_ir_type(ctx.module_context, a) for a in ctx.avals_in],
            [mlir.aval_to_ir_type(ctx.module_context, a) for a in ctx.avals_out])
    return attributes


def _cpu_lowering(ctx, *args):
    if not native_available():
        return mlir.lower_fun(assemble_xla, multiple_results=False)(ctx, *args)
    num_batch = len(ctx.avals_in[0].shape) - 2
    return jax.ffi.ffi_lowering(TARGET, extra_attributes=_sharding_attributes(ctx, num_batch))(
        ctx, *args)


def _make_primitive():
    """The primitive with its rules, or None (with a warning) where this JAX lacks the API."""
    if Primitive is None:
        return None
    try:
        primitive = Primitive("tabx_assemble_observation")
        primitive.def_abstract_eval(_abstract_eval)
        primitive.def_impl(jax.jit(primitive.bind))
        batching.primitive_batchers[primitive] = _batch
        ad.primitive_jvps[primitive] = _jvp
        mlir.register_lowering(primitive, mlir.lower_fun(assemble_xla, multiple_results=False))
        mlir.register_lowering(primitive, _cpu_lowering, platform="cpu")
        jax.ffi.register_ffi_target_as_batch_partitionable(TARGET)
    except (AttributeError, TypeError) as err:  # pragma: no cover - depends on the JAX version
        warnings.warn(f"tabx: observations use the XLA version on this JAX ({err})",
                      stacklevel=2)
        return None
    return primitive


assemble_p = _make_primitive()


def assemble_observation(own: jax.Array, position: jax.Array, inv_half: jax.Array,
                         team: jax.Array, seen: jax.Array, attackable: jax.Array,
                         zones: jax.Array) -> jax.Array:
    """(..., N, 14 + 16 (N-1) + ZF) observation rows from own (..., N, 14) masked own
    features, position (..., N, 2), inv_half (..., 2) = 1 / half the arena, team (..., N),
    seen (..., N, N) bool (viewer sees unit, both slots active), attackable (..., N, N) bool
    and zones (..., N, ZF) masked zone features; `...` is any batch shape (none for one env),
    and inv_half and team broadcast over it. Other unit j's block in viewer i's row: health,
    health ratio, (p_j - p_i) * inv_half, heading .. alive (own features 4..12), is ally,
    attackable, speed; zeros where i does not see j."""
    batch, n = own.shape[:-2], own.shape[-2]
    bind = assemble_xla if assemble_p is None else assemble_p.bind
    return bind(own.astype(jnp.float32), position.astype(jnp.float32),
                           jnp.broadcast_to(inv_half, (*batch, 2)).astype(jnp.float32),
                           jnp.broadcast_to(team, (*batch, n)).astype(jnp.int32),
                           seen.astype(bool), attackable.astype(bool),
                           zones.astype(jnp.float32))


__all__ = ["assemble_observation", "assemble_p", "assemble_xla"]
