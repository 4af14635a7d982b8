"""Tests of ``lao(..., implementation="pallas")``: the Pallas kernels (run here in
Pallas' interpreter) against the XLA march and the gather reference, in values and
in every gradient; jit, vmap and grad; hard cases; and that the kernels lower to
Triton for a GPU (checked on the CPU by exporting for CUDA, on a GPU as jit lowers
them). On an H200 with JAX 0.11.2 this file and ``test_composition.py`` pass with
the kernels compiled by Triton (167 tests, 2026-12-04), as ``test_hard_cases.py``
did in an earlier run."""

import re
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference
from jax import export
from reference_lao import lao_reference

import volshade.directions as vdirs
from volshade.lao import LocalAmbientOcclusion, lao

pallas = pytest.importorskip("volshade._lao_pallas")
lao_module = sys.modules["volshade.lao"]


def _alpha(shape, seed, dtype=jnp.float64):
    return jnp.asarray(np.random.default_rng(seed).uniform(0, 1, shape) ** 2, dtype)


CASES = [
    # shape, directions, radius, offset, samples, correction, weights, max_radius
    ((9, 12, 7), vdirs.fibonacci(5), 4.6, 0.7, 7, False, False, 5.0),
    ((8, 8, 8), vdirs.icosphere(0), 3.9, 0.0, 5, True, True, 4.0),
    # a traced radius and no max_radius: the padding is the whole extent and shifts clamp
    ((7, 10, 6), vdirs.fibonacci(4), 9.0, 1.5, 4, True, False, None),
    # rays along +-x, +-y, +-z with every sample on a voxel plane (s = 1, 3, 5): the
    # cell, and so the slope, is the one the ray enters, as in the XLA march
    ((6, 7, 8), np.concatenate([np.eye(3), -np.eye(3)]), 8.0, 0.0, 4, False, False, 9.0),
]


def _call(case, implementation, alpha, radius, offset, weights):
    _, dirs, _, _, samples, corr, _, max_radius = CASES[case]
    return lao(alpha, directions=dirs, radius=radius, offset=offset, samples=samples,
               weights=weights, opacity_correction=corr, max_radius=max_radius,
               implementation=implementation)


def _inputs(case, dtype=jnp.float64):
    shape, dirs, radius, offset, _, _, weighted, _ = CASES[case]
    weights = None
    if weighted:
        weights = jnp.asarray(np.random.default_rng(case).uniform(0.2, 2.0, dirs.shape[0]),
                              dtype)
    return _alpha(shape, case, dtype), jnp.asarray(radius, dtype), jnp.asarray(offset, dtype), \
        weights


@pytest.mark.parametrize("case", range(len(CASES)))
def test_values_match_xla_march_and_gather_reference(case):
    alpha, radius, offset, weights = _inputs(case)
    _, dirs, _, _, samples, corr, _, _ = CASES[case]
    fn = jax.jit(lambda a, r, o: _call(case, "pallas", a, r, o, weights))
    out = fn(alpha, radius, offset)
    np.testing.assert_allclose(out, _call(case, "xla", alpha, radius, offset, weights),
                               rtol=0, atol=1e-13)
    ref = lao_reference(alpha, dirs, radius, offset, samples, weights=weights,
                        opacity_correction=corr)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("scale", [0.001, 0.3])
def test_float32_with_many_samples_matches_the_float64_reference(scale):
    """Many samples of nearly transparent (or half-opaque) voxels: float32 rounding
    must not accumulate over the march (summing the transmittances would, 2e-6)."""
    alpha = jnp.asarray(np.random.default_rng(4).uniform(0, scale, (6, 7, 9)), jnp.float32)
    dirs = vdirs.fibonacci(3)
    out = lao(alpha, directions=dirs, radius=5.0, samples=200, implementation="pallas")
    ref = lao_reference(alpha.astype(jnp.float64), dirs, 5.0, 1.0, 200)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)


def test_bad_launch():
    for launch in (pallas.Launch(cotangent_tile=(3, 8, 32)), pallas.Launch(vector=0),
                   pallas.Launch(num_warps=3), pallas.Launch(tile=(4, 8))):
        with pytest.raises(ValueError, match="powers of"):
            pallas.occlusion_sum(jnp.zeros((4, 4, 4)), vdirs.fibonacci(2), jnp.ones(2), 2.0,
                                 1.0, pad=(3, 3, 3), samples=4, correction=False,
                                 launch=launch)
    for chunk in (0, 2.5):
        with pytest.raises(ValueError, match="`chunk` of at least one"):
            pallas.occlusion_sum(jnp.zeros((4, 4, 4)), vdirs.fibonacci(2), jnp.ones(2), 2.0,
                                 1.0, pad=(3, 3, 3), samples=4, correction=False,
                                 launch=pallas.Launch(chunk=chunk))


def test_chunking():
    """Reverse-mode chunks: about sqrt(n) samples by default, at most ``longest``, as
    even as they can be, and never longer than the samples."""
    chunking = lao_module._chunking
    assert chunking(49) == (7, 7)
    assert chunking(5) == (2, 3)
    assert chunking(49, 5) == (10, 5)
    assert chunking(49, 4) == (13, 4)
    assert chunking(10, 4) == (3, 4)
    assert chunking(5, 1) == (5, 1)
    assert chunking(5, 2) == (3, 2)
    assert chunking(5, 9) == (1, 5)
    assert chunking(0, 3) == (0, 0)


def test_float32_matches_gather_reference():
    alpha, radius, offset, _ = _inputs(0, jnp.float32)
    dirs = vdirs.fibonacci(5)
    out = lao(alpha, directions=dirs, radius=radius, offset=offset, samples=7,
              implementation="pallas")
    assert out.dtype == jnp.float32
    ref = lao_reference(alpha, dirs, radius, offset, 7)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_gradients_match_xla_march(case):
    """Every cotangent (opacity, radius, offset, weights) of the Pallas VJP equals the
    XLA VJP's, which test_lao checks against finite differences. Case 2 has masked
    samples (3 samples in 2 chunks of 2) and clamped shifts."""
    alpha, radius, offset, weights = _inputs(case)
    if weights is None:
        weights = jnp.full((CASES[case][1].shape[0],), 1.0)
    alpha = alpha.at[3, 4, 2].set(1.0)  # an opaque voxel: S, not division, carries it
    ct = jnp.asarray(np.random.default_rng(7).normal(size=alpha.shape))

    def loss(implementation):
        return lambda *args: jnp.sum(ct * _call(case, implementation, *args))

    # both VJPs from one compiled program
    got, want = jax.jit(lambda *args: tuple(jax.grad(loss(impl), argnums=(0, 1, 2, 3))(*args)
                                            for impl in ("pallas", "xla")))(
        alpha, radius, offset, weights)
    for g, w in zip(got, want, strict=True):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, w, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_forward_mode_matches_xla_march(case):
    """Forward mode has no kernel: the XLA march's tangent pass runs beside the kernels'
    values. A JVP in every argument at once (opacity, radius, offset, weights) equals
    the XLA march's, which test_lao checks against finite differences."""
    alpha, radius, offset, weights = _inputs(case)
    if weights is None:
        weights = jnp.full((CASES[case][1].shape[0],), 1.0)
    rng = np.random.default_rng(8)
    primals = (alpha, radius, offset, weights)
    tangents = (jnp.asarray(rng.normal(size=alpha.shape)), jnp.asarray(0.7),
                jnp.asarray(-0.3), jnp.asarray(rng.normal(size=weights.shape)))
    got = jax.jit(lambda p, t: jax.jvp(lambda *a: _call(case, "pallas", *a), p, t))(
        primals, tangents)
    want = jax.jvp(lambda *a: _call(case, "xla", *a), primals, tangents)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-11, atol=1e-12)
    assert float(jnp.max(jnp.abs(got[1]))) > 1e-3


def test_forward_mode_is_the_transpose_of_reverse_mode_and_refuses_second_derivatives():
    # jax.jacfwd (the XLA tangent pass) equals jax.jacrev (the kernels) in the radius and
    # offset; a second derivative would differentiate the kernels: refused by name
    alpha, _, _, _ = _inputs(1)
    ct = jnp.asarray(np.random.default_rng(9).normal(size=alpha.shape))

    def loss(y):
        return jnp.sum(ct * _call(1, "pallas", alpha, y[0], y[1], None))

    y = jnp.asarray([3.3, 0.4])
    fwd, rev = jax.jit(lambda y: (jax.jacfwd(loss)(y), jax.jacrev(loss)(y)))(y)
    np.testing.assert_allclose(fwd, rev, rtol=1e-11)
    message = "second derivatives are not available with implementation='pallas'"
    for second in (jax.hessian, lambda f: jax.jacfwd(jax.jacfwd(f))):
        with pytest.raises(ValueError, match=message):  # (while tracing: nothing compiles)
            jax.jit(second(loss))(y)


_LAUNCH_CASE = dict(dirs=vdirs.fibonacci(4), weights=jnp.asarray([0.1, 0.2, 0.3, 0.4]),
                    pad=(4, 4, 4), samples=6, offset=0.5)


def _launch_loss(alpha, radius, ct, launch):
    c = _LAUNCH_CASE
    return jnp.sum(ct * pallas.occlusion_sum(alpha, c["dirs"], c["weights"], radius,
                                             c["offset"], pad=c["pad"], samples=c["samples"],
                                             correction=False, launch=launch))


@pytest.fixture(scope="module")
def launch_reference():
    """Inputs, and the XLA march's loss and gradients for them."""
    c = _LAUNCH_CASE
    alpha, radius = _alpha((5, 9, 13), 11), jnp.asarray(3.2)
    ct = jnp.asarray(np.random.default_rng(2).normal(size=alpha.shape))

    def xla(a, r):
        return jnp.sum(ct * lao_module._occlusion_sum(
            c["pad"], a.shape, False, c["samples"], jnp.pad(a, c["pad"][0]), c["dirs"],
            c["weights"], r, c["offset"]))

    return (alpha, radius, ct), jax.value_and_grad(xla, argnums=(0, 1))(alpha, radius)


# num_warps is a Triton setting: the interpreter runs Launch(num_warps=8) as the default;
# (2, 8, 32) with vector=1 covers both a half-depth tile and the unshifted reads; the
# case's 5 samples make chunks of 1, 2 (the last one masked) and one of all of them
@pytest.mark.parametrize("launch", (pallas.Launch(), pallas.Launch(tile=(4, 8, 64)),
                                    pallas.Launch(tile=(2, 8, 32), vector=1, chunk=1),
                                    pallas.Launch(tile=(1, 8, 32), cotangent_tile=(4, 8, 32),
                                                  chunk=2),
                                    pallas.Launch(tile=(4, 4, 4), cotangent_tile=(1, 1, 1),
                                                  vector=8, chunk=9)))
def test_every_launch_computes_the_same(launch, launch_reference):
    """Tiles, warps, the shifted copies (``vector``) and the reverse-mode chunk change
    how the kernels run, not what they compute; the volume is smaller than some tiles
    and not a multiple of any, and its ``w`` extent is not a multiple of ``vector``."""
    args, (want, want_grads) = launch_reference
    got, grads = jax.value_and_grad(_launch_loss, argnums=(0, 1))(*args, launch)
    np.testing.assert_allclose(got, want, rtol=1e-13)
    for g, w in zip(grads, want_grads, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-11, atol=1e-12)


@pytest.mark.slow
def test_radius_and_opacity_gradients_match_finite_differences():
    alpha, radius, offset, _ = _inputs(0)
    ct = jnp.asarray(np.random.default_rng(3).normal(size=alpha.shape))

    def loss(a, r):
        return jnp.sum(ct * _call(0, "pallas", a, r, offset, None))

    # both gradients from one reverse pass (one backward program, not one per argument),
    # and every difference from one compiled loss
    g_alpha, g_radius = jax.jit(jax.grad(loss, argnums=(0, 1)))(alpha, radius)
    value = jax.jit(loss)
    fd = central_difference(lambda r: value(alpha, r), radius, 1.0)
    np.testing.assert_allclose(g_radius, fd, rtol=1e-4)
    direction = jnp.zeros_like(alpha).at[4, 6, 3].set(1.0).at[5, 5, 4].set(-0.5)
    fd = central_difference(lambda a: value(a, radius), alpha, direction)
    np.testing.assert_allclose(jnp.vdot(g_alpha, direction), fd, rtol=1e-4)


def test_vmap_over_volumes_and_radii():
    alphas = jnp.stack([_alpha((6, 9, 8), seed) for seed in range(3)])
    radii = jnp.asarray([2.0, 3.0, 4.5])

    def f(implementation):
        return lambda a, r: lao(a, directions=6, radius=r, samples=5, max_radius=5.0,
                                implementation=implementation)

    got = jax.jit(jax.vmap(f("pallas")))(alphas, radii)
    np.testing.assert_allclose(got, jax.jit(jax.vmap(f("xla")))(alphas, radii), rtol=0,
                               atol=1e-13)
    assert not np.allclose(got[0], got[1])

    def loss(implementation):
        return jax.jit(jax.vmap(jax.grad(lambda a, r: jnp.sum(f(implementation)(a, r) ** 2),
                                         argnums=(0, 1))))

    for g, w in zip(loss("pallas")(alphas, radii), loss("xla")(alphas, radii), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-11, atol=1e-12)


def test_module_and_filter_grad():
    alpha = _alpha((8, 8, 8), 4)
    kw = dict(directions=6, samples=5, opacity_correction=True)
    grads = [eqx.filter_jit(eqx.filter_grad(lambda m: jnp.sum(m(alpha))))(
        LocalAmbientOcclusion(3.0, implementation=impl, **kw)) for impl in ("pallas", "xla")]
    np.testing.assert_allclose(grads[0].radius, grads[1].radius, rtol=1e-12)
    np.testing.assert_allclose(grads[0].offset, grads[1].offset, rtol=1e-12)


def _sparse(shape, seed):
    a = np.zeros(shape)
    rng = np.random.default_rng(seed)
    a[2:5, 3:6, 12:15] = rng.uniform(0.2, 1.0, (3, 3, 3))
    return jnp.asarray(a)


@pytest.mark.slow
@pytest.mark.parametrize("brick", [4, 8])
def test_bricks_skip_empty_tiles_and_change_nothing(brick):
    """With ``brick_size`` the Pallas forward skips the tiles far from any opacity:
    values and gradients equal the unbricked march and the bricked XLA march."""
    alpha = _sparse((16, 12, 24), brick)
    kw = dict(directions=vdirs.fibonacci(5), radius=2.5, offset=0.5, samples=5)
    out = lao(alpha, brick_size=brick, implementation="pallas", **kw)
    np.testing.assert_array_equal(out, lao(alpha, implementation="pallas", **kw))
    np.testing.assert_allclose(out, lao(alpha, brick_size=brick, **kw), rtol=0, atol=1e-14)
    ct = jnp.asarray(np.random.default_rng(1).normal(size=alpha.shape))

    def loss(a, **extra):
        return jnp.sum(ct * lao(a, **kw, **extra))

    np.testing.assert_allclose(
        jax.grad(lambda a: loss(a, brick_size=brick, implementation="pallas"))(alpha),
        jax.grad(loss)(alpha), rtol=1e-11, atol=1e-12)


def test_skipped_tiles_have_no_opacity_within_reach():
    """The skipping criterion itself, against a brute-force dilation: every tile left
    out has no opacity within ``pad`` voxels of any of its voxels, and some are left
    out (so the kernels really skip)."""
    from scipy.ndimage import maximum_filter

    alpha = _sparse((16, 12, 24), 0)
    pad, brick = (3, 3, 3), 4
    tile, grid, _ = pallas._tiling(alpha.shape, (2, 4, 8))
    active = np.asarray(pallas._active_tiles(alpha, pad, brick, tile, grid))
    assert 0 < active.sum() < active.size
    near = maximum_filter(np.asarray(alpha) > 0, size=2 * pad[0] + 1, mode="constant")
    for t in zip(*np.nonzero(active == 0), strict=True):
        window = tuple(slice(i * s, (i + 1) * s) for i, s in zip(t, tile, strict=True))
        assert not near[window].any()
    assert np.all(pallas._active_tiles(alpha, pad, None, tile, grid) == 1)


def test_hard_cases():
    dirs = vdirs.icosphere(0)
    kw = dict(directions=dirs, radius=3.0, samples=6, implementation="pallas")
    # empty volume: exactly 1, and samples = 1 takes no sample at all
    assert np.all(lao(jnp.zeros((5, 6, 7)), **kw) == 1)
    assert np.all(lao(_alpha((5, 6, 7), 1), **{**kw, "samples": 1}) == 1)
    # one voxel, fully opaque: rays start inside it
    one = lao(jnp.ones((1, 1, 1)), directions=dirs, radius=3.0, offset=0.0, samples=6,
              implementation="pallas")
    np.testing.assert_allclose(one, lao_reference(jnp.ones((1, 1, 1)), dirs, 3.0, 0.0, 6))
    # opaque everywhere, with opacity correction: gradients stay finite
    g = jax.grad(lambda a: jnp.sum(lao(a, opacity_correction=True, **kw)))(jnp.ones((6, 6, 6)))
    assert np.all(np.isfinite(g))


def test_bad_input():
    alpha = jnp.zeros((6, 6, 6))
    with pytest.raises(ValueError, match="implementation"):
        lao(alpha, directions=6, radius=2.0, implementation="cuda")
    with pytest.raises(ValueError, match="implementation"):
        LocalAmbientOcclusion(2.0, implementation="triton")


def test_half_precision_is_computed_in_float32():
    alpha = _alpha((6, 7, 8), 5, jnp.float32)
    kw = dict(directions=6, radius=3.0, samples=5, implementation="pallas")
    half = lao(alpha.astype(jnp.bfloat16), **kw)
    assert half.dtype == jnp.bfloat16
    # the same float32 march of the same (rounded) opacity, rounded once at the end
    full = lao(alpha.astype(jnp.bfloat16).astype(jnp.float32), **kw)
    np.testing.assert_array_equal(np.asarray(half, np.float32),
                                  np.asarray(full.astype(jnp.bfloat16), np.float32))


@pytest.mark.parametrize("extent, pad", [(7, 7), (20, 5), (9, 4)])
def test_every_window_lies_inside_its_buffer(extent, pad):
    """Triton does not check bounds (and Pallas' interpreter clamps windows, so an
    out-of-bounds read would not show in the value tests): the index arithmetic the
    kernels use keeps every window inside the source (``out + 2 pad``) and the halo'd
    cotangent buffer (``out + 2 pad``) for every tile and any shift, also far beyond
    the padding (a clamped shift when the padding is the extent)."""
    for tile_edge in (1, 2, 4, 8):
        tile, _, out = pallas._tiling((extent,) * 3, (tile_edge,) * 3)
        size = out[0] + 2 * pad
        origins = jnp.arange(0, out[0], tile[0])[:, None, None]
        shifts = jnp.arange(-3 * pad - 3, 3 * pad + 3)[None, :, None]
        corners = jnp.arange(2)[None, None, :]
        for start in (pallas.window_start, pallas.adjoint_start):
            at = start(origins, pad, shifts, corners)
            assert int(jnp.min(at)) >= 0 and int(jnp.max(at)) + tile[0] <= size


def _kernel_calls(fn, *args) -> list[str]:
    """The custom calls (kernels) of ``fn`` lowered for CUDA: on a GPU as jit lowers it;
    elsewhere by exporting for CUDA from this machine, which jaxlib <= 0.10.2 does by
    embedding the Triton IR in the custom call (compiled by XLA on the GPU), while later
    ones compile to PTX while lowering and need a GPU (jaxlib 0.11.2 has no
    ``has_compilation_handler`` to ask). The interpreter lowers to plain loops, with
    no custom call."""
    from jax._src.lib import triton, version

    if jax.default_backend() == "gpu":
        text = jax.jit(fn).lower(*args).as_text()
    else:
        if version > (0, 10, 2) and not getattr(triton, "has_compilation_handler",
                                                lambda _: False)("cuda"):
            pytest.skip("this jaxlib compiles Triton kernels while lowering: needs a GPU")
        text = export.export(
            jax.jit(fn), platforms=["cuda"],
            disabled_checks=[export.DisabledSafetyCheck.custom_call(target)
                             for target in ("__gpu$xla.gpu.triton", "triton_kernel_call_ffi")]
        )(*args).mlir_module()
    return re.findall(r'custom_call @"?([^"(\s]+)', text)


@pytest.mark.parametrize("launch", dict.fromkeys(
    pallas.LAUNCHES + pallas.GRADIENT_LAUNCHES + pallas.CORRECTED_GRADIENT_LAUNCHES))
def test_kernels_lower_to_triton(launch):
    """The four kernels (forward; chunk starts, cotangents and adjoint of the VJP)
    lower to Triton for every launch the GPU benchmark times, vmapped too with the
    default launch (a batch adds a grid axis, whatever the tiles), and not to the
    interpreter. Triton's compilation to PTX happens on a GPU, when XLA
    compiles (``benchmarks/gpu.py``), or here on jaxlib > 0.10.2 with CUDA."""
    dirs = vdirs.fibonacci(6).astype(jnp.float32)

    def value_and_grad(alpha, radius):
        def total(a, r):
            return jnp.sum(1 - pallas.occlusion_sum(
                a, dirs, jnp.full((6,), 1 / 6, jnp.float32), r, 1.0, pad=(9, 9, 9),
                samples=9, correction=True, launch=launch))
        return jax.value_and_grad(total, argnums=(0, 1))(alpha, radius)

    struct = jax.ShapeDtypeStruct
    calls = _kernel_calls(value_and_grad, struct((20, 24, 40), jnp.float32),
                          struct((), jnp.float32))
    assert len(calls) == 4, calls
    if launch == pallas.DEFAULT_LAUNCH:
        calls = _kernel_calls(jax.vmap(value_and_grad), struct((2, 20, 24, 40), jnp.float32),
                              struct((2,), jnp.float32))
        assert len(calls) == 4, calls


def test_half_precision_lowers_to_triton():
    """Triton has no half-precision division: bf16 and f16 volumes are promoted."""
    def f(alpha):
        return pallas.occlusion_sum(alpha, vdirs.fibonacci(4), jnp.full((4,), 0.25), 3.0,
                                    1.0, pad=(4, 4, 4), samples=5, correction=False)

    for dtype in (jnp.bfloat16, jnp.float16):
        calls = _kernel_calls(f, jax.ShapeDtypeStruct((8, 8, 8), dtype))
        assert len(calls) == 1, calls


def test_scene_renders_with_the_pallas_march():
    """A scene's LAO ambient term through the Pallas kernels renders as through the
    XLA march (the Module's gradients: test_module_and_filter_grad)."""
    from volshade import Camera, Scene, render
    from volshade.transfer import preset

    vol = _alpha((8, 9, 10), 6)
    cam = Camera.orbit(azimuth=25.0, elevation=15.0, image_shape=(4, 4))

    def image(implementation):
        params = LocalAmbientOcclusion(3.0, offset=0.5, directions=6, samples=4,
                                       implementation=implementation)
        return eqx.filter_jit(render)(Scene(volume=vol, transfer=preset("grey"),
                                            ambient="lao", lao=params, shading="phong"), cam)

    np.testing.assert_allclose(image("pallas"), image("xla"), rtol=0, atol=1e-13)


@pytest.mark.slow
def test_a_fit_through_the_pallas_march_recovers_the_radius_of_an_xla_render():
    """The fit's solvers use forward mode (a least-squares Jacobian), which the Pallas
    march takes from the XLA march's tangent pass. (Its custom VJP had no forward mode,
    and the fit refused it by name.) The target is rendered by the XLA march: a loss down
    to 1e-20 (residuals of 1e-10) at the true radius says that the Pallas march renders
    the XLA march's image there and that the fit finds it. A second fit, through the XLA
    march, compiled a solver of its own (about 6 s) to show what test_fit.py shows."""
    from volshade import Camera, Scene, fit, render
    from volshade.transfer import preset

    vol = _alpha((8, 9, 10), 6)
    cam = Camera.orbit(azimuth=25.0, elevation=15.0, image_shape=(4, 4))

    def scene(implementation, radius):
        return Scene(volume=vol, transfer=preset("grey"), ambient="lao",
                     lao=LocalAmbientOcclusion(radius, directions=4, samples=4, max_radius=4.0,
                                               implementation=implementation))

    target = render(scene("xla", 3.0), cam)
    result = fit(scene("pallas", 2.2), cam, target, params={"lao.radius": (1.0, 4.0)})
    assert int(result.steps) > 0 and float(result.loss) < 1e-20
    np.testing.assert_allclose(float(result.values["lao.radius"]), 3.0, atol=1e-6)

