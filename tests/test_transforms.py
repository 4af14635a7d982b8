"""jit, vmap and grad of the public kernels and parameter modules not covered in their
own modules' tests: jit equals eager, vmap equals a loop, and (where differentiable)
grad equals central finite differences in float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_obscurance as ref
from helpers import check_grad_fd, strongly_typed

import volshade as vs
from volshade.directions import icosphere, icosphere_points
from volshade.gradient import gradient_magnitude, regression_gradient
from volshade.saliency import opacity_factor
from volshade.sampling import trilinear

RNG = np.random.default_rng(42)
SHAPE = (8, 9, 7)
ALPHA = jnp.asarray(RNG.uniform(0, 1, SHAPE) ** 3)
VOLUME = jnp.asarray(RNG.uniform(0, 1, SHAPE))
VIEWS = icosphere(0)
VIEWS4 = np.asarray(VIEWS[:4])  # concrete: directions set the sweep
TF = vs.transfer.preset("grey")
FEATURE_OPACITIES = jnp.stack([jnp.where(VOLUME < 0.3, ALPHA, 0.0),
                               jnp.where(VOLUME > 0.6, ALPHA, 0.0)])
# saliency growing along d: the most / least salient views change (vs VOLUME's)
SAL_RAMP = VOLUME * jnp.linspace(0.0, 1.0, SHAPE[0])[:, None, None]


def _smooth(seed):
    """A smooth field (no ties, no flat regions) on SHAPE."""
    g = np.stack(np.meshgrid(*[np.linspace(0, 1, s) for s in SHAPE], indexing="ij"))
    return jnp.asarray(0.5 + 0.3 * np.sin(3 * g[0] + seed) * np.cos(2 * g[1] - g[2] * seed))


CLIP = vs.SphereClip(center=(4.0, 4.0, 3.0), radius=2.5)
LAO = dict(directions=VIEWS, radius=3.3, offset=0.7, samples=4)
# opacity linear in the intensity: no kink for a finite difference to straddle
RAMP_FEATURE = vs.TransferFunction.from_points([(0.0, 1, 1, 1, 0.05), (1.0, 1, 1, 1, 0.6)])
FALL_FEATURE = vs.TransferFunction.from_points([(0.0, 1, 1, 1, 0.5), (1.0, 1, 1, 1, 0.1)])
# (d, h, w) at least 0.2 voxels from the voxel centres, where trilinear interpolation has
# kinks; some lie in the half voxel outside the volume, interpolating towards the zeros
POINTS = jnp.asarray(RNG.integers(-1, SHAPE, (2, 20, 3)) + RNG.uniform(0.2, 0.8, (2, 20, 3)))
GRADIENTS = (jnp.stack([_smooth(1), _smooth(2), _smooth(3)], -1),
             jnp.stack([_smooth(4), _smooth(5), _smooth(6)], -1))
CAMERA = vs.Camera.orbit(azimuth=25.0, elevation=10.0, image_shape=(6, 6))


def _render(volume, shininess=8.0):
    """A small Phong-shaded render with LAO (a few short rays) as its ambient term."""
    lao = vs.LocalAmbientOcclusion(2.7, offset=0.6, directions=6, samples=3, max_radius=4.0)
    scene = vs.Scene(volume=volume, transfer=TF, step=0.5, shading="phong", ambient="lao",
                     lao=lao, phong=vs.Phong(shininess=shininess))
    return vs.render(scene, CAMERA)


# name: (function of one array, two inputs for vmap, differentiable)
CASES = {
    "LocalAmbientOcclusion(radius)": (
        lambda r: vs.LocalAmbientOcclusion(r, directions=6, samples=5, max_radius=5.0)(ALPHA),
        strongly_typed((3.3, 4.1)), True),
    "occluder_distances": (
        lambda d: vs.occluder_distances(d, directions=VIEWS4), (VOLUME, 1 - VOLUME), False),
    "threshold": (lambda x: vs.threshold(x, 0.2, 0.8), (VOLUME * 0.5 + 0.25, _smooth(1)), True),
    "obscurance_shading": (
        lambda n: vs.obscurance_shading(n, (0.3, 0.2, 0.9), (0.9, 0.1, 0.3), VOLUME, k_s=0.5,
                                        shininess=8.0),
        (jnp.stack([_smooth(1), _smooth(2), _smooth(3)], -1),
         jnp.stack([_smooth(4), _smooth(5), _smooth(6)], -1)), True),
    "ObscuranceParams(d_max)": (
        lambda dm: vs.ObscuranceParams(d_max=dm, low=0.1, high=0.9)(VOLUME, TF),
        strongly_typed((3.5, 6.0)), True),
    "saliency": (vs.saliency, (_smooth(1), _smooth(2)), True),
    "projected_area": (lambda a: vs.projected_area(a, VIEWS),
                       (ALPHA, jnp.where(VOLUME > 0.9, ALPHA, 0.0)), False),  # sparse: holes
    "most_salient_view": (lambda s: vs.most_salient_view(s, ALPHA, VIEWS), (VOLUME, SAL_RAMP),
                          False),
    "least_salient_view": (lambda s: vs.least_salient_view(s, ALPHA, VIEWS), (VOLUME, SAL_RAMP),
                           False),
    "modulate_opacity": (lambda a: vs.modulate_opacity(a, _smooth(1), threshold=0.3),
                         (ALPHA * 0.9, ALPHA ** 2), True),
    "SaliencyModulation(d_max)": (
        lambda dm: vs.SaliencyModulation(d_max=dm, threshold=0.1, level=0, size=3)(VOLUME, TF),
        strongly_typed((3.5, 6.0)), True),
    "sample_importance(Importance)": (
        lambda x: vs.sample_importance(vs.Importance(intensity=1.5, extinction=0.5),
                                       intensity=x, extinction=x ** 2)[0],
        (VOLUME, _smooth(1)), True),
    "focus_weights(center)": (
        lambda c: vs.focus_weights((6, 7), center=c, radius=2.5, kind="gaussian"),
        (jnp.asarray([2.0, 3.5]), jnp.asarray([3.1, 1.2])), True),
    "Focus(radius)": (lambda r: vs.Focus(radius=r).weights((6, 7)),
                      strongly_typed((0.3, 0.45)), True),
    # sparse feature opacities: one-feature, mixed and empty neighbourhoods all occur
    "merge_feature_ao(neighbourhood)": (
        lambda ao: vs.merge_feature_ao(ao, FEATURE_OPACITIES, merge="neighbourhood"),
        (jnp.stack([ALPHA, VOLUME]), jnp.stack([VOLUME, _smooth(1)])), True),
    "merge_feature_ao(max)": (
        lambda ao: vs.merge_feature_ao(ao, FEATURE_OPACITIES, merge="max"),
        (jnp.stack([ALPHA, VOLUME]), jnp.stack([VOLUME, _smooth(1)])), True),
    "merge_feature_ao(feature)": (
        lambda ao: vs.merge_feature_ao(ao, FEATURE_OPACITIES, merge="feature"),
        (jnp.stack([ALPHA, VOLUME]), jnp.stack([VOLUME, _smooth(1)])), True),
    # through the weights of the mean (positive opacities: no voxel changes feature)
    "merge_feature_ao(neighbourhood, opacities)": (
        lambda op: vs.merge_feature_ao(jnp.stack([ALPHA, VOLUME]), op, merge="neighbourhood"),
        (0.05 + 0.9 * jnp.stack([ALPHA, VOLUME]), 0.05 + 0.9 * jnp.stack([_smooth(1), ALPHA])),
        True),
    "IntervalFeature": (lambda v: vs.IntervalFeature(0.2, 0.7).opacity(v, TF),
                        (VOLUME, _smooth(1)), False),
    # the base's opacities inside (0, 1): a finite difference must not step out of range
    "IntervalFeature(base opacities)": (
        lambda o: vs.IntervalFeature(0.2, 0.6).opacity(
            VOLUME, vs.TransferFunction(TF.points, TF.colors, o), step=0.5),
        (jnp.asarray([0.05, 0.1, 0.3]), jnp.asarray([0.2, 0.1, 0.6])), True),
    "lao(weights)": (
        lambda w: vs.lao(ALPHA, weights=w, **LAO),
        (jnp.linspace(0.5, 1.5, 12), jnp.linspace(1.5, 0.5, 12) ** 2), True),
    "FeatureAmbientOcclusion(radius)": (
        lambda r: vs.FeatureAmbientOcclusion(
            [vs.IntervalFeature(0.2, 0.5), vs.IntervalFeature(0.5, 1.0)],
            lao=vs.LocalAmbientOcclusion(r, offset=0.7, directions=6, samples=4, max_radius=5.0),
            merge="neighbourhood")(VOLUME, base=TF),
        strongly_typed((3.3, 4.1)), True),
    "feature_ao(volume)": (
        lambda v: vs.feature_ao(v, features=[RAMP_FEATURE, FALL_FEATURE], directions=6,
                                radius=3.3, offset=0.7, samples=4, merge="max"),
        (_smooth(1), _smooth(2)), True),
    # VOLUME keeps > 1e-4 from the intervals' ends and the base's kink at 0.1, far beyond
    # the finite differences' step
    "feature_opacities(volume)": (
        lambda v: vs.transfer.feature_opacities(v, [vs.IntervalFeature(0.2, 0.6), RAMP_FEATURE],
                                                base=TF, step=0.5),
        (VOLUME, _smooth(1)), True),
    "TransferFunction.opacity": (lambda v: TF.opacity(v, step=0.5), (VOLUME, _smooth(1)), True),
    # lambdas, not bound methods: jax.jit would hash the method's Module, arrays and all
    "TransferFunction.color": (lambda v: TF.color(v), (VOLUME, _smooth(1)), True),
    "TransferFunction.extinction": (lambda v: TF.extinction(v), (VOLUME, _smooth(1)), True),
    "clip_opacity": (lambda a: vs.clip_opacity(a, CLIP), (ALPHA, ALPHA ** 2), True),
    "affected_mask(radius)": (lambda r: vs.affected_mask(SHAPE, CLIP, radius=r),
                              strongly_typed((1.0, 3.0)), False),
    # VOLUME keeps > 1e-4 from the threshold and from the edge of the boosted top (0.8)
    "opacity_factor": (lambda s: opacity_factor(s, threshold=0.3, boost_top=0.2),
                       (VOLUME, _smooth(1)), True),
    "gradient_magnitude": (gradient_magnitude, GRADIENTS, True),
    "regression_gradient(size=3)": (
        lambda v: regression_gradient(v, size=3, spacing=(1.0, 2.0, 0.5)), (VOLUME, _smooth(1)),
        True),
    "regression_gradient(size=5)": (
        lambda v: regression_gradient(v, size=5, spacing=(1.0, 2.0, 0.5)), (VOLUME, _smooth(1)),
        True),
    "trilinear(points)": (lambda p: trilinear(VOLUME, p), (POINTS[0], POINTS[1]), True),
    "render(volume)": (_render, (_smooth(1), _smooth(2)), True),
    "render(Phong.shininess)": (lambda n: _render(_smooth(1), n),
                                strongly_typed((8.0, 12.0)), True),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_jit_equals_eager_and_vmap_equals_loop(name):
    fn, (x1, x2), _ = CASES[name]
    eager = [np.asarray(fn(x)) for x in (x1, x2)]  # each once: eager runs are the slow part
    np.testing.assert_allclose(np.asarray(jax.jit(fn)(x1)), eager[0], rtol=1e-12, atol=1e-12)
    # different outputs, or a vmap that mixes up the batch elements would pass
    assert not np.allclose(eager[0], eager[1], rtol=1e-6, atol=1e-6), name
    batched = jax.jit(jax.vmap(fn))(jnp.stack([x1, x2]))
    for k in range(2):
        np.testing.assert_allclose(np.asarray(batched[k]), eager[k], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", sorted(k for k, v in CASES.items() if v[2]))
def test_grad_matches_finite_differences(name):
    fn, (x1, _), _ = CASES[name]
    weights = jnp.asarray(np.random.default_rng(7).normal(size=jax.eval_shape(fn, x1).shape))
    g = check_grad_fd(lambda x: jnp.sum(weights * fn(x)), x1, rtol=1e-4)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.max(jnp.abs(g))) > 0


# kernels whose own tests check only the dtype of a float32 run
LOW_PRECISION = {
    "contextual_ao": (
        lambda a: vs.contextual_ao(a, clip=CLIP, unclipped=vs.lao(a, **LAO), brick_size=4, **LAO),
        ALPHA),
    "trilinear": (lambda v: trilinear(v, POINTS[0].astype(v.dtype)), VOLUME),
}


@pytest.mark.parametrize("name", sorted(LOW_PRECISION))
def test_float32_agrees_with_float64(name):
    fn, x = LOW_PRECISION[name]
    low = fn(x.astype(jnp.float32))
    assert low.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(low, np.float64), np.asarray(fn(x)), rtol=0, atol=2e-6)


def _threshold(o, low, high):
    """Section 5.1 written out: 0 below low, 1 from high on, linear in between."""
    return np.where(o < low, 0.0, np.where(o >= high, 1.0, (o - low) / (high - low)))


@pytest.mark.parametrize("color_bleeding", [False, True])
@pytest.mark.parametrize("density", ["opacity", "intensity"])
def test_obscurance_params_value_matches_reference_and_thresholds(density, color_bleeding):
    # the shells preset's opacity is not monotone in the intensity: the two densities
    # give different occluders
    vol = np.asarray(VOLUME[:7, :8, :6])
    tf = vs.transfer.preset("shells")
    kwargs = dict(d_max=3.5, low=0.5, high=0.85, rho="linear", level=0,
                  color_bleeding=color_bleeding)
    got = np.asarray(vs.ObscuranceParams(**kwargs, density=density)(jnp.asarray(vol), tf))
    occluders = np.asarray(tf.opacity(jnp.asarray(vol))) if density == "opacity" else vol
    # (a voxel without opacity, an occluder by intensity, reflects the ambient white)
    opacity = np.asarray(tf.opacity(jnp.asarray(vol)))[..., None]
    colors = (np.where(opacity > 0, np.asarray(tf.color(jnp.asarray(vol))), 1.0)
              if color_bleeding else None)
    raw = ref.obscurance(occluders, icosphere_points(0), 3.5, "linear", colors=colors)
    # every band of the thresholds is populated, so dropping or moving them shows
    for band in (raw < 0.5, (raw >= 0.5) & (raw < 0.85), raw >= 0.85):
        assert band.mean() > 0.1
    np.testing.assert_allclose(got, _threshold(raw, 0.5, 0.85), rtol=0, atol=1e-12)
    other = "intensity" if density == "opacity" else "opacity"
    swapped = np.asarray(vs.ObscuranceParams(**kwargs, density=other)(jnp.asarray(vol), tf))
    assert np.abs(swapped - got).max() > 0.1
