"""A linear map with a hand-written transpose, as a JAX primitive.

A kernel with a hand-written reverse mode (a ``jax.custom_vjp``) has no forward mode:
``jax.jvp``, ``jax.jacfwd`` and optimistix's default forward-mode Jacobians fail on it.
Written instead as a ``jax.custom_jvp`` whose tangent is one of these primitives, it has
both: forward mode evaluates the tangent map ``fn``, which can be a cheap pass of its
own, and reverse mode transposes it by calling the hand-written ``transpose``, so the
gradient costs what it did. (``jax.custom_derivatives.linear_call`` couples a map and
its transpose the same way but has no batching rule, so it fails under ``jax.vmap``.)

The primitive's operands are ``residuals`` (values the map depends on non-linearly) and
``linear`` ones; ``fn(*residuals, *linear, **static)`` returns a tuple of arrays, linear
in the ``linear`` operands, and ``transpose(*residuals, *cotangents, **static)`` returns
one cotangent per linear operand. ``static`` holds hashable configuration, and ``live``,
which flags the linear operands that are not zero: the tangents of a custom JVP rule
defined with ``symbolic_zeros=True`` are taken as they come, a symbolic zero passed as a
scalar zero that ``fn`` need not read (a derivative in the radius alone does not march
a zero opacity tangent) and whose cotangent ``transpose`` need not form. ``jax.vmap``
adds a batch level: ``fn`` and ``transpose`` are then mapped with ``jax.vmap``, each
operand over the levels it carries, and a linear operand's cotangent is summed over the
levels it does not carry.
"""

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir


def jvp_of_live(fn: Callable, primals: list, tangents: list, live) -> tuple:
    """``jax.jvp(fn, primals, tangents)`` in the arguments that ``live`` flags, the others
    held constant (their tangents are not read): a zero tangent instantiated would be
    carried through ``fn``'s loops, e.g. a zero ``(S, ..., 3)`` colour tangent for a
    derivative in the opacities alone."""
    def given(*moving):
        it = iter(moving)
        return fn(*(next(it) if on else x for x, on in zip(primals, live, strict=True)))

    return jax.jvp(given, [x for x, on in zip(primals, live, strict=True) if on],
                   [t for t, on in zip(tangents, live, strict=True) if on])


def jvp_of_nonzero(fn: Callable, primals, tangents) -> tuple:
    """:func:`jvp_of_live` for a custom JVP rule defined with ``symbolic_zeros=True``:
    ``primals`` and ``tangents`` are argument tuples (pytrees), and the leaves whose
    tangent is a ``SymbolicZero`` are held constant."""
    leaves, tree = jax.tree.flatten(primals)
    dots = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
    live = [not isinstance(t, SymbolicZero) for t in dots]
    return jvp_of_live(lambda *x: fn(*jax.tree.unflatten(tree, x)), leaves, dots, live)


def _mapped(fn: Callable, levels: tuple) -> Callable:
    """``fn`` vmapped over the batch ``levels`` (outermost first): at each level the
    operands that carry it are mapped over their leading axis."""
    for mask in reversed(levels):
        fn = jax.vmap(fn, in_axes=tuple(0 if m else None for m in mask))
    return fn


def _mapped_transpose(transpose: Callable, levels: tuple, n_residuals: int) -> Callable:
    """``transpose`` vmapped over ``levels`` like :func:`_mapped` (the cotangents carry
    every level), each linear operand's cotangent summed over the levels it lacks."""
    for mask in reversed(levels):
        def level(*args, _inner=transpose, _mask=mask):
            res_mask, lin_mask = _mask[:n_residuals], _mask[n_residuals:]
            n_cts = len(args) - n_residuals
            outs = jax.vmap(_inner, in_axes=(*(0 if m else None for m in res_mask),
                                             *(0,) * n_cts))(*args)
            return tuple(o if m else jnp.sum(o, axis=0)
                         for o, m in zip(outs, lin_mask, strict=True))

        transpose = level
    return transpose


def linear_primitive(name: str, fn: Callable, transpose: Callable,
                     n_residuals: int) -> Callable:
    """``apply(residuals, tangents, **static)``: ``fn(*residuals, *tangents, live=...,
    **static)`` (a tuple) as a primitive that is linear in the tangents, transposed by
    ``transpose`` (see the module docstring). Differentiating it in its residuals (a
    second derivative) goes through JAX's own forward mode of ``fn``."""
    prim = Primitive(name)
    prim.multiple_results = True

    def impl(*operands, levels, **static):
        return _mapped(functools.partial(fn, **static), levels)(*operands)

    def abstract_eval(*avals, levels, **static):
        shapes = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in avals]
        outs = jax.eval_shape(functools.partial(impl, levels=levels, **static), *shapes)
        return [jax.core.ShapedArray(o.shape, o.dtype) for o in outs]

    def jvp(primals, tangents, *, levels, **static):
        res, lin = primals[:n_residuals], primals[n_residuals:]
        d_res, d_lin = tangents[:n_residuals], tangents[n_residuals:]
        out = prim.bind(*primals, levels=levels, **static)
        if all(type(t) is ad.Zero for t in d_lin):
            d_out = [jnp.zeros_like(o) for o in out]
        else:
            d_out = prim.bind(*res, *map(ad.instantiate_zeros, d_lin), levels=levels,
                              **static)
        if any(type(t) is not ad.Zero for t in d_res):
            _, d_second = jax.jvp(lambda *r: impl(*r, *lin, levels=levels, **static), res,
                                  tuple(map(ad.instantiate_zeros, d_res)))
            d_out = [a + b for a, b in zip(d_out, d_second, strict=True)]
        return out, d_out

    def transpose_rule(cotangents, *operands, levels, **static):
        res, lin = operands[:n_residuals], operands[n_residuals:]
        if any(ad.is_undefined_primal(r) for r in res):
            raise ValueError(f"volshade: {name} is linear only in its last "
                             f"{len(lin)} operands; it was transposed in its residuals.")
        if all(type(ct) is ad.Zero for ct in cotangents):
            return [None] * len(operands)
        cts = _mapped_transpose(functools.partial(transpose, **static), levels, n_residuals)(
            *res, *map(ad.instantiate_zeros, cotangents))
        return [None] * n_residuals + [ct if ad.is_undefined_primal(x) else None
                                       for ct, x in zip(cts, lin, strict=True)]

    def batch(args, dims, *, levels, **static):
        mask = tuple(d is not None for d in dims)
        args = [a if d is None else jnp.moveaxis(a, d, 0)
                for a, d in zip(args, dims, strict=True)]
        outs = prim.bind(*args, levels=(mask, *levels), **static)
        return outs, [0] * len(outs)

    prim.def_impl(impl)
    prim.def_abstract_eval(abstract_eval)
    ad.primitive_jvps[prim] = jvp
    ad.primitive_transposes[prim] = transpose_rule
    batching.primitive_batchers[prim] = batch
    mlir.register_lowering(prim, mlir.lower_fun(impl, multiple_results=True))

    def apply(residuals, tangents, **static):
        tangents = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
        live = tuple(not isinstance(t, SymbolicZero) for t in tangents)
        linear = [t if on else jnp.zeros((), t.aval.dtype)
                  for t, on in zip(tangents, live, strict=True)]
        if not any(live):
            return [jnp.zeros(o.shape, o.dtype) for o in jax.eval_shape(
                functools.partial(impl, levels=(), live=live, **static), *residuals, *linear)]
        return prim.bind(*residuals, *linear, levels=(), live=live, **static)

    return apply
