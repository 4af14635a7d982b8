import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade.scene as scene_module
from volshade.camera import Camera
from volshade.render import march
from volshade.scene import Scene, render
from volshade.shading import Phong
from volshade.transfer import preset


def _volume():
    return jnp.asarray(np.random.default_rng(0).random((6, 6, 6)))


def test_render_equals_march_with_the_scene_options():
    cam = Camera.orbit(azimuth=40.0, image_shape=(4, 4))
    vol = _volume()
    ao = jnp.full((6, 6, 6), 0.7)
    s = Scene(volume=vol, transfer=preset("grey"), shading="phong", ambient="volume",
              ambient_volume=ao, background=(0.1, 0.2, 0.3), step=0.8)
    np.testing.assert_allclose(
        render(s, cam),
        march(vol, preset("grey"), cam, shading="phong", ambient=ao, step=0.8,
              background=(0.1, 0.2, 0.3)), atol=1e-12)
    assert s.plan() == {"ambient": "volume", "shading": "phong", "composition": "standard"}


def test_effects_that_are_off_are_not_traced(monkeypatch):
    calls = []
    real = scene_module.AMBIENT["volume"]
    monkeypatch.setitem(scene_module.AMBIENT, "volume",
                        lambda sc: calls.append("ambient") or real(sc))
    cam = Camera.orbit(image_shape=(3, 3))
    off = Scene(volume=_volume(), transfer=preset("grey"))
    jaxpr_off = str(jax.make_jaxpr(lambda s: render(s, cam))(off))
    assert calls == []
    assert "conv_general_dilated" not in jaxpr_off  # no gradient volume without Phong
    on = Scene(volume=_volume(), transfer=preset("grey"), shading="phong", ambient="volume",
               ambient_volume=jnp.ones((6, 6, 6)))
    jaxpr_on = str(jax.make_jaxpr(lambda s: render(s, cam))(on))
    assert calls == ["ambient"]
    assert "conv_general_dilated" in jaxpr_on


def test_scene_is_a_pytree_for_jit_vmap_grad():
    cam = Camera.orbit(azimuth=15.0, image_shape=(4, 4))
    s = Scene(volume=_volume(), transfer=preset("grey"), shading="phong")
    f = eqx.filter_jit(render)
    np.testing.assert_allclose(f(s, cam), render(s, cam), atol=1e-12)
    scenes = jax.vmap(lambda k: eqx.tree_at(lambda t: t.phong.diffuse, s, k))(jnp.array([0.2, 0.9]))
    imgs = eqx.filter_vmap(lambda sc: render(sc, cam))(scenes)
    np.testing.assert_allclose(imgs[1], render(eqx.tree_at(lambda t: t.phong.diffuse, s, 0.9), cam),
                               atol=1e-12)
    grads = eqx.filter_jit(eqx.filter_grad(lambda sc: jnp.sum(render(sc, cam))))(s)
    assert float(jnp.abs(grads.phong.diffuse)) > 0
    assert all(np.isfinite(x) for x in jax.tree.leaves(grads.phong))
    assert np.all(np.isfinite(grads.transfer.opacities))
    assert np.all(np.isfinite(grads.volume))


def test_scene_errors():
    tf = preset("grey")
    with pytest.raises(ValueError, match="unknown ambient 'ssao'"):
        Scene(volume=_volume(), transfer=tf, ambient="ssao")
    with pytest.raises(ValueError, match="unknown shading"):
        Scene(volume=_volume(), transfer=tf, shading="toon")
    with pytest.raises(ValueError, match="unknown composition"):
        Scene(volume=_volume(), transfer=tf, composition="mip")
    with pytest.raises(ValueError, match="ambient_volume"):
        Scene(volume=_volume(), transfer=tf, ambient="volume")
    with pytest.raises(ValueError, match="3 dimensions"):
        Scene(volume=jnp.zeros((3, 3)), transfer=tf)
    with pytest.raises(TypeError, match="TransferFunction"):
        Scene(volume=_volume(), transfer="grey")
    with pytest.raises(ValueError, match="spacing"):
        Scene(volume=_volume(), transfer=tf, spacing=(1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="step"):
        Scene(volume=_volume(), transfer=tf, step=-1.0)
    with pytest.raises(ValueError, match="background"):
        Scene(volume=_volume(), transfer=tf, background=(0.0, 0.0))
    assert isinstance(Scene(volume=_volume(), transfer=tf).phong, Phong)
