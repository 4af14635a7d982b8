"""Tests of volshade._linear: a linear primitive with a hand-written transpose, against
JAX's own derivatives of the same map, under every transformation a kernel meets."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.custom_derivatives import SymbolicZero

from volshade._linear import linear_primitive

_TRANSPOSED = []


def _scale(r, x, y, *, k, live=(True, True)):
    """A map linear in ``(x, y)``: ``k sin(r) x + cos(r) y`` and ``r x`` (``live`` flags
    the tangents that are not zero: the others are scalar zeros)."""
    x, y = (t if on else jnp.zeros_like(r) for t, on in zip((x, y), live, strict=True))
    return k * jnp.sin(r) * x + jnp.cos(r) * y, r * x


def _scale_transpose(r, c0, c1, *, k, live):
    _TRANSPOSED.append(live)  # traced only: records that this transpose, not JAX's, ran
    return k * jnp.sin(r) * c0 + r * c1, jnp.cos(r) * c0


_apply = linear_primitive("test_linear_scale", _scale, _scale_transpose, n_residuals=1)


@jax.custom_jvp
def _f(r, x, y):
    """``sum`` of the two outputs of :func:`_scale` at ``(r, x, y)`` minus ``r^2``: its
    derivative in ``(x, y)`` is the primitive, in ``r`` plain JAX."""
    return _plain(r, x, y)


def _plain(r, x, y):
    a, b = _scale(r, x, y, k=2.0)
    return a + b - r**2


def _f_jvp(primals, tangents):
    r, x, y = primals
    dr, dx, dy = tangents
    a, b = _apply((r,), (dx, dy), k=2.0)
    # the residual's derivative, through JAX (as a kernel's rule would give it)
    _, d_r = jax.jvp(lambda r: _plain(r, x, y), (r,), (dr,))
    return _f(r, x, y), a + b + d_r


_f.defjvp(_f_jvp)


@jax.custom_jvp
def _g(r, x, y):
    """:func:`_f` with a rule that passes symbolic zeros on to the primitive."""
    return _plain(r, x, y)


def _g_jvp(primals, tangents):
    r, x, y = primals
    dr, dx, dy = tangents
    a, b = _apply((r,), (dx, dy), k=2.0)
    if isinstance(dr, SymbolicZero):
        return _g(r, x, y), a + b
    return _g(r, x, y), a + b + jax.jvp(lambda r: _plain(r, x, y), (r,), (dr,))[1]


_g.defjvp(_g_jvp, symbolic_zeros=True)


def _args(seed, batch=()):
    rng = np.random.default_rng(seed)
    return tuple(jnp.asarray(rng.normal(size=(*batch, 5))) for _ in range(3))


def _close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-14)


def test_forward_and_reverse_mode_equal_jax_on_the_plain_map():
    # first derivatives eagerly (the primitive's rules run op by op), the rest and JAX's
    # references each jitted alone: eagerly the second derivatives compiled some 250
    # small programs, one per operation and shape (merged into one jitted program the
    # references compiled slower still)
    args = _args(0)
    t = _args(1)
    jit = jax.jit
    want_jvp = jit(lambda a, t: jax.jvp(_plain, a, t))(args, t)
    _close(jax.jvp(_f, args, t), want_jvp)
    _TRANSPOSED.clear()
    loss = lambda *a: jnp.sum(jnp.sin(_f(*a)))  # noqa: E731
    plain_loss = lambda *a: jnp.sum(jnp.sin(_plain(*a)))  # noqa: E731
    _close(jax.grad(loss, (0, 1, 2))(*args), jit(jax.grad(plain_loss, (0, 1, 2)))(*args))
    assert _TRANSPOSED  # reverse mode went through the hand-written transpose
    _close(jit(jax.grad(loss, (1, 2)))(*args), jit(jax.grad(plain_loss, (1, 2)))(*args))
    _close(jit(jax.grad(jax.checkpoint(loss), 1))(*args), jit(jax.grad(plain_loss, 1))(*args))
    _close(jit(jax.jacfwd(_f, (0, 1, 2)))(*args), jit(jax.jacrev(_plain, (0, 1, 2)))(*args))
    # second derivatives: forward over reverse, reverse over forward, forward over forward
    _close(jit(jax.hessian(loss, (0, 1)))(*args), jit(jax.hessian(plain_loss, (0, 1)))(*args))
    _close(jit(jax.jacrev(jax.jacfwd(loss, 1), 0))(*args),
           jit(jax.jacrev(jax.jacfwd(plain_loss, 1), 0))(*args))
    _close(jit(jax.jacfwd(jax.jacfwd(loss, 2), 0))(*args),
           jit(jax.jacfwd(jax.jacfwd(plain_loss, 2), 0))(*args))
    # a VJP transposed back into forward mode
    out, vjp = jax.vjp(_f, *args)
    _close(jax.linear_transpose(vjp, out)(t), want_jvp[1])


def test_symbolic_zero_tangents_are_flagged_and_not_formed():
    # a derivative in x alone: y's tangent is a symbolic zero, flagged as not live for
    # the map and its transpose; in r alone, no linear operand is live (zeros, no bind)
    args = _args(8)
    loss = lambda f: lambda *a: jnp.sum(jnp.sin(f(*a)))  # noqa: E731
    _TRANSPOSED.clear()
    _close(jax.grad(loss(_g), 1)(*args), jax.grad(loss(_plain), 1)(*args))
    assert _TRANSPOSED == [(True, False)]
    _close(jax.grad(loss(_g), 0)(*args), jax.grad(loss(_plain), 0)(*args))
    _close(jax.jvp(_g, args, (jnp.zeros(5), jnp.zeros(5), jnp.ones(5))),
           jax.jvp(_plain, args, (jnp.zeros(5), jnp.zeros(5), jnp.ones(5))))
    _close(jax.vmap(jax.grad(loss(_g), 2))(*_args(9, (2,))),
           jax.vmap(jax.grad(loss(_plain), 2))(*_args(9, (2,))))


@pytest.mark.parametrize("axes", [(0, 0, 0), (0, None, None), (None, 0, None), (None, None, 0)])
def test_vmap_maps_each_operand_over_the_levels_it_carries(axes):
    # a residual shared by the batch, or linear operands shared: the transpose sums the
    # cotangent of an operand over the levels it does not carry
    batched = _args(2, (3,))
    args = tuple(b if a == 0 else b[0] for a, b in zip(axes, batched, strict=True))
    t = _args(3, (3,))
    def jvp(g):
        return jax.vmap(lambda r, x, y, tr, tx, ty: jax.jvp(g, (r, x, y), (tr, tx, ty))[1],
                        (*axes, 0, 0, 0))

    def mapped_loss(g):
        return lambda *a: jnp.sum(jnp.cos(jax.vmap(g, axes)(*a)))

    def mapped_grad(g):
        return jax.vmap(jax.grad(lambda *a: jnp.sum(jnp.cos(g(*a))), (0, 1, 2)), axes)

    # JAX's references jitted (eagerly each compiled a program per operation)
    _close(jax.jit(jvp(_f))(*args, *t), jax.jit(jvp(_plain))(*args, *t))
    _close(jax.grad(mapped_loss(_f), (0, 1, 2))(*args),
           jax.jit(jax.grad(mapped_loss(_plain), (0, 1, 2)))(*args))
    _close(mapped_grad(_f)(*args), jax.jit(mapped_grad(_plain))(*args))


@pytest.mark.parametrize("size", [2, 0])
def test_an_output_no_mapped_operand_reaches_keeps_its_cotangent(size):
    # the map's second output r x does not depend on y: under a vmap over y alone it stays
    # unmapped, and its cotangent reaches x also when the vmap is empty (it came out 0)
    r, x, ys = _args(10)[0], _args(11)[1], _args(12, (size,))[2]

    def second(x, scale):
        return jax.vmap(lambda y: tuple(scale((r,), (x, y), k=2.0)), out_axes=(0, None))(ys)[1]

    out, vjp = jax.vjp(lambda x: second(x, _apply), x)
    want_out, want_vjp = jax.vjp(lambda x: second(x, lambda res, lin, k: _scale(*res, *lin, k=k)),
                                 x)
    c = _args(13)[0]
    _close((out, vjp(c)), (want_out, want_vjp(c)))
    assert float(jnp.max(jnp.abs(vjp(c)[0]))) > 0.1


def test_nested_vmap_with_operands_on_different_levels():
    # the residual on the outer level, x on the inner one, y on both
    r = _args(4, (2,))[0]
    x = _args(5, (3,))[1]
    y = _args(6, (2, 3))[2]

    def nested(f):
        return jax.vmap(jax.vmap(f, (None, 0, 0)), (0, None, 0))

    # JAX's references jitted (eagerly each compiled a program per operation)
    _close(jax.jit(nested(_f))(r, x, y), jax.jit(nested(_plain))(r, x, y))
    loss = lambda f: lambda *a: jnp.sum(jnp.sin(nested(f)(*a)))  # noqa: E731
    _close(jax.grad(loss(_f), (0, 1, 2))(r, x, y),
           jax.jit(jax.grad(loss(_plain), (0, 1, 2)))(r, x, y))
    t = (jnp.ones_like(r), jnp.ones_like(x), jnp.ones_like(y))
    _close(jax.jvp(loss(_f), (r, x, y), t),
           jax.jit(lambda *a: jax.jvp(loss(_plain), a, t))(r, x, y))


def test_inside_scan_and_cond():
    args = _args(7)

    def through(f):
        def body(c, s):
            out = jax.lax.cond(s > 0, lambda: f(args[0] * s, c, args[2]), lambda: c)
            return out, jnp.sum(out)

        return lambda x: jnp.sum(jax.lax.scan(body, x, jnp.asarray([0.5, -1.0, 2.0]))[1])

    _close(jax.grad(through(_f))(args[1]), jax.grad(through(_plain))(args[1]))
    _close(jax.jvp(through(_f), (args[1],), (args[2],)),
           jax.jvp(through(_plain), (args[1],), (args[2],)))


def test_transposing_in_a_residual_is_refused():
    # the map is linear in its linear operands only: a transpose in the residual is a
    # misuse of the primitive, refused by name
    def g(r):
        return _apply((r,), (jnp.ones(5), jnp.ones(5)), k=1.0)[0]

    with pytest.raises(ValueError, match="linear only in its last 2 operands"):
        jax.linear_transpose(g, jnp.ones(5))(jnp.ones(5))


def test_a_python_number_residual_keeps_the_outputs_dtype():
    # a weakly typed residual (a Python float) beside float32 operands under x64: the
    # primitive's abstract value dropped the weak type, so its outputs came out float64
    # where the map gives float32, and jax.grad refused the rule (found by a review)
    x = jnp.ones(2, jnp.float32)
    tangent = jax.jvp(lambda x: _f(1.5, x, x), (x,), (x,))[1]
    assert tangent.dtype == jnp.float32
    grad = jax.jit(jax.grad(lambda x: jnp.sum(_f(1.5, x, x))))(x)
    assert grad.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(grad), np.asarray(jax.grad(
        lambda x: jnp.sum(_plain(1.5, x, x)))(x)), rtol=1e-6)  # (float32)
