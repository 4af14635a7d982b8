"""float32 against float64 for whole renders: every effect a scene can call for,
computed in both precisions from the same parameters (the suite runs with x64)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade as vs

VOL = vs.data.phantom("shells", shape=16)
TF = vs.transfer.preset("shells")
CAM = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))

SCENES = {
    "emission-absorption": dict(),
    "phong + lao": dict(shading="phong", ambient="lao",
                        lao=vs.LocalAmbientOcclusion(4.0, directions=12, samples=6)),
    "obscurance shading + colour bleeding": dict(
        shading="obscurance", ambient="obscurance",
        obscurance=vs.ObscuranceParams(d_max=6.0, level=0, color_bleeding=True)),
    "saliency modulation": dict(modulation="saliency",
                                saliency=vs.SaliencyModulation(d_max=6.0, level=0,
                                                               threshold=0.1)),
    "importance + focus": dict(shading="phong", composition="importance",
                               importance=vs.Importance(intensity=2.0, gradient=1.0,
                                                        silhouette=1.0, unocclusion=1.0),
                               focus=vs.Focus(radius=0.3)),
}


def _cast(tree, dtype):
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_render_float32_agrees_with_float64(name):
    scene = vs.Scene(volume=VOL, transfer=TF, **SCENES[name])
    render = eqx.filter_jit(vs.render)
    hi = render(_cast(scene, jnp.float64), _cast(CAM, jnp.float64))
    lo = render(_cast(scene, jnp.float32), _cast(CAM, jnp.float32))
    assert hi.dtype == jnp.float64 and lo.dtype == jnp.float32
    assert float(jnp.max(hi[..., 3])) > 0.1  # something is drawn
    np.testing.assert_allclose(lo, hi, atol=2e-5)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_volumes_render_in_float32(dtype):
    # a half-precision volume is upcast (exactly) and rendered as a float32 one
    parts = _cast(dict(transfer=TF, phong=vs.Phong(), background=jnp.zeros(3)), jnp.float32)
    camera = _cast(CAM, jnp.float32)
    image = vs.render(vs.Scene(volume=VOL.astype(dtype), shading="phong", **parts), camera)
    want = vs.render(vs.Scene(volume=VOL.astype(dtype).astype(jnp.float32), shading="phong",
                              **parts), camera)
    assert image.dtype == jnp.float32
    np.testing.assert_array_equal(image, want)


@pytest.mark.parametrize("name", ["phong + lao", "obscurance shading + colour bleeding",
                                  "saliency modulation"])
def test_half_precision_volumes_feed_every_effect(name):
    # effects classify the volume themselves (LAO, obscurance, saliency): in float32 too
    vol = VOL.astype(jnp.bfloat16)
    scene = _cast(vs.Scene(volume=vol.astype(jnp.float32), transfer=TF, **SCENES[name]),
                  jnp.float32)
    image = vs.render(eqx.tree_at(lambda s: s.volume, scene, vol), _cast(CAM, jnp.float32))
    assert image.dtype == jnp.float32
    np.testing.assert_array_equal(image, vs.render(scene, _cast(CAM, jnp.float32)))


def test_half_precision_cameras_and_foci_place_pixels_in_float32():
    # a bfloat16 pixel grid past 256 pixels misplaced rays by a pixel (0.85 in the
    # image of a 300 x 300 render) and the focus centre by several
    cam = _cast(vs.Camera.orbit(azimuth=33, elevation=17, image_shape=(300, 300)), jnp.bfloat16)
    origins, directions = cam.rays()
    want_origins, want_directions = _cast(cam, jnp.float32).rays()
    assert directions.dtype == jnp.float32
    np.testing.assert_array_equal(directions, want_directions)
    np.testing.assert_array_equal(origins, want_origins)

    focus = _cast(vs.Focus(center=(0.37, 0.61), radius=0.2), jnp.bfloat16)
    weights = focus.weights((300, 300))
    assert weights.dtype == jnp.bfloat16
    # only the final rounding to bfloat16 (8 significant bits) differs
    np.testing.assert_allclose(weights.astype(jnp.float32),
                               _cast(focus, jnp.float32).weights((300, 300)), atol=2 ** -8)


def test_half_precision_features_weigh_importance_in_float32():
    importance, scale = vs.sample_importance(vs.Importance(intensity=7e4),
                                             intensity=jnp.ones(3, jnp.float16))
    assert importance.dtype == scale.dtype == jnp.float32
    np.testing.assert_array_equal(importance, 7e4)  # float16 overflowed to inf


def test_cameras_and_foci_with_python_numbers_set_in_them():
    # found by a review: the float32-at-least cast read `.dtype` of a number set with
    # eqx.tree_at (AttributeError)
    cam = vs.Camera.orbit(image_shape=(4, 5))
    rays = eqx.tree_at(lambda c: c.fov, cam, 45.0).rays()
    want = eqx.tree_at(lambda c: c.fov, cam, jnp.asarray(45.0)).rays()
    for got, expected in zip(rays, want, strict=True):
        np.testing.assert_array_equal(got, expected)
    focus = vs.Focus(center=(0.37, 0.61), radius=0.2)
    np.testing.assert_array_equal(eqx.tree_at(lambda f: f.radius, focus, 0.3).weights((6, 7)),
                                  eqx.tree_at(lambda f: f.radius, focus,
                                              jnp.asarray(0.3)).weights((6, 7)))
