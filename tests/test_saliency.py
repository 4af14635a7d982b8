"""Obscurance saliency, viewpoint saliency and opacity modulation (Ruiz et al. 2008, s. 4-5)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd, temp_bytes, tol
from reference_gradient import regression_gradient_reference

from volshade.directions import icosphere
from volshade.gradient import gradient_magnitude, regression_gradient
from volshade.obscurance import _direction_array, _static_dirs, obscurance
from volshade.saliency import (
    SaliencyModulation,
    _viewpoint_sums,
    least_salient_view,
    modulate_opacity,
    most_salient_view,
    opacity_factor,
    projected_area,
    saliency,
    viewpoint_saliency,
)

VIEWS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, -0.5, 0.8],
                  [-1.0, -1.0, 1.0], [0.1, 0.2, -0.97]])


def reference_viewpoint_saliency(sal, alpha, views, visibility="transmittance"):
    """Per voxel: walk the digital line towards the viewer, multiply (1 - alpha')."""
    sal, alpha = np.asarray(sal, np.float64), np.asarray(alpha, np.float64)
    shape = np.array(alpha.shape)
    out = []
    for v in np.asarray(views, np.float64):
        a = int(np.argmax(np.abs(v)))
        sign = 1 if v[a] > 0 else -1
        s = v / abs(v[a])
        step = np.linalg.norm(s)
        total = 0.0
        for p in np.ndindex(*alpha.shape):
            i = p[a] if sign > 0 else shape[a] - 1 - p[a]
            trans = 1.0
            for t in range(1, shape[a]):
                q = np.array(p) + (np.floor((i + t) * s + 0.5) - np.floor(i * s + 0.5)).astype(int)
                q[a] = p[a] + sign * t
                if np.any(q < 0) or np.any(q >= shape):
                    break
                trans *= (1 - alpha[tuple(q)]) ** step
            own = 1 - (1 - alpha[p]) ** step
            total += sal[p] * (trans if visibility == "transmittance" else trans * own)
        # a composite sums per pixel: each line stands for |v_a| / |v| of the image plane
        out.append(total if visibility == "transmittance" else total / step)
    return np.array(out)


def bumpy_cube(n=20):
    """An opaque cube with a row of bumps on its +w face only."""
    a = np.zeros((n, n, n))
    a[5:15, 5:15, 5:15] = 1.0
    a[6:14:2, 6:14:2, 15:17] = 1.0
    return jnp.asarray(a)


# ------------------------------------------------------------------ voxel saliency


def test_linear_field_gradient_exact_and_saliency_uniform():
    coef = np.array([0.3, -0.2, 0.5])
    spacing = (1.0, 2.0, 0.5)
    idx = np.stack(np.meshgrid(*[np.arange(12.0)] * 3, indexing="ij"), -1)
    field = jnp.asarray(idx @ (coef * np.array(spacing)))  # value per mm along each axis
    for size in (3, 5):
        g = regression_gradient(field, spacing=spacing, size=size)
        np.testing.assert_allclose(np.asarray(g[2:-2, 2:-2, 2:-2]),
                                   np.broadcast_to(coef, (8, 8, 8, 3)), rtol=1e-12)
        s = saliency(field, size=size, spacing=spacing)
        np.testing.assert_allclose(np.asarray(s[2:-2, 2:-2, 2:-2]), 1.0, rtol=1e-12)
        assert float(s.max()) == pytest.approx(1.0, rel=1e-15)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("value", [0.0, 0.37, 1.0])
def test_constant_field_saliency_exactly_zero(dtype, value):
    s = saliency(jnp.full((7, 8, 9), value, dtype))
    assert s.dtype == dtype
    assert bool(jnp.all(s == 0))
    rgb = saliency(jnp.full((7, 8, 9, 3), value, dtype), size=3)
    assert bool(jnp.all(rgb == 0))
    g = jax.grad(lambda o: jnp.sum(saliency(o)))(jnp.full((6, 6, 6), value, jnp.float64))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_saliency_range_and_rgb_norm():
    o = jnp.asarray(np.random.default_rng(0).random((9, 9, 9, 3)))
    s = saliency(o)
    assert float(s.min()) >= 0 and float(s.max()) == pytest.approx(1.0)
    mag = np.sqrt(sum(np.sum(regression_gradient_reference(o[..., c]) ** 2, -1)
                      for c in range(3)))
    np.testing.assert_allclose(np.asarray(s), mag / mag.max(), rtol=1e-10)


@pytest.mark.parametrize("scale", [1e21, 1e-25])
def test_saliency_does_not_depend_on_the_scale_of_the_field(scale):
    # found by a review: the squared components overflowed (NaN) or underflowed (0) in
    # float32, though the scaled saliency is invariant to the field's scale
    o = jnp.asarray(np.random.default_rng(1).random((8, 8, 8)), jnp.float32)
    s = saliency(o)
    got = saliency(o * jnp.float32(scale))
    np.testing.assert_allclose(np.asarray(got), np.asarray(s), rtol=1e-5, atol=1e-6)
    grad = jax.grad(lambda o: jnp.sum(saliency(o) ** 2))
    # the saliency of c o is that of o, so its gradient there is the gradient at o over c
    np.testing.assert_allclose(np.asarray(grad(o * jnp.float32(scale))) * scale,
                               np.asarray(grad(o)), rtol=1e-4, atol=1e-5)
    big = jnp.asarray([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], jnp.float32) * jnp.float32(scale)
    np.testing.assert_allclose(np.asarray(gradient_magnitude(big)),
                               [5 * scale, 0.0], rtol=1e-6)


def test_saliency_grad_and_jit():
    o = jnp.asarray(np.random.default_rng(1).random((8, 8, 8)))
    w = jnp.asarray(np.random.default_rng(2).random((8, 8, 8)))
    f = jax.jit(lambda x: jnp.sum(w * saliency(x)))
    np.testing.assert_allclose(float(f(o)), float(jnp.sum(w * saliency(o))), rtol=1e-13)
    check_grad_fd(f, o)


@pytest.mark.parametrize("size", [3, 5])
def test_saliency_weighting_matches_least_squares_reference(size):
    # a random field: the three weightings give three different saliencies
    o = np.random.default_rng(6).random((8, 9, 7))
    spacing = (1.0, 2.0, 0.5)
    results = {}
    for weighting in ("distance", "inverse_distance", "uniform"):
        got = np.asarray(saliency(jnp.asarray(o), size=size, spacing=spacing,
                                  weighting=weighting))
        mag = np.linalg.norm(regression_gradient_reference(o, spacing, size, weighting), axis=-1)
        np.testing.assert_allclose(got, mag / mag.max(), rtol=1e-10, atol=1e-12)
        results[weighting] = got
    for a, b in (("distance", "inverse_distance"), ("distance", "uniform"),
                 ("inverse_distance", "uniform")):
        assert np.abs(results[a] - results[b]).max() > 1e-2, (a, b)
    assert np.array_equal(results["distance"],
                          np.asarray(saliency(jnp.asarray(o), size=size, spacing=spacing)))


def test_saliency_float32_agrees_with_float64():
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 10)] * 3, indexing="ij"))
    smooth = 0.5 + 0.4 * np.sin(3 * grid[0]) * np.cos(2 * grid[1] + grid[2])
    rgb = np.random.default_rng(7).random((10, 10, 10, 3))
    for o, kwargs in ((smooth, dict(size=5, spacing=(1.0, 2.0, 0.5))),
                      (rgb, dict(size=3, weighting="inverse_distance"))):
        hi = saliency(jnp.asarray(o, jnp.float64), **kwargs)
        lo = saliency(jnp.asarray(o, jnp.float32), **kwargs)
        assert hi.dtype == jnp.float64 and lo.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(lo, np.float64), np.asarray(hi), rtol=0, atol=1e-5)


# ------------------------------------------------------------------ viewpoint saliency


def test_contribution_is_an_image_integral_not_a_count_of_lines():
    # a salient opaque ball: every line that meets it composites a saliency of 1, so the
    # contribution summed over the image plane is the projected area, from every side
    # alike (pi r^2, up to the voxels' staircase: 5% at r = 10); the transmittance, a
    # sum over voxels, counts one step of the line per pixel: sqrt(3) voxels on a
    # diagonal view (whole numbers of lines and areas: exact in float32)
    n, radius = 32, 10.0
    r = np.sqrt(np.sum((np.indices((n, n, n)) - (n - 1) / 2) ** 2, axis=0))
    alpha = jnp.asarray(r < radius, jnp.float32)
    views = np.concatenate([[[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 1.0]],
                            icosphere(1)])
    contrib = np.asarray(viewpoint_saliency(alpha, alpha, views, visibility="contribution"))
    np.testing.assert_allclose(contrib, np.asarray(projected_area(alpha, views)),
                               rtol=1e-12)
    np.testing.assert_allclose(contrib, np.pi * radius**2, rtol=0.06)
    trans = np.asarray(viewpoint_saliency(alpha, alpha, views[:3]))
    np.testing.assert_allclose(trans[1:] / trans[0], [np.sqrt(2), np.sqrt(3)], rtol=0.03)


@pytest.mark.parametrize("visibility", ["transmittance", "contribution"])
def test_viewpoint_saliency_matches_per_voxel_reference(visibility):
    rng = np.random.default_rng(3)
    sal, alpha = rng.random((5, 6, 4)), 0.6 * rng.random((5, 6, 4))
    got = viewpoint_saliency(jnp.asarray(sal), jnp.asarray(alpha), VIEWS, visibility=visibility)
    want = reference_viewpoint_saliency(sal, alpha, VIEWS, visibility)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12)


@pytest.mark.parametrize("visibility", ["transmittance", "contribution"])
def test_cumulative_and_sequential_transmittance_agree(visibility):
    # a CPU takes the transmittance as a scan over slices, other backends as a cumprod
    rng = np.random.default_rng(5)
    sal, alpha = jnp.asarray(rng.random((6, 5, 7))), jnp.asarray(rng.random((6, 5, 7)))
    alpha = alpha.at[2, 2].set(1.0)  # opaque voxels
    views = _static_dirs(_direction_array(VIEWS, "viewpoints", "test"))

    def total(a, sequential):
        return jnp.sum(_viewpoint_sums(sal, a, dirs=views, visibility=visibility,
                                       sequential=sequential) ** 2)

    # the value and its gradient as one program per path (the eager gradient compiled two
    # more of each)
    both = jax.jit(jax.value_and_grad(total), static_argnums=1)
    (scan, scan_grad), (cumprod, cumprod_grad) = both(alpha, True), both(alpha, False)
    np.testing.assert_allclose(float(scan), float(cumprod), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(scan_grad), np.asarray(cumprod_grad), rtol=1e-11,
                               atol=1e-13)


def test_hidden_detail_visible_from_one_side_only():
    sal = jnp.zeros((8, 8, 8)).at[1, 4, 4].set(1.0)
    alpha = jnp.zeros((8, 8, 8)).at[4:].set(1.0)
    s = viewpoint_saliency(sal, alpha, np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]))
    np.testing.assert_array_equal(np.asarray(s), [1.0, 0.0, 1.0])


@pytest.mark.slow
def test_best_view_of_asymmetric_phantom():
    alpha = bumpy_cube()
    sal = saliency(obscurance(alpha, directions=icosphere(0), d_max=6.0))
    views = icosphere(1)
    best = most_salient_view(sal, alpha, views)
    np.testing.assert_allclose(np.asarray(best), [0.0, 0.0, 1.0], atol=1e-12)
    assert float(least_salient_view(sal, alpha, views)[2]) < -0.5
    best_area = most_salient_view(sal, alpha, views, per_area=True)
    assert float(best_area[2]) > 0.8
    values = viewpoint_saliency(sal, alpha, views)
    assert int(jnp.argmax(values)) == int(np.argmax(np.asarray(views)[:, 2]))


def test_projected_area_and_per_area():
    alpha = jnp.zeros((8, 8, 8)).at[2:4, 2:6, 1:7].set(0.5)
    views = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0.0]])
    area = projected_area(alpha, views)
    np.testing.assert_allclose(np.asarray(area[:3]), [24.0, 12.0, 8.0])
    assert 12.0 < float(area[3]) < 40.0
    sal = jnp.ones((8, 8, 8))
    s = viewpoint_saliency(sal, alpha, views)
    per = viewpoint_saliency(sal, alpha, views, per_area=True)
    np.testing.assert_allclose(np.asarray(per), np.asarray(s / area), rtol=1e-14)
    empty = viewpoint_saliency(sal, jnp.zeros((8, 8, 8)), views, per_area=True)
    assert bool(jnp.all(empty == 0))


def test_viewpoint_saliency_grad_vmap_dtype():
    rng = np.random.default_rng(4)
    sal, alpha = jnp.asarray(rng.random((5, 5, 5))), jnp.asarray(0.5 * rng.random((5, 5, 5)))
    f = jax.jit(lambda a: jnp.sum(viewpoint_saliency(sal, a, VIEWS) ** 2))
    check_grad_fd(f, alpha)
    # fully opaque: finite (jitted: eagerly the forward and backward passes compiled apart)
    g = jax.jit(jax.grad(f))(jnp.ones((5, 5, 5)))
    assert bool(jnp.all(jnp.isfinite(g)))
    alphas = jnp.stack([alpha, 1 - alpha])
    batched = jax.jit(jax.vmap(lambda a: viewpoint_saliency(sal, a, VIEWS)))(alphas)
    for got, a in zip(batched, alphas, strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(viewpoint_saliency(sal, a, VIEWS)),
                                   rtol=1e-14)
    assert np.all(np.abs(np.asarray(batched[0] - batched[1])) > 0.01)  # two different results
    # float32 in, float32 out, as traced (the values: the float32 agreement test below)
    out32 = jax.eval_shape(lambda s, a: viewpoint_saliency(s, a, VIEWS),
                           sal.astype(jnp.float32), alpha.astype(jnp.float32))
    assert out32.dtype == jnp.float32


@pytest.mark.parametrize("visibility", ["transmittance", "contribution"])
def test_viewpoint_saliency_reverse_mode_does_not_keep_every_view(visibility):
    # found by a reverse-mode memory audit: every view's sheared columns were kept for
    # the reverse pass (32^3, 42 views: 650 volumes of temporaries, 10x the forward's).
    # A compiled
    # program's buffer plan, not a timing: its gradient against its forward, 42 views
    spec = jax.ShapeDtypeStruct((16, 16, 16), jnp.float32)
    views = icosphere(1)

    def f(s, a):
        return jnp.sum(viewpoint_saliency(s, a, views, visibility=visibility))

    forward, grad = (temp_bytes(fn, spec, spec) for fn in (f, jax.grad(f, (0, 1))))
    assert grad <= 2 * forward, grad / forward


def test_salient_views_float32_agree_with_float64():
    # a cube of random opacities with bumps on one face: the best and the worst of 42
    # views lead the next by 0.6% of the largest saliency, float32 rounds it by 5e-7
    a = np.zeros((12, 12, 12))
    a[3:9, 3:9, 3:9] = np.random.default_rng(9).uniform(0.3, 0.9, (6, 6, 6))
    a[4:8:2, 4:8:2, 9:11] = 0.8
    sal, views = saliency(jnp.asarray(a)), icosphere(1)
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        args = (sal.astype(dtype), jnp.asarray(a, dtype), views)
        out[dtype] = [viewpoint_saliency(*args), most_salient_view(*args),
                      least_salient_view(*args)]
        assert all(x.dtype == dtype for x in out[dtype])
    values, best, worst = (np.asarray(x) for x in out[jnp.float64])
    ranked = np.sort(values)
    assert min(ranked[-1] - ranked[-2], ranked[1] - ranked[0]) > 1e-3 * ranked[-1]
    np.testing.assert_allclose(best, views[np.argmax(values)], rtol=0, atol=1e-15)
    np.testing.assert_allclose(worst, views[np.argmin(values)], rtol=0, atol=1e-15)
    got_values, got_best, got_worst = (np.asarray(x, np.float64) for x in out[jnp.float32])
    np.testing.assert_allclose(got_values, values, rtol=tol(jnp.float32))
    np.testing.assert_allclose(got_best, best, rtol=0, atol=1e-7)  # the same view
    np.testing.assert_allclose(got_worst, worst, rtol=0, atol=1e-7)


@pytest.mark.parametrize("visibility", ["transmittance", "contribution"])
def test_viewpoint_saliency_float32_agrees_with_float64(visibility):
    rng = np.random.default_rng(8)
    sal, alpha = rng.random((9, 8, 10)), rng.random((9, 8, 10)) ** 3
    alpha[3, 2:5] = 1.0  # opaque voxels
    views = VIEWS
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        args = (jnp.asarray(sal, dtype), jnp.asarray(alpha, dtype), views)
        out[dtype] = viewpoint_saliency(*args, visibility=visibility)
        assert out[dtype].dtype == dtype
        per_area = viewpoint_saliency(*args, visibility=visibility, per_area=True)
        out[dtype, "per_area"] = np.asarray(per_area, np.float64)
    hi = np.asarray(out[jnp.float64])
    assert np.ptp(hi) > 0.01 * hi.max()  # the views differ
    np.testing.assert_allclose(np.asarray(out[jnp.float32], np.float64), hi, rtol=1e-5)
    np.testing.assert_allclose(out[jnp.float32, "per_area"], out[jnp.float64, "per_area"],
                               rtol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_sums_in_float32(dtype):
    # found by a review: viewpoint saliency, projected area and the regression gradient
    # summed in the input's half precision (bfloat16: 1.7 % and 1.9 % off), and the
    # saliency per area divided two rounded results; now the regression gradient is
    # rounded once, and the sums over a view are returned in float32 (see below)
    rng = np.random.default_rng(3)
    sal = jnp.asarray(rng.uniform(0.5, 1.0, (16, 16, 16)), dtype)
    alpha = jnp.asarray(rng.uniform(0.0, 0.05, (16, 16, 16)), dtype)
    views = np.array([[1.0, 0, 0], [0.3, -0.5, 0.8]])
    half_ulp = float(jnp.finfo(dtype).eps) / 2
    for got, want in (
            (regression_gradient(sal), regression_gradient(sal.astype(jnp.float32))),):
        assert got.dtype == dtype
        np.testing.assert_allclose(np.asarray(got, np.float32), want, rtol=half_ulp,
                                   atol=float(jnp.finfo(dtype).smallest_normal))
    for got, want in (
            (viewpoint_saliency(sal, alpha, views),
             viewpoint_saliency(sal.astype(jnp.float32), alpha.astype(jnp.float32), views)),
            (projected_area(jnp.ones((48, 48, 48), dtype), views),
             projected_area(jnp.ones((48, 48, 48), jnp.float32), views)),
            (viewpoint_saliency(sal, alpha, views, per_area=True),
             viewpoint_saliency(sal.astype(jnp.float32), alpha.astype(jnp.float32), views,
                                per_area=True))):
        assert got.dtype == jnp.float32
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_view_sums_do_not_overflow(dtype):
    # found by a review: the sums over a view were rounded to the saliency's dtype, so in
    # float16 they overflowed to inf (two views both inf: the first was picked as the most
    # salient, whatever the true order), and an area of 256 x 256 voxels did too
    sal = jnp.full((16, 16, 16), 32.0, dtype)
    alpha = jnp.zeros((16, 16, 16), dtype).at[15].set(0.5)
    views = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    got = viewpoint_saliency(sal, alpha, views)
    # from +d the slab d = 15 (opacity 1/2) is in front and halves what lies behind it
    np.testing.assert_allclose(got, [256 * 32 + 15 * 256 * 32 * 0.5, 16 * 256 * 32],
                               rtol=1e-6)
    assert got.dtype == jnp.float32
    np.testing.assert_array_equal(most_salient_view(sal, alpha, views), [-1.0, 0, 0])
    np.testing.assert_array_equal(least_salient_view(sal, alpha, views), [1.0, 0, 0])
    area = projected_area(jnp.ones((1, 256, 256), dtype), np.array([[1.0, 0, 0]]))
    np.testing.assert_array_equal(area, [65536.0])


def test_viewpoint_saliency_gradient_exact_at_opacity_one():
    # one salient voxel (opacity 1/2) behind one voxel of opacity a, viewed along +d
    # (|s| = 1, so the opacity correction is the identity): S is linear in a, with
    # dS/da = -1 (transmittance) or -1/2 (contribution), also at a = 1 exactly
    sal = jnp.zeros((4, 1, 1)).at[0, 0, 0].set(1.0)
    view = np.array([[1.0, 0.0, 0.0]])
    for visibility, slope in (("transmittance", -1.0), ("contribution", -0.5)):
        def f(a, visibility=visibility):
            alpha = jnp.zeros((4, 1, 1)).at[0, 0, 0].set(0.5).at[2, 0, 0].set(a)
            return viewpoint_saliency(sal, alpha, view, visibility=visibility)[0]
        for a in (0.5, 1.0):
            np.testing.assert_allclose(float(jax.grad(f)(a)), slope, rtol=1e-12)


# ------------------------------------------------------------------ opacity modulation


def test_modulate_opacity():
    a = jnp.full((1, 1, 5), 0.6)
    s = jnp.array([[[0.1, 0.2, 0.5, 0.95, 1.0]]])
    np.testing.assert_allclose(np.asarray(modulate_opacity(a, s))[0, 0],
                               [0.0, 0.12, 0.3, 0.57, 0.6], rtol=1e-14)
    np.testing.assert_allclose(np.asarray(modulate_opacity(a, s, multiply=False))[0, 0],
                               [0.0, 0.6, 0.6, 0.6, 0.6])
    np.testing.assert_allclose(np.asarray(modulate_opacity(a, s, boost_top=0.1))[0, 0],
                               [0.0, 0.12, 0.3, 1.0, 1.0], rtol=1e-14)
    g = jax.grad(lambda x: jnp.sum(modulate_opacity(x, s, boost_top=0.1)))(a)
    np.testing.assert_allclose(np.asarray(g)[0, 0], [0.0, 0.2, 0.5, 0.0, 0.0], rtol=1e-14)
    assert modulate_opacity(a.astype(jnp.float32), s).dtype == jnp.float32


# ------------------------------------------------------------------ errors


def test_errors():
    v = jnp.zeros((4, 4, 4))
    with pytest.raises(ValueError, match="obscurance"):
        saliency(jnp.zeros((4, 4)))
    with pytest.raises(ValueError, match="size"):
        saliency(v, size=4)
    # named for saliency, also under jit
    for fn, error in ((saliency, ValueError), (eqx.filter_jit(saliency), eqx.EquinoxRuntimeError)):
        with pytest.raises(error, match=r"saliency: `obscurance` contains NaN or inf"):
            fn(v.at[0, 0, 0].set(jnp.inf))
    with pytest.raises(ValueError, match="same"):
        viewpoint_saliency(v, jnp.zeros((4, 4, 5)), VIEWS)
    with pytest.raises(ValueError, match="unknown visibility"):
        viewpoint_saliency(v, v, VIEWS, visibility="seen")
    with pytest.raises(ValueError, match="viewpoints"):
        viewpoint_saliency(v, v, np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"viewpoint_saliency: `opacity` must lie in \[0, 1\]"):
        viewpoint_saliency(v, v + 2.0, VIEWS)
    with pytest.raises(ValueError, match="boost_top"):
        modulate_opacity(v, v, boost_top=1.5)
    for bad in (1.5, 0.0, -1.0, True, float("nan")):
        with pytest.raises(ValueError, match="boost_top"):
            opacity_factor(v, boost_top=bad)
        with pytest.raises(ValueError, match="boost_top"):
            SaliencyModulation(boost_top=bad)
    # a concrete scalar array is stored as the number (a static field compares by value)
    for given in (jnp.asarray(0.25), np.float32(0.25), jnp.asarray(1)):
        kept = SaliencyModulation(boost_top=given).boost_top
        assert type(kept) is float and kept == float(given)
    # opacity_factor checks its saliency as modulate_opacity does, with a saliency's hint
    for fn in (opacity_factor, lambda s: modulate_opacity(jnp.ones_like(s), s)):
        with pytest.raises(ValueError, match="`saliency` contains NaN"):
            fn(v.at[0, 0, 0].set(jnp.nan))
        with pytest.raises(ValueError, match=r"`saliency` must lie in \[0, 1\] \(a scaled "
                                             r"saliency: `vs.saliency`"):
            fn(v + 5.0)
    with pytest.raises(ValueError, match="`saliency` must have 3 dimensions"):
        opacity_factor(jnp.zeros((4, 4)))
    # a 0/1 mask of ints is a saliency too: the threshold 0.2 is not rounded to 0
    mask = [[[0, 1]]]
    assert opacity_factor(mask, multiply=False).tolist() == [[[0.0, 1.0]]]
    assert modulate_opacity(jnp.ones((1, 1, 2)), mask, multiply=False).tolist() == [[[0.0, 1.0]]]
    half = jnp.full((1, 1, 2), 0.5)
    np.testing.assert_allclose(  # a NumPy float is a fraction too
        np.asarray(modulate_opacity(half, jnp.ones((1, 1, 2)), boost_top=np.float32(0.5))), 1.0)
    with pytest.raises(ValueError, match=r"`opacity` must lie in \[0, 1\]"):
        modulate_opacity(half - 1.0, jnp.ones((1, 1, 2)))
    for kwargs, match in (({"rho": "cubic"}, "rho"), ({"level": 7}, "level"),
                          ({"size": 4}, "size")):
        with pytest.raises(ValueError, match=match):
            SaliencyModulation(**kwargs)
    assert SaliencyModulation(level=4).level == 4  # 2562 directions, as icosphere allows
    for boost in (jnp.float32(0.5), np.asarray(0.5)):  # concrete 0-d arrays are numbers
        np.testing.assert_allclose(np.asarray(opacity_factor(jnp.ones((1, 1, 2)),
                                                             boost_top=boost)), 2.0)
    with pytest.raises(TypeError, match="static"):
        jax.jit(lambda b: opacity_factor(v, boost_top=b))(0.5)
    with pytest.raises(ValueError, match="at least one channel"):
        saliency(jnp.zeros((4, 4, 4, 0)))
    with pytest.raises(ValueError, match="`level` must be a finite"):
        projected_area(v, VIEWS, level=jnp.nan)


def test_inputs_a_review_found_accepted():
    # found by a review, each accepted without a word before
    cube = jnp.zeros((4, 4, 4)).at[1:3, 1:3, 1:3].set(1.0)
    views = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    # a level of 1 or more gave every view the area 0, a negative one counted empty voxels
    for level in (1.0, 5.0, -3.0):
        with pytest.raises(ValueError, match=r"`level` must be an opacity in \[0, 1\)"):
            projected_area(cube, views, level=level)
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`level` must be an opacity"):
        eqx.filter_jit(lambda lv: projected_area(cube, views, level=lv))(1.0)
    np.testing.assert_array_equal(projected_area(cube, views, level=0.999), [4.0, 4.0])
    # a float16 level just below 1 is compared in float32, not rounded to 1
    np.testing.assert_array_equal(
        projected_area(cube.astype(jnp.float16), views, level=0.9999), [4.0, 4.0])
    # a negative saliency made the view that hides it the most salient
    hidden = jnp.zeros((4, 4, 4)).at[0].set(-1.0)
    for fn in (viewpoint_saliency, most_salient_view, least_salient_view):
        with pytest.raises(ValueError, match=r"`saliency` must be >= 0 \(a gradient magnitude"):
            fn(hidden, cube, views)
    with pytest.raises(eqx.EquinoxRuntimeError, match="`saliency` must be >= 0"):
        eqx.filter_jit(lambda s: viewpoint_saliency(s, cube, views))(hidden)
    # an unscaled saliency is still accepted
    np.testing.assert_allclose(viewpoint_saliency(cube * 7.0, cube, views), [28.0, 28.0])
    # the error for an empty (D, H, W, C) obscurance showed the shape without C
    with pytest.raises(ValueError, match=r"must not be empty, got shape \(0, 2, 2, 3\)"):
        saliency(jnp.ones((0, 2, 2, 3)))


def test_opacity_factor_compares_as_modulate_opacity_does():
    # found by a review: opacity_factor compared a bfloat16 saliency with 1 - boost_top in
    # bfloat16 (0.9 rounds to 0.8984), modulate_opacity in float32, so they doubled
    # different voxels and min(1, f alpha) was not the modulated opacity
    s = jnp.array([[[0.8984375, 0.2001953125]]], jnp.bfloat16)
    a = jnp.full((1, 1, 2), 0.25)
    factor = opacity_factor(s, boost_top=0.1, threshold=0.201)
    assert factor.dtype == jnp.bfloat16
    np.testing.assert_array_equal(
        jnp.minimum(1, factor.astype(jnp.float32) * a),
        modulate_opacity(a, s, boost_top=0.1, threshold=0.201))
    np.testing.assert_array_equal(factor.astype(jnp.float32), [[[0.8984375, 0.0]]])


def test_half_precision_partner_does_not_round_the_other_volume():
    # found by a review: viewpoint saliency cast the opacity to a bfloat16 saliency's
    # dtype (0.999 became 1: a visible voxel was hidden, 0.99 gave a 37 % error), and
    # modulate_opacity compared a float32 saliency of 0.1999 with the threshold 0.2 in a
    # bfloat16 opacity's dtype (it rounded up and was kept)
    sal = jnp.zeros((4, 1, 1), jnp.bfloat16).at[0].set(1.0)
    alpha = jnp.zeros((4, 1, 1), jnp.float32).at[1:3].set(0.99)
    view = np.array([[1.0, 0, 0]])
    got = viewpoint_saliency(sal, alpha, view)
    want = viewpoint_saliency(sal.astype(jnp.float32), alpha, view)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(want, [0.01 ** 2], rtol=1e-5)
    opacity = jnp.full((1, 1, 2), 0.5, jnp.bfloat16)
    out = modulate_opacity(opacity, jnp.array([[[0.1999, 0.2]]], jnp.float32))
    assert out.dtype == jnp.bfloat16
    assert float(out[0, 0, 0]) == 0.0
    assert float(out[0, 0, 1]) == float(jnp.bfloat16(0.5 * 0.2))


def test_half_precision_saliency_is_finite_whatever_the_voxel_size():
    # found by a review: float16 gradients of 4 nm voxels overflowed (inf / inf = NaN in
    # the scaling), though the saliency does not depend on the scale
    obs = jnp.zeros((12, 12, 12)).at[6:].set(1.0)
    half = saliency(obs.astype(jnp.float16), spacing=4e-6)
    assert half.dtype == jnp.float16 and bool(jnp.all(jnp.isfinite(half)))
    np.testing.assert_allclose(np.asarray(half, np.float64),
                               np.asarray(saliency(obs, spacing=4e-6)), atol=1e-3)
