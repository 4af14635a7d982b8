import dataclasses
import re
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_composition as ref
from helpers import one_medium_written_twice, strongly_typed, tol

import volshade as vs
import volshade.scene as scene_module
from volshade.camera import Camera
from volshade.importance import Focus, Importance, focus_weights
from volshade.lao import LocalAmbientOcclusion, lao
from volshade.obscurance import ObscuranceParams, obscurance
from volshade.render import march
from volshade.saliency import SaliencyModulation, opacity_factor, saliency
from volshade.scene import Scene, render
from volshade.shading import Phong
from volshade.transfer import preset


def _volume():
    return jnp.asarray(np.random.default_rng(0).random((6, 6, 6)))


def test_render_equals_march_with_the_scene_options():
    cam = strongly_typed(Camera.orbit(azimuth=40.0, image_shape=(4, 4)))
    vol = _volume()
    ao = jnp.full((6, 6, 6), 0.7)
    s = Scene(volume=vol, transfer=preset("grey"), shading="phong", ambient="volume",
              ambient_volume=ao, background=(0.1, 0.2, 0.3), step=0.8)
    np.testing.assert_allclose(
        render(s, cam),
        march(vol, preset("grey"), cam, shading="phong", phong=strongly_typed(Phong()), ambient=ao,
              step=0.8, background=(0.1, 0.2, 0.3)), atol=1e-12)
    assert s.plan() == {"ambient": "volume", "modulation": "none", "shading": "phong",
                        "composition": "standard"}


def _count_gradients(monkeypatch, calls):
    """Append "gradient" to ``calls`` whenever a render asks for the gradient volume."""
    render_module = sys.modules["volshade.render"]
    real = render_module._shared_volumes

    def counting(*args, **kwargs):
        if kwargs["gradient"]:
            calls.append("gradient")
        return real(*args, **kwargs)

    monkeypatch.setattr(render_module, "_shared_volumes", counting)


def test_effects_that_are_off_are_not_traced(monkeypatch):
    calls = []
    real = scene_module.AMBIENT["volume"]
    monkeypatch.setitem(scene_module.AMBIENT, "volume",
                        lambda sc: calls.append("ambient") or real(sc))
    _count_gradients(monkeypatch, calls)
    cam = Camera.orbit(image_shape=(3, 3))
    off = Scene(volume=_volume(), transfer=preset("grey"))
    jax.make_jaxpr(lambda s: render(s, cam))(off)
    assert calls == []  # no ambient volume, no gradient volume without Phong
    on = Scene(volume=_volume(), transfer=preset("grey"), shading="phong", ambient="volume",
               ambient_volume=jnp.ones((6, 6, 6)))
    jax.make_jaxpr(lambda s: render(s, cam))(on)
    assert sorted(calls) == ["ambient", "gradient"]


@pytest.mark.slow
def test_several_views_share_what_does_not_depend_on_the_view(monkeypatch):
    calls = []
    real_lao = scene_module.AMBIENT["lao"]
    monkeypatch.setitem(scene_module.AMBIENT, "lao", lambda sc: calls.append("lao") or real_lao(sc))
    _count_gradients(monkeypatch, calls)
    scene = Scene(volume=jnp.asarray(np.random.default_rng(1).random((8, 8, 8))),
                  transfer=preset("grey"), shading="phong", ambient="lao",
                  lao=LocalAmbientOcclusion(2.5, directions=6, samples=3),
                  composition="importance", importance=Importance(intensity=2.0),
                  focus=Focus(center=(0.4, 0.6), radius=0.3))
    for name in ("march_view", "march_views"):
        real = getattr(scene_module, name)
        monkeypatch.setattr(scene_module, name,
                            lambda *a, real=real: calls.append("view") or real(*a))
    alike = [Camera.orbit(azimuth=a, elevation=15.0, image_shape=(5, 4)) for a in (0, 70, 140)]
    mixed = (alike[0], Camera.orbit(azimuth=250.0, image_shape=(3, 6),
                                    projection="orthographic"))
    for cameras, views in ((alike, 1), (mixed, 2)):  # one mapped march; one each
        calls.clear()
        images = eqx.filter_jit(render)(scene, cameras)
        # the shared volumes once, not once per camera
        assert sorted(calls) == ["gradient", "lao", *["view"] * views]
        assert isinstance(images, list) and len(images) == len(cameras)
        # against eager renders (their march compiled alone: half the time of a jitted
        # render per camera structure)
        for image, cam in zip(images, cameras, strict=True):
            np.testing.assert_allclose(image, render(scene, cam), atol=1e-12)

    plain = Scene(volume=scene.volume, transfer=scene.transfer, shading="phong", ambient="lao",
                  lao=scene.lao)  # standard compositing: a cheaper gradient to compile

    def loss(radius, cameras):
        s = eqx.tree_at(lambda s: s.lao.radius, plain, radius)
        images = render(s, cameras) if isinstance(cameras, list) else [render(s, cameras)]
        return sum(jnp.sum(jnp.arange(i.size).reshape(i.shape) * i) for i in images)

    grad = eqx.filter_jit(jax.grad(loss))
    radius = scene.lao.radius
    np.testing.assert_allclose(grad(radius, alike), sum(grad(radius, c) for c in alike),
                               rtol=1e-10)
    for bad in ([], (), [alike[0], "front"], iter(alike), None):
        with pytest.raises(TypeError, match="`camera` must be a volshade.Camera|every entry"):
            render(scene, bad)
    blind = eqx.tree_at(lambda c: c.target, alike[1], alike[1].eye)  # eye == target
    with pytest.raises(ValueError, match=r"`camera\[1\]`: .*`eye` and `target` must differ"):
        render(scene, [alike[0], blind])


def test_an_eager_turntable_traces_its_march_once(monkeypatch):
    # found by a review: eagerly, lax.map over a closure made by each render call traced
    # and compiled the march again on every call (4.4-4.7 s a call for three 16^2 views)
    traced = []
    render_module = sys.modules["volshade.render"]
    real = render_module._march_view
    monkeypatch.setattr(render_module, "_march_view",
                        lambda *a: traced.append(1) or real(*a))
    scene = Scene(volume=_volume(), transfer=preset("grey"), shading="phong")
    counts = []
    for turn in (0.0, 20.0, 40.0):
        cameras = [Camera.orbit(azimuth=a + turn, image_shape=(4, 5)) for a in (0, 90, 180)]
        images = render(scene, cameras)
        counts.append(len(traced))
    assert counts[0] <= 1 and counts == counts[:1] * 3, counts
    for image, cam in zip(images, cameras, strict=True):
        np.testing.assert_allclose(image, render(scene, cam), atol=1e-12)


def test_leaves_set_to_python_floats_render():
    # eqx.tree_at may put a Python float where a constructor would put an array
    scene = Scene(volume=_volume(), transfer=preset("grey"), shading="phong",
                  composition="importance", importance=Importance(silhouette=1.0))
    cam = Camera.orbit(image_shape=(4, 4))
    want = render(scene, cam)
    floats = eqx.tree_at(lambda s: (s.phong.shininess, s.importance.darkening), scene,
                         (float(scene.phong.shininess), float(scene.importance.darkening)))
    wide = eqx.tree_at(lambda c: c.fov, cam, float(cam.fov))
    for image in render(floats, [wide, cam]):
        np.testing.assert_allclose(image, want, atol=1e-12)


@pytest.mark.slow
def test_scene_is_a_pytree_for_jit_vmap_grad():
    cam = Camera.orbit(azimuth=15.0, image_shape=(4, 4))
    s = Scene(volume=_volume(), transfer=preset("grey"), shading="phong")
    f = eqx.filter_jit(render)
    np.testing.assert_allclose(f(s, cam), render(s, cam), atol=1e-12)
    diffuse = jnp.array([0.2, 0.9])
    scenes = jax.vmap(lambda k: eqx.tree_at(lambda t: t.phong.diffuse, s, k))(diffuse)
    imgs = eqx.filter_jit(eqx.filter_vmap(lambda sc: render(sc, cam)))(scenes)
    assert float(jnp.max(jnp.abs(imgs[0] - imgs[1]))) > 0.1
    for image, k in zip(imgs, diffuse, strict=True):
        np.testing.assert_allclose(image, render(eqx.tree_at(lambda t: t.phong.diffuse, s, k),
                                                 cam), atol=1e-12)
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
    with pytest.raises(ValueError, match="`ambient_volume` is used only with ambient='volume'"):
        Scene(volume=_volume(), transfer=tf, ambient_volume=jnp.ones((6, 6, 6)))  # ambient none
    with pytest.raises(ValueError, match="`feature_ao` is used only with ambient='feature_ao'"):
        Scene(volume=_volume(), transfer=tf, ambient="lao",
              feature_ao=vs.FeatureAmbientOcclusion([vs.IntervalFeature(0.0, 0.5)]))
    with pytest.raises(ValueError, match="3 dimensions"):
        Scene(volume=jnp.zeros((3, 3)), transfer=tf)
    with pytest.raises(TypeError, match="TransferFunction"):
        Scene(volume=_volume(), transfer="grey")
    with pytest.raises(ValueError, match="spacing"):
        Scene(volume=_volume(), transfer=tf, spacing=(1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="step"):
        Scene(volume=_volume(), transfer=tf, step=-1.0)
    with pytest.raises(ValueError, match="unknown modulation"):
        Scene(volume=_volume(), transfer=tf, modulation="edges")
    with pytest.raises(ValueError, match="focus"):
        Scene(volume=_volume(), transfer=tf, focus=Focus())
    with pytest.raises(ValueError, match="background"):
        Scene(volume=_volume(), transfer=tf, background=(0.0, 0.0))
    with pytest.raises(ValueError, match=r"`ambient_volume` must have the shape of `volume`, "
                                         r"\(6, 6, 6\) .*got \(6, 6, 5\)"):
        Scene(volume=_volume(), transfer=tf, ambient="volume", ambient_volume=jnp.ones((6, 6, 5)))
    # leaves that the scene's other settings leave unread: set, they would change nothing
    with pytest.raises(ValueError, match=r"`importance.global_weight` is not read by this "
                                         r"scene \(the focus's `inside` and `outside`"):
        Scene(volume=_volume(), transfer=tf, composition="importance", focus=Focus(),
              importance=Importance(global_weight=0.5))
    with pytest.raises(ValueError, match=r"`phong.ambient` is not read by this scene "
                                         r"\(shading='obscurance'.*default, 0.35"):
        Scene(volume=_volume(), transfer=tf, ambient="obscurance", shading="obscurance",
              phong=Phong(ambient=0.9))
    # ... and not refused where they hold their defaults, also when built under jit
    for effects in ({"ambient": "obscurance", "shading": "obscurance"},
                    {"composition": "importance", "focus": Focus()}):
        scene = Scene(volume=_volume(), transfer=tf, **effects)
        copy = eqx.filter_jit(lambda s: dataclasses.replace(s, step=0.5))(scene)
        assert copy.step == 0.5
    # effect parameters of the wrong kind, named here rather than failing inside the render
    for name, value, kind in (("lao", 6.0, "LocalAmbientOcclusion"),
                              ("importance", 2.0, "Importance"),
                              ("obscurance", 16.0, "ObscuranceParams"),
                              ("phong", {"ambient": 0.2}, "Phong"),
                              ("saliency", 0.2, "SaliencyModulation"),
                              ("focus", (0.5, 0.5), "Focus")):
        with pytest.raises(TypeError, match=f"`{name}` must be a volshade.{kind}, got"):
            Scene(volume=_volume(), transfer=tf, composition="importance", **{name: value})
    with pytest.raises(TypeError, match="`scene` must be a volshade.Scene, got ArrayImpl; wrap"):
        render(_volume(), Camera.orbit(image_shape=(4, 4)))



def test_effect_parameters_default_when_used_and_are_refused_when_not():
    tf = preset("grey")
    plain = Scene(volume=_volume(), transfer=tf)
    assert (plain.lao, plain.obscurance, plain.saliency, plain.phong, plain.importance) == (
        None,) * 5
    used = Scene(volume=_volume(), transfer=tf, ambient="lao", shading="obscurance",
                 composition="importance")
    # the defaults, as leaves a fit can name
    assert eqx.tree_equal(used.lao, LocalAmbientOcclusion())
    assert eqx.tree_equal(used.phong, Phong())
    assert eqx.tree_equal(used.importance, Importance())
    assert isinstance(Scene(volume=_volume(), transfer=tf, ambient="obscurance").obscurance,
                      ObscuranceParams)
    assert isinstance(Scene(volume=_volume(), transfer=tf, modulation="saliency").saliency,
                      SaliencyModulation)
    # given, but the scene never reads them: a render would look as if they did nothing
    for name, value, wanted in (
            ("lao", LocalAmbientOcclusion(4.0), "ambient='lao'"),
            ("obscurance", ObscuranceParams(d_max=8.0), "ambient='obscurance'"),
            ("saliency", SaliencyModulation(), "modulation='saliency'"),
            ("phong", Phong(ambient=0.2), "shading='phong' or shading='obscurance'"),
            ("importance", Importance(intensity=2.0), "composition='importance'")):
        with pytest.raises(ValueError, match=f"`{name}` is used only with {wanted}, got "
                                             f"[a-z]+='(none|standard)'; set .* or leave "
                                             f"`{name}` out"):
            Scene(volume=_volume(), transfer=tf, **{name: value})
    # given explicitly and used: kept, not replaced by the defaults
    lit = Scene(volume=_volume(), transfer=tf, shading="phong", phong=Phong(ambient=0.2))
    assert float(lit.phong.ambient) == 0.2
    # switching an effect on through a copy fills in its defaults, and switching it off
    # drops them; parameters the user gave (or changed) are refused instead
    on = dataclasses.replace(plain, ambient="lao")
    assert isinstance(on.lao, LocalAmbientOcclusion)
    assert dataclasses.replace(on, ambient="none").lao is None
    assert dataclasses.replace(used, ambient="obscurance").lao is None
    for given in (dataclasses.replace(lit, shading="phong", ambient="lao"),
                  dataclasses.replace(used, phong=Phong(specular=0.2)),
                  eqx.tree_at(lambda s: s.phong.ambient, used, 0.3)):
        with pytest.raises(ValueError, match=r"`phong` is used only .* pass `phong=None` too"):
            dataclasses.replace(given, shading="none")
    assert dataclasses.replace(lit, shading="none", phong=None).phong is None


@pytest.mark.slow
def test_lao_obscurance_saliency_and_importance_effects_match_their_kernels():
    vol = _volume()
    tf = preset("grey")
    cam = strongly_typed(Camera.orbit(azimuth=25.0, elevation=15.0, image_shape=(4, 4)))
    params = LocalAmbientOcclusion(3.0, offset=0.5, directions=6, samples=4)
    s = Scene(volume=vol, transfer=tf, ambient="lao", lao=params, shading="phong")
    ao = lao(tf.opacity(vol), directions=params.directions, radius=3.0, offset=0.5, samples=4)
    phong = strongly_typed(Phong())
    np.testing.assert_allclose(render(s, cam), march(vol, tf, cam, shading="phong", phong=phong,
                                                     ambient=ao), atol=1e-12)
    obs_params = ObscuranceParams(d_max=4.0, level=0, color_bleeding=True)
    s = Scene(volume=vol, transfer=tf, ambient="obscurance", obscurance=obs_params,
              shading="obscurance")
    from volshade.directions import icosphere

    obs = obscurance(tf.opacity(vol), directions=icosphere(0), d_max=4.0, colors=tf.color(vol))
    np.testing.assert_allclose(render(s, cam),
                               march(vol, tf, cam, shading="obscurance", phong=phong,
                                     ambient=obs), atol=1e-12)
    s = Scene(volume=vol, transfer=tf, modulation="saliency",
              saliency=SaliencyModulation(d_max=4.0, level=0, size=3))
    factor = opacity_factor(saliency(obscurance(tf.opacity(vol), directions=icosphere(0),
                                                d_max=4.0), size=3), threshold=0.2)
    np.testing.assert_allclose(render(s, cam), march(vol, tf, cam, opacity_scale=factor),
                               atol=1e-12)
    imp = strongly_typed(Importance(intensity=3.0, silhouette=1.0))
    focus = Focus(center=(0.5, 0.5), radius=0.3, kind="circular")
    s = Scene(volume=vol, transfer=tf, composition="importance", importance=imp, focus=focus)
    np.testing.assert_allclose(
        render(s, cam), march(vol, tf, cam, composition="importance", importance=imp,
                              focus=focus.weights((4, 4))), atol=1e-12)
    assert not np.allclose(render(s, cam), march(vol, tf, cam), atol=1e-3)


@pytest.mark.parametrize("shading", ["phong", "obscurance"])
def test_lighting_does_not_depend_on_which_side_the_classification_takes(shading):
    # one opaque ball, written as bright on dark and as dark on bright with the mirrored
    # transfer function: the gradients point opposite ways, the picture is the same (a
    # one-sided N.L left the second ball black under shading="obscurance")
    x = jnp.arange(12) - 5.5
    r = jnp.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2)
    ball = jnp.clip((4 - r) / 2 + 0.5, 0, 1)
    bright = vs.TransferFunction.from_points([(0, 1, 1, 1, 0), (0.4, 1, 1, 1, 0),
                                              (0.6, 1, 1, 1, 1), (1, 1, 1, 1, 1)])
    dark = vs.TransferFunction.from_points([(0, 1, 1, 1, 1), (0.4, 1, 1, 1, 1),
                                            (0.6, 1, 1, 1, 0), (1, 1, 1, 1, 0)])
    cam = Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(8, 8))
    images = [render(Scene(volume=v, transfer=tf, shading=shading, ambient="volume",
                           ambient_volume=jnp.ones_like(ball)), cam)
              for v, tf in ((ball, bright), (1 - ball, dark))]
    assert float(images[0][4, 4, :3].min()) > 0.5
    np.testing.assert_allclose(images[1], images[0], atol=1e-12)


_PROFILE = np.random.default_rng(3).uniform(0.1, 0.95, 12)  # intensities along h
_TABLE = np.array([[0.0, 0.1, 0.1, 0.1, 0.0], [0.3, 0.9, 0.2, 0.1, 0.35],
                   [1.0, 0.1, 0.3, 0.9, 0.25]])  # rows (x, r, g, b, opacity per 1 mm)


def _reference_importance_ray(weights, global_weight, background, *, sh, step):
    # one ray along -h through a volume that varies along h only: samples at the midpoints
    # of `step` mm segments from the +h face (the last one shorter), intensity linear
    # between voxel centres (held past the outer centres), opacity corrected to the
    # segment, I_s = W_g (W_int x + W_tau ln(1 + tau) + W_unocc (20 - sum tau d)) with the
    # optical depth of the samples in front, then eq. 8 and the background layer
    # (reference_composition)
    w_int, w_ext, w_unocc, w_bg = weights
    n = len(_PROFILE)
    length = n * sh
    colors, alphas, importances, depth, k = [], [], [], 0.0, 0
    while k * step < length - 1e-9:
        seg = min(step, length - k * step)
        index = (length - (k * step + seg / 2)) / sh - 0.5
        x = np.interp(index, np.arange(n), _PROFILE)
        alpha0 = np.interp(x, _TABLE[:, 0], _TABLE[:, 4])
        color = np.array([np.interp(x, _TABLE[:, 0], _TABLE[:, c]) for c in (1, 2, 3)])
        tau = -np.log1p(-alpha0)
        alpha = 1 - (1 - alpha0) ** seg
        importances.append(global_weight * (w_int * x + w_ext * np.log1p(tau)
                                            + w_unocc * (20 - depth)))
        colors.append(alpha * color)
        alphas.append(alpha)
        depth += tau * seg
        k += 1
    return (ref.importance(colors, alphas, importances, background, global_weight * w_bg),
            ref.standard(colors, alphas, background))


@pytest.mark.parametrize("case", ["intensity", "extinction", "unocclusion", "focus"])
def test_importance_render_matches_a_per_ray_reference(case):
    # importance-aware rendering of parallel rays along -h through a (4, 12, 4) volume with
    # 0.75 mm voxels along h (9 mm paths), one importance measure at a time, equals an
    # independent per-ray transcription of sec. IV and eq. 8; the focus case also checks
    # the per-ray global weights of a Focus (w = o + (n - o) exp(-r^2 / 2R^2), pixels)
    weights = {"intensity": (6.0, 0.0, 0.0, 0.0), "extinction": (0.0, 3.0, 0.0, 0.0),
               "unocclusion": (0.0, 0.0, 0.8, 17.0), "focus": (6.0, 0.0, 0.0, 2.0)}[case]
    imp = Importance(intensity=weights[0], extinction=weights[1], unocclusion=weights[2],
                     background=weights[3])
    image_shape, background = (4, 6), np.array([0.2, 0.3, 0.4])
    focus, g = None, np.ones(image_shape)
    if case == "focus":
        focus = Focus(center=(0.3, 0.6), radius=0.3, kind="gaussian", inside=1.5, outside=0.2)
        rows, cols = np.meshgrid(np.arange(4.0), np.arange(6.0), indexing="ij")
        r2 = (rows - (0.3 * 4 - 0.5)) ** 2 + (cols - (0.6 * 6 - 0.5)) ** 2
        g = 0.2 + 1.3 * np.exp(-r2 / (2 * (0.3 * 4) ** 2))
    tf = vs.TransferFunction.from_points(_TABLE)
    vol = jnp.broadcast_to(jnp.asarray(_PROFILE)[None, :, None], (4, 12, 4))
    cam = Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=image_shape,
                       projection="orthographic", width=0.25)  # every ray crosses the box
    scene = Scene(volume=vol, transfer=tf, spacing=(1.0, 0.75, 1.0), step=0.7,
                  composition="importance", importance=imp, focus=focus, background=background)
    image = np.asarray(render(scene, cam))
    standard = np.asarray(render(Scene(volume=vol, transfer=tf, spacing=(1.0, 0.75, 1.0),
                                       step=0.7, background=background), cam))
    for i, j in np.ndindex(*image_shape):
        expected, std = _reference_importance_ray(weights, g[i, j], background, sh=0.75,
                                                  step=0.7)
        np.testing.assert_allclose(image[i, j], expected, atol=1e-10)
        np.testing.assert_allclose(standard[i, j], std, atol=1e-10)
    assert np.max(np.abs(image - standard)) > 5e-3  # the measure changes the image


def test_focus_weights_on_a_non_square_image():
    # (row, column) order on an 8 x 16 image: Focus fractions are of (H, W), the radius a
    # fraction of H; the weights follow o + (n - o) f(r) with r in pixels from the centre
    h, w = 8, 16
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    center = (2.5 / h, 11.5 / w)  # pixel (2, 11)
    for kind in ("gaussian", "circular", "screen_door"):
        weights = np.asarray(Focus(center=center, radius=0.25, kind=kind, inside=2.0,
                                   outside=0.5).weights((h, w)))
        assert weights.shape == (h, w)
        r2 = (rows - 2.0) ** 2 + (cols - 11.0) ** 2
        gauss = np.exp(-r2 / (2 * 2.0 ** 2))  # R = 0.25 * 8 pixels
        assert weights[2, 11] == 2.0
        if kind == "gaussian":
            assert np.unravel_index(np.argmax(weights), weights.shape) == (2, 11)
            np.testing.assert_allclose(weights, 0.5 + 1.5 * gauss, rtol=1e-12)
        elif kind == "circular":
            np.testing.assert_array_equal(weights, np.where(r2 <= 4.0, 2.0, 0.5))
        else:  # a dither of the Gaussian: certain near the centre, absent far from it
            assert set(np.unique(weights)) <= {0.5, 2.0}
            assert np.all(weights[gauss > 15.5 / 16] == 2.0)
            assert np.all(weights[gauss < 0.5 / 16] == 0.5)
            assert 0.1 < np.mean(weights[(gauss > 0.2) & (gauss < 0.8)] == 2.0) < 0.9
    direct = np.asarray(focus_weights((h, w), center=(6.0, 3.0), radius=3.0, kind="gaussian",
                                      inside=1.0, outside=0.0))
    np.testing.assert_allclose(direct, np.exp(-((rows - 6.0) ** 2 + (cols - 3.0) ** 2) / 18.0),
                               rtol=1e-12)


def test_importance_with_zero_weights_equals_standard_render():
    cam = Camera.orbit(azimuth=25.0, elevation=15.0, image_shape=(5, 5))
    vol = _volume()
    std = render(Scene(volume=vol, transfer=preset("grey"), shading="phong"), cam)
    imp = render(Scene(volume=vol, transfer=preset("grey"), shading="phong",
                       composition="importance"), cam)
    assert imp.dtype == jnp.float64
    np.testing.assert_allclose(imp, std, rtol=0, atol=tol(jnp.float64))  # measured: 2.5e-16


@pytest.mark.slow
def test_fitting_leaves_get_gradients_without_recompiling():
    vol = _volume()
    cam = Camera.orbit(azimuth=25.0, elevation=15.0, image_shape=(3, 3))
    s = Scene(volume=vol, transfer=preset("grey"), ambient="lao", shading="phong",
              lao=LocalAmbientOcclusion(2.5, offset=0.5, directions=6, samples=4),
              composition="importance", importance=Importance(intensity=1.0))
    # the fitted leaves apart from the rest of the scene, as a fit with equinox takes them
    # (a gradient for every leaf, the volume's through LAO and the importance among
    # them, took 1.7 times as long to compile)
    def fitted(t):
        return t.lao.radius, t.importance.intensity

    spec = eqx.tree_at(fitted, jax.tree.map(lambda _: False, s), (True, True))
    loss = eqx.filter_jit(eqx.filter_grad(
        lambda params, rest: jnp.sum(render(eqx.combine(params, rest), cam))))
    g = loss(*eqx.partition(s, spec))
    assert np.isfinite(g.lao.radius) and float(g.lao.radius) != 0
    assert np.isfinite(g.importance.intensity) and float(g.importance.intensity) != 0
    s2 = eqx.tree_at(fitted, s, (s.lao.radius + 0.5, 2 * s.importance.intensity))
    loss(*eqx.partition(s2, spec))
    assert loss._cached._cache_size() == 1


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_non_finite_parameters_are_refused_by_name(jit):
    vol = vs.data.phantom("shells", shape=12)
    tf = vs.transfer.preset("shells")
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(6, 6))
    render = eqx.filter_jit(vs.render) if jit else vs.render
    with pytest.raises(ValueError, match="`diffuse` must be a finite number"):
        vs.Phong(diffuse=jnp.nan)  # known values: refused at construction
    with pytest.raises(ValueError, match="Camera.orbit: `azimuth` must be finite, got nan"):
        vs.Camera.orbit(azimuth=float("nan"))
    # as a fit could set it: an array of the leaf's dtype (a weakly typed one, as
    # jnp.full(3, jnp.nan) makes, compiled a render of its own under jit)
    nan_eye = eqx.tree_at(lambda c: c.eye, cam, jnp.full_like(cam.eye, jnp.nan))
    # one scene with every parameter below: under jit each scene structure compiled a
    # render of its own
    lit_scene = vs.Scene(volume=vol, transfer=tf, shading="phong", composition="importance",
                         importance=Importance(intensity=1.0))
    cases = [
        # a NaN that skipped construction (a fit, eqx.tree_at): refused at render
        (eqx.tree_at(lambda s: s.phong.diffuse, lit_scene, jnp.asarray(jnp.nan)),
         cam, "scene.phong.diffuse"),
        (eqx.tree_at(lambda s: s.background, lit_scene, jnp.asarray([jnp.inf, 0.0, 0.0])),
         cam, "scene.background"),
        (lit_scene, nan_eye, "camera.eye"),
        # -inf is allowed only where Importance declares it (the background), never +inf
        (eqx.tree_at(lambda s: s.importance.background, lit_scene,
                     jnp.asarray(jnp.inf)), cam, "scene.importance.background"),
        (eqx.tree_at(lambda s: s.importance.intensity, lit_scene,
                     jnp.asarray(-jnp.inf)), cam, "scene.importance.intensity"),
    ]
    cases.append((vs.Scene(volume=vol, transfer=tf),  # one of several views
                  [cam, nan_eye], "camera[1].eye"))
    nan_float = eqx.tree_at(lambda s: s.phong.diffuse, cases[0][0], float("nan"))
    cases.append((nan_float, cam, "scene.phong.diffuse"))  # a Python float leaf
    for scene, camera, name in cases:
        with pytest.raises(Exception, match=re.escape(f"`{name}` contains NaN or inf")):
            jax.block_until_ready(render(scene, camera))
    # the volume is the render's to refuse, before an effect classifies it (few
    # directions and samples: under jit the defaults' 42 directions took seconds to
    # compile, and any effect classifies the volume alike)
    holed = vol.at[3, 4, 5].set(jnp.nan)
    for scene in (eqx.tree_at(lambda s: s.volume, lit_scene, holed),
                  vs.Scene(volume=holed, transfer=tf, ambient="lao",
                           lao=LocalAmbientOcclusion(3.0, directions=6, samples=2)),
                  vs.Scene(volume=holed, transfer=tf, ambient="obscurance",
                           obscurance=ObscuranceParams(d_max=4.0, level=0))):
        with pytest.raises(Exception, match=re.escape("volshade.render: `volume` contains NaN")):
            jax.block_until_ready(render(scene, cam))


def test_no_background_importance_is_allowed_with_a_focus():
    # -inf background importance is "no background" (volshade.composite); outside the
    # focus (weight 0) importance is off, which must give 0, not 0 * -inf = NaN
    vol = vs.data.phantom("shells", shape=12)
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))
    scene = vs.Scene(volume=vol, transfer=vs.transfer.preset("shells"), composition="importance",
                     importance=Importance(intensity=2.0, background=-jnp.inf),
                     focus=Focus(radius=0.2, kind="circular"))
    image = render(scene, cam)
    assert np.all(np.isfinite(np.asarray(image)))
    far = eqx.tree_at(lambda s: s.importance.background, scene, jnp.asarray(-1e30))
    np.testing.assert_allclose(np.asarray(image), np.asarray(render(far, cam)), atol=1e-12)


def test_corrected_lao_sees_the_medium_not_how_the_transfer_function_is_written():
    # one medium, written per 1 mm and per 0.5 mm: with the opacity correction LAO reads
    # the opacity of a one-voxel step, so its ambient term is the same for both
    from volshade.scene import _lao_ambient

    per_mm, per_half_mm = one_medium_written_twice()
    vol = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (10, 10, 10)))
    params = vs.LocalAmbientOcclusion(3.0, offset=0.5, directions=6, samples=4,
                                      opacity_correction=True)
    aos = [_lao_ambient(vs.Scene(volume=vol, transfer=tf, ambient="lao", lao=params,
                                 spacing=(2.0, 2.0, 2.0))) for tf in (per_mm, per_half_mm)]
    np.testing.assert_allclose(np.asarray(aos[0]), np.asarray(aos[1]), atol=1e-12)
    # 2 mm voxels: the one-voxel opacity is 1 - 0.7^2
    direct = params(jnp.full((10, 10, 10), 1 - 0.7 ** 2))
    np.testing.assert_allclose(np.asarray(aos[0]), np.asarray(direct), atol=1e-12)


@pytest.mark.parametrize("effects", [
    {"ambient": "lao", "lao": LocalAmbientOcclusion(3.0, directions=6, samples=4)},
    {"ambient": "obscurance", "obscurance": ObscuranceParams(d_max=4.0, level=0,
                                                             density="opacity")},
    {"modulation": "saliency"},
])
def test_an_integer_volume_renders_as_its_float_values(effects):
    # the effects classify the scene's volume themselves (the march converts it apart)
    tf = vs.TransferFunction.from_points([(0.0, 1, 1, 1, 0.0), (1.0, 1, 1, 1, 0.0),
                                          (2.0, 1, 1, 1, 0.9)])
    vol = np.zeros((8, 8, 8), np.int32)
    vol[2:6, 2:6, 2:6] = 2
    cam = Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))
    images = [render(Scene(volume=v, transfer=tf, shading="phong", **effects), cam)
              for v in (vol, vol.astype(float))]
    np.testing.assert_allclose(images[0], images[1], atol=1e-12)
    assert float(jnp.max(images[1][..., 3])) > 0.5
