import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd, run_with_user_xla_flags, temp_bytes
from jax.test_util import check_grads
from reference_gradient import regression_gradient_reference

from volshade.gradient import gradient_magnitude, regression_gradient, regression_kernel
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


_VOXEL_CENTRE_POINTS = """
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates
import volshade as vs
from volshade.sampling import trilinear

rng = np.random.default_rng(9)
vol = rng.uniform(0, 1, (3, 3, 7))
vol[rng.uniform(size=vol.shape) < 0.3] = 0
opacity = np.interp(vol, [0.0, 1.0], [1.0, 0.02])
channels = jnp.asarray(np.stack([vol, 1 - vol, vol ** 2, opacity], -1))
o, d = vs.Camera.orbit(azimuth=90, elevation=0, distance=2.0, image_shape=(5, 4),
                       projection="orthographic", width=0.85).rays()
half, to_index = jnp.asarray([3 / 7, 3 / 14, 0.5]), jnp.asarray([3.5, 7.0, 7.0])


def raw(v, p):  # what trilinear does for channels, without its checks
    return jnp.moveaxis(jax.vmap(lambda c: map_coordinates(
        c, [p[..., i] for i in range(3)], order=1, mode="nearest"), in_axes=-1)(v), 0, -1)


def march(sample):
    def run(v, o, d):
        moving, inside = d != 0, jnp.abs(o) <= half
        safe = jnp.where(moving, d, 1.0)
        t1 = jnp.where(moving, (-half - o) / safe, 0)
        t2 = jnp.where(moving, (half - o) / safe, 0)
        lo = jnp.where(moving, jnp.minimum(t1, t2), jnp.where(inside, -1e300, 1e300))
        hi = jnp.where(moving, jnp.maximum(t1, t2), jnp.where(inside, 1e300, -1e300))
        tn, tfar = jnp.maximum(jnp.max(lo, -1), 0), jnp.min(hi, -1)
        hit = tfar > tn
        length, tn = jnp.where(hit, tfar - tn, 0), jnp.where(hit, tn, 0)
        dt = 1.0 / 7.0

        def body(t, k):
            seg = jnp.clip(length - k * dt, 0, dt)
            p = (o + (tn + k * dt + 0.5 * seg)[..., None] * d + half) * to_index - 0.5
            a0 = sample(v, p)[..., 3]
            a = 1 - (1 - a0) ** (seg * 3.5)
            return t * (1 - a), (p, a0)
        return jax.lax.scan(body, jnp.ones(o.shape[:-1]), jnp.arange(11.0))
    return jax.jit(run)


for sample in (raw, lambda v, p: trilinear(v, p, mode="nearest")):
    _, (points, got) = march(sample)(channels, o, d)
    print(float(jnp.max(jnp.abs(got - trilinear(channels[..., 3], points, mode="nearest")))))
"""


@pytest.mark.slow
def test_multichannel_trilinear_reads_one_copy_of_points_computed_in_the_same_jit():
    # the renderer's case (see test_render), with the public trilinear: points computed in
    # the caller's jit land within an ulp of the plane d = 1, and XLA on a CPU recomputes
    # them in each fusion that reads them, contracting some copies into fused
    # multiply-adds; a channel-last sample that took its voxel from one copy and its
    # weights from another read d = 0 (the "raw" vmapped map_coordinates: 0.54 off with
    # jaxlib 0.10). trilinear's finiteness check passes the points through a conditional,
    # which stores them once. The suite's own XLA flags hide this: a subprocess.
    raw, public = (float(x) for x in run_with_user_xla_flags(_VOXEL_CENTRE_POINTS))
    assert public < 1e-12, (raw, public)


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
def test_regression_gradient_reverse_mode_keeps_few_volumes(size):
    # The cotangents of the stencil's shifted reads were kept as separate padded-size
    # buffers when the volume was edge-padded by jnp.pad (a 64^3 float32 volume, 5^3:
    # 153 MiB, about 150 volumes; 3^3: 34 MiB): the buffer plan of the compiled gradient,
    # in volumes (32^3: 36 and 182 then, 12 and 15 now). The pullback, the transpose of
    # the custom JVP rule's operator, agrees with the primal: <w, G v> = <G^T w, v>.
    n = 32
    spec = jax.ShapeDtypeStruct((n, n, n), jnp.float32)

    def grad(v):
        return jax.grad(lambda v: jnp.sum(jnp.sin(regression_gradient(v, size=size))))(v)

    temp = temp_bytes(grad, spec)
    assert temp <= 24 * n**3 * 4, temp / (n**3 * 4)
    rng = np.random.default_rng(5)
    v, t = (jnp.asarray(rng.normal(size=(8, 9, 10))) for _ in range(2))
    w = jnp.asarray(rng.normal(size=(8, 9, 10, 3)))
    _, pullback = jax.vjp(lambda v: regression_gradient(v, size=size), v)
    np.testing.assert_allclose(jnp.vdot(w, regression_gradient(t, size=size)),
                               jnp.vdot(pullback(w)[0], t), rtol=1e-12)


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


@pytest.mark.parametrize("scale", [1e-35, 1e-20, 2.0**70, 3e38])
def test_regression_gradient_of_a_volume_in_tiny_or_huge_units(scale):
    # found by a review: in float32 the weighted differences of a volume in units of
    # 1e-35 fell to subnormals (flushed on a CPU: 1e-2 relative error, all zeros at
    # 1e-36), and +-3e38 overflowed them to inf. The volume is now taken to unit size by
    # a power of two, so the gradient is that of the float64 volume to float32 rounding,
    # and scaling by a power of two commutes with it exactly.
    rng = np.random.default_rng(4)
    vol = jnp.asarray((0.5 + rng.random((7, 7, 7))) * rng.choice([-1, 1], (7, 7, 7)),
                      jnp.float32) * jnp.float32(scale / 1.5)
    got = regression_gradient(vol)
    ref = regression_gradient(vol.astype(jnp.float64))
    assert got.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(got)))
    # (below float32's smallest normal number, 1.2e-38, a CPU flushes the result to 0)
    atol = max(1e-6 * float(jnp.max(jnp.abs(ref))), float(jnp.finfo(jnp.float32).tiny))
    np.testing.assert_allclose(got, ref, rtol=0, atol=atol)
    unit = jnp.asarray(vol / jnp.float32(scale), jnp.float32)
    if scale == 2.0**70:
        np.testing.assert_array_equal(got, regression_gradient(unit) * jnp.float32(scale))
    # linear in the volume: the derivative does not depend on the units either
    w = jnp.asarray(rng.normal(size=(7, 7, 7, 3)), jnp.float32)
    grads = [jax.grad(lambda v: jnp.sum(w * regression_gradient(v)))(v) for v in (vol, unit)]
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("spacing", [1e-120, 1e200, (1e-120, 3e-120, 1e-121)])
def test_regression_gradient_with_extreme_spacing(spacing):
    # found by a review: sum(w x^2) of the kernel, growing as spacing^3, underflowed to 0
    # or overflowed (a 0 / 0 or inf / inf kernel: NaN gradients). The gradient is per mm,
    # so it scales as 1 / spacing
    vol = jnp.asarray(np.random.default_rng(5).random((6, 6, 6)))
    unit = np.asarray(spacing) / np.max(spacing)
    for size in (3, 5):
        got = regression_gradient(vol, spacing=spacing, size=size) * np.max(spacing)
        np.testing.assert_allclose(got, regression_gradient(vol, spacing=tuple(unit) if
                                                            unit.ndim else 1.0, size=size),
                                   rtol=1e-12, atol=1e-15)
    # and its checks name the function called
    with pytest.raises(ValueError, match="volshade.regression_gradient: `size`"):
        regression_gradient(vol, spacing=spacing, size=4)


def test_gradient_magnitude_of_huge_components_and_its_checks():
    # found by a review: XLA on a CPU divides by a broadcast value through its
    # reciprocal, subnormal (flushed to 0) for a divisor above 8.5e37: a float32
    # component of 1e38 had magnitude 0, and made the scaled field all zeros
    g = jnp.asarray([[1e38, 0.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], jnp.float32)
    np.testing.assert_allclose(gradient_magnitude(g), [1e38, 5.0, 0.0], rtol=1e-6)
    np.testing.assert_allclose(jax.jit(lambda g: gradient_magnitude(g, scaled=True))(g),
                               [1.0, 5e-38, 0.0], rtol=1e-5)
    # the derivative is the unit vector, not p (d|g/p|), which took a cotangent of 10
    # through 10 p = inf first
    # (compiled: eagerly, each gradient compiled some 30 small programs)
    grad = jax.jit(jax.grad(lambda g, scale: scale * jnp.sum(gradient_magnitude(g))))
    np.testing.assert_allclose(grad(g, 10.0), [[10.0, 0, 0], [6.0, 8.0, 0], [0, 0, 0]],
                               rtol=1e-6)
    tiny = jnp.asarray([[3e-30, -4e-30, 0.0]], jnp.float32)  # |g|^2 underflows
    np.testing.assert_allclose(grad(tiny, 1.0), [[0.6, -0.8, 0.0]], rtol=1e-6)
    g64 = jnp.asarray(np.random.default_rng(6).normal(size=(4, 3)))
    check_grads(jax.jit(gradient_magnitude), (g64,), order=2, modes=["fwd", "rev"])
    where = "volshade.gradient.gradient_magnitude"
    for bad in (jnp.asarray([[jnp.nan, 0.0, 0.0]]), jnp.asarray([jnp.inf, 1.0, 0.0])):
        with pytest.raises(ValueError, match=f"{where}: `gradient` contains NaN or inf"):
            gradient_magnitude(bad)
        with pytest.raises(Exception, match="`gradient` contains NaN or inf"):
            jax.jit(gradient_magnitude)(bad)
    with pytest.raises(ValueError, match=f"{where}: `gradient` must have at least one axis"):
        gradient_magnitude(jnp.asarray(3.0))
    with pytest.raises(ValueError, match=f"{where}: `gradient` is empty"):
        gradient_magnitude(jnp.zeros((0, 3)), scaled=True)
    assert gradient_magnitude(jnp.zeros((0, 3))).shape == (0,)
    with pytest.raises(TypeError, match="`gradient`"):
        gradient_magnitude("x")


def test_regression_gradient_keeps_values_far_below_a_huge_peak():
    # found by a review of the rescaling: taking the whole volume to unit size put values
    # 38 orders of magnitude below a 1e30 peak under float32's normal numbers (their
    # gradient came out 0); it is now scaled only as far as the edge of the safe range
    vol = np.fromfunction(lambda d, h, w: 1e-7 * (d / 12 + 0.1 * np.sin(h)), (12, 12, 12))
    vol[0, 0, 0] = 1e30
    got = np.asarray(regression_gradient(jnp.asarray(vol, jnp.float32)), np.float64)
    ref = np.asarray(regression_gradient(jnp.asarray(vol)))
    far = (slice(4, 12),) * 3
    np.testing.assert_allclose(got[far], ref[far], rtol=0,
                               atol=1e-5 * np.abs(ref[far]).max())
