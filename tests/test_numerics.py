import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade as vs
from volshade import _numerics as nm


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_values_keep_dtype(dtype):
    x = jnp.asarray([0.0, 0.25, 1.0], dtype)
    for fn in (nm.safe_log, nm.log1m, nm.safe_sqrt):
        assert fn(x).dtype == dtype
    assert nm.safe_div(x, x).dtype == dtype
    assert nm.correct_opacity(x, 2.0).dtype == dtype


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_edge_pad_equals_jnp_pad_and_its_transpose(dtype):
    # the same values, tiny and huge, with one-voxel axes and uneven widths (compared as
    # values: a -0 comes out +0); its pullback is jnp.pad's (the border cotangents summed
    # onto the edge voxels)
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(4, 1, 5)) * 10.0 ** rng.integers(-30, 30, size=(4, 1, 5)),
                    dtype).at[0, 0, 0].set(-0.0)
    widths = [(2, 1), (0, 3), (1, 0)]
    got, ref = nm.edge_pad(x, widths), jnp.pad(x, widths, mode="edge")
    assert got.dtype == dtype and got.shape == ref.shape
    assert np.array_equal(np.asarray(got), np.asarray(ref))
    w = jnp.asarray(rng.normal(size=ref.shape), dtype)

    def pullback(pad):  # jitted: eagerly it compiled a program per operation
        return jax.jit(lambda x, w: jax.vjp(pad, x)[1](w)[0])(x, w)

    np.testing.assert_allclose(pullback(lambda x: nm.edge_pad(x, widths)),
                               pullback(lambda x: jnp.pad(x, widths, mode="edge")),
                               rtol=1e-6 if dtype == jnp.float32 else 1e-14)


def test_safe_div_singular_point():
    assert float(nm.safe_div(1.0, 0.0)) == 0.0
    g_num, g_den = jax.grad(nm.safe_div, argnums=(0, 1))(1.0, 0.0)
    assert float(g_num) == 0.0 and float(g_den) == 0.0
    np.testing.assert_allclose(jax.grad(nm.safe_div, argnums=1)(3.0, 2.0), -0.75)


def test_quotient_slopes_without_den_squared():
    num, den = jnp.asarray([3.0, -1.5]), jnp.asarray([2.0, 0.25])
    np.testing.assert_array_equal(nm.quotient(num, den), num / den)
    # each Jacobian jitted (eagerly it compiled a program per operation)
    for jac in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(jax.jit(jac(nm.quotient, (0, 1)))(num, den),
                                   jax.jit(jac(jnp.divide, (0, 1)))(num, den), rtol=1e-15)
    # float32, den = 1e-20: den ** -2 overflows (`/` gives -inf here), the slope
    # -num / den ** 2 = -1e20 does not
    num32, den32 = jnp.float32(1e-20), jnp.float32(1e-20)
    np.testing.assert_allclose(jax.grad(nm.quotient, 1)(num32, den32), -1e20, rtol=1e-6)
    np.testing.assert_allclose(jax.grad(nm.quotient)(num32, den32), 1e20, rtol=1e-6)
    # an integer operand is a float without a tangent
    np.testing.assert_allclose(jax.grad(lambda d: nm.quotient(jnp.arange(3), d).sum())(2.0),
                               -0.75)
    np.testing.assert_allclose(jax.grad(lambda n: nm.quotient(n, 4).sum())(jnp.ones(3)),
                               [0.25] * 3)
    assert nm.quotient(3, 2).dtype == jnp.result_type(float)
    # safe_div and smoothstep differentiate through it: edges 1e-20 apart in float32
    np.testing.assert_allclose(jax.grad(nm.safe_div, 1)(num32, den32), -1e20, rtol=1e-6)
    x = jnp.asarray([0.0, 3e-21, 0.5], jnp.float32)
    g0, g1 = jax.grad(lambda e0, e1: jnp.sum(nm.smoothstep(e0, e1, x)), (0, 1))(
        jnp.float32(0.0), den32)
    # t = x / e1 = 0.3 at 3e-21: d/de1 = -6 t (1 - t) t / e1, d/de0 = 6 t (1 - t) (t - 1) / e1
    np.testing.assert_allclose([g0, g1], [6 * 0.21 * -0.7 / 1e-20, -6 * 0.21 * 0.3 / 1e-20],
                               rtol=1e-5)


def test_safe_log_and_log1m():
    assert float(nm.safe_log(0.0)) == -np.inf
    assert float(jax.grad(nm.safe_log)(0.0)) == 0.0
    np.testing.assert_allclose(jax.grad(nm.safe_log)(2.0), 0.5)
    assert float(nm.log1m(1.0)) == -np.inf
    assert float(jax.grad(nm.log1m)(1.0)) == 0.0
    np.testing.assert_allclose(nm.log1m(1e-12), -1e-12, rtol=1e-12)
    np.testing.assert_allclose(jax.grad(nm.log1m)(0.5), -2.0)
    # NaN stays NaN (a review: it took the branch of x <= 0, -inf, and e.g. the
    # renderer's clamped optical depth made it a finite number)
    for fn in (nm.safe_log, nm.log1m, nm.safe_sqrt, lambda x: nm.safe_pow(x, 2.0),
               lambda x: nm.correct_opacity(x, 2.0), lambda r: nm.correct_opacity(1.0, r)):
        assert np.isnan(float(fn(jnp.nan)))


def test_safe_sqrt_norm_normalize_at_zero():
    assert float(jax.grad(nm.safe_sqrt)(0.0)) == 0.0
    g = jax.grad(lambda v: nm.safe_norm(v))(jnp.zeros(3))
    np.testing.assert_array_equal(g, 0.0)
    np.testing.assert_array_equal(nm.safe_normalize(jnp.zeros(3)), 0.0)
    jac = jax.jacrev(nm.safe_normalize)(jnp.zeros(3))
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(nm.safe_normalize(jnp.array([3.0, 0, 4])), [0.6, 0, 0.8])


@pytest.mark.parametrize("scale", [1e20, 3e38])
def test_safe_normalize_of_a_huge_vector(scale):
    # found by a review: float32 |x|^2 overflowed above 1.8e19 and x / inf gave the zero
    # vector (obscurance_shading of such a gradient: 0, not 1)
    x = jnp.asarray([3.0, 0.0, 4.0], jnp.float32)
    big = x * jnp.float32(scale / 4)
    np.testing.assert_allclose(nm.safe_normalize(big), [0.6, 0, 0.8], rtol=1e-6)
    # the direction is scale-invariant, so its Jacobian at c x is that at x over c (at
    # 3e38 that is below float32's normal numbers)
    jac = jax.jit(jax.jacrev(nm.safe_normalize))  # one program for its three calls
    if scale < 1e30:
        np.testing.assert_allclose(np.asarray(jac(big), np.float64) * (scale / 4),
                                   jac(x), rtol=1e-5, atol=1e-7)
    assert np.all(np.isfinite(jac(big)))
    shade = vs.obscurance_shading(big[None], jnp.asarray([0.6, 0, 0.8]),
                                  jnp.asarray([0.6, 0, 0.8]), jnp.asarray([1.0]),
                                  k_d=0.6, k_s=0.4, shininess=8.0)
    np.testing.assert_allclose(shade, [1.0], rtol=1e-6)
    # components of at most 1 are not rescaled: the same bits as before
    small = jnp.asarray([0.3, -1.0, 0.5], jnp.float32)
    np.testing.assert_array_equal(nm.safe_normalize(small), small / jnp.linalg.norm(small))


def test_correct_opacity_exact_ends_and_composition_law():
    # Two half steps compose to one full step: 1 - (1 - a')^2 == a.
    a = jnp.linspace(0, 1, 11)
    half = nm.correct_opacity(a, 0.5)
    np.testing.assert_allclose(1 - (1 - half) ** 2, a, atol=1e-12)
    assert float(nm.correct_opacity(1.0, 0.3)) == 1.0
    assert float(nm.correct_opacity(0.0, 0.3)) == 0.0


# opacities on [0, 1] and step ratios below, at and above 1
_ALPHA, _RATIO = np.meshgrid(np.linspace(0, 1, 201), [0.25, 0.5, 1.0, 1.7, 3.0], indexing="ij")


def test_correct_opacity_is_the_step_correction():
    # alpha' = 1 - (1 - alpha)^r, written out here (the LAO reference uses the same formula)
    got = nm.correct_opacity(jnp.asarray(_ALPHA), jnp.asarray(_RATIO))
    np.testing.assert_allclose(got, 1 - (1 - _ALPHA) ** _RATIO, rtol=1e-13, atol=1e-14)


def test_correct_opacity_gradients_are_analytic():
    # d/da = r (1 - a)^(r - 1), d/dr = -(1 - a)^r log(1 - a), below a = 1 (a = 1 is
    # test_correct_opacity_at_one's). atol: jax differentiates expm1 as expm1 + 1, which
    # holds (1 - a)^r to an absolute, not relative, float64 eps (rel. 1e-10 at 1e-7)
    a, r = _ALPHA[:-1], _RATIO[:-1]
    g_a, g_r = jax.vmap(jax.vmap(jax.grad(nm.correct_opacity, argnums=(0, 1))))(
        jnp.asarray(a), jnp.asarray(r))
    np.testing.assert_allclose(g_a, r * (1 - a) ** (r - 1), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(g_r, -(1 - a) ** r * np.log1p(-a), rtol=1e-12, atol=1e-13)


def test_opacity_from_extinction_and_smoothstep():
    np.testing.assert_allclose(nm.opacity_from_extinction(2.0, 0.5), 1 - np.exp(-1.0))
    x = jnp.array([-1.0, 0.4, 0.7, 1.0, 2.0])
    np.testing.assert_allclose(nm.smoothstep(0.4, 1.0, x), [0, 0, 0.5, 1, 1], atol=1e-12)
    assert np.isfinite(jax.grad(lambda e: nm.smoothstep(e, e, 0.5))(0.5))
    # equal edges: the step to 1 at the edge (0/0 made it 0 everywhere)
    np.testing.assert_array_equal(nm.smoothstep(0.4, 0.4, x), [0, 1, 1, 1, 1])


def test_safe_pow_at_zero():
    assert float(nm.safe_pow(0.0, 3.0)) == 0.0
    gx, gp = jax.grad(nm.safe_pow, argnums=(0, 1))(0.0, 3.0)
    assert float(gx) == 0.0 and float(gp) == 0.0
    # one-sided slopes at 0: p 0^(p - 1) is 1 for p = 1 (it was given as 0: found by a
    # review, with an exponent of 1 on a gradient magnitude of 0)
    for p, slope in ((1.0, 1.0), (2.5, 0.0)):
        assert float(jax.grad(nm.safe_pow)(0.0, p)) == slope
        assert float(jax.grad(nm.safe_pow, argnums=1)(0.0, p)) == 0.0
    assert float(jax.grad(nm.safe_pow)(-1e-16, 1.0)) == 0.0 == float(nm.safe_pow(-1e-16, 1.0))
    np.testing.assert_allclose(nm.safe_pow(2.0, 3.0), 8.0)
    np.testing.assert_allclose(jax.grad(nm.safe_pow, argnums=1)(2.0, 3.0), 8.0 * np.log(2.0))


@pytest.mark.parametrize("ratio, slope", [(1.0, 1.0), (2.0, 0.0), (0.5, 0.0)])
def test_correct_opacity_at_one(ratio, slope):
    # d/da [1 - (1 - a)^r] = r (1 - a)^(r - 1) at a = 1: 1 for r = 1 (the identity), 0 for
    # r > 1; infinite for r < 1, where 0 keeps gradients finite
    assert float(nm.correct_opacity(1.0, ratio)) == 1.0
    assert float(jax.grad(nm.correct_opacity)(1.0, ratio)) == slope
    assert float(jax.grad(nm.correct_opacity, argnums=1)(1.0, ratio)) == 0.0
    if ratio >= 1:  # the left difference agrees
        left = (nm.correct_opacity(1.0, ratio) - nm.correct_opacity(1.0 - 1e-6, ratio)) / 1e-6
        np.testing.assert_allclose(float(left), slope, atol=1e-5)


def test_correct_opacity_of_a_zero_length_segment_is_zero():
    # a ray that misses the volume, or a sample past its exit, has length 0: no opacity,
    # also where the classified opacity is exactly 1
    alpha = jnp.asarray([0.0, 0.5, 0.999, 1.0])
    np.testing.assert_array_equal(nm.correct_opacity(alpha, 0.0), 0.0)
    g = jax.grad(lambda a: jnp.sum(nm.correct_opacity(a, 0.0)))(alpha)
    np.testing.assert_array_equal(g, 0.0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_correct_opacity_float_below_one_counts_as_one(dtype):
    # an interpolated 1 can round to the float just below 1, where the slope
    # r (1 - a)^(r - 1) would be ~1e9 for r < 1: it counts as 1 (and only that float)
    below = jnp.asarray(1 - jnp.finfo(dtype).epsneg, dtype)
    assert float(nm.correct_opacity(below, 0.4)) == 1.0
    assert float(jax.grad(nm.correct_opacity)(below, 0.4)) == 0.0
    two_below = jnp.nextafter(below, jnp.asarray(0, dtype))
    assert float(nm.correct_opacity(two_below, 1.0)) == float(two_below)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_correct_opacity_half_precision_keeps_values_below_one(dtype):
    below = jnp.asarray(1 - jnp.finfo(dtype).epsneg, dtype)
    assert float(nm.correct_opacity(below, 1.0)) == float(below)  # the identity


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16, jnp.float32, jnp.float64])
def test_tiny_is_that_of_the_dtype(dtype):
    # it was float32's for half precision (promoted, then cast: 0 in float16)
    t = nm.tiny(jnp.ones(2, dtype))
    assert t.dtype == dtype and float(t) == float(jnp.finfo(dtype).tiny)
