"""Parameter modules and entry points: float leaves that get gradients, and bad input
refused with a message that names the argument (found by a new-user walkthrough)."""

import dataclasses
import re
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade as vs
from volshade import scene as scene_module
from volshade.directions import icosphere, icosphere_points
from volshade.render import march
from volshade.saliency import opacity_factor

VOL = vs.data.phantom("shells", shape=12)
TF = vs.transfer.preset("shells")
CAM = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(6, 6))
RNG = np.random.default_rng(0)
DENSITY = jnp.asarray(RNG.random((8, 8, 8)), jnp.float32)
VOL_SCENE = vs.Scene(volume=VOL, transfer=TF)


def _obscurance_scene(params):
    return vs.Scene(volume=VOL, transfer=TF, shading="phong", ambient="obscurance",
                    obscurance=params)


@pytest.mark.slow
def test_int_parameters_become_float_leaves_that_get_gradients():
    # an int leaf would silently get no gradient from eqx.filter_grad
    modules = [vs.ObscuranceParams(d_max=4, low=0, high=1), vs.SaliencyModulation(d_max=4),
               vs.Phong(ambient=1, diffuse=1, specular=0, shininess=8),
               vs.Camera(eye=[0, 3, 0], target=[0, 0, 0], up=[1, 0, 0], fov=30, width=1),
               vs.Focus(center=(0, 0), radius=1, inside=2, outside=0),
               # with every effect whose defaults a scene fills in
               vs.Scene(volume=VOL, transfer=TF, background=(0, 0, 0), ambient="lao",
                        modulation="saliency", shading="phong", composition="importance"),
               vs.Scene(volume=VOL, transfer=TF, ambient="obscurance")]
    for module in modules:
        for leaf in jax.tree_util.tree_leaves(eqx.filter(module, eqx.is_array)):
            assert jnp.issubdtype(leaf.dtype, jnp.floating), (type(module).__name__, leaf)

    # the gradient in the obscurance parameters alone: in the whole scene's (the volume's
    # too) the program took 5 s to compile
    def loss(params):
        return jnp.sum(vs.render(_obscurance_scene(params), CAM)[..., :3])

    grad = eqx.filter_jit(eqx.filter_grad(loss))  # one compile for both modules
    g_int = grad(vs.ObscuranceParams(d_max=4, level=0))
    g_float = grad(vs.ObscuranceParams(d_max=4.0, level=0))
    assert g_int.d_max is not None
    assert float(g_int.d_max) == float(g_float.d_max) != 0.0


def test_integers_past_jaxs_integer_dtype_are_numbers():
    # a review: 2**31 (past int32 without x64) failed in jnp.asarray with a bare
    # OverflowError naming nothing; a float holds it. Past a float's range: refused by name
    big = 2**63 if jax.config.jax_enable_x64 else 2**31
    camera = vs.Camera(eye=[0, big, 0], target=[0, 0, 0], up=[1, 0, 0], fov=30, width=1)
    assert float(camera.eye[1]) == float(big)
    assert float(vs.LocalAmbientOcclusion(2.0, offset=1, max_radius=big).max_radius) \
        == float(big)
    with pytest.raises(ValueError, match="`radius` holds an integer beyond the range of a "
                                         "float"):
        vs.LocalAmbientOcclusion(10**400)
    with pytest.raises(ValueError, match=r"`step` must be a finite number > 0"):
        vs.Scene(volume=VOL, transfer=TF, step=10**400)
    with pytest.raises(TypeError, match=r"`spacing` must be a number or 3 numbers"):
        vs.Scene(volume=VOL, transfer=TF, spacing=[1, [2, 3]])


def test_lao_module_with_a_batch_axis_vmaps():
    # a batch of radii and of weights (the constructor checks one member's shapes)
    dirs = icosphere(0)
    p = vs.LocalAmbientOcclusion(jnp.array([3.0, 4.0]), directions=dirs, samples=3,
                                 max_radius=5.0, weights=jnp.stack([jnp.ones(12),
                                                                    jnp.arange(12.0)]))
    axes = eqx.tree_at(lambda q: (q.radius, q.weights), jax.tree_util.tree_map(lambda _: None, p),
                       (0, 0), is_leaf=lambda x: x is None)
    alpha = jnp.asarray(np.random.default_rng(0).uniform(0, 0.5, (6, 6, 6)))
    out = eqx.filter_vmap(lambda q: q(alpha), in_axes=(axes,))(p)
    for i, (radius, weights) in enumerate(((3.0, jnp.ones(12)), (4.0, jnp.arange(12.0)))):
        one = vs.LocalAmbientOcclusion(radius, directions=dirs, samples=3, max_radius=5.0,
                                       weights=weights)
        np.testing.assert_allclose(out[i], one(alpha), rtol=1e-12)


def test_nested_lists_become_arrays():
    # as a user types them: lists, ints among floats
    tf = vs.TransferFunction([0, 1], [[0, 0, 0], [1, 1, 1]], [0.0, 0.5])
    assert all(isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating)
               for x in (tf.points, tf.colors, tf.opacities))
    vol = jnp.linspace(0, 1, 64).reshape(4, 4, 4)
    listed = vs.Scene(volume=vol, transfer=tf, ambient="volume",
                      ambient_volume=np.full((4, 4, 4), 0.5).tolist())
    assert isinstance(listed.ambient_volume, jax.Array)
    arrayed = eqx.tree_at(lambda s: s.ambient_volume, listed, jnp.full((4, 4, 4), 0.5))
    cam = vs.Camera.orbit(image_shape=(4, 4))
    np.testing.assert_array_equal(vs.render(listed, cam), vs.render(arrayed, cam))


@pytest.mark.parametrize("build, exc, match", [
    (lambda: vs.ObscuranceParams(d_max=-1.0), ValueError, "d_max"),
    (lambda: vs.ObscuranceParams(low=0.9, high=0.1), ValueError, "`low` must be <= `high`"),
    (lambda: vs.ObscuranceParams(high=float("nan")), ValueError, "finite"),
    (lambda: vs.ObscuranceParams(color_bleeding="no"), TypeError, "color_bleeding"),
    (lambda: vs.SaliencyModulation(d_max=0.0), ValueError, "d_max"),
    (lambda: vs.SaliencyModulation(threshold=float("nan")), ValueError, "threshold"),
    (lambda: vs.SaliencyModulation(multiply="no"), TypeError, "multiply"),
    (lambda: vs.Phong(diffuse=[1.0, -2.0]), ValueError, "diffuse` must be a finite number"),
    (lambda: vs.Phong(shininess=0.0), ValueError, "shininess` must be > 0"),
    (lambda: vs.Phong(specular=-1.0), ValueError, "specular"),
    (lambda: vs.LocalAmbientOcclusion(-1.0), ValueError, "radius` must be .* got -1.0"),
    (lambda: vs.LocalAmbientOcclusion(1.0), ValueError, r"`radius` \(1.0\) must be > `offset`"),
    (lambda: vs.LocalAmbientOcclusion(4.0, offset=-1.0), ValueError, "`offset` must be"),
    # the options lao() refuses, refused when the module is built, not at its first call
    (lambda: vs.LocalAmbientOcclusion(3.0, opacity_correction="no"), TypeError,
     "`opacity_correction` must be True or False"),
    # a bool is not a number here (it would pass as 0 or 1), nor an int a random key
    (lambda: vs.affected_mask((8, 8, 8), vs.SphereClip(center=(4.0, 4.0, 4.0), radius=1.0),
                              radius=True), TypeError, "affected_mask: `radius` must be a number"),
    (lambda: vs.obscurance_shading(jnp.ones((1, 3)), jnp.ones(3), jnp.ones(3), jnp.ones(1),
                                   shininess=jnp.array(True)), TypeError,
     "obscurance_shading: `shininess` must be a number, got the bool"),
    (lambda: vs.directions.random_polar(3, key=0), TypeError,
     "random_polar: `key` must be one jax.random key"),
    # a truthy string would silently switch these on
    (lambda: vs.viewpoint_saliency(DENSITY, DENSITY, icosphere_points(0), per_area="no"),
     TypeError, "viewpoint_saliency: `per_area` must be True or False"),
    (lambda: vs.most_salient_view(DENSITY, DENSITY, icosphere_points(0), per_area="no"),
     TypeError, "most_salient_view: `per_area` must be True or False"),
    (lambda: vs.gradient.gradient_magnitude(jnp.ones((2, 3)), scaled="no"), TypeError,
     "gradient_magnitude: `scaled` must be True or False"),
    # found by a review: NumPy's "zero-size array to reduction operation max"
    (lambda: vs.gradient.gradient_magnitude(jnp.ones((3, 0))), ValueError,
     r"gradient_magnitude: `gradient` has shape \(3, 0\): its last axis holds the vector "
     r"components, and there are none"),
    (lambda: vs.gradient.gradient_magnitude(jnp.ones((0, 3)), scaled=True), ValueError,
     r"`gradient` is empty, shape \(0, 3\): `scaled=True` divides by the largest"),
    (lambda: vs.LocalAmbientOcclusion(3.0, brick_size=0), ValueError, "`brick_size` must be >= 1"),
    (lambda: vs.LocalAmbientOcclusion(3.0, brick_size=4.0), TypeError, "`brick_size` must be"),
    (lambda: vs.LocalAmbientOcclusion(3.0, max_radius=2.0), ValueError,
     r"`radius` \(3.0\) exceeds `max_radius` \(2.0\)"),
    (lambda: vs.LocalAmbientOcclusion(3.0, max_radius="5"), TypeError, "`max_radius` must be"),
    (lambda: vs.LocalAmbientOcclusion(3.0, directions=12, weights=jnp.ones(3)), ValueError,
     r"`weights` must have shape \(L,\) = \(12,\)"),
    (lambda: vs.LocalAmbientOcclusion(3.0, directions=vs.directions.icosphere(0).T), ValueError,
     r"`directions` must have shape \(L, 3\)"),
    (lambda: vs.LocalAmbientOcclusion(3.0, directions=0), ValueError, "`directions` must be >= 1"),
    (lambda: vs.lao(jnp.zeros((4, 4, 4)), directions=6, radius="3"), TypeError,
     r"`radius` must be a real number \(voxels\), got '3'"),
    (lambda: vs.Scene(volume=VOL, transfer=TF, step="0.5"), TypeError, "`step` must be a number"),
    (lambda: vs.Focus(radius=0.0), ValueError, "`radius` must be a finite number > 0 .*image "
                                               "height"),
    # found by a review: known NaN or inf were refused only by weights(), at the render
    (lambda: vs.Focus(radius=jnp.inf), ValueError, "Focus: `radius` must be a finite number"),
    (lambda: vs.Focus(outside=jnp.nan), ValueError, "Focus: `outside` must be finite"),
    (lambda: vs.Focus(center=(jnp.nan, 0.5)), ValueError, "Focus: `center` must be finite"),
    (lambda: vs.Focus(inside=jnp.inf), ValueError, "Focus: `inside` must be finite"),
    # found by a review: NumPy's "data type 'foo' not understood"
    (lambda: vs.focus_weights((3, 3), center=(1.0, 1.0), radius=1.0, dtype="x"), TypeError,
     r"focus_weights: `dtype` must be a floating dtype \(e.g. jnp.float32\), got 'x'"),
    (lambda: vs.TransferFunction.from_points([(0.0, 0, 0, 0, 0), (1.0, 1, 1, 1, 1)],
                                             dtype="foo"), TypeError,
     "from_points: `dtype` must be a floating dtype"),
    (lambda: vs.Focus(center=(32.0, 32.0)), ValueError, "`center` must be .*fractions .*"
     "focus_weights"),
    (lambda: vs.Focus(center=(0.5, -0.1)), ValueError, r"in \[0, 1\]"),
    (lambda: vs.Importance(darkening=-10.0), ValueError, "`darkening` must be >= 0"),
    (lambda: vs.Importance(specular_exponent=-1.0), ValueError, "`specular_exponent` must be > 0"),
    (lambda: vs.Importance(silhouette_start=0.9, silhouette_end=0.1), ValueError,
     "`silhouette_start` must be < `silhouette_end`"),
    # not real numbers: refused by name, not converted (a string) or kept (complex, bool)
    (lambda: vs.Importance(intensity="2"), TypeError,
     "volshade.Importance: `intensity` must be a real number"),
    (lambda: vs.Phong(ambient=0.3 + 0.1j), TypeError, "volshade.Phong: `ambient` .*complex"),
    (lambda: vs.Focus(radius=True), TypeError, "volshade.Focus: `radius` .*bool"),
    (lambda: vs.lao(DENSITY, directions=6, radius=3.0 + 1j), TypeError,
     r"volshade.lao: `radius` must be a real number \(voxels\), got \(3\+1j\)"),
    (lambda: vs.lao(DENSITY, directions=6, radius=3.0, offset=np.complex64(1)), TypeError,
     "volshade.lao: `offset` must be a real number"),
    (lambda: vs.lao(DENSITY, directions=np.eye(3) * (1 + 1j), radius=3.0), TypeError,
     "volshade.lao: `directions` must have a real floating .* complex128"),
    (lambda: vs.obscurance(DENSITY, directions=icosphere(0), d_max=np.complex64(4)), TypeError,
     "obscurance: `d_max` must be a real number"),
    (lambda: vs.obscurance(DENSITY, directions=np.eye(3) * (1 + 1j), d_max=4.0), TypeError,
     "obscurance: `directions` must be real"),
    # found by a review: composite took bool backgrounds as 1 and rounded the background
    # to half-precision samples before its check (-1e-8 passed as -0, 1e5 became inf)
    (lambda: vs.composite(jnp.full((1, 2, 3), 0.5), jnp.full((1, 2), 0.5),
                          background=(True, 0.5, 0.5)), TypeError,
     "composite: `background` must be a number or numbers, got a bool"),
    (lambda: vs.composite(jnp.full((1, 2, 3), 0.5), jnp.full((1, 2), 0.5),
                          importance=jnp.ones((1, 2)), background_importance=True), TypeError,
     "composite: `background_importance` must be a number or numbers, got a bool"),
    (lambda: vs.composite(jnp.full((1, 2, 3), 0.5, jnp.float16),
                          jnp.full((1, 2), 0.5, jnp.float16),
                          background=np.asarray([-1e-8, 0.0, 0.0])), ValueError,
     "composite: `background` .*negative"),
    # found by a review: Phong leaves set with tree_at shaded a bool as 1, and a string or
    # None failed inside JAX without the field's name
    (lambda: march(VOL, TF, CAM, shading="phong",
                   phong=eqx.tree_at(lambda p: p.ambient, vs.Phong(), True)), TypeError,
     "volshade.Phong: `ambient` must be a real number or an array of them, got True"),
    (lambda: march(VOL, TF, CAM, shading="phong",
                   phong=eqx.tree_at(lambda p: p.shininess, vs.Phong(), "x")), TypeError,
     "volshade.Phong: `shininess` must be a real number or an array of them, got 'x'"),
    # found by a review: lao took bools as 0 or 1 (0-d bool arrays, beside numbers), the
    # Module accepted weights lao refuses, and None or ragged directions ended in NumPy's
    # error without the argument's name
    (lambda: vs.lao(DENSITY, directions=4, radius=3.0, offset=np.array(False)), TypeError,
     r"lao: `offset` must be a number \(voxels\), got the bool array\(False\)"),
    (lambda: vs.lao(DENSITY, directions=4, radius=3.0, weights=(True, 1.0, 1.0, 1.0)),
     TypeError, "lao: `weights` must be a number or numbers, got a bool"),
    (lambda: vs.lao(DENSITY, directions=[[True, 0, 0], [0, 1.0, 0]], radius=3.0), TypeError,
     "lao: `directions` must hold numbers, got a bool"),
    (lambda: vs.LocalAmbientOcclusion(3.0, max_radius=np.array(True)), TypeError,
     "`max_radius` must be a number"),
    (lambda: vs.LocalAmbientOcclusion(3.0, directions=4, weights=[-1.0, 1, 1, 1]), ValueError,
     "LocalAmbientOcclusion: `weights` must be finite, >= 0 and not all zero"),
    (lambda: vs.lao(DENSITY, directions=None, radius=3.0), TypeError,
     r"lao: `directions` must be an \(L, 3\) array .* got NoneType"),
    (lambda: vs.LocalAmbientOcclusion(3.0, directions=[[1, 0, 0], [1, 0]]), TypeError,
     r"LocalAmbientOcclusion: `directions` must be an \(L, 3\) array .* got list"),
    # found by a review: march ignored parameters it does not read (a Scene refuses them)
    # and met objects of another type with an AttributeError
    (lambda: march(VOL, TF, CAM, importance=vs.Importance(intensity=50.0)), ValueError,
     "render: `importance` is read only with composition='importance'"),
    (lambda: march(VOL, TF, CAM, phong=vs.Phong(ambient=0.9)), ValueError,
     "render: `phong` is read only with shading='phong' or 'obscurance'"),
    (lambda: march(VOL, TF, CAM, composition="importance", importance=1.0), TypeError,
     "render: `importance` must be a volshade.Importance, got float"),
    (lambda: march(VOL, TF, CAM, shading="phong", phong=1.0), TypeError,
     "render: `phong` must be a volshade.Phong, got float"),
    (lambda: march(VOL, TF, None), TypeError, "render: `camera` must be a volshade.Camera"),
    (lambda: vs.sample_importance(None, intensity=jnp.ones(2)), TypeError,
     "sample_importance: `params` must be a volshade.Importance, got NoneType"),
    (lambda: vs.IntervalFeature(0.2, 0.4).opacity(VOL, None), TypeError,
     "IntervalFeature.opacity: `base` must be a volshade.TransferFunction"),
    # found by a review: march rendered NaN where an Importance leaf set with tree_at was NaN
    (lambda: march(VOL, TF, CAM, composition="importance", importance=eqx.tree_at(
        lambda i: i.intensity, vs.Importance(), jnp.nan)), ValueError,
     "render: `intensity` must be finite"),
    # found by a review: bools passed as 0 or 1, also beside numbers (NumPy promotes them),
    # and an integer dtype truncated every weight and opacity to 0
    (lambda: vs.focus_weights((3, 3), center=(1.0, 1.0), radius=True), TypeError,
     "focus_weights: `radius` must be a number or numbers, got a bool"),
    (lambda: vs.focus_weights((3, 3), center=(1.0, 1.0), radius=1.0, dtype=jnp.int32),
     TypeError, "focus_weights: `dtype` must be a floating dtype, got int32"),
    (lambda: march(VOL, TF, CAM, background=(True, False, True)), TypeError,
     "render: `background` must be a number or numbers, got a bool"),
    (lambda: march(VOL, TF, CAM, spacing=(True, 1, 1)), TypeError,
     r"render: `spacing` must be a number or 3 numbers"),
    (lambda: TF.opacity(VOL, step=True), TypeError, "opacity: `step` must be a number"),
    (lambda: vs.TransferFunction.from_points([(0.0, 0, 0, 0, False), (1.0, 1, 1, 1, True)]),
     TypeError, "from_points: `points` must be rows of 5 real numbers .* got a bool"),
    (lambda: vs.TransferFunction.from_points([(0.0, 0, 0, 0, 0), (1.0, 1, 1, 1, 1)],
                                             dtype=jnp.int32), TypeError,
     "from_points: `dtype` must be a floating dtype, got int32"),
    # found by a review: converted to float64, strings parsed and bools passed as 1
    (lambda: vs.obscurance(DENSITY, directions=[["1", "0", "0"]], d_max=4.0), TypeError,
     r"obscurance: `directions` must be an \(L, 3\) array of real numbers, got dtype <U1"),
    (lambda: vs.viewpoint_saliency(DENSITY, DENSITY, [[True, False, False]]), TypeError,
     "viewpoint_saliency: `viewpoints` must be a .* real numbers, got dtype bool"),
    (lambda: vs.Scene(volume=VOL, transfer=TF, background=None), TypeError,
     "volshade.Scene: `background` must be a real number"),
    (lambda: vs.LocalAmbientOcclusion("3"), TypeError, "`radius` must be a real number"),
    (lambda: vs.IntervalFeature(0.2, "1"), TypeError, "IntervalFeature: `high`"),
    # found by a review: an array of ends broadcast over the volume's last axis (under jit
    # silently; eagerly NumPy's "inhomogeneous shape")
    (lambda: eqx.filter_jit(lambda f: f.opacity(VOL, TF))(vs.IntervalFeature(
        jnp.asarray([0.0, 0.5]), jnp.ones(2))), ValueError,
     r"IntervalFeature.opacity: the interval's `low` must have shape \(\) where it is used, "
     r"got \(2,\)"),
    (lambda: vs.feature_ao(VOL, features=[vs.IntervalFeature(0.2, jnp.asarray([0.6, 0.9]))],
                           base=TF, directions=4, radius=2.0), ValueError,
     r"feature_ao: features\[0\], the interval's `high` must have shape \(\)"),
    (lambda: vs.Camera.orbit(fov="30"), TypeError, "Camera.orbit: `fov`"),
    (lambda: vs.SphereClip(center=(1.0, 2.0, None), radius=2.0), TypeError, "`center`"),
    (lambda: vs.Camera.orbit(target=(0.0, 0.0)), ValueError,
     r"Camera.orbit: `target` must be a point \(d, h, w\), got shape \(2,\)"),
    (lambda: vs.Focus(radius=jnp.array([0.1, 0.2])).weights((8, 8)), ValueError,
     r"volshade.Focus: `radius` must have shape \(\), got \(2,\); .* inside jax.vmap"),
    (lambda: vs.Camera.orbit(target=(0.0, jnp.inf, 0.0)), ValueError,
     "Camera.orbit: `target` must be finite"),
    (lambda: vs.TransferFunction([0.0, 1.0], "white", [0.0, 1.0]), TypeError,
     "TransferFunction: `colors` must be a real number"),
    (lambda: vs.BoxClip(center=(6.0, 6.0, 6.0), half_size="2"), TypeError,
     "BoxClip: `half_size` must be a real number"),
    (lambda: vs.BoxClip(center=(6.0, 6.0, 6.0), half_size=(1.0, 2.0)), ValueError,
     r"`half_size` must be one number or three .* got shape \(2,\)"),
    # a batch of sizes or of camera settings would fail later, in a broadcast naming nothing
    (lambda: vs.clip_mask(VOL.shape, vs.SphereClip(center=(6.0, 6.0, 6.0), radius=[1.0, 2.0])),
     ValueError, r"SphereClip: `radius` must have shape \(\) .* jax.vmap over them"),
    (lambda: vs.affected_mask(VOL.shape, vs.TorusClip(center=(6.0, 6.0, 6.0), major=3.0,
                                                      minor=[1.0, 2.0]), radius=2.0),
     ValueError, r"TorusClip: `minor` must have shape \(\)"),
    (lambda: vs.clip_mask(8, vs.SphereClip(center=(4.0, 4.0, 4.0), radius=1.0)), TypeError,
     r"clip_mask: `shape` must be 3 positive ints"),
    (lambda: vs.affected_mask(VOL, vs.SphereClip(center=(4.0, 4.0, 4.0), radius=1.0),
                              radius=2.0), TypeError,
     r"affected_mask: `shape` .* got an array of shape \(12, 12, 12\); pass `volume.shape`"),
    (lambda: vs.Camera.orbit(fov=[30.0, 40.0]).rays(), ValueError,
     "Camera: `fov` must be a scalar where the rays are made, .* list of cameras"),
    (lambda: vs.render(VOL_SCENE, vs.Camera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0),
                                            up=(1.0, 0.0, 0.0), fov=30.0, width=[1.0, 2.0],
                                            projection="orthographic")), ValueError,
     r"volshade.Camera: `width` must be a scalar where the rays are made"),
    (lambda: vs.Scene(volume=VOL, transfer=TF, ambient="volume",
                      ambient_volume=jnp.full(VOL.shape, 0.5 + 0.5j)), TypeError,
     "volshade.Scene: `ambient_volume` must have a real floating"),
    (lambda: eqx.filter_jit(lambda s: vs.Scene(volume=VOL, transfer=TF, step=s))(
        jnp.asarray(0.5)), TypeError, "volshade.Scene: `step` is static .* cannot be traced"),
    (lambda: vs.Scene(volume=VOL, transfer=TF, background=(0.0, -0.5, 0.0)), ValueError,
     r"volshade.Scene: `background` must lie in \[0, 1\] \(an RGB colour\)"),
    (lambda: vs.projected_area(DENSITY, None), TypeError,
     r"projected_area: `viewpoints` must be a \(V, 3\) array of directions, got None"),
    (lambda: vs.render(vs.Scene(volume=VOL, transfer=TF, shading="phong",
                                phong=vs.Phong(ambient=[0.2, 0.4])), CAM), ValueError,
     "Phong: `ambient` must be a scalar to shade, got shape \\(2,\\); .* jax.vmap"),
    (lambda: vs.threshold(DENSITY, False, True), TypeError,
     "threshold: `low` must be a number, got the bool False"),
    (lambda: vs.threshold(DENSITY, True, False), TypeError,
     "threshold: `low` must be a number, got the bool True"),
    (lambda: vs.threshold(DENSITY, 0.2, jnp.ones(2)), ValueError,
     r"threshold: `high` must be a scalar, got shape \(2,\)"),
    (lambda: jax.grad(lambda r: vs.TransferFunction.from_points(r).opacities[1])(
        jnp.asarray([(0.0, 0, 0, 0, 0), (1.0, 1, 1, 1, 0.5)])), TypeError,
     r"from_points: `points` is traced .*`TransferFunction\(points\[:, 0\]"),
    (lambda: vs.data.phantom("noise", seed=-1), ValueError, "phantom: `seed` must be >= 0"),
    # None and ragged lists: jnp.asarray raises a ValueError naming neither the argument
    # nor the fix (found by a review)
    (lambda: vs.Scene(volume=[[[0.0]], [[0.0, 1.0]]], transfer=TF), TypeError,
     "volshade.Scene: `volume` must be an array of numbers .* got list"),
    (lambda: vs.obscurance(None, directions=icosphere(0), d_max=2.0), TypeError,
     "obscurance: `density` must be an array of numbers .* got NoneType"),
    (lambda: vs.saliency(None), TypeError, "saliency: `obscurance` must be an array"),
    (lambda: vs.threshold(DENSITY, None, 1.0), TypeError,
     "threshold: `low` must be a real number, got None"),
    (lambda: vs.contextual_ao(DENSITY, clip=vs.SphereClip(center=(4.0, 4.0, 4.0), radius=1.0),
                              unclipped=None, directions=3, radius=2.0), TypeError,
     "contextual_ao: `unclipped` must be an array"),
])
def test_bad_values_are_refused_by_name(build, exc, match):
    # at construction where the module can tell, else where the value is used
    with pytest.raises(exc, match=match):
        build()


@pytest.mark.slow
def test_modules_built_with_a_batch_axis_vmap():
    # leaves may carry a batch axis (one Module for several settings, then vmap)
    batched = vs.Phong(ambient=[0.2, 0.4], diffuse=[0.6, 0.6], specular=[0.2, 0.0],
                       shininess=[8.0, 16.0])
    scene = vs.Scene(volume=VOL, transfer=TF, shading="phong")
    render = eqx.filter_jit(lambda p: vs.render(eqx.tree_at(lambda s: s.phong, scene, p), CAM))
    images = eqx.filter_jit(jax.vmap(render))(batched)
    for i in range(2):
        one = vs.Phong(**{k: getattr(batched, k)[i] for k in
                          ("ambient", "diffuse", "specular", "shininess")})
        # float32: the batched program rounds differently (up to 3e-7 here; either is
        # within 1.5e-6 of the float64 render)
        np.testing.assert_allclose(images[i], render(one), rtol=1e-6, atol=1e-6)
    params = vs.ObscuranceParams(d_max=[3.0, 5.0], low=[0.0, 0.1], high=[1.0, 0.9], level=0)
    out = eqx.filter_jit(jax.vmap(lambda p: p(VOL, TF)))(params)
    for i in range(2):
        one = vs.ObscuranceParams(d_max=params.d_max[i], low=params.low[i],
                                  high=params.high[i], level=0)
        # float32: the batched program may round differently by an ulp (6e-8 here)
        np.testing.assert_allclose(out[i], one(VOL, TF), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="`low` must be <= `high`"):
        vs.ObscuranceParams(low=[0.0, 0.9], high=[1.0, 0.5])
    # a clip's sizes and a camera's fov too, mapped over that leaf alone
    only = lambda module, leaf: eqx.tree_at(  # noqa: E731
        leaf, jax.tree_util.tree_map(lambda _: None, module), 0, is_leaf=lambda x: x is None)
    for clips, leaf, single in (
            (vs.SphereClip(center=(6.0, 6.0, 6.0), radius=[1.0, 2.5]), lambda c: c.radius,
             lambda r: vs.SphereClip(center=(6.0, 6.0, 6.0), radius=r)),
            (vs.TorusClip(center=(6.0, 5.0, 6.0), major=3.5, minor=[1.0, 2.0]),
             lambda c: c.minor, lambda r: vs.TorusClip(center=(6.0, 5.0, 6.0), major=3.5,
                                                       minor=r)),
            (vs.BoxClip(center=(6.0, 6.0, 6.0), half_size=[[1.0, 2.0, 1.5], [2.5, 3.0, 2.0]]),
             lambda c: c.half_size, lambda h: vs.BoxClip(center=(6.0, 6.0, 6.0), half_size=h))):
        masks = eqx.filter_vmap(lambda c: vs.clip_mask(VOL.shape, c),
                                in_axes=(only(clips, leaf),))(clips)
        eager = [np.asarray(vs.clip_mask(VOL.shape, single(r))) for r in leaf(clips)]
        assert 0 < eager[0].sum() < eager[1].sum()  # the sizes differ
        for got, want in zip(masks, eager, strict=True):
            np.testing.assert_array_equal(np.asarray(got), want)
    cameras = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(6, 6), fov=[20.0, 40.0])
    rays = eqx.filter_vmap(lambda c: c.rays()[1],
                           in_axes=(only(cameras, lambda c: c.fov),))(cameras)
    for got, fov in zip(rays, (20.0, 40.0), strict=True):
        np.testing.assert_allclose(got, vs.Camera.orbit(azimuth=30, elevation=20,
                                                        image_shape=(6, 6), fov=fov).rays()[1],
                                   rtol=0, atol=1e-14)


def test_a_traced_focus_centre_outside_the_image_is_refused_where_it_is_used():
    # Focus checks a known centre when built; a traced one, where its weights are made
    weights = jax.jit(lambda c: vs.Focus(center=c).weights((8, 8)))
    assert weights(jnp.asarray([0.5, 0.25])).shape == (8, 8)
    with pytest.raises(Exception, match=r"`center` must be \(row, column\) fractions"):
        jax.block_until_ready(weights(jnp.asarray([32.0, 32.0])))


def test_parameter_modules_accept_traced_values():
    # constructed under jit the values are unknown: nothing is refused at construction
    out = jax.jit(lambda d, t: (vs.ObscuranceParams(d_max=d).d_max,
                                vs.SaliencyModulation(threshold=t).threshold))(4.0, 0.2)
    assert [float(x) for x in out] == [4.0, pytest.approx(0.2)]


def test_traced_values_out_of_range_are_refused_by_the_renderer():
    # under jit (or in a fit) construction cannot see the values; the render checks them
    def render(phong_ambient, darkening, red):
        scene = vs.Scene(volume=VOL, transfer=TF, shading="phong",
                         phong=vs.Phong(ambient=phong_ambient), composition="importance",
                         importance=vs.Importance(silhouette=1.0, darkening=darkening),
                         background=jnp.stack([red, 0.0, 0.0]))
        return vs.render(scene, CAM)

    # every argument given: jit compiled a call without `red` apart
    assert np.all(np.isfinite(jax.jit(render)(0.3, 4.0, 1.0)))
    with pytest.raises(Exception, match="volshade.Phong: `ambient` must be a finite number"):
        jax.block_until_ready(jax.jit(render)(-1.0, 4.0, 0.0))
    with pytest.raises(Exception, match="volshade.Importance: `darkening` must be >= 0"):
        jax.block_until_ready(jax.jit(render)(0.3, -10.0, 0.0))
    # a background set by a fit is checked for NaN only: the fit may converge to 0 or 1
    # with a rounding error either side, and its scene must render (traced or not)
    assert np.all(np.isfinite(jax.jit(render)(0.3, 4.0, -1e-9)))
    fitted = eqx.tree_at(lambda s: s.background, VOL_SCENE, jnp.asarray([0.7, -3e-10, 1.0]))
    assert np.all(np.isfinite(vs.render(fitted, CAM)))
    # a known one passed to march is refused, as by Scene (a PNG would clip it)
    with pytest.raises(ValueError, match=r"volshade.render: `background` must lie in \[0, 1\]"):
        march(VOL, TF, CAM, background=(0.0, 1.5, 0.0))


def test_from_view_refuses_zero_and_nan_directions():
    for view in (jnp.zeros(3), jnp.array([jnp.nan, 1.0, 0.0]), [0.0, jnp.inf, 0.0]):
        with pytest.raises(ValueError, match="from_view: `view` must be a finite, non-zero"):
            vs.Camera.from_view(view)
    with pytest.raises(ValueError, match="shape"):
        vs.Camera.from_view([1.0, 0.0])
    build = jax.jit(lambda v: vs.Camera.from_view(v, image_shape=4).eye)
    assert np.allclose(build(jnp.array([0.0, 1.0, 0.0])), [0.0, 2.5, 0.0], atol=1e-6)
    with pytest.raises(Exception, match="`view` must be a finite, non-zero"):
        jax.block_until_ready(build(jnp.zeros(3)))
    # found by a review: subnormal components passed the host's "non-zero" check, then
    # XLA flushed them to 0 and the error blamed `azimuth`, never passed
    tiny = jnp.array([1e-39, 1e-39, 0.0], jnp.float32)
    with pytest.raises(ValueError, match="from_view: `view` must be a finite, non-zero"):
        vs.Camera.from_view(tiny)
    with pytest.raises(eqx.EquinoxRuntimeError, match="`view` must be a finite, non-zero"):
        eqx.filter_jit(lambda v: vs.Camera.from_view(v).eye)(tiny)
    np.testing.assert_allclose(vs.Camera.from_view(jnp.array([1e-37, 0.0, 0.0])).eye,
                               [2.5, 0.0, 0.0], atol=1e-6)


def test_image_shape_must_be_an_ordered_pair():
    # found by a review: any iterable was taken, a set in its own order ({6, 4} -> (4, 6))
    for shape in ({6, 4}, {6: "H", 4: "W"}, "ab", None, 3.0, np.zeros((2, 2), int)):
        with pytest.raises(TypeError, match=r"`image_shape` must be \(H, W\), a tuple or "
                                            r"list of two ints, or one int"):
            vs.Camera.orbit(image_shape=shape)
    for shape, want in (([6, 4], (6, 4)), ((6, 4), (6, 4)), (np.array([6, 4]), (6, 4)),
                        (5, (5, 5))):
        assert vs.Camera.orbit(image_shape=shape).image_shape == want


def test_camera_fields_set_with_tree_at_are_checked_by_the_render():
    # found by a review: the constructor refuses these, but a field set with eqx.tree_at
    # rendered (a (1,) target broadcast to (3,), a bool fov as 1) or failed inside NumPy
    for field, value, error, match in (
            ("target", jnp.array([0.2]), ValueError, r"`target` must have shape \(3,\), got \(1"),
            ("eye", jnp.array([2.5, 1.0, 1.0, 0.0]), ValueError, r"`eye` must have shape \(3,\)"),
            ("eye", "abc", TypeError, "`eye` must be a real number or an array of them"),
            ("fov", jnp.asarray(True), TypeError, "`fov` must be a real number"),
            ("width", None, TypeError, "`width` must be a real number")):
        cam = eqx.tree_at(lambda c, f=field: getattr(c, f), CAM, value)
        with pytest.raises(error, match=f"volshade.Camera: {match}"):
            vs.render(VOL_SCENE, cam)
        with pytest.raises(error, match=match):
            vs.render(VOL_SCENE, [CAM, cam])
    # numbers are fine, as the constructor takes them
    np.testing.assert_allclose(vs.render(VOL_SCENE, eqx.tree_at(lambda c: c.fov, CAM, 30)),
                               vs.render(VOL_SCENE, CAM), atol=1e-6)  # float32 rounding


def test_unread_parameters_are_refused_however_they_are_set():
    # found by a review: the constructor refused a parameter the scene does not read,
    # set to other than its default, only when built from known values: set with
    # eqx.tree_at, or with the scene built under jit, it was ignored by the render
    focused = lambda g: vs.Scene(volume=VOL, transfer=TF, composition="importance",  # noqa: E731
                                 importance=vs.Importance(global_weight=g), focus=vs.Focus())
    render = eqx.filter_jit(lambda g: vs.render(focused(g), CAM))
    # arrays: filter_jit holds a Python number static, and compiled a program for each
    assert render(jnp.asarray(1.0)).shape == (6, 6, 4)
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`importance.global_weight` is not read"):
        render(jnp.asarray(5.0))
    dark = vs.Scene(volume=VOL, transfer=TF, ambient="lao", shading="obscurance",
                    lao=vs.LocalAmbientOcclusion(2.0, directions=6, samples=2))
    for value in (0.9, jnp.asarray(0.9)):
        with pytest.raises(ValueError, match=r"volshade.render: `phong.ambient` is not read by "
                                             r"this scene \(shading='obscurance'.*default, 0.35"):
            vs.render(eqx.tree_at(lambda s: s.phong.ambient, dark, value), CAM)
    np.testing.assert_array_equal(
        vs.render(eqx.tree_at(lambda s: s.phong.ambient, dark, 0.35), CAM), vs.render(dark, CAM))
    # a copy under jit that turns an effect off: a changed parameter cannot be told from
    # the defaults while tracing, so the copy's render refuses it when it runs
    lit = vs.Scene(volume=VOL, transfer=TF, shading="phong")
    changed = eqx.tree_at(lambda s: s.phong.diffuse, lit, jnp.asarray(0.3))
    unlit = eqx.filter_jit(lambda s: vs.render(dataclasses.replace(s, shading="none"), CAM))
    np.testing.assert_allclose(unlit(lit), vs.render(VOL_SCENE, CAM), atol=1e-6)
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`phong` is used only with "
                                                      r"shading='phong'.*pass `phong=None` too"):
        unlit(changed)


def test_obscurance_input_errors_name_the_argument():
    dirs = icosphere(0)
    # a d_max beyond float32 was refused as "not finite" (the cast made it inf)
    with pytest.raises(ValueError, match=r"`d_max` = 1e\+39 \(voxels\) lies beyond the range "
                                         r"of float32"):
        vs.obscurance(DENSITY, directions=dirs, d_max=1e39)
    with pytest.raises(TypeError, match=r"`d_max` must be a real number \(voxels\), got None"):
        vs.obscurance(DENSITY, directions=dirs, d_max=None)
    with pytest.raises(ValueError, match="`rho\\(d, d_max\\)` must return one value per"):
        vs.obscurance(DENSITY, directions=dirs, d_max=4.0, rho=lambda d, m: jnp.ones(3))
    # a constant rho is a scalar: broadcast (occluded directions count 0.5, the others 1)
    constant = vs.obscurance(DENSITY, directions=dirs, d_max=4.0, rho=lambda d, m: 0.5)
    ao = vs.obscurance(DENSITY, directions=dirs, d_max=4.0, rho="ao")
    np.testing.assert_allclose(constant, 0.5 + 0.5 * ao, atol=1e-6)
    with pytest.raises(ValueError, match="`ambient` .* needs `colors`"):
        vs.obscurance(DENSITY, directions=dirs, d_max=4.0, ambient=(1.0, 1.0, 1.0))
    with pytest.raises(TypeError, match="got the number 42.*icosphere_points"):
        vs.obscurance(DENSITY, directions=42, d_max=4.0)
    colors = jnp.stack([DENSITY] * 3, -1)
    for bad in ({"colors": 255 * colors}, {"colors": -colors},
                {"colors": colors, "ambient": (2.0, 1.0, 1.0)}):
        with pytest.raises(Exception, match="must lie in \\[0, 1\\] \\(RGB reflectances\\)"):
            jax.block_until_ready(vs.obscurance(DENSITY, directions=dirs, d_max=4.0, **bad))


def test_obscurance_shading_input_errors():
    normal, obs = jnp.ones((5, 3)), jnp.ones(5)
    with pytest.raises(ValueError, match="`light` must have shape \\(3,\\) or one that"):
        vs.obscurance_shading(normal, jnp.ones((4, 3)), jnp.ones(3), obs)
    with pytest.raises(ValueError, match="`k_d` must be a scalar"):
        vs.obscurance_shading(normal, jnp.ones(3), jnp.ones(3), obs, k_d=jnp.ones(2))
    for n in (0.0, -1.0):
        with pytest.raises(ValueError, match="`shininess` must be > 0"):
            vs.obscurance_shading(normal, jnp.ones(3), jnp.ones(3), obs, shininess=n)
    # traced: refused even where every N.H is a known 0 (the specular term folds away)
    side, light = jnp.array([[0.0, 1.0, 0.0]]), jnp.array([1.0, 0.0, 0.0])
    shade = jax.jit(lambda s: vs.obscurance_shading(side, light, light, jnp.ones(1), k_s=1.0,
                                                    shininess=s))
    for n in (-1.0, jnp.nan):
        with pytest.raises(Exception, match="`shininess` (must be > 0|contains NaN or inf)"):
            jax.block_until_ready(shade(n))
    # per-sample light directions that broadcast are fine
    out = vs.obscurance_shading(normal, jnp.ones((5, 3)), jnp.ones((1, 3)), obs)
    assert out.shape == (5,)
    # negative light and obscurances outside [0, 1] (known or traced) are refused
    for name in ("k_d", "k_s"):
        with pytest.raises(ValueError, match=f"`{name}` must be >= 0"):
            vs.obscurance_shading(normal, jnp.ones(3), jnp.ones(3), obs, **{name: -1.0})
        with pytest.raises(Exception, match=f"`{name}` must be >= 0"):
            jax.block_until_ready(jax.jit(lambda k, name=name: vs.obscurance_shading(
                normal, jnp.ones(3), jnp.ones(3), obs, **{name: k}))(-0.5))
    for bad in (1.5 * obs, -obs, jnp.ones((5, 3)).at[2, 1].set(2.0)):
        with pytest.raises(ValueError, match=r"`obscurance` must lie in \[0, 1\]"):
            vs.obscurance_shading(normal, jnp.ones(3), jnp.ones(3), bad)
    with pytest.raises(Exception, match=r"`obscurance` must lie in \[0, 1\]"):
        jax.block_until_ready(jax.jit(lambda o: vs.obscurance_shading(
            normal, jnp.ones(3), jnp.ones(3), o))(1.5 * obs))


def test_saliency_errors_name_saliency_and_the_argument():
    with pytest.raises(TypeError, match="volshade.saliency: `spacing` is static"):
        jax.jit(lambda s: vs.saliency(DENSITY, spacing=s))(jnp.ones(3))
    with pytest.raises(ValueError, match="volshade.saliency: `size` .* pass the Python int 5"):
        vs.saliency(DENSITY, size=jnp.int32(5))
    with pytest.raises(ValueError, match="got Array\\(3.7"):
        vs.saliency(DENSITY, size=jnp.asarray(3.7))
    with pytest.raises(ValueError, match="volshade.saliency: `spacing`"):
        vs.saliency(DENSITY, spacing=(1.0, 2.0))
    with pytest.raises(ValueError, match="volshade.saliency: `obscurance` must not be empty"):
        vs.saliency(jnp.zeros((0, 4, 4)))
    with pytest.raises(ValueError, match="most_salient_view: `saliency` and `opacity`"):
        vs.most_salient_view(DENSITY, DENSITY[:, :, :4], icosphere(0))
    # named after the function called, not the helper that checks
    with pytest.raises(ValueError, match="volshade.modulate_opacity: `threshold`"):
        vs.modulate_opacity(DENSITY, DENSITY, threshold=jnp.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="volshade.modulate_opacity: `boost_top`"):
        vs.modulate_opacity(DENSITY, DENSITY, boost_top=2)
    with pytest.raises(TypeError, match="volshade.modulate_opacity: `multiply` must be True or"):
        vs.modulate_opacity(DENSITY, DENSITY, multiply="no")
    with pytest.raises(ValueError, match="saliency.opacity_factor: `threshold`"):
        opacity_factor(DENSITY, threshold=jnp.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="projected_area: `level` must be a scalar"):
        vs.projected_area(DENSITY, icosphere(0), level=jnp.array([0.1, 0.2]))
    # saliency lies in [0, 1]: a threshold above 1 would make every voxel transparent
    level = r"`threshold` must be a saliency level in \[0, 1\]"
    for t in (1.5, -0.1):
        with pytest.raises(ValueError, match="modulate_opacity: " + level):
            vs.modulate_opacity(DENSITY, DENSITY, threshold=t)
        with pytest.raises(ValueError, match="SaliencyModulation: " + level):
            vs.SaliencyModulation(threshold=t)
        with pytest.raises(Exception, match="opacity_factor: " + level):
            jax.block_until_ready(jax.jit(lambda t: opacity_factor(DENSITY, threshold=t))(t))
    for t in (0.0, 1.0):
        assert np.isfinite(vs.modulate_opacity(DENSITY, DENSITY, threshold=t)).all()


def test_scene_saliency_modulation_uses_the_scene_spacing():
    vol = vs.data.phantom("orange", shape=(10, 16, 16))
    tf = vs.transfer.preset("grey")
    spacing = (2.0, 1.0, 1.0)
    modulation = vs.SaliencyModulation(d_max=6.0, level=0, threshold=0.0)
    scene = vs.Scene(volume=vol, transfer=tf, spacing=spacing, modulation="saliency",
                     saliency=modulation)
    obs = vs.obscurance(tf.opacity(vol), directions=icosphere_points(0), d_max=6.0)
    want = opacity_factor(vs.saliency(obs, spacing=spacing), threshold=0.0)
    unit = opacity_factor(vs.saliency(obs), threshold=0.0)
    assert float(jnp.max(jnp.abs(want - unit))) > 1e-2  # the spacing matters here
    np.testing.assert_allclose(scene_module._saliency_factor(scene), want, atol=1e-6)


def test_scene_refuses_an_ambient_volume_outside_the_unit_range():
    scene = vs.Scene(volume=VOL, transfer=TF, shading="phong", ambient="volume",
                     ambient_volume=jnp.full(VOL.shape, 5.0))
    with pytest.raises(Exception, match="`scene.ambient_volume` must lie in \\[0, 1\\]"):
        jax.block_until_ready(vs.render(scene, CAM))


def test_scene_turns_a_nested_list_volume_into_an_array():
    scene = vs.Scene(volume=np.asarray(VOL).tolist(), transfer=TF)
    assert isinstance(scene.volume, jax.Array)
    # (a list of Python floats becomes float64 under x64)
    np.testing.assert_allclose(vs.render(scene, CAM),
                               vs.render(vs.Scene(volume=VOL, transfer=TF), CAM), atol=1e-5)


@pytest.mark.parametrize("value", [jnp.asarray(0.5), np.float32(0.5), np.asarray(0.5)])
def test_static_steps_given_as_arrays_are_kept_as_python_floats(value, recwarn):
    # a JAX array was kept in the static field (documented as a float) and equinox
    # warned: the step and step0 become Python floats, as spacing becomes a tuple
    scene = vs.Scene(volume=VOL, transfer=vs.TransferFunction(
        TF.points, TF.colors, TF.opacities, step0=2 * value), step=value)
    assert type(scene.step) is float and scene.step == 0.5
    assert type(scene.transfer.step0) is float and scene.transfer.step0 == 1.0
    hash(jax.tree_util.tree_structure(scene))
    assert not [w for w in recwarn if "static" in str(w.message)]
    np.testing.assert_allclose(
        vs.render(scene, CAM),
        vs.render(vs.Scene(volume=VOL, transfer=vs.TransferFunction(
            TF.points, TF.colors, TF.opacities, step0=1.0), step=0.5), CAM), atol=1e-12)


def test_lists_set_with_tree_at_become_arrays_and_dicts_are_refused_by_path():
    # eqx.tree_at skips the modules' converters: a list of opacities failed inside the
    # render ('list' object has no attribute 'astype'); it is made an array, as built
    listed = eqx.tree_at(lambda s: s.transfer.opacities, VOL_SCENE,
                         np.asarray(TF.opacities).tolist())
    moved = [CAM, eqx.tree_at(lambda c: c.eye, CAM, tuple(np.asarray(CAM.eye).tolist()))]
    np.testing.assert_array_equal(vs.render(listed, CAM), vs.render(VOL_SCENE, CAM))
    for got, want in zip(vs.render(VOL_SCENE, moved), vs.render(VOL_SCENE, [CAM, CAM]),
                         strict=True):
        np.testing.assert_array_equal(got, want)
    features = vs.Scene(volume=VOL, transfer=TF, ambient="feature_ao",
                        feature_ao=vs.FeatureAmbientOcclusion([vs.IntervalFeature(0.2, 0.6),
                                                               TF]))
    for where, value, name in [
            (lambda s: s.background, {"r": 0.0}, "scene.background"),
            (lambda s: s.feature_ao.features[1].opacities, [[0.0], [0.0, 1.0]],
             "scene.feature_ao.features[1].opacities")]:
        scene = features if "feature" in name else VOL_SCENE
        with pytest.raises(TypeError, match=re.escape(f"volshade.render: `{name}` must be an "
                                                      f"array, got a")):
            vs.render(eqx.tree_at(where, scene, value), CAM)


def test_modules_set_with_tree_at_are_checked_where_they_are_used():
    # found by a pytree review: eqx.tree_at skips the constructors' checks. An
    # Importance weight of 16 values (the rays of a group of an 8 x 8 image) rendered a
    # wrong image without a word; a transfer function's colours of shape (K, 4) were
    # accepted; an interval's end set to a Python float failed with "'float' object has
    # no attribute 'astype'"; a clip put into an obscurance scene rendered unclipped
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))
    important = vs.Scene(volume=VOL, transfer=TF, composition="importance",
                         importance=vs.Importance(intensity=2.0))
    vector = eqx.tree_at(lambda s: s.importance.intensity, important, jnp.linspace(0, 4, 16))
    scalar_match = r"Importance: `intensity` must be a scalar, got shape \(16,\)"
    with pytest.raises(ValueError, match=scalar_match):
        vs.render(vector, cam)
    with pytest.raises(ValueError, match=scalar_match):
        eqx.filter_jit(vs.render)(vector, cam)
    with pytest.raises(ValueError, match=r"`intensity` must be a scalar, got shape \(3,\)"):
        vs.sample_importance(eqx.tree_at(lambda i: i.intensity, vs.Importance(), jnp.ones(3)),
                             intensity=jnp.ones(3))
    k = TF.points.shape[0]
    for where, value, match in [
            (lambda t: t.colors, jnp.zeros((k, 4)), rf"`colors` must have shape \({k}, 3\)"),
            (lambda t: t.opacities, jnp.zeros(k - 1), rf"`opacities` must have shape \({k},\)"),
            (lambda t: t.points, jnp.stack([TF.points] * 2),
             r"`points` must be a non-empty 1-D array, got shape .*; a batch of transfer "
             r"functions is for jax.vmap")]:
        tf = eqx.tree_at(where, TF, value)
        with pytest.raises(ValueError, match=match):
            tf.opacity(VOL)
        with pytest.raises(ValueError, match=match):
            vs.render(eqx.tree_at(lambda s: s.transfer, VOL_SCENE, tf), CAM)
    listed = eqx.tree_at(lambda t: t.opacities, TF, np.asarray(TF.opacities).tolist())
    np.testing.assert_array_equal(listed.opacity(VOL), TF.opacity(VOL))
    # a feature's transfer function too, which feature AO checks against the volume first
    stacked = eqx.tree_at(lambda t: t.points, TF, jnp.stack([TF.points] * 2))
    listed_points = eqx.tree_at(lambda t: t.points, TF, np.asarray(TF.points).tolist())
    with pytest.raises(ValueError, match="a batch of transfer functions is for jax.vmap"):
        vs.feature_ao(VOL, features=[stacked], directions=4, radius=2.0, samples=4)
    np.testing.assert_array_equal(
        vs.feature_ao(VOL, features=[listed_points], directions=4, radius=2.0, samples=4),
        vs.feature_ao(VOL, features=[TF], directions=4, radius=2.0, samples=4))
    interval = vs.IntervalFeature(0.2, 0.6)
    np.testing.assert_array_equal(
        eqx.tree_at(lambda f: f.low, interval, 0.2).opacity(VOL, TF), interval.opacity(VOL, TF))
    # tuples where arrays go, used by the modules' own methods (the render converts them)
    focus = vs.Focus(center=(0.4, 0.6))
    np.testing.assert_array_equal(
        eqx.tree_at(lambda f: f.center, focus, (0.4, 0.6)).weights((8, 8)), focus.weights((8, 8)))
    for got, want in zip(eqx.tree_at(lambda c: c.eye, cam, tuple(np.asarray(cam.eye).tolist()))
                         .rays(), cam.rays(), strict=True):
        np.testing.assert_array_equal(got, want)
    # the scene's structure, as the constructor checks it
    clip = vs.SphereClip(center=(6.0, 6.0, 6.0), radius=3.0)
    lit = vs.Scene(volume=VOL, transfer=TF, shading="phong")
    for scene, where, value, exc, match in [
            (_obscurance_scene(vs.ObscuranceParams(d_max=4.0)), lambda s: s.clip, clip,
             ValueError, "ambient='obscurance' does not take `clip` into account"),
            (lit, lambda s: s.lao, vs.LocalAmbientOcclusion(2.0), ValueError,
             "`lao` is used only with ambient='lao'"),
            (lit, lambda s: s.focus, vs.Focus(), ValueError,
             "`focus` needs composition='importance'"),
            (vs.Scene(volume=VOL, transfer=TF, ambient="lao"), lambda s: s.lao, vs.Phong(),
             TypeError, "`lao` must be a volshade.LocalAmbientOcclusion, got Phong")]:
        with pytest.raises(exc, match=f"volshade.render: {re.escape(match)}"):
            vs.render(eqx.tree_at(where, scene, value, is_leaf=lambda x: x is None), CAM)


def test_numpy_scalars_in_static_fields_become_python_values(recwarn):
    # equinox warned "A JAX array is being set as static!" and kept the NumPy scalar
    modules = {"level": vs.ObscuranceParams(level=np.int64(1), color_bleeding=np.bool_(True),
                                            density=np.str_("opacity")),
               "size": vs.SaliencyModulation(size=np.int64(3), multiply=np.bool_(False)),
               "kind": vs.Focus(kind=np.str_("circular")),
               "merge": vs.FeatureAmbientOcclusion([TF], merge=np.str_("feature")),
               "projection": vs.Camera(eye=(0.0, 3.0, 0.0), target=(0.0, 0.0, 0.0),
                                       up=(1.0, 0.0, 0.0), fov=30.0, width=1.2,
                                       projection=np.str_("perspective")),
               "image_shape": vs.Camera.orbit(image_shape=(np.int64(4), np.int64(4))),
               "implementation": vs.LocalAmbientOcclusion(implementation=np.str_("xla")),
               "options": vs.Scene(volume=VOL, transfer=TF, shading=np.str_("phong"),
                                   ambient=np.str_("lao"), composition=np.str_("standard"))}
    assert not [w for w in recwarn if "static" in str(w.message)]
    for module in modules.values():
        for field in dataclasses.fields(module):
            if field.metadata.get("static"):
                value = getattr(module, field.name)
                for v in value if isinstance(value, tuple) else (value,):
                    assert not isinstance(v, np.generic), field.name
    assert type(modules["size"].size) is int and type(modules["kind"].kind) is str


def test_mistakes_a_new_user_made_are_named():
    # found by a new-user walkthrough; each was accepted, or refused without the fix
    cam = vs.Camera.orbit(image_shape=(4, 4))
    scene = vs.Scene(volume=VOL, transfer=TF, ambient="lao",
                     lao=vs.LocalAmbientOcclusion(2.0, directions=4, samples=2, max_radius=6.0))
    target = vs.render(scene, cam)
    # a float target of 0-255 ended with the solver's "maximum number of steps"; noise a
    # little outside [0, 1] is kept
    with pytest.raises(ValueError, match=r"fit: `target` holds values far outside \[0, 1\], "
                                         r"where renders lie \(beyond \[-1, 2\]\); divide"):
        vs.fit(scene, cam, target * 255, params=("lao.radius",))
    noisy = target + 0.05 * jax.random.normal(jax.random.PRNGKey(0), target.shape)
    assert float(jnp.min(noisy)) < 0
    ((_, kept, _),) = sys.modules["volshade.fit"]._views(cam, noisy, None)
    np.testing.assert_array_equal(kept, noisy)
    # bounds beyond the static max_radius stopped the fit with the kernel's error
    with pytest.raises(ValueError, match=r"the bounds of 'lao.radius' reach 20, beyond "
                                         r"`lao.max_radius` \(6, static\)"):
        vs.fit(scene, cam, target, params={"lao.radius": (1.5, 20.0)})
    # an interval outside the transfer function's points selected nothing: AO 1
    for interval in ((40.0, 100.0), (1.2, 2.0)):
        with pytest.raises(ValueError, match=r"features\[0\], the interval .* lies outside "
                                             r"`base`'s control points \[0, 1\]"):
            vs.feature_ao(VOL, features=[vs.IntervalFeature(*interval)], base=TF,
                          directions=4, radius=2.0)
        with pytest.raises(ValueError, match=r"IntervalFeature.opacity: the interval .* lies "
                                             r"outside `base`'s control points"):
            vs.IntervalFeature(*interval).opacity(VOL, TF)
    # an effect's parameters, or a volume, where its option's name goes: a warning and
    # the whole array printed in the error
    with pytest.raises(TypeError, match=r"`shading` must name an option, one of 'none', "
                                         r"'phong', 'obscurance', got Phong; Phong "
                                         r"coefficients go in `phong=`"):
        vs.Scene(volume=VOL, transfer=TF, shading=vs.Phong())
    with pytest.raises(TypeError, match=r"`ambient` must name an option.* got ndarray; an "
                                         r"ambient volume of your own goes in `ambient_volume=`"):
        vs.Scene(volume=VOL, transfer=TF, ambient=np.ones(VOL.shape))
    # a transfer function, or its method, where its values go
    with pytest.raises(TypeError, match=r"`alpha` must be an array .* got TransferFunction; "
                                        r"classify the volume first, e.g. `tf.opacity\(volume\)`"):
        vs.lao(TF, directions=4, radius=2.0)
    with pytest.raises(TypeError, match=r"`colors` must be an array .* classify the volume"):
        vs.obscurance(TF.opacity(VOL), directions=icosphere(0), d_max=4.0, colors=TF.color)
    # 0-255 colours composited to values up to 255
    with pytest.raises(TypeError, match=r"composite: `colors` has the integer dtype uint8"):
        vs.composite(np.full((2, 3, 3), 200, np.uint8), np.full((2, 3), 0.5))
    # found by a review: a bool mask composited as 0 and 1 (a bool background is refused)
    with pytest.raises(TypeError, match=r"composite: `colors` has the dtype bool"):
        vs.composite(np.ones((2, 3, 3), bool), np.full((2, 3), 0.5))
    # a nested list is an array of numbers (the integer check failed on it), a string not
    np.testing.assert_array_equal(vs.composite([[0.5, 0.0, 0.0]], [0.5]), [0.5, 0, 0, 0.5])
    with pytest.raises(TypeError, match=r"composite: `colors` must be an array of numbers"):
        vs.composite("red", [0.5])
