"""A linear map with a hand-written transpose, as a pair of JAX primitives.

A kernel with a hand-written reverse mode (a ``jax.custom_vjp``) has no forward mode:
``jax.jvp``, ``jax.jacfwd`` and optimistix's default forward-mode Jacobians fail on it.
Written instead as a ``jax.custom_jvp`` whose tangent is computed by one of these
primitives, it has both: forward mode evaluates the tangent map ``fn``, which can be a
cheap pass of its own, and reverse mode binds the transpose primitive, which evaluates
the hand-written ``transpose``, so the gradient costs what it did. The two primitives
transpose into each other, as ``jax.custom_derivatives.linear_call`` does (which has
no batching rule, so it fails under ``jax.vmap``).

The operands are ``residuals`` (values the map depends on non-linearly) and linear
ones: ``fn(*residuals, *tangents, live=..., **static)`` returns a tuple of arrays, linear
in the tangents, and ``transpose(*residuals, *cotangents, live=..., **static)`` one
cotangent per tangent. ``static`` holds hashable configuration, and ``live`` flags the
tangents that are not zero: a custom JVP rule's tangents (``symbolic_zeros=True``) are
taken as they come, a symbolic zero passed as a scalar zero that ``fn`` need not read
(a derivative in the radius alone does not march a zero opacity tangent) and whose
cotangent ``transpose`` need not form.

Derivatives in the residuals (second derivatives, e.g. ``jax.hessian``, forward over
reverse) are JAX's forward mode through ``fn`` or ``transpose``, except in the residuals
named ``constant``: the map is taken at a fixed value of those, and a derivative in them
is refused with the message given.

Batching: each ``jax.vmap`` adds a level. The map at a level is ``jax.vmap`` of the
level below, each operand mapped if it carries the level, and each output mapped if it
depends on an operand that does (found on the map's jaxpr), else left unmapped. The
transpose of a mapped level maps the transpose back: the cotangent of a tangent the
level did not map is summed over the level, and the cotangent of an output it did not
map (which depends on no mapped operand) is shared out, ``1/size`` to each element (an
empty level gives it whole to one element, at mapped operands of zero).
"""

import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jax.interpreters import partial_eval as pe


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


class _Level(NamedTuple):
    """One batch level: which residuals, linear operands and outputs carry it (their
    leading axis), its size, and whether it is the transpose of a mapped level."""

    residuals: tuple[bool, ...]
    linear: tuple[bool, ...]
    outputs: tuple[bool, ...]
    size: int
    transposed: bool

    def transpose(self) -> "_Level":
        return _Level(self.residuals, self.outputs, self.linear, self.size,
                      not self.transposed)


def _axes(mask) -> tuple:
    return tuple(0 if m else None for m in mask)


def _mapped(fn: Callable, levels: tuple[_Level, ...]) -> Callable:
    """``fn(*residuals, *linear)`` over the batch ``levels``, outermost first (see the
    module docstring)."""
    for level in reversed(levels):
        def at_level(*operands, _inner=fn, _level=level):
            n = len(_level.residuals)
            if not _level.transposed:
                return jax.vmap(_inner, in_axes=_axes(_level.residuals + _level.linear),
                                out_axes=_axes(_level.outputs), axis_size=_level.size)(
                    *operands)
            # the transpose of a mapped level: an unmapped cotangent belongs to an output
            # that no mapped operand reaches, and is shared out over the level; an empty
            # level has no element to share it out to, so one element takes it whole, at
            # mapped operands of zero (which that output does not depend on)
            mapped = _level.residuals + _level.linear
            size = max(_level.size, 1)
            if _level.size == 0:
                operands = [jnp.zeros((1, *x.shape[1:]), x.dtype) if m else x
                            for x, m in zip(operands, mapped, strict=True)]
            linear = [x if m else x / size
                      for x, m in zip(operands[n:], _level.linear, strict=True)]
            outs = jax.vmap(_inner, in_axes=_axes(mapped), axis_size=size)(
                *operands[:n], *linear)
            return tuple((o if _level.size else o[:0]) if m else jnp.sum(o, axis=0)
                         for o, m in zip(outs, _level.outputs, strict=True))

        fn = at_level
    return fn


def linear_primitive(name: str, fn: Callable, transpose: Callable, n_residuals: int,
                     constant: Mapping[int, str] | None = None) -> Callable:
    """``apply(residuals, tangents, **static)``: ``fn(*residuals, *tangents, live=...,
    **static)`` (a tuple) as a primitive linear in the tangents, whose transpose is a
    primitive evaluating ``transpose`` (see the module docstring). ``constant`` maps the
    index of a residual the map is taken at a fixed value of to the message that refuses
    a derivative in it."""
    constant = dict(constant or {})
    forward, backward = Primitive(name), Primitive(f"{name}_transpose")
    partner = {forward: (backward, fn), backward: (forward, transpose)}

    def define(prim: Primitive) -> None:
        other, body = partner[prim]
        prim.multiple_results = True

        # the map at given levels and configuration as one jit, so that abstract
        # evaluation, batching, lowering and JAX's forward mode reuse one trace per
        # operand type instead of tracing the map again each (a bricked LAO Hessian
        # traced in 2.0 s instead of 7.4 s)
        @functools.lru_cache(maxsize=256)
        def program(levels, static):
            return jax.jit(_mapped(functools.partial(body, **dict(static)), levels))

        def impl(*operands, levels, **static):
            return program(levels, tuple(sorted(static.items())))(*operands)

        def abstract_eval(*avals, levels, **static):
            # (weak types kept: a Python-number residual must not widen the outputs)
            shapes = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                      for a in avals]
            outs = jax.eval_shape(functools.partial(impl, levels=levels, **static), *shapes)
            return [jax.core.ShapedArray(o.shape, o.dtype, weak_type=o.weak_type)
                    for o in outs]

        def jvp(primals, tangents, *, levels, **static):
            res, lin = primals[:n_residuals], primals[n_residuals:]
            d_res, d_lin = tangents[:n_residuals], tangents[n_residuals:]
            for i, message in constant.items():
                if type(d_res[i]) is not ad.Zero:
                    raise ValueError(message)
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
                raise ValueError(f"volshade: {name} is linear only in its last {len(lin)} "
                                 f"operands; it was transposed in its residuals.")
            if all(type(ct) is ad.Zero for ct in cotangents):
                return [None] * len(operands)
            cts = other.bind(*res, *map(ad.instantiate_zeros, cotangents),
                             levels=tuple(level.transpose() for level in levels), **static)
            return [None] * n_residuals + [ct if ad.is_undefined_primal(x) else None
                                           for ct, x in zip(cts, lin, strict=True)]

        def batch(args, dims, *, levels, **static):
            mapped = tuple(d is not None for d in dims)
            size = next(a.shape[d] for a, d in zip(args, dims, strict=True) if d is not None)
            args = [a if d is None else jnp.moveaxis(a, d, 0)
                    for a, d in zip(args, dims, strict=True)]
            # an output that no mapped operand reaches stays unmapped (its value and
            # tangent must agree on that, e.g. a compositor's transmittance under a vmap
            # over the colours alone)
            shapes = [jax.ShapeDtypeStruct(a.shape[1:] if m else a.shape, a.dtype)
                      for a, m in zip(args, mapped, strict=True)]
            jaxpr = jax.make_jaxpr(functools.partial(impl, levels=levels, **static))(
                *shapes).jaxpr
            n_outs = len(jaxpr.outvars)
            outputs = []
            for k in range(n_outs):
                _, used = pe.dce_jaxpr(jaxpr, [j == k for j in range(n_outs)])
                outputs.append(any(u and m for u, m in zip(used, mapped, strict=True)))
            level = _Level(mapped[:n_residuals], mapped[n_residuals:], tuple(outputs), size,
                           False)
            outs = prim.bind(*args, levels=(level, *levels), **static)
            return outs, [0 if m else None for m in outputs]

        prim.def_impl(impl)
        prim.def_abstract_eval(abstract_eval)
        ad.primitive_jvps[prim] = jvp
        ad.primitive_transposes[prim] = transpose_rule
        batching.primitive_batchers[prim] = batch
        mlir.register_lowering(prim, mlir.lower_fun(impl, multiple_results=True))

    define(forward)
    define(backward)

    def apply(residuals, tangents, **static):
        tangents = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
        live = tuple(not isinstance(t, SymbolicZero) for t in tangents)
        linear = [t if on else jnp.zeros((), t.aval.dtype)
                  for t, on in zip(tangents, live, strict=True)]
        if not any(live):
            # the shapes of a map of tangents taken as given (zeros), so that a map need
            # not handle all its tangents being zero
            shapes = jax.eval_shape(functools.partial(fn, **static, live=(True,) * len(live)),
                                    *residuals, *(t.aval for t in tangents))
            return [jnp.zeros(o.shape, o.dtype) for o in shapes]
        return forward.bind(*residuals, *linear, levels=(), live=live, **static)

    return apply
