import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd
from reference_gradient import regression_gradient_reference

from volshade.gradient import regression_gradient, regression_kernel
from volshade.sampling import trilinear


def _reference_trilinear(vol, p, mode):
    """Eight corners, written out; zero or clamped outside."""
    vol = np.asarray(vol)
    base = np.floor(p).astype(int)
    frac = p - base
    out = 0.0
    for corner in np.ndindex(2, 2, 2):
        idx = base + np.array(corner)
        w = np.prod(np.where(np.array(corner) == 1, frac, 1 - frac))
        if mode == "nearest":
            idx = np.clip(idx, 0, np.array(vol.shape) - 1)
        elif np.any(idx < 0) or np.any(idx >= vol.shape):
            continue
        out += w * vol[tuple(idx)]
    return out


@pytest.mark.parametrize("mode", ["constant", "nearest"])
def test_trilinear_matches_reference(mode):
    rng = np.random.default_rng(0)
    vol = rng.random((5, 6, 7))
    pts = rng.uniform(-1.5, 7.5, size=(50, 3))
    got = trilinear(jnp.asarray(vol), jnp.asarray(pts), mode=mode)
    want = [_reference_trilinear(vol, p, mode) for p in pts]
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_trilinear_channels_jit_vmap_grad():
    rng = np.random.default_rng(1)
    vol = jnp.asarray(rng.random((4, 4, 4, 3)))
    pts = jnp.asarray(rng.uniform(0, 3, size=(6, 3)))
    out = jax.jit(trilinear)(vol, pts)
    assert out.shape == (6, 3)
    np.testing.assert_allclose(out[:, 1], trilinear(vol[..., 1], pts))
    batched = jax.vmap(trilinear, in_axes=(None, 0))(vol[..., 0], pts[:, None, :])
    np.testing.assert_allclose(batched[:, 0], out[:, 0])
    g = jax.grad(lambda v: jnp.sum(trilinear(v, pts)))(vol[..., 0])
    np.testing.assert_allclose(jnp.sum(g), 6.0)  # trilinear weights sum to 1 inside


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_trilinear_half_precision_keeps_its_coordinates(dtype):
    # coordinates are not rounded to the volume's dtype (bfloat16 cannot hold 257)
    vol = jnp.zeros((1, 1, 300), dtype).at[0, 0, 257].set(1).at[0, 0, 200].set(1)
    out = trilinear(vol, jnp.asarray([[0.0, 0.0, 257.0], [0.0, 0.0, 199.75]]))
    assert out.dtype == dtype
    np.testing.assert_allclose(np.asarray(out, np.float64), [1.0, 0.75])


def test_trilinear_errors():
    with pytest.raises(ValueError, match="mode"):
        trilinear(jnp.zeros((2, 2, 2)), jnp.zeros(3), mode="wrap")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        trilinear(jnp.zeros((2, 2, 2)), jnp.zeros(2))
    with pytest.raises(ValueError, match="D, H, W"):
        trilinear(jnp.zeros((2, 2)), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"not empty, got shape \(0, 3, 3\)"):
        trilinear(jnp.zeros((0, 3, 3)), jnp.zeros(3))


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf, -jnp.inf])
def test_trilinear_refuses_non_finite_volumes_and_points(bad):
    """A NaN or inf voxel or point is refused by name, eagerly and under jit (it would
    otherwise come back as NaN, or as a value sampled from the clamped end)."""
    vol, pts = jnp.zeros((3, 3, 3)), jnp.ones((2, 3))
    bad_vol, bad_pts = vol.at[1, 1, 1].set(bad), pts.at[1, 0].set(bad)
    for args, name in (((bad_vol, pts), "`volume`"), ((vol, bad_pts), "`points`")):
        with pytest.raises(ValueError, match=f"{name} contains NaN or inf"):
            trilinear(*args, mode="nearest")
        with pytest.raises(eqx.EquinoxRuntimeError, match=f"{name} contains NaN or inf"):
            eqx.filter_jit(trilinear)(*args)


@pytest.mark.parametrize("size", [3, 5])
@pytest.mark.parametrize("weighting", ["distance", "inverse_distance", "uniform"])
def test_regression_gradient_exact_on_linear_fields(size, weighting):
    spacing = (2.0, 1.0, 0.5)
    grid = np.stack(np.meshgrid(*[np.arange(10)] * 3, indexing="ij"), -1) * np.array(spacing)
    coef = np.array([0.3, -1.2, 2.0])
    vol = jnp.asarray(grid @ coef + 4.0)
    g = regression_gradient(vol, spacing=spacing, size=size, weighting=weighting)
    h = size // 2
    np.testing.assert_allclose(g[h:-h, h:-h, h:-h], np.broadcast_to(coef, (10 - 2 * h,) * 3 + (3,)),
                               atol=1e-10)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 1.0, 0.5)])
@pytest.mark.parametrize("size", [3, 5])
@pytest.mark.parametrize("weighting", ["distance", "inverse_distance", "uniform"])
def test_regression_gradient_matches_weighted_least_squares_on_random_field(weighting, size,
                                                                            spacing):
    # on a random (non-linear) field the weights matter: each weighting is its own fit
    vol = np.random.default_rng(3).random((9, 10, 8))
    g = np.asarray(regression_gradient(jnp.asarray(vol), spacing=spacing, size=size,
                                       weighting=weighting))
    want = regression_gradient_reference(vol, spacing, size, weighting)
    np.testing.assert_allclose(g, want, rtol=1e-10, atol=1e-12)
    for other in {"distance", "inverse_distance", "uniform"} - {weighting}:
        assert np.abs(regression_gradient_reference(vol, spacing, size, other) - want).max() > 1e-2


def test_regression_gradient_against_central_differences_on_smooth_field():
    n = 24
    x = np.arange(n) / n
    d, h, w = np.meshgrid(x, x, x, indexing="ij")
    vol = np.sin(2 * d) * np.cos(1.5 * h) + 0.5 * w**2
    g = np.asarray(regression_gradient(jnp.asarray(vol), spacing=1.0 / n, size=3))
    cd = np.stack(np.gradient(vol, 1.0 / n), -1)
    exact = np.stack([2 * np.cos(2 * d) * np.cos(1.5 * h), -1.5 * np.sin(2 * d) * np.sin(1.5 * h),
                      w], -1)
    inner = (slice(2, -2),) * 3
    # Both are second-order estimates: they agree with each other and with the exact gradient.
    np.testing.assert_allclose(g[inner], cd[inner], atol=5e-3)
    np.testing.assert_allclose(g[inner], exact[inner], atol=1e-2)


@pytest.mark.slow
def test_regression_gradient_dtype_jit_vmap_grad_and_errors():
    rng = np.random.default_rng(2)
    vols = rng.random((2, 6, 6, 6))
    vol = jnp.asarray(vols[0], jnp.float32)
    g = jax.jit(regression_gradient)(vol)
    assert g.dtype == jnp.float32 and g.shape == (6, 6, 6, 3)
    # float32 values of about 0.1: 1e-7 is a few ulps (jit and vmap measured exact, the
    # float64 gradient 1.6e-8 away)
    np.testing.assert_allclose(g, regression_gradient(vol), rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(g, np.float64),
                               regression_gradient(jnp.asarray(vols[0])), rtol=0, atol=1e-7)
    batch = jax.vmap(regression_gradient)(jnp.asarray(vols, jnp.float32))
    for got, v in zip(batch, vols, strict=True):
        np.testing.assert_allclose(got, regression_gradient(jnp.asarray(v, jnp.float32)),
                                   rtol=0, atol=1e-7)
    w = jnp.asarray(rng.normal(size=(6, 6, 6, 3)))
    check_grad_fd(lambda v: jnp.sum(w * regression_gradient(v)), jnp.asarray(vols[0]))
    with pytest.raises(ValueError, match="3 or 5"):
        regression_kernel(4)
    with pytest.raises(ValueError, match="3 or 5"):  # a static size, not a float
        regression_kernel(3.0)
    with pytest.raises(ValueError, match="weighting"):
        regression_kernel(3, weighting="gauss")
    with pytest.raises(ValueError, match="spacing"):
        regression_gradient(vol, spacing=(1.0, -1.0, 1.0))
    for not_numbers in ("2", True, ("1", "1", "1")):  # a string would parse, a bool pass
        with pytest.raises(TypeError, match="`spacing` must be a number or 3 numbers"):
            regression_gradient(vol, spacing=not_numbers)


@pytest.mark.parametrize("size", [3, 5])
def test_regression_gradient_is_exactly_zero_where_the_volume_is_flat(size):
    # two flat regions of unrelated values: every voxel whose neighbourhood lies in one
    # region gets an exactly zero gradient (a convolution would leave rounding noise)
    vol = jnp.full((12, 12, 12), 0.3).at[6:].set(0.7123456789)
    g = regression_gradient(vol, size=size)
    h = size // 2
    assert np.all(np.asarray(g[: 6 - h]) == 0) and np.all(np.asarray(g[6 + h:]) == 0)
    assert float(jnp.min(jnp.abs(g[6 - h:6 + h, ..., 0]))) > 0
    g32 = regression_gradient(jnp.full((5, 5, 5), 0.1, jnp.float32), size=size)
    assert np.all(np.asarray(g32) == 0)
