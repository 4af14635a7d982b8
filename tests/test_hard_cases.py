"""Hard cases as tests: opacity exactly 0 and 1, huge importance gaps, empty and
one-voxel volumes, radii and sample positions on voxel boundaries.

Every test asserts values (analytic, or the brute-force references kept in
``tests/``). Where a hard case is differentiable, its gradient is checked, in the same
test or the next one, against float64 finite differences or the analytic derivative;
where the point has no derivative (an opacity at 0 or 1, a tie of importances), against
the one-sided one. Not so: the LAO of the thick slab (values only), of opaque blocks
(float32 against float64) and the ray of the 1e30 gaps whose importance ends tied with
the background's (see there).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_composition as ref_comp
import reference_obscurance as ref_obs
from helpers import central_difference, check_grad_fd, check_grads_fd
from reference_gradient import regression_gradient_reference
from reference_lao import lao_reference

import volshade as vs
from volshade.camera import Camera
from volshade.composition import composite
from volshade.gradient import regression_gradient
from volshade.lao import lao
from volshade.obscurance import obscurance
from volshade.render import march
from volshade.saliency import (
    least_salient_view,
    modulate_opacity,
    most_salient_view,
    projected_area,
    saliency,
    viewpoint_saliency,
)
from volshade.transfer import TransferFunction

DTYPES = [jnp.float32, jnp.float64]
AXES6 = np.concatenate([np.eye(3), -np.eye(3)])  # the six axis directions (d, h, w)
DIRS12 = np.asarray(vs.directions.icosphere(0))
BG = (0.1, 0.2, 0.3)


def _finite(*arrays):
    return all(bool(jnp.all(jnp.isfinite(a))) for a in jax.tree.leaves(arrays))


# =========================================================================== composite


@pytest.mark.parametrize(("dtype", "batch"), [(jnp.float32, (2, 2)), (jnp.float64, ())])
@pytest.mark.parametrize("importance_aware", [False, True])
def test_composite_rays_without_samples_give_the_background(dtype, batch, importance_aware):
    colors, alphas = jnp.zeros((*batch, 0, 3), dtype), jnp.zeros((*batch, 0), dtype)
    bg = jnp.asarray(BG, dtype)
    kw = {"importance": alphas, "background_importance": 1e4} if importance_aware else {}

    @jax.jit
    def f(colors, alphas, bg):
        return composite(colors, alphas, background=bg, **kw)

    out = f(colors, alphas, bg)
    assert out.dtype == dtype and out.shape == (*batch, 4)
    want = np.broadcast_to(np.asarray([*BG, 0.0], dtype), (*batch, 4))
    np.testing.assert_array_equal(np.asarray(out), want)
    g_c, g_a, g_bg = jax.grad(lambda *x: jnp.sum(f(*x)), (0, 1, 2))(colors, alphas, bg)
    assert g_c.shape == colors.shape and g_a.shape == alphas.shape
    # nothing in front: the background shows through with weight 1 on every ray
    np.testing.assert_array_equal(np.asarray(g_bg), np.full(3, int(np.prod(batch))))


# one ray per (alpha, I_bg): I_s = 0 and the background importance is none (-inf), ahead
# by 1e4 (never fades) or 0.7 (m = 1), behind by 0.7 (m = e^-0.7) or by 1e4 (m = 0: the
# volume vanishes)
_ONE_ALPHAS = np.repeat([0.0, 0.4, 1.0], 5)
_ONE_BG_IMP = np.tile([-np.inf, -1e4, -0.7, 0.7, 1e4], 3)
_ONE_RGB = np.array([0.9, 0.5, 0.2])
_ONE_W = np.array([0.3, -1.1, 0.7, 1.9])  # weights of the RGBA outputs in the loss


def _one_sample_analytic(c, a, i_s, bg, i_bg):
    """Closed form of one sample over a background (eq. 8 with sec. IV-C), per ray:
    m = exp(min(0, I_s - I_bg)), rgb = m C + (1 - m a) bg, alpha = m a (jnp, so that its
    gradient is the analytic one)."""
    m = jnp.exp(jnp.minimum(0.0, i_s - i_bg))
    return jnp.concatenate([m[:, None] * c + (1 - m * a)[:, None] * bg[None], (m * a)[:, None]],
                           -1)


@pytest.mark.parametrize("dtype", DTYPES)
def test_composite_one_sample_importance_analytic(dtype):
    n = len(_ONE_ALPHAS)
    c = jnp.asarray(_ONE_ALPHAS[:, None] * _ONE_RGB, dtype)
    a = jnp.asarray(_ONE_ALPHAS, dtype)
    i_s = jnp.zeros(n, dtype)
    bg = jnp.asarray(BG, dtype)
    i_bg = jnp.asarray(_ONE_BG_IMP, dtype)

    def loss(c, a, i_s):
        out = composite(c[:, None], a[:, None], importance=i_s[:, None], background=bg,
                        background_importance=i_bg)
        return jnp.sum(jnp.asarray(_ONE_W, dtype)[None] * out), out

    (_, out), grads = jax.jit(jax.value_and_grad(loss, (0, 1, 2), has_aux=True))(c, a, i_s)
    assert out.dtype == dtype
    want = np.stack([ref_comp.importance(_ONE_ALPHAS[k] * _ONE_RGB[None], [_ONE_ALPHAS[k]],
                                         [0.0], BG, _ONE_BG_IMP[k]) for k in range(n)])
    closed = _one_sample_analytic(jnp.asarray(_ONE_ALPHAS[:, None] * _ONE_RGB),
                                  jnp.asarray(_ONE_ALPHAS), 0.0, jnp.asarray(BG),
                                  jnp.asarray(_ONE_BG_IMP))
    np.testing.assert_allclose(want, np.asarray(closed), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(out), want, rtol=0, atol=10 * jnp.finfo(dtype).eps)
    empty = _ONE_ALPHAS == 0  # the background exactly, whatever its importance
    np.testing.assert_array_equal(np.asarray(out)[empty],
                                  np.broadcast_to(np.asarray([*BG, 0.0], dtype), (5, 4)))
    assert _finite(grads)
    # gradients of the closed form where the sample is there (at alpha = 0 it is absent:
    # its colour is not used)
    want_grads = jax.grad(
        lambda c, a, i: jnp.sum(_ONE_W[None] * _one_sample_analytic(c, a, i, jnp.asarray(BG),
                                                              jnp.asarray(_ONE_BG_IMP))),
        (0, 1, 2))(jnp.asarray(_ONE_ALPHAS[:, None] * _ONE_RGB), jnp.asarray(_ONE_ALPHAS),
                   jnp.zeros(n))
    for got, exp in zip(grads, want_grads, strict=True):
        np.testing.assert_allclose(np.asarray(got)[~empty], np.asarray(exp)[~empty],
                                   rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
def test_composite_one_sample_standard_analytic(dtype):
    alphas = np.array([0.0, 0.4, 1.0])
    c = jnp.asarray(alphas[:, None, None] * _ONE_RGB, dtype)
    a = jnp.asarray(alphas[:, None], dtype)
    bg = jnp.asarray(BG, dtype)
    out, (g_c, g_a, g_bg) = jax.jit(jax.value_and_grad(
        lambda c, a, bg: jnp.sum(composite(c, a, background=bg)), (0, 1, 2)))(c, a, bg)
    out = jax.jit(composite)(c, a, background=bg)
    want = np.concatenate([alphas[:, None] * _ONE_RGB + (1 - alphas[:, None]) * np.asarray(BG),
                           alphas[:, None]], -1)
    np.testing.assert_allclose(np.asarray(out), want, rtol=0, atol=4 * jnp.finfo(dtype).eps)
    np.testing.assert_allclose(want[1], ref_comp.standard(0.4 * _ONE_RGB[None], [0.4], BG),
                               atol=1e-15)
    # d/dC = 1, d/dalpha = 1 - sum(bg), d/dbg = sum of (1 - alpha): exact at 0 and 1 too
    np.testing.assert_array_equal(np.asarray(g_c), np.ones((3, 1, 3)))
    np.testing.assert_allclose(np.asarray(g_a), np.full((3, 1), 1 - sum(BG)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g_bg), np.full(3, np.sum(1 - alphas)), rtol=1e-6)


def test_composite_one_sample_gradients_match_finite_differences():
    c = jnp.asarray([[[0.36, 0.2, 0.08]], [[0.1, 0.3, 0.2]]])
    a = jnp.asarray([[0.4], [0.7]])
    i_s = jnp.asarray([[0.0], [0.3]])
    i_bg = jnp.asarray([-jnp.inf, 0.7])
    w = jnp.asarray([0.3, -1.1, 0.7, 1.9])

    @jax.jit
    def loss(c, a, i_s, i_bg):
        return jnp.sum(w[None] * composite(c, a, importance=i_s, background=jnp.asarray(BG),
                                           background_importance=i_bg))

    check_grad_fd(lambda x: loss(x, a, i_s, i_bg), c)
    check_grad_fd(lambda x: loss(c, x, i_s, i_bg), a)
    check_grad_fd(lambda x: loss(c, a, x, i_bg), i_s)
    check_grad_fd(lambda x: loss(c, a, i_s, jnp.stack([-jnp.inf, x])), jnp.float64(0.7), n_dirs=1)


# Importance gaps far beyond exp's range (1e30 vs -1e30). Only differences matter, and
# any gap past ~750 saturates exp in float64 exactly as 1e30 does, so the float64
# reference is evaluated with the importances scaled to 1e3 (at 1e30 it would lose
# ln(alpha) ~ 1 against 1e30 in its accumulated importance; the library carries
# I - ln(alpha) as an exact input value plus a small offset and does not).
HUGE_GAP_RAYS = [  # unit importances (x 1e30), alphas
    ([1, -1, 0, 1, -1], [0.3, 1.0, 0.0, 0.6, 1.0]),
    ([-1, 1, -1, 1, 0], [0.3, 1.0, 0.0, 0.6, 1.0]),
    ([-1, 1, 1, -1, -1], [1.0, 0.5, 0.0, 1.0, 0.25]),
    ([0, 1, -1, 1, -1], [1.0, 1e-3, 1.0, 0.5, 0.0]),
]


def _ray_loss(c, a, i, i_bg):
    """sum(RGBA) of one ray by the float64 reference (eq. 8 literally)."""
    return np.sum(ref_comp.importance(c, a, i, BG, i_bg))


def _one_sided(f, x, k, lo, hi, h=1e-6):
    """Second-order one-sided differences of scalar ``f`` in ``x[k]``, each way that stays in
    ``[lo, hi]`` (float64)."""
    e = np.zeros_like(x)
    e[k] = h
    return [w * (-3 * f(x) + 4 * f(x + w * e) - f(x + 2 * w * e)) / (2 * h)
            for w in (1, -1) if lo <= x[k] + 2 * w * h <= hi]


@pytest.mark.parametrize("dtype", DTYPES)
def test_composite_importance_gaps_of_1e30(dtype):
    rng = np.random.default_rng(0)
    units, alphas, colors, bg_units, want = [], [], [], [], []
    for ray_units, ray_alphas in HUGE_GAP_RAYS:
        unit, alpha = np.asarray(ray_units, float), np.asarray(ray_alphas, float)
        for bg_unit in (-np.inf, -1.0, 0.0, 1.0):   # background importance (x 1e30)
            color = rng.uniform(0, 1, (len(alpha), 3)) * alpha[:, None]
            units.append(unit)
            alphas.append(alpha)
            colors.append(color)
            bg_units.append(bg_unit)
            want.append(ref_comp.importance(color, alpha, 1e3 * unit, BG, 1e3 * bg_unit))
    args = (jnp.asarray(np.stack(colors), dtype), jnp.asarray(np.stack(alphas), dtype),
            jnp.asarray(1e30 * np.stack(units), dtype))

    def f(c, a, i):
        return composite(c, a, importance=i, background=jnp.asarray(BG, dtype),
                         background_importance=jnp.asarray(1e30 * np.asarray(bg_units), dtype))

    out, vjp = jax.vjp(jax.jit(f), *args)
    assert out.dtype == dtype
    np.testing.assert_allclose(np.asarray(out), np.stack(want), rtol=0,
                               atol=1e-6 if dtype == jnp.float32 else 1e-13)
    grads = [np.asarray(g, float) for g in vjp(jnp.ones_like(out))]
    assert _finite(grads)
    # d sum(RGBA) against the float64 reference (importances x 1e3, as above)
    atol = 1e-5 if dtype == jnp.float32 else 1e-6
    for r, (c, a, i, i_bg) in enumerate(zip(colors, alphas, 1e3 * np.stack(units),
                                            1e3 * np.asarray(bg_units), strict=True)):
        # linear in the colours: their weights; where alpha_s = 0, the weight's limit as
        # alpha_s -> 0+ (the one-sided derivative)
        for s in range(len(a)):
            lifted = np.where(np.arange(len(a)) == s, np.maximum(a, 1e-9), a)
            e = np.zeros_like(c)
            e[s] = 1
            weight = (_ray_loss(c + e, lifted, i, i_bg) - _ray_loss(c, lifted, i, i_bg)) / 3
            np.testing.assert_allclose(grads[0][r, s], weight, rtol=0, atol=atol)
        # alpha and importance: the derivative where both one-sided differences agree, else
        # (alpha at 0 or 1, a tie of importances) one side's. Not where the accumulated
        # importance ends tied with the background's (the ray 1e30 x [-1, 1, -1, 1, 0] over
        # 1e30): there a tie with the background meets ties between samples, each taken as
        # behind, and the derivative of sample 3 (1.56) is neither side's (0.49, 0); a lone
        # tie with the background is test_composition's
        c_n, a_n, i_n, _ = ref_comp.importance(c, a, i, return_state=True)
        if abs(i_n - np.log(a_n) - i_bg) < 1e-9:
            continue
        by_alpha = functools.partial(_ray_loss, c, i=i, i_bg=i_bg)
        by_importance = functools.partial(_ray_loss, c, a, i_bg=i_bg)
        for s in range(len(a)):
            for got, sides in ((grads[1][r, s], _one_sided(by_alpha, a, s, 0, 1)),
                               (grads[2][r, s], _one_sided(by_importance, i, s, -np.inf, np.inf))):
                assert min(abs(got - side) for side in sides) <= atol, (r, s, got, sides)


# =========================================================================== lao


@pytest.mark.parametrize(("corr", "brick_size"), [(False, None), (True, 4)])
def test_lao_one_voxel_offset_one_is_exactly_one(corr, brick_size):
    # the first sample lies at s = a + (R - a) / 2M = 1.25, and icosphere(0)'s directions
    # have a largest component of 0.85: every sample is more than one voxel from the voxel
    # along that axis, outside its trilinear support, and reads the zero padding. So AO = 1,
    # and small changes of alpha, R or a keep it so: the gradient is exactly 0 (checked on
    # the plain march: the bricks' backward pass takes seconds to compile)
    def f(alpha, radius, offset):
        return lao(alpha, directions=DIRS12, radius=radius, offset=offset, samples=4,
                   opacity_correction=corr, brick_size=brick_size, max_radius=4.0)[0, 0, 0]

    assert 1.25 * np.max(np.abs(DIRS12), axis=1).min() > 1
    for value in (0.0, 1.0):
        alpha = jnp.full((1, 1, 1), value)
        assert float(f(alpha, 3.0, 1.0)) == 1.0
        if brick_size is None:
            grads = jax.grad(f, (0, 1, 2))(alpha, 3.0, 1.0)
            assert all(bool(jnp.all(g == 0)) for g in grads), grads


@pytest.mark.parametrize("corr", [False, True])
def test_lao_one_voxel_sees_its_own_cell(corr):
    # offset 0, R = 1, M = 2: the one sample lies at s = 1/4 along an axis, inside the
    # voxel's trilinear support, where the opacity is (1 - 1/4) alpha = 0.75 alpha.
    # I = (1 + (1 - alpha'))/2 with alpha' = 0.75 alpha, or corrected to the step 1/2,
    # alpha' = 1 - (1 - 0.75 alpha)^(1/2). On the diagonals the voxel's trilinear weight
    # at s = 1/4 is (1 - s/sqrt3)^3.
    diag = np.array([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]])
    for dirs, weight in ((AXES6, 0.75), (diag, (1 - 0.25 / np.sqrt(3)) ** 3)):
        for value in (0.0, 0.3, 1.0):
            alpha = jnp.full((1, 1, 1), value)
            ao = lao(alpha, directions=dirs, radius=1.0, offset=0.0, samples=2,
                     opacity_correction=corr)
            a_s = weight * value
            transmit = (1 - a_s) ** 0.5 if corr else 1 - a_s
            np.testing.assert_allclose(float(ao[0, 0, 0]), (1 + transmit) / 2, rtol=1e-14)
    ref = lao_reference(alpha, diag, 1.0, 0.0, 2, opacity_correction=corr)
    np.testing.assert_allclose(np.asarray(ao), np.asarray(ref), rtol=0, atol=1e-14)


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_lao_one_voxel_gradients_analytic(value):
    # as above with correction: AO = (1 + sqrt(1 - 0.75 alpha))/2 at R = 1; along R (alpha
    # = 1, offset 0, M = 2): s = R/4, alpha' = 1 - (R/4)^(R/2), AO = (1 + (R/4)^(R/2))/2.
    def f(alpha, radius):
        return lao(alpha, directions=AXES6, radius=radius, offset=0.0, samples=2,
                   opacity_correction=True, max_radius=2.0)[0, 0, 0]

    g_alpha, g_r = jax.grad(f, (0, 1))(jnp.full((1, 1, 1), value), jnp.float64(1.0))
    np.testing.assert_allclose(float(g_alpha[0, 0, 0]),
                               -0.75 / (4 * np.sqrt(1 - 0.75 * value)), rtol=1e-12)
    if value == 1.0:
        g = 0.25 ** 0.5
        np.testing.assert_allclose(float(g_r), g * (0.5 * np.log(0.25) + 0.5) / 2, rtol=1e-12)
    else:
        assert float(g_r) == 0.0  # AO = 1 whatever the radius


def test_lao_one_voxel_thick_slab():
    dtype = jnp.float32
    # (1, 5, 5) opaque slab, rays along +-h, offset 0.5, R = 4.5, M = 4: samples at
    # s = 1, 2, 3 (voxel centres). A voxel with a neighbour ahead is stopped at the first
    # sample (I = 1/4); on the last row every sample is outside (I = 1).
    alpha = jnp.ones((1, 5, 5), dtype)
    dirs = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    ao = lao(alpha, directions=dirs, radius=4.5, offset=0.5, samples=4, max_radius=5.0)
    want = np.full((5, 5), 0.25)
    want[[0, -1]] = (0.25 + 1.0) / 2
    np.testing.assert_allclose(np.asarray(ao[0]), want, rtol=0, atol=4 * jnp.finfo(dtype).eps)
    # along +-d nothing is ever reached
    ao = lao(alpha, directions=AXES6[[0, 3]], radius=4.5, offset=0.5, samples=4, max_radius=5.0)
    assert bool(jnp.all(ao == 1))
    # random opacities, all directions, rays leaving the slab at once
    alpha = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (1, 6, 5)), dtype)
    dirs = DIRS12[::4]
    ao = lao(alpha, directions=dirs, radius=3.3, offset=0.2, samples=5, opacity_correction=True)
    ref = lao_reference(alpha, dirs, 3.3, 0.2, 5, opacity_correction=True)
    np.testing.assert_allclose(np.asarray(ao), np.asarray(ref), rtol=0, atol=1e-6)


# (radius, offset) with M = 4 samples: every sample distance s_i is an integer (voxel
# centres, the kinks of trilinear interpolation) or a half-integer (voxel faces), and
# reaches end on or beyond the volume's far face
BOUNDARY_RADII = [(8.0, 0.0), (4.0, 0.0), (6.0, 2.0)]


# opacities on a 1/64 grid (the same numbers in float32 and float64), exact 0 and 1 among them
_BOUNDARY_ALPHA = np.round(np.random.default_rng(0).uniform(-0.3, 1.3, (6, 6, 6)).clip(0, 1)
                           * 64) / 64
_BOUNDARY_DIRS = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0], [0, -1.0, 1.0]])


@functools.cache
def _boundary_reference(radius, offset, corr):
    return np.asarray(lao_reference(_BOUNDARY_ALPHA, _BOUNDARY_DIRS, radius, offset, 4,
                                    opacity_correction=corr))


@pytest.mark.parametrize("dtype", DTYPES)
def test_lao_radius_on_voxel_boundaries_matches_reference(dtype):
    alpha = jnp.asarray(_BOUNDARY_ALPHA, dtype)
    assert bool(jnp.any(alpha == 0)) and bool(jnp.any(alpha == 1))
    for radius, offset in BOUNDARY_RADII:
        corr = radius != 4.0
        ao = lao(alpha, directions=_BOUNDARY_DIRS, radius=radius, offset=offset, samples=4,
                 opacity_correction=corr, max_radius=8.0)  # one compilation for all radii
        assert ao.dtype == dtype
        np.testing.assert_allclose(np.asarray(ao), _boundary_reference(radius, offset, corr),
                                   rtol=0, atol=1e-6 if dtype == jnp.float32 else 1e-13)


_LAO_W = jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, (6, 6, 6)))


def _lao_loss(alpha, radius, offset):
    ao = lao(alpha, directions=AXES6, radius=radius, offset=offset, samples=4,
             opacity_correction=True, max_radius=9.0)
    return jnp.sum(_LAO_W * ao ** 2)


_lao_loss_jit = jax.jit(_lao_loss)
_lao_grad_jit = jax.jit(jax.grad(_lao_loss, (0, 1, 2)))


def _one_sided_directional(f, x, v, h=1e-5):
    """Second-order one-sided difference of ``f`` at ``x`` along ``v`` (into the domain)."""
    return (-3 * f(x) + 4 * f(x + h * v) - f(x + 2 * h * v)) / (2 * h)


@pytest.mark.parametrize(("value", "radius", "offset"), [
    (0.0, 4.0, 0.0),   # step ratio (R - a)/M = 1, samples on voxel faces
    (1.0, 4.0, 0.0),
    (1.0, 8.0, 0.0),   # ratio 2, samples on voxel centres (kinks)
    (1.0, 6.0, 2.0),   # ratio 1, offset 2
])
def test_lao_gradients_at_opacity_zero_and_one(value, radius, offset):
    # alpha = 0 or 1 everywhere, corrected opacities: with step ratios 1 and 2 the AO is
    # a polynomial in alpha up to the ends of [0, 1], so one-sided differences (into
    # [0, 1]) must match; at alpha = 1 and ratio 2 the derivative is exactly 0
    # (float64, not weakly typed: the tests below share the compiled loss and gradient)
    alpha = jnp.full((6, 6, 6), value, jnp.float64)
    r, a = jnp.float64(radius), jnp.float64(offset)
    g_alpha, g_r, g_a = _lao_grad_jit(alpha, r, a)
    assert _finite(g_alpha, g_r, g_a)
    rng = np.random.default_rng(int(radius))
    sign = 1.0 if value == 0 else -1.0
    for _ in range(2):
        v = sign * jnp.asarray(np.abs(rng.standard_normal(alpha.shape)))
        v = v / jnp.linalg.norm(v)
        fd = float(_one_sided_directional(lambda x: _lao_loss_jit(x, r, a), alpha, v))
        ad = float(jnp.vdot(g_alpha, v))
        assert abs(ad - fd) <= 1e-4 * abs(fd) + 1e-7, (ad, fd)  # fd error O(h^2)


@pytest.mark.parametrize("implementation", ["xla", "pallas"])
def test_lao_opaque_blocks_blend_to_exactly_one_in_any_direction(implementation):
    # oblique rays blend eight 1s; summed with their weights they can round a few ulps
    # below 1, where the corrected opacity's slope r (1 - alpha)^(r - 1) (r = 0.34 here)
    # is ~1e8 in float64 but ~0.5 in float32: the nested lerps keep exactly 1
    dirs = vs.directions.fibonacci(20)
    grads, values = [], []
    for dtype in (jnp.float64, jnp.float32):
        def loss(a, dtype=dtype):
            return jnp.sum(vs.lao(a, directions=dirs.astype(dtype), radius=2.0, offset=0.3,
                                  samples=5, opacity_correction=True,
                                  implementation=implementation))
        # compiled whole (eagerly, the forward and backward passes were compiled apart)
        value, grad = jax.jit(jax.value_and_grad(loss))(jnp.ones((6, 6, 6), dtype))
        values.append(float(value))
        grads.append(np.asarray(grad, np.float64))
    assert np.max(np.abs(grads[0])) < 1  # the border's rays leave the block: O(1) slopes
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-5, atol=1e-6)
    assert values[1] == pytest.approx(values[0], rel=1e-6)


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_lao_radius_gradient_at_opacity_zero_and_one(value):
    # a radius off the kinks (samples between voxel centres): d/dR and d/da match central
    # differences; with alpha = 0 the AO is exactly 1 for every radius
    alpha = jnp.full((6, 6, 6), value, jnp.float64)
    r, a = jnp.float64(5.3), jnp.float64(0.6)
    _, g_r, g_a = _lao_grad_jit(alpha, r, a)
    for g, x, f in ((g_r, r, lambda x: _lao_loss_jit(alpha, x, a)),
                    (g_a, a, lambda x: _lao_loss_jit(alpha, r, x))):
        fd = float((f(x + 1e-6) - f(x - 1e-6)) / 2e-6)
        if value == 0:
            assert float(g) == 0.0 and fd == 0.0
        else:
            assert abs(float(g) - fd) <= 1e-4 * abs(fd), (float(g), fd)


def test_lao_gradients_at_boundary_radius_match_finite_differences():
    # interior opacities (smooth in alpha), samples exactly on voxel centres (R = 8, a = 0,
    # M = 4: s = 1, 3, 5) and the reach ending beyond the volume
    rng = np.random.default_rng(7)
    alpha = jnp.asarray(0.05 + 0.9 * rng.uniform(0, 1, (6, 6, 6)))
    r, a = jnp.float64(8.0), jnp.float64(0.0)
    g_alpha, g_r, g_a = _lao_grad_jit(alpha, r, a)
    assert _finite(g_alpha, g_r, g_a)
    # differences of the loss compiled for the tests above, against their gradient (a
    # new function would compile both again)
    check_grads_fd(lambda x: (_lao_loss_jit(x, r, a), _lao_grad_jit(x, r, a)), (alpha,),
                   n_dirs=2)
    # at the kink the radius derivative lies between the one-sided differences
    f = lambda x: _lao_loss_jit(alpha, x, a)  # noqa: E731
    h, at = 1e-6, float(f(r))
    left, right = (at - float(f(r - h))) / h, (float(f(r + h)) - at) / h
    assert abs(left - right) > 1e-3  # a real kink
    assert min(left, right) - 1e-4 <= float(g_r) <= max(left, right) + 1e-4


# =========================================================================== obscurance


@pytest.mark.parametrize("dtype", DTYPES)
def test_obscurance_one_voxel_is_exactly_one(dtype):
    for value in (0.0, 0.5, 1.0):
        density = jnp.full((1, 1, 1), value, dtype)
        for rho in ("ao", "linear", "exponential", "sqrt") if dtype == jnp.float64 else ("sqrt",):
            out = obscurance(density, directions=DIRS12, d_max=4.0, rho=rho)
            assert out.dtype == dtype and out.shape == (1, 1, 1)
            assert float(out[0, 0, 0]) == 1.0
            np.testing.assert_array_equal(
                np.asarray(out, float), ref_obs.obscurance(np.asarray(density, float), DIRS12,
                                                           4.0, rho))
        assert bool(jnp.all(jnp.isinf(vs.occluder_distances(density, directions=DIRS12))))
        # colour bleeding of one voxel: the ambient colour (the mean of L equal colours)
        rgb = obscurance(density, directions=DIRS12, d_max=4.0, colors=jnp.full((1, 1, 1, 3), 0.3,
                                                                               dtype),
                         ambient=(0.2, 0.5, 0.9))
        np.testing.assert_allclose(np.asarray(rgb[0, 0, 0]), np.asarray([0.2, 0.5, 0.9], dtype),
                                   rtol=4 * jnp.finfo(dtype).eps)


def test_colour_bleeding_without_occluders_is_the_ambient_colour():
    dtype = jnp.float64
    # all-0 and all-1 densities: nothing is strictly denser, so no direction is occluded
    shape = (3, 4, 2)
    colors = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (*shape, 3)), dtype)

    def f(density, colors, amb):
        return obscurance(density, directions=DIRS12, d_max=3.0, rho="sqrt", colors=colors,
                          ambient=amb)

    for value in (0.0, 1.0):
        density = jnp.full(shape, value, dtype)
        for ambient in (None, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.2, 0.5, 0.9)):
            amb = np.asarray((1.0, 1.0, 1.0) if ambient is None else ambient)
            out = f(density, colors, None if ambient is None else jnp.asarray(amb, dtype))
            assert out.dtype == dtype
            # the mean of L equal colours: exact for 0 and 1, to rounding otherwise
            np.testing.assert_allclose(np.asarray(out),
                                       np.broadcast_to(amb.astype(dtype), (*shape, 3)),
                                       rtol=4 * jnp.finfo(dtype).eps, atol=0)
    want = ref_obs.obscurance(np.asarray(density, float), DIRS12, 3.0, "sqrt",
                              colors=np.asarray(colors, float), ambient=amb)
    np.testing.assert_allclose(np.asarray(out, float), want, rtol=4 * jnp.finfo(dtype).eps)
    # d/dcolours = 0 (nothing reflects), d/dambient = the number of voxels
    g_c, g_amb = jax.jit(jax.grad(lambda c, a: jnp.sum(f(density, c, a)), (0, 1)))(
        colors, jnp.asarray(amb, dtype))
    assert bool(jnp.all(g_c == 0))
    np.testing.assert_allclose(np.asarray(g_amb), np.full(3, np.prod(shape)), rtol=1e-14)


@pytest.mark.parametrize("rho", ["linear", "exponential", "sqrt"])
def test_obscurance_d_max_gradient_below_a_voxel_is_zero_not_nan(rho):
    # d_max below one voxel: nothing is near enough to occlude, so O = 1 and dO/dd_max = 0;
    # float32 squared d_max = 1e-20 to 0 in the slope of rho(d_max, d_max), which the
    # unoccluded directions compute and discard (0 * inf was NaN)
    density = jnp.asarray(np.random.default_rng(3).uniform(0, 1, (4, 5, 3)), jnp.float32)
    value_and_grad = jax.jit(jax.value_and_grad(lambda m: jnp.sum(
        obscurance(density, directions=DIRS12, d_max=m, rho=rho))))  # compiled once, whole
    for d_max in (0.5, 1e-20):
        out, grad = value_and_grad(jnp.float32(d_max))
        assert float(out) == density.size and float(grad) == 0.0


@pytest.mark.parametrize("gap", [1e-3, 1e-20])
def test_threshold_gradients_with_nearly_equal_low_and_high(gap):
    # ramp (o - low) / (high - low) between them: d/dlow = (o - high) / gap^2 and
    # d/dhigh = -(o - low) / gap^2 there, 0 elsewhere; finite in float32 although gap^2
    # underflows (0 * inf was NaN for the values outside the ramp)
    o = jnp.asarray([0.0, 0.3 * gap, 0.5, 0.9], jnp.float32)
    g_low, g_high = jax.grad(lambda lo, hi: jnp.sum(vs.threshold(o, lo, hi)), (0, 1))(
        jnp.float32(0.0), jnp.float32(gap))
    # the value 0 sits on `low`, inside the ramp (0 there): slopes -1/gap and 0
    want_low = (0.3 * gap - gap) / gap**2 - 1 / gap
    np.testing.assert_allclose([g_low, g_high], [want_low, -0.3 / gap], rtol=1e-5)


# =========================================================================== saliency


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 2, 2), (1, 3, 2)])
@pytest.mark.parametrize("size", [3, 5])
def test_regression_gradient_of_volumes_smaller_than_the_kernel(shape, size):
    rng = np.random.default_rng(size)
    f = jnp.asarray(rng.uniform(0, 1, shape))
    cotangent = jnp.asarray(rng.standard_normal((*shape, 3)))

    @jax.jit  # the fit and its vector-Jacobian product, compiled together
    def grad(x):
        g, vjp = jax.vjp(lambda x: regression_gradient(x, size=size), x)
        return g, vjp(cotangent)[0]

    g, vjp = grad(f)
    assert g.shape == (*shape, 3)
    np.testing.assert_allclose(np.asarray(g), regression_gradient_reference(f, size=size),
                               rtol=0, atol=1e-12)
    # the fit is linear in the field: its vector-Jacobian product is the reference's
    # Jacobian (its response to each unit field) applied to the cotangent
    jacobian = np.stack([regression_gradient_reference(e.reshape(shape), size=size)
                         for e in np.eye(f.size)])
    np.testing.assert_allclose(np.asarray(vjp).ravel(),
                               np.tensordot(jacobian, cotangent, f.ndim + 1), rtol=0, atol=1e-12)
    # a constant field: exactly 0, whatever the edge replication (in f's dtype: a weakly
    # typed field compiled the fit again)
    for value in (0.0, 0.37, 1.0):
        assert bool(jnp.all(grad(jnp.full(shape, value, f.dtype))[0] == 0))


@pytest.mark.parametrize(("dtype", "size"), [(jnp.float32, 5), (jnp.float64, 3)])
def test_saliency_of_one_voxel_and_of_volumes_smaller_than_the_kernel(dtype, size):
    sal = jax.jit(lambda o: saliency(o, size=size))
    # one voxel: no neighbour, gradient 0, saliency 0 (the maximum is 0)
    for value in (0.0, 0.6, 1.0):
        s = sal(jnp.full((1, 1, 1), value, dtype))
        assert s.dtype == dtype and float(s[0, 0, 0]) == 0.0
    # (2, 2, 2) linear along d: every voxel has the same gradient, saliency exactly 1
    ramp = jnp.arange(2, dtype=dtype)[:, None, None] * jnp.ones((2, 2, 2), dtype)
    assert bool(jnp.all(sal(ramp) == 1))
    # random (2, 2, 2) and RGB: |g| / max |g| of the brute-force gradient
    obs = np.random.default_rng(size).uniform(0, 1, (2, 2, 2, 3))
    mags = np.sqrt(sum(np.sum(regression_gradient_reference(obs[..., c], size=size) ** 2, -1)
                       for c in range(3)))
    s = sal(jnp.asarray(obs, dtype))
    np.testing.assert_allclose(np.asarray(s), mags / mags.max(), rtol=10 * jnp.finfo(dtype).eps)


def test_saliency_gradients_on_tiny_volumes():
    w = jnp.asarray([[[0.3, 1.2], [0.8, 0.5]], [[1.1, 0.4], [0.9, 1.5]]])
    obs = jnp.asarray(np.random.default_rng(3).uniform(0, 1, (2, 2, 2)))
    loss = jax.jit(lambda o: jnp.sum(w * saliency(o, size=3)))
    grad = jax.jit(jax.grad(loss))
    g = grad(obs)
    rng = np.random.default_rng(0)
    for _ in range(2):
        v = jnp.asarray(rng.standard_normal(obs.shape))
        fd = float(central_difference(loss, obs, v / jnp.linalg.norm(v)))
        assert abs(float(jnp.vdot(g, v / jnp.linalg.norm(v))) - fd) <= 1e-4 * abs(fd)
    assert bool(jnp.all(grad(jnp.ones((2, 2, 2))) == 0))  # constant: zero, not NaN
    g = jax.grad(lambda o: jnp.sum(saliency(o, size=3)))(jnp.full((1, 1, 1), 0.5))
    assert float(g[0, 0, 0]) == 0.0  # one voxel: no neighbour, zero gradient


# =========================================================================== viewpoints

VIEWS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0],
                  [1.0, 1.0, 1.0], [0.3, -0.5, 0.8], [1.0, 2.0, 0.0]])
UNIT = VIEWS / np.linalg.norm(VIEWS, axis=1, keepdims=True)
MAJOR = np.max(np.abs(UNIT), axis=1)   # |v_a|: 1 along an axis, 1/sqrt(3) on the diagonal
STEP = 1 / MAJOR                       # |s| = |v| / |v_a|


@pytest.mark.parametrize("opacity", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("dtype", DTYPES)
def test_projected_area_of_one_voxel(opacity, dtype):
    area = projected_area(jnp.full((1, 1, 1), opacity, dtype), VIEWS)
    assert area.dtype == dtype
    want = MAJOR if opacity > 0 else np.zeros(len(VIEWS))
    np.testing.assert_allclose(np.asarray(area), want, rtol=4 * jnp.finfo(dtype).eps)
    assert bool(jnp.all(area[:4] == (1.0 if opacity > 0 else 0.0)))
    # a level of exactly the voxel's opacity: not above it, not seen (a level of 1, which
    # no opacity can exceed, is refused)
    if opacity < 1:
        assert bool(jnp.all(projected_area(jnp.full((1, 1, 1), opacity, dtype), VIEWS,
                                           level=opacity) == 0))
    else:
        with pytest.raises(ValueError, match=r"`level` must be an opacity in \[0, 1\)"):
            projected_area(jnp.full((1, 1, 1), opacity, dtype), VIEWS, level=opacity)


@pytest.mark.parametrize("opacity", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("sal", [0.0, 0.7])
@pytest.mark.parametrize("dtype", DTYPES)
def test_viewpoint_saliency_of_one_voxel(opacity, sal, dtype):
    # nothing lies between the voxel and any viewer: V = 1; the contribution is its own
    # opacity corrected to the step, alpha' = 1 - (1 - alpha)^|s|, over its line's share
    # of the image plane, |v_a| = 1 / |s|
    o, s = jnp.full((1, 1, 1), opacity, dtype), jnp.full((1, 1, 1), sal, dtype)
    tol = 1e-6 if dtype == jnp.float32 else 1e-13
    trans = viewpoint_saliency(s, o, VIEWS)
    assert trans.dtype == dtype
    np.testing.assert_allclose(np.asarray(trans), np.full(len(VIEWS), sal), rtol=tol)
    own = 1 - (1 - opacity) ** STEP
    contrib = viewpoint_saliency(s, o, VIEWS, visibility="contribution")
    np.testing.assert_allclose(np.asarray(contrib), sal * own * MAJOR, rtol=tol, atol=tol)
    per_area = viewpoint_saliency(s, o, VIEWS, per_area=True)
    want = sal / MAJOR if opacity > 0 else np.zeros(len(VIEWS))  # unseen: 0, not 0/0
    np.testing.assert_allclose(np.asarray(per_area), want, rtol=tol)


def test_viewpoint_saliency_gradients_of_one_voxel():
    dtype = jnp.float32  # where a NaN from 0^(|s| - 1) would show first
    def grad(visibility, per_area):
        return jax.jit(jax.grad(lambda o, s: jnp.sum(viewpoint_saliency(
            s, o, VIEWS, visibility=visibility, per_area=per_area)), (0, 1)))

    ones = jnp.ones((1, 1, 1), dtype)
    # at opacity 1: d alpha'/d alpha = |s| (1 - alpha)^(|s| - 1) is 1 on the four axis
    # views (|s| = 1) and 0 on the others; d/dsaliency = sum of |v_a| alpha' / area, 1
    # per view
    g = grad("contribution", True)
    g_o, g_s = g(ones, ones)
    np.testing.assert_allclose(float(g_o[0, 0, 0]), 4.0, rtol=1e-6)
    np.testing.assert_allclose(float(g_s[0, 0, 0]), len(VIEWS), rtol=1e-6)
    # opacity 0: nothing seen, area 0, and a view that sees nothing scores 0 (not 0/0),
    # with slope 0 in both (the quotient is cut where the area is 0, a step in opacity)
    g_o, g_s = g(0 * ones, ones)
    assert float(g_o[0, 0, 0]) == 0.0 and float(g_s[0, 0, 0]) == 0.0
    # the transmittance in front of the voxel does not involve its own opacity: slope 0 in
    # it, and 1 per view in its saliency, at opacity 1 and 0 alike
    g = grad("transmittance", False)
    for opacity in (ones, 0 * ones):
        g_o, g_s = g(opacity, ones)
        assert float(g_o[0, 0, 0]) == 0.0 and float(g_s[0, 0, 0]) == len(VIEWS)


@pytest.mark.parametrize(("visibility", "per_area"), [("transmittance", False),
                                                     ("contribution", True)])
def test_ties_go_to_the_first_viewpoint(visibility, per_area):
    # all-zero saliency: every view scores 0; the first viewpoint wins, normalised
    views = np.array([[0.3, -0.5, 0.8], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    first = views[0] / np.linalg.norm(views[0])
    z = jnp.zeros((3, 3, 3))
    for opacity in (jnp.zeros((3, 3, 3)), jnp.ones((3, 3, 3))):
        kw = {"per_area": per_area, "visibility": visibility}
        np.testing.assert_allclose(np.asarray(most_salient_view(z, opacity, views, **kw)),
                                   first, rtol=1e-15)
        np.testing.assert_allclose(np.asarray(least_salient_view(z, opacity, views, **kw)),
                                   first, rtol=1e-15)


# =========================================================================== modulation


@pytest.mark.parametrize("dtype", DTYPES)
def test_modulate_opacity_at_zero_one_and_the_threshold(dtype):
    #                  opacity, saliency
    cases = np.array([[0.0, 0.2], [1.0, 0.2], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0],
                      [0.5, 0.2], [1.0, 0.5]])
    op = jnp.asarray(cases[:, 0].reshape(1, 1, -1), dtype)
    sal = jnp.asarray(cases[:, 1].reshape(1, 1, -1), dtype)
    s32 = np.asarray(sal, float).ravel()  # 0.2 as stored in this dtype
    # saliency equal to the threshold is kept (only S < threshold is cleared)
    got = modulate_opacity(op, sal, threshold=0.2)
    assert got.dtype == dtype
    np.testing.assert_allclose(np.asarray(got).ravel(), cases[:, 0] * s32 * (s32 >= s32[0]),
                               rtol=1e-7)
    got = modulate_opacity(op, sal, threshold=0.2, multiply=False)
    np.testing.assert_array_equal(np.asarray(got).ravel(),
                                  np.asarray(cases[:, 0] * (s32 >= s32[0]), dtype))
    # just above the saliency: cleared
    above = float(np.nextafter(np.asarray(sal).ravel()[0], np.asarray(2, dtype)))
    got = modulate_opacity(op, sal, threshold=above, multiply=False)
    np.testing.assert_array_equal(np.asarray(got).ravel(),
                                  np.asarray(cases[:, 0] * (s32 > s32[0]), dtype))
    # threshold 0 keeps everything (S >= 0), threshold 1 keeps S = 1 only
    np.testing.assert_array_equal(np.asarray(modulate_opacity(op, sal, threshold=0.0,
                                                              multiply=False)), np.asarray(op))
    np.testing.assert_array_equal(np.asarray(modulate_opacity(op, sal, threshold=1.0)).ravel(),
                                  np.asarray([0, 0, 0, 1, 0, 0, 0], dtype))
    # boost at its boundary: 1 - boost_top = 0.5 exactly, so S = 0.5 is doubled; 2 x 1 -> 1
    got = modulate_opacity(op, sal, threshold=0.2, boost_top=0.5)
    np.testing.assert_allclose(np.asarray(got).ravel(),
                               np.minimum(1, cases[:, 0] * s32 * (s32 >= s32[0])
                                          * np.where(s32 >= 0.5, 2, 1)), rtol=1e-7)
    g = jax.grad(lambda x: jnp.sum(modulate_opacity(x, sal, threshold=0.2, boost_top=0.5)))(op)
    # factor b S where kept and the result is not clipped; 0 where clipped (2 x 1 x 1 > 1);
    # where b S alpha is exactly 1 (2 x 0.5 x 1) any value between the two sides
    factor = s32 * (s32 >= s32[0]) * np.where(s32 >= 0.5, 2, 1)
    g = np.asarray(g, float).ravel()
    product = cases[:, 0] * factor
    np.testing.assert_allclose(g[product != 1], np.where(product > 1, 0, factor)[product != 1],
                               rtol=1e-7)
    assert np.all((g[product == 1] >= 0) & (g[product == 1] <= factor[product == 1]))


# =========================================================================== render


# Orthographic rays along -h through a (1, 6, 1) volume, one sample at each voxel centre
# (step = 1 voxel: no interpolation between voxels, alpha = alpha0): every ray sees the
# profile _GAP_X back to front. Colour and opacity are linear in the intensity, so the
# intensity maximum has the largest importance also with extinction weighted -1e30.
_GAP_X = np.array([0.2, 0.9, 0.5, 0.3, 0.6, 0.4])
_GAP_C0, _GAP_C1 = np.array([0.1, 0.9, 0.3]), np.array([0.8, 0.2, 0.6])
_GAP_CAM = Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=(2, 2),
                        projection="orthographic", width=0.2)
_GAP_W = np.random.default_rng(4).uniform(0.5, 1.5, (2, 2, 4))  # weights of the loss
_GAP_IMPORTANCE = {"1e30": vs.Importance(intensity=1e30, extinction=-1e30, background=-1e30),
                   "1e6": vs.Importance(intensity=1e6, extinction=0.0, background=0.0)}


def _gap_render(volume, imp):
    tf = TransferFunction.from_points([(0.0, *_GAP_C0, 0.3), (1.0, *_GAP_C1, 0.8)],
                                      dtype=volume.dtype)
    return march(volume, tf, _GAP_CAM, step=1.0, composition="importance", importance=imp,
                 background=BG)


def _gap_limit(x):
    """RGBA of one ray through samples ``x`` (front first) as the gaps grow without bound
    (eq. 8 with m = 0 for a new peak, 1 behind it): the maximum, at k, replaces what lies in
    front of it and takes its opacity, 1 - T_{k+1}; the samples behind it and the background
    composite as usual."""
    alpha = 0.3 + 0.5 * x
    color = _GAP_C0 + x[:, None] * (_GAP_C1 - _GAP_C0)
    t = np.concatenate([[1.0], np.cumprod(1 - alpha)])
    k = np.argmax(x)
    rgb = ((1 - t[k + 1]) * color[k] + (t[k + 1:-1] * alpha[k + 1:]) @ color[k + 1:]
           + t[-1] * np.asarray(BG))
    return np.concatenate([rgb, [1 - t[-1]]])


@pytest.mark.slow
def test_render_with_huge_importance_gaps():
    def loss(volume, imp):
        img = _gap_render(volume, imp)
        return jnp.sum(_GAP_W * img), img

    # (the weights are array leaves: one compilation for both)
    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))
    front_first = _GAP_X[::-1]  # the rays run along -h
    assert np.argmax(front_first) not in (0, len(front_first) - 1)  # things on both sides
    want = _gap_limit(front_first)
    # the gradient of the limit (central differences of the closed form, in voxel order):
    # what lies in front of the maximum counts by its opacity only, and the importances
    # (slopes e^-gap = 0) not at all
    w = _GAP_W.sum((0, 1))
    want_grad = [w @ (_gap_limit(front_first + 1e-6 * e) - _gap_limit(front_first - 1e-6 * e))
                 / 2e-6 for e in np.eye(len(front_first))][::-1]
    volume = _GAP_X.reshape(1, 6, 1)
    for name, imp in _GAP_IMPORTANCE.items():  # from both sides of exp's range
        (_, img), grad = value_and_grad(jnp.asarray(volume), imp)
        assert img.dtype == jnp.float64 and img.shape == (2, 2, 4)
        np.testing.assert_allclose(np.asarray(img), np.broadcast_to(want, img.shape), rtol=0,
                                   atol=1e-14, err_msg=name)
        np.testing.assert_allclose(np.asarray(grad).ravel(), want_grad, rtol=1e-8, err_msg=name)
    img = jax.jit(_gap_render)(jnp.asarray(volume, jnp.float32), _GAP_IMPORTANCE["1e30"])
    assert img.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(img, float), np.broadcast_to(want, img.shape), rtol=0,
                               atol=1e-6)


@pytest.mark.slow
def test_render_one_voxel_volume():
    dtype = jnp.float32
    # orthographic rays along -h through a one-voxel box (half extent 1/2): pixels at
    # +-1/4 cross one voxel (alpha = alpha0 whatever the step), pixels at +-3/4 miss
    alpha0, rgb = 0.3, np.array([0.2, 0.4, 0.6])
    tf = TransferFunction.from_points([(0.0, *rgb, alpha0), (1.0, *rgb, alpha0)], dtype=dtype)
    cam = Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=(4, 4), projection="orthographic",
                       width=2.0)
    weights = np.random.default_rng(6).uniform(0.5, 1.5, (4, 4, 4))

    def loss(volume, tf):
        img = march(volume, tf, cam, step=0.3, composition="importance",
                    importance=vs.Importance(intensity=5.0), background=BG)
        return jnp.sum(jnp.asarray(weights, dtype) * img), img

    (_, img), (g_volume, g_tf) = jax.jit(jax.value_and_grad(loss, (0, 1), has_aux=True))(
        jnp.full((1, 1, 1), 0.5, dtype), tf)
    assert img.dtype == dtype
    hit = np.zeros((4, 4), bool)
    hit[1:3, 1:3] = True
    want = np.where(hit[..., None], np.concatenate([alpha0 * rgb + (1 - alpha0) * np.asarray(BG),
                                                    [alpha0]]), np.asarray([*BG, 0.0]))
    np.testing.assert_allclose(np.asarray(img), want, rtol=0, atol=1e-6)
    # the hit pixels are alpha0 c + (1 - alpha0) bg and alpha0 (the segments' corrected
    # opacities compose to alpha0 exactly), whose slopes are c - bg and 1 in alpha0 and alpha0
    # in c; the value 0.5 takes half of each from the two control points. The volume moves
    # no colour or opacity (the transfer function is constant) and all the samples'
    # importances together (compositing sees only their differences): slope 0
    w_hit = weights[hit].sum(0)
    np.testing.assert_allclose(np.asarray(g_tf.opacities),
                               np.full(2, 0.5 * (w_hit[:3] @ (rgb - np.asarray(BG)) + w_hit[3])),
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(g_tf.colors),
                               np.broadcast_to(0.5 * alpha0 * w_hit[:3], (2, 3)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(g_tf.points), 0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(g_volume), 0, atol=1e-6)


# =========================================================================== transfer


@pytest.mark.parametrize("dtype", DTYPES)
def test_transfer_function_with_one_control_point(dtype):
    # the minimum: K = 1. It classifies its own intensity (constant colour and opacity)
    @jax.jit
    def classify(tf, v):
        return (tf.opacity(v), tf.color(v), tf.opacity(v, step=2.0), tf.opacity(v, step=0.0),
                tf.extinction(v), jax.grad(lambda t: jnp.sum(t.opacity(v, step=2.0)))(tf))

    tf = TransferFunction.from_points([(0.5, 0.2, 0.4, 0.6, 0.3)], dtype=dtype)
    v = jnp.full((2, 3), 0.5, dtype)
    opacity, color, thick, thin, tau, g = classify(tf, v)
    tol = 1e-6 if dtype == jnp.float32 else 1e-14
    np.testing.assert_allclose(np.asarray(opacity), 0.3, rtol=tol)
    np.testing.assert_allclose(np.asarray(color), np.broadcast_to([0.2, 0.4, 0.6], (2, 3, 3)),
                               rtol=tol)
    np.testing.assert_allclose(np.asarray(thick), 1 - 0.7 ** 2, rtol=tol)
    np.testing.assert_array_equal(np.asarray(thin), 0)
    np.testing.assert_allclose(np.asarray(tau), -np.log(0.7), rtol=tol)
    # d/dalpha0 of 1 - (1 - alpha0)^2 = 2 (1 - alpha0), for each of the 6 values
    np.testing.assert_allclose(np.asarray(g.opacities), [6 * 2 * 0.7], rtol=tol)
    assert _finite(g.colors, g.points)
    # opacity exactly 1: 1 for any positive step, 0 for a zero-length step, tau = inf,
    # and a finite gradient (0: the corrected opacity is 1 whatever alpha0 near 1)
    opaque = TransferFunction.from_points([(0.5, 1, 1, 1, 1.0)], dtype=dtype)
    opacity, color, thick, thin, tau, g = classify(opaque, v)
    assert bool(jnp.all(opacity == 1)) and bool(jnp.all(thick == 1))
    assert bool(jnp.all(thin == 0)) and bool(jnp.all(tau == jnp.inf))
    assert _finite(g) and float(g.opacities[0]) == 0.0
    # anything but its point is refused, with a clear message
    with pytest.raises(Exception, match="outside the transfer function's control points"):
        tf.opacity(jnp.asarray([0.5, 0.4], dtype))


def test_transfer_function_without_control_points_is_refused():
    with pytest.raises(ValueError, match="rows"):
        TransferFunction.from_points(np.zeros((0, 5)))
    with pytest.raises(ValueError, match="non-empty"):
        TransferFunction(jnp.zeros((0,)), jnp.zeros((0, 3)), jnp.zeros((0,)))
