"""Tests of volshade.importance: importance measures and focus-plus-context weights."""

import dataclasses
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd
from jax.flatten_util import ravel_pytree

from volshade.composition import composite
from volshade.gradient import regression_gradient
from volshade.importance import (
    Focus,
    Importance,
    focus_weights,
    lighting_importance,
    normalized_gradient_magnitude,
    sample_importance,
    silhouetteness,
)

WEIGHTS = ("intensity", "extinction", "gradient", "silhouette", "unocclusion", "lighting")


# --------------------------------------------------------------------------- reference


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def _unit(x):
    """``x / |x|``; the zero vector stays 0 (documented: it gives ``|V . N| = 0``)."""
    norm = np.linalg.norm(x)
    return x / norm if norm > 0 else np.zeros_like(x)


def reference_measures(p, intensity, tau, m_g, normal, view, light, depth):
    """Sec. IV-A per sample, in plain float64 numpy loops: ``{weight name: measure}``."""
    q = {f.name: float(getattr(p, f.name)) for f in dataclasses.fields(p)}
    rows = []
    for x, t, g, n, v, li, d in zip(intensity, tau, m_g, normal, view, light, depth, strict=True):
        n, v, li = _unit(n), _unit(v), _unit(li)
        sil = g ** q["silhouette_exponent"] * _smoothstep(
            q["silhouette_start"], q["silhouette_end"], 1 - abs(v @ n))
        if n @ v < 0:
            n = -n
        h = _unit(li + v)
        light_imp = (3 - max(n @ h, 0) ** q["specular_exponent"]
                     - max(n @ li, 0) ** q["diffuse_exponent"] - (1 - g) ** q["gradient_exponent"])
        rows.append([x, np.log(1 + t), g, sil, q["unocclusion_offset"] - d, light_imp])
    return dict(zip(WEIGHTS, np.array(rows, float).T, strict=True))


def reference_importance(p, *features):
    """Sec. IV-A/B per sample: the importance and the silhouette colour scale."""
    q = {f.name: float(getattr(p, f.name)) for f in dataclasses.fields(p)}
    measures = reference_measures(p, *features)
    total = sum(q[w] * measures[w] for w in WEIGHTS)
    strength = min(max(q["global_weight"], 0.0), 1.0)
    scale = np.exp(-q["darkening"] * measures["silhouette"] * strength) if q["silhouette"] \
        else np.ones_like(total)
    return q["global_weight"] * total, scale


def random_features(n, seed=0, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    feats = {
        "intensity": rng.uniform(0, 1, n),
        "extinction": rng.uniform(0, 5, n),
        "gradient_magnitude": rng.uniform(0.05, 0.95, n),
        "normal": rng.normal(size=(n, 3)),
        "view": rng.normal(size=(n, 3)),
        "light": rng.normal(size=(n, 3)),
        "optical_depth": rng.uniform(0, 10, n),
    }
    return {k: jnp.asarray(v, dtype) for k, v in feats.items()}


PARAMS = Importance(global_weight=1.5, intensity=2.0, extinction=0.7, gradient=1.3,
                    silhouette=2.5, unocclusion=0.2, lighting=0.9)


def test_matches_reference():
    f = random_features(50, seed=1)
    imp, scale = sample_importance(PARAMS, **f)
    expected, exp_scale = reference_importance(
        PARAMS, *(np.asarray(f[k]) for k in ("intensity", "extinction", "gradient_magnitude",
                                             "normal", "view", "light", "optical_depth")))
    np.testing.assert_allclose(imp, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(scale, exp_scale, rtol=1e-12)


def test_the_light_defaults_to_the_view_direction():
    # a headlight: leaving `light` out is passing the view, and differs from a light
    # along the normal (what the lighting measure would get were the default the normal)
    f = random_features(50, seed=6)
    without = dict(f)
    del without["light"]
    imp, scale = sample_importance(PARAMS, **without)
    headlight = sample_importance(PARAMS, **{**without, "light": f["view"]})
    np.testing.assert_array_equal(imp, headlight[0])
    np.testing.assert_array_equal(scale, headlight[1])
    along_normal = sample_importance(PARAMS, **{**without, "light": f["normal"]})[0]
    assert np.max(np.abs(np.asarray(imp - along_normal))) > 1e-3


def test_defaults_and_leaves():
    p = Importance()
    assert float(p.global_weight) == 1.0
    assert all(float(getattr(p, w)) == 0.0 for w in WEIGHTS)
    assert (float(p.silhouette_exponent), float(p.silhouette_start), float(p.silhouette_end)) \
        == pytest.approx((1.7, 0.4, 1.0))
    assert (float(p.specular_exponent), float(p.diffuse_exponent), float(p.gradient_exponent)) \
        == (50.0, 5.0, 30.0)
    assert float(p.unocclusion_offset) == 20.0 and float(p.darkening) == 4.0
    leaves = jax.tree_util.tree_leaves(p)
    assert len(leaves) == len(dataclasses.fields(p)) and all(eqx.is_array(x) for x in leaves)
    with pytest.raises(ValueError, match="scalar"):
        Importance(intensity=jnp.ones(3))


def test_zero_weights_give_standard_compositing():
    f = random_features(8 * 5, seed=2)
    imp, scale = sample_importance(Importance(), **f)
    np.testing.assert_array_equal(imp, 0)
    np.testing.assert_array_equal(scale, 1)
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 1, (8, 5))
    c = rng.uniform(0, 1, (8, 5, 3)) * a[..., None]
    out = composite(c, a, importance=imp.reshape(8, 5))
    # m = 1: the standard step up to the rounding of its weights (measured: 1 eps)
    np.testing.assert_allclose(out, composite(c, a), rtol=0, atol=8 * np.finfo(float).eps)


def test_silhouetteness_analytic():
    v = jnp.array([[1.0, 0, 0]] * 4)
    n = jnp.array([[0, 1.0, 0], [1.0, 0, 0], [0, 3.0, 0], [-2.0, 0, 0]])
    sil = silhouetteness(n, v, jnp.array([1.0, 1.0, 0.5, 0.3]))
    np.testing.assert_allclose(sil, [1.0, 0.0, 0.5 ** 1.7, 0.0], rtol=1e-12)
    # halfway: |V.N| = 0.3 -> smoothstep(0.4, 1, 0.7) = 0.5
    n = jnp.array([0.3, np.sqrt(1 - 0.09), 0])
    np.testing.assert_allclose(silhouetteness(n, v[0], jnp.asarray(1.0)), 0.5, rtol=1e-12)


def test_lighting_analytic_and_two_sided():
    v = jnp.array([0.0, 0, 1.0])
    for n in (v, -v):  # the normal's sign does not matter
        np.testing.assert_allclose(lighting_importance(n, v, v, jnp.asarray(1.0)), 1.0)
        np.testing.assert_allclose(lighting_importance(n, v, v, jnp.asarray(0.0)), 0.0, atol=1e-15)
    # a normal perpendicular to light and view is unlit: importance 3 - (1 - m_G)^30
    n = jnp.array([1.0, 0, 0])
    np.testing.assert_allclose(lighting_importance(n, v, v, jnp.asarray(0.5)), 3 - 0.5 ** 30)


@pytest.mark.slow
def test_silhouetteness_and_lighting_under_jit_vmap_grad_and_their_errors():
    f = random_features(6, seed=5)
    n, v, m_g = f["normal"], jnp.broadcast_to(f["view"], f["normal"].shape), f["gradient_magnitude"]
    for fn in (lambda *a: silhouetteness(*a, exponent=2.0),
               lambda n, v, m: lighting_importance(n, v, v, m, gradient_exponent=3.0)):
        eager = fn(n, v, m_g)
        np.testing.assert_allclose(jax.jit(fn)(n, v, m_g), eager, rtol=1e-13)
        np.testing.assert_allclose(jax.vmap(fn)(n, v, m_g), eager, rtol=1e-13)
        check_grad_fd(lambda m, fn=fn: jnp.sum(fn(n, v, m) ** 2), m_g)
    # m_G outside [0, 1] is refused, not clipped; so are exponents <= 0 and s1 >= s2:
    # at once on concrete values, at run time under jit
    bad = [(lambda m: silhouetteness(n, v, m), m_g.at[0].set(1.5), "gradient_magnitude"),
           (lambda m: lighting_importance(n, v, v, m), m_g.at[0].set(-0.1),
            "gradient_magnitude"),
           (lambda m: lighting_importance(n, v, v, m, gradient_exponent=0.0), m_g,
            "gradient_exponent"),
           (lambda m: silhouetteness(n, v, m, start=0.8, end=0.2), m_g, "start"),
           (lambda m: silhouetteness(n.at[0, 1].set(jnp.nan), v, m), m_g, "normal")]
    for fn, m, name in bad:
        with pytest.raises(ValueError, match=f"`{name}`"):
            fn(m)
        with pytest.raises(eqx.EquinoxRuntimeError, match=f"`{name}`"):
            jax.block_until_ready(eqx.filter_jit(fn)(m))
    with pytest.raises(ValueError, match=r"`light` must be \(\.\.\., 3\)"):
        lighting_importance(n, v, jnp.ones(2), m_g)


def test_measures_individually():
    f = random_features(6, seed=4)
    one = {w: 0.0 for w in WEIGHTS}
    for w, expected in [("intensity", f["intensity"]), ("extinction", jnp.log1p(f["extinction"])),
                        ("gradient", f["gradient_magnitude"]),
                        ("unocclusion", 20 - f["optical_depth"])]:
        p = Importance(**{**one, w: 1.0})
        np.testing.assert_allclose(sample_importance(p, **f)[0], expected, rtol=1e-12)
    # global weight scales everything; per-ray weights replace it
    p2 = Importance(global_weight=3.0, intensity=1.0)
    np.testing.assert_allclose(sample_importance(p2, intensity=f["intensity"])[0],
                               3 * f["intensity"], rtol=1e-12)
    g = jnp.linspace(0, 1, 6)
    np.testing.assert_allclose(
        sample_importance(p2, intensity=f["intensity"], global_weight=g)[0], g * f["intensity"])


def test_colour_scale_only_with_silhouette_weight():
    f = random_features(10, seed=5)
    _, scale = sample_importance(Importance(intensity=1.0), **f)
    np.testing.assert_array_equal(scale, 1)
    _, scale = sample_importance(Importance(silhouette=1.0), **f)
    sil = silhouetteness(f["normal"], f["view"], f["gradient_magnitude"])
    np.testing.assert_allclose(scale, jnp.exp(-4 * sil))
    assert np.all((scale > 0) & (scale <= 1))
    # context rays (per-ray global weight 0) are not darkened
    _, scale = sample_importance(Importance(silhouette=1.0), **f, global_weight=jnp.zeros(10))
    np.testing.assert_array_equal(scale, 1)
    # the darkening fades with the per-ray weight (focus plus context, sec. IV-D)
    half = sample_importance(Importance(silhouette=1.0), **f, global_weight=jnp.full(10, 0.5))[1]
    np.testing.assert_allclose(half, jnp.exp(-2 * sil))
    more = sample_importance(Importance(silhouette=1.0), **f, global_weight=jnp.full(10, 3.0))[1]
    np.testing.assert_allclose(more, jnp.exp(-4 * sil))


HARD = {
    "zero_normal": dict(normal=jnp.zeros((4, 3))),
    "normal_along_view": dict(normal=jnp.array([[1.0, 0, 0]] * 4)),
    "normal_against_view": dict(normal=jnp.array([[-1.0, 0, 0]] * 4)),
    "zero_gradient": dict(gradient_magnitude=jnp.zeros(4)),
    "unit_gradient": dict(gradient_magnitude=jnp.ones(4)),
    "light_opposite_view": dict(light=jnp.array([-1.0, 0, 0])),
}


def _composite_loss(imp, scale, bg_imp):
    dtype = imp.dtype
    a = jnp.asarray([[1.0, 0.0], [0.5, 1.0]], dtype)
    # distinct colours: with equal ones, which sample shows would not matter
    rgb = jnp.asarray([[[0.9, 0.2, 0.1], [0.1, 0.8, 0.3]], [[0.2, 0.3, 1.0], [0.6, 0.1, 0.4]]],
                      dtype)
    c = rgb * (a * scale.reshape(2, 2))[..., None]
    rgba = composite(c, a, importance=imp.reshape(2, 2), background_importance=bg_imp)
    return jnp.sum(rgba * jnp.asarray([[1.0, 2.0, 3.0, 4.0]], dtype))


def _hard_loss(p, feats):
    return _composite_loss(*sample_importance(p, **feats), p.background_importance())


_jit_hard_grad = jax.jit(jax.grad(_hard_loss))
_jit_composite_grad = jax.jit(jax.grad(_composite_loss, (0, 1, 2)))
_jit_importance = jax.jit(lambda p, f: sample_importance(p, **f))


@pytest.mark.parametrize("case", sorted(HARD))
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_hard_features_values_and_weight_gradients(case, dtype):
    base = dict(intensity=jnp.array([0.0, 0.3, 1.0, 0.5]),
                extinction=jnp.array([0.0, 1.0, 0.0, 9.0]),
                gradient_magnitude=jnp.array([0.0, 0.5, 1.0, 0.2]),
                normal=jnp.array([[0.0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 0]]),
                view=jnp.array([1.0, 0, 0]), light=jnp.array([0.0, 1, 1]),
                optical_depth=jnp.array([0.0, 1.0, 25.0, 3.0]))
    feats = {k: jnp.asarray(v, dtype) for k, v in {**base, **HARD[case]}.items()}
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), PARAMS)
    imp, scale = _jit_importance(params, feats)
    assert imp.dtype == dtype and scale.dtype == dtype
    args = [np.broadcast_to(np.asarray(feats[k], float), shape) for k, shape in (
        ("intensity", (4,)), ("extinction", (4,)), ("gradient_magnitude", (4,)),
        ("normal", (4, 3)), ("view", (4, 3)), ("light", (4, 3)), ("optical_depth", (4,)))]
    measures = reference_measures(PARAMS, *args)
    want_imp, want_scale = reference_importance(PARAMS, *args)
    # measured: 1.2e-7 in float32 (powers up to 50 of rounded dot products), 1.3e-16 in
    # float64
    rtol = 1e-6 if dtype == jnp.float32 else 1e-14
    np.testing.assert_allclose(np.asarray(imp, float), want_imp, rtol=rtol)
    np.testing.assert_allclose(np.asarray(scale, float), want_scale, rtol=rtol)
    if case == "zero_normal":
        # by hand (PARAMS): |V . N| = 0 gives sil = m_G^1.7 (the smoothstep at 1), and
        # N . H = N . L = 0 leave lighting 3 - (1 - m_G)^30
        x, tau, m_g, depth = (args[i] for i in (0, 1, 2, 6))
        sil = m_g ** 1.7
        hand = 1.5 * (2 * x + 0.7 * np.log1p(tau) + 1.3 * m_g + 2.5 * sil + 0.2 * (20 - depth)
                      + 0.9 * (3 - (1 - m_g) ** 30))
        np.testing.assert_allclose(np.asarray(imp, float), hand, rtol=rtol)
        np.testing.assert_allclose(np.asarray(scale, float), np.exp(-4 * sil), rtol=rtol)
    # I_s is linear in the measure weights: dL/dW_n = W_global sum_s dL/dI_s I_n(s), and
    # dL/dk = -sum_s dL/dscale_s sil_s scale_s (darkening strength clip(1.5, 0, 1) = 1)
    grads = _jit_hard_grad(params, feats)
    lam_imp, lam_scale, lam_bg = (np.asarray(x, float) for x in _jit_composite_grad(
        imp, scale, params.background_importance()))
    g_w = float(PARAMS.global_weight)
    want = {w: g_w * lam_imp @ measures[w] for w in WEIGHTS}
    want["global_weight"] = lam_imp @ (want_imp / g_w)   # (W_bg = 0: no background term)
    want["background"] = g_w * lam_bg
    want["darkening"] = -lam_scale @ (measures["silhouette"] * want_scale)
    for name in (f.name for f in dataclasses.fields(grads)):
        got = np.asarray(getattr(grads, name), float)
        assert np.isfinite(got), name
        if name in want:
            np.testing.assert_allclose(got, want[name], rtol=rtol, atol=rtol, err_msg=name)


def test_weight_gradients_match_finite_differences():
    f = random_features(12, seed=6)
    rng = np.random.default_rng(7)
    a = jnp.asarray(rng.uniform(0.1, 0.9, (3, 4)))
    colors = jnp.asarray(rng.uniform(0, 1, (3, 4, 3)))
    flat, unravel = ravel_pytree(PARAMS)
    flat = flat.astype(jnp.float64)

    def loss(x):
        p = unravel(x)
        imp, scale = sample_importance(p, **f)
        c = colors * (a * scale.reshape(3, 4))[..., None]
        rgba = composite(c, a, importance=imp.reshape(3, 4), background=jnp.ones(3) * 0.5,
                         background_importance=p.background_importance())
        return jnp.sum(rgba * jnp.asarray([[1.0, 2.0, 3.0, 0.5]]))

    g = check_grad_fd(jax.jit(loss), flat, n_dirs=4)
    assert np.all(np.isfinite(g))


def test_jit_and_vmap():
    f = random_features(12, seed=8)
    eager = sample_importance(PARAMS, **f)
    jitted = eqx.filter_jit(sample_importance)(PARAMS, **f)
    np.testing.assert_allclose(jitted[0], eager[0], rtol=1e-13)
    batched = {k: v.reshape(3, 4, *v.shape[1:]) for k, v in f.items()}
    vm = jax.vmap(lambda kw: sample_importance(PARAMS, **kw))(batched)
    np.testing.assert_allclose(vm[0].reshape(12), eager[0], rtol=1e-13)
    np.testing.assert_allclose(vm[1].reshape(12), eager[1], rtol=1e-13)


def test_sample_importance_errors():
    with pytest.raises(ValueError, match="at least one feature"):
        sample_importance(Importance())
    with pytest.raises(ValueError, match="normal"):
        sample_importance(Importance(), normal=jnp.ones((4, 2)))
    with pytest.raises(ValueError, match="broadcast"):
        sample_importance(Importance(), intensity=jnp.ones(4), extinction=jnp.ones(5))
    # NaN or inf weights: refused by name when built, and at run time when traced
    for field, value in (("intensity", jnp.nan), ("darkening", jnp.inf),
                         ("silhouette_end", jnp.inf), ("background", jnp.inf)):
        with pytest.raises(ValueError, match=f"Importance: `{field}` must be finite"):
            Importance(**{field: value})
    assert float(Importance(background=-jnp.inf).background) == -np.inf  # no background
    # found by a review: what no measure reads was dropped without a word (vectors without
    # a gradient magnitude gave importance 0 under silhouette and lighting weights of 5)
    vectors = dict(normal=jnp.ones((2, 3)), view=jnp.ones(3), light=jnp.ones(3))
    with pytest.raises(ValueError, match=r"`normal`, `view`, `light` would be unread: .* "
                                         r"also need `gradient_magnitude`"):
        sample_importance(Importance(silhouette=5.0, lighting=5.0), **vectors)
    with pytest.raises(ValueError, match=r"`light` would be unread: .* also need `normal`, "
                                         r"`view`, `gradient_magnitude`"):
        sample_importance(Importance(), intensity=jnp.ones(2), light=jnp.ones(3))
    for weight, given, missing in (("silhouette", dict(gradient_magnitude=jnp.ones(2)),
                                    "`normal`, `view`"),
                                   ("extinction", dict(intensity=jnp.ones(2)), "`extinction`"),
                                   ("unocclusion", dict(intensity=jnp.ones(2)),
                                    "`optical_depth`")):
        with pytest.raises(ValueError, match=rf"`params.{weight}` is 2, but its measure needs "
                                             rf"{missing}, not given"):
            sample_importance(Importance(**{weight: 2.0}), **given)
    # a global weight of 0 turns every measure off, unless per-ray weights replace it
    off = Importance(global_weight=0.0, silhouette=5.0)
    np.testing.assert_array_equal(sample_importance(off, intensity=jnp.ones(2))[0], [0, 0])
    with pytest.raises(ValueError, match=r"`params.silhouette` is 5"):
        sample_importance(off, intensity=jnp.ones(2), global_weight=jnp.ones(2))
    # a traced weight cannot be known to be non-zero: its measure is left out (0)
    np.testing.assert_array_equal(jax.jit(lambda w: sample_importance(
        Importance(intensity=1.0, lighting=w), intensity=jnp.ones(2))[0])(2.0), [1.0, 1.0])
    weighted = jax.jit(lambda w: sample_importance(Importance(intensity=w),
                                                   intensity=jnp.ones(2))[0])
    np.testing.assert_allclose(weighted(2.0), [2.0, 2.0])
    with pytest.raises(Exception, match="sample_importance: `intensity` must be finite"):
        jax.block_until_ready(weighted(jnp.nan))


def test_float32_in_float32_out():
    f = random_features(5, seed=9, dtype=jnp.float32)
    imp, scale = sample_importance(PARAMS, **f)
    assert imp.dtype == jnp.float32 and scale.dtype == jnp.float32
    imp64, _ = sample_importance(PARAMS, **random_features(5, seed=9))
    np.testing.assert_allclose(imp, imp64, rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------- gradient magnitude


def test_normalized_gradient_magnitude():
    d = jnp.arange(8.0)
    vol = jnp.broadcast_to(d[:, None, None] ** 2 / 49.0, (8, 8, 8))
    m = normalized_gradient_magnitude(regression_gradient(vol, size=3))
    assert m.shape == (8, 8, 8)
    # a symmetric fit's slope of d^2 is 2d exactly (the odd moments of x^2 vanish), so the
    # interior is 2d / (2 * 6) = d / 6; the edges replicate their value: (f(1) - f(0)) / 2
    # = 1/98 and (f(7) - f(6)) / 2 = 13/98, i.e. 1/24 and 13/24 of the maximum 12/49
    want = np.r_[0.25, np.arange(1, 7), 3.25] / 6
    np.testing.assert_allclose(m, np.broadcast_to(want[:, None, None], m.shape), rtol=1e-14)
    np.testing.assert_array_equal(normalized_gradient_magnitude(jnp.zeros((4, 4, 4, 3))), 0)
    # a constant volume: the norm's derivative at the zero vector is taken as 0, not NaN
    # (compiled: eagerly, about 100 small programs)
    g = jax.jit(jax.grad(lambda v: normalized_gradient_magnitude(
        regression_gradient(v, size=3)).sum()))(jnp.zeros((6, 6, 6)))
    np.testing.assert_array_equal(g, 0)
    with pytest.raises(ValueError, match="D, H, W, 3"):
        normalized_gradient_magnitude(jnp.zeros((4, 4, 3)))


# --------------------------------------------------------------------------- focus + context


def test_focus_circular():
    w = focus_weights((20, 30), center=(10.0, 12.0), radius=5.0, kind="circular",
                      inside=2.0, outside=0.5)
    assert w.shape == (20, 30)
    assert w[10, 12] == 2.0 and w[10, 17] == 2.0 and w[10, 18] == 0.5 and w[0, 0] == 0.5
    rows, cols = np.mgrid[:20, :30]
    inside = (rows - 10.0) ** 2 + (cols - 12.0) ** 2 <= 25
    np.testing.assert_array_equal(w, np.where(inside, 2.0, 0.5))


def test_focus_gaussian_values_and_gradients():
    w = focus_weights((16, 16), center=(4.0, 6.0), radius=3.0, kind="gaussian")
    np.testing.assert_allclose(w[4, 6], 1.0)
    np.testing.assert_allclose(w[4, 9], np.exp(-0.5), rtol=1e-12)
    np.testing.assert_allclose(w[7, 6], np.exp(-0.5), rtol=1e-12)
    # differentiable in centre and radius
    x0 = jnp.array([4.3, 6.2, 3.0])

    def f(x):
        return jnp.sum(focus_weights((16, 16), center=x[:2], radius=x[2], kind="gaussian") ** 2)

    check_grad_fd(jax.jit(f), x0)
    # a centre exactly on a pixel: that pixel's distance is 0, where its norm has no
    # derivative; the gradient is finite and matches central differences
    check_grad_fd(jax.jit(lambda c: focus_weights((8, 8), center=c, radius=2.0).sum()),
                  jnp.array([3.0, 3.0]), h=1e-5, n_dirs=2)


def test_focus_gaussian_float32_agrees_with_float64():
    def f(x):
        return focus_weights((12, 16), center=x[:2], radius=x[2], kind="gaussian", inside=2.0,
                             outside=0.5)

    x0 = np.array([4.3, 6.2, 3.0])
    w32, w64 = (f(jnp.asarray(x0, dt)) for dt in (jnp.float32, jnp.float64))
    assert w32.dtype == jnp.float32 and w64.dtype == jnp.float64
    # measured: 1.8e-7 (weights up to 2), and 1e-7 relative on the gradient
    np.testing.assert_allclose(np.asarray(w32, float), w64, rtol=0, atol=1e-6)
    g32, g64 = (jax.grad(lambda x: jnp.sum(f(x) ** 2))(jnp.asarray(x0, dt))
                for dt in (jnp.float32, jnp.float64))
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(g32, float), g64, rtol=1e-5)


@pytest.mark.parametrize("radius", [1e-20, 1e-30])
def test_focus_gaussian_gradient_finite_at_tiny_radius(radius):
    # pixel (0, 0) lies exactly one radius from the centre, every other pixel past 40;
    # d/dR exp(-d^2 / 2R^2) = exp(-1/2) / R there, although 1/R^2 overflows float32
    # (where the plain quotient rule gave NaN)
    def f(r, c):
        return focus_weights((4, 4), center=c, radius=r, kind="gaussian")

    r, center = jnp.asarray(radius), jnp.asarray([0.0, radius])
    w = f(r, center)
    np.testing.assert_allclose(w[0, 0], np.exp(-0.5), rtol=1e-12)
    assert np.all(np.asarray(w).ravel()[1:] == 0)
    g_r, g_c = jax.grad(lambda r, c: f(r, c).sum(), argnums=(0, 1))(r, center)
    np.testing.assert_allclose(g_r, np.exp(-0.5) / radius, rtol=1e-12)
    # moving the centre away from pixel (0, 0) lowers its weight
    np.testing.assert_allclose(g_c, [0.0, -np.exp(-0.5) / radius], rtol=1e-12)
    # float32 squares the tiny distance to 0 (pixel (0, 0) gets weight 1, slope 0), but
    # the far pixels' slopes, 0 times an overflowing 1/R^2 before, stay finite
    g32 = jax.grad(lambda r, c: f(r, c).sum(), argnums=(0, 1))(
        r.astype(jnp.float32), center.astype(jnp.float32))
    assert all(np.all(np.isfinite(g)) for g in g32)


def test_focus_screen_door():
    w = focus_weights((64, 64), center=(32.0, 32.0), radius=8.0, kind="screen_door",
                      inside=1.0, outside=0.0)
    assert set(np.unique(np.asarray(w))) <= {0.0, 1.0}
    assert np.all(w[30:34, 30:34] == 1.0) and np.all(w[:8, :8] == 0.0)
    # the local density follows the Gaussian: mean over 4x4 dither cells
    gauss = focus_weights((64, 64), center=(32.0, 32.0), radius=8.0, kind="gaussian")
    cells = np.asarray(w).reshape(16, 4, 16, 4).mean(axis=(1, 3))
    gcells = np.asarray(gauss).reshape(16, 4, 16, 4).mean(axis=(1, 3))
    assert np.abs(cells - gcells).mean() < 0.05
    g = jax.grad(lambda c: focus_weights((8, 8), center=c, radius=2.0, kind="screen_door").sum())(
        jnp.array([3.0, 3.0]))
    assert np.all(np.isfinite(g))


def test_focus_weights_drive_sample_importance():
    w = focus_weights((4, 5), center=(1.0, 1.0), radius=1.0, kind="circular")
    imp, _ = sample_importance(Importance(intensity=2.0), intensity=jnp.ones((4, 5)),
                               global_weight=w)
    np.testing.assert_allclose(imp, 2 * w)


def test_focus_errors_and_dtype():
    with pytest.raises(ValueError, match="kind"):
        focus_weights((4, 4), center=(1.0, 1.0), radius=1.0, kind="square")
    with pytest.raises(ValueError, match="center"):
        focus_weights((4, 4), center=(1.0, 1.0, 1.0), radius=1.0)
    with pytest.raises(ValueError, match="image_shape"):
        focus_weights((4,), center=(1.0, 1.0), radius=1.0)
    # found by a review: the Focus method unpacked its argument first ('cannot unpack')
    for shape in (16, (16, 16, 3)):
        with pytest.raises(ValueError, match=r"Focus.weights: `image_shape` must be \(H, W\)"):
            Focus(center=(0.5, 0.5), radius=0.2).weights(shape)
    with pytest.raises(Exception, match="radius"):
        focus_weights((4, 4), center=(1.0, 1.0), radius=0.0)
    for name in ("inside", "outside"):     # a per-column weight is not what either means
        with pytest.raises(ValueError, match=f"`{name}` must be a scalar.*global_weight"):
            focus_weights((4, 3), center=(1.0, 1.0), radius=1.0, **{name: jnp.ones(3)})
    w = focus_weights((4, 4), center=jnp.array([1.0, 1.0], jnp.float32),
                      radius=jnp.asarray(1.0, jnp.float32))
    assert w.dtype == jnp.float32
    assert focus_weights((4, 4), center=(1.0, 1.0), radius=1.0, dtype=jnp.float32).dtype \
        == jnp.float32


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_focus_radius_is_not_rounded_to_a_half_precision_output(dtype):
    # found by a review: the radius was cast to the output dtype before the float32
    # geometry, so 1e-8 became 0 in float16 (a NaN weight at the centre) and 259 became
    # 260 in bfloat16 (one pixel too many inside)
    tiny = focus_weights((3, 3), center=(1.0, 1.0), radius=1e-8, dtype=dtype)
    np.testing.assert_array_equal(np.asarray(tiny, np.float32),
                                  np.asarray(focus_weights((3, 3), center=(1.0, 1.0),
                                                           radius=1e-8), np.float32))
    wide = focus_weights((1, 300), center=(0.0, 0.0), radius=259.0, kind="circular",
                         dtype=dtype)
    assert float(jnp.sum(wide.astype(jnp.float32))) == 260.0  # columns 0 .. 259


def test_background_importance_no_background_and_weight_off():
    none = Importance(global_weight=2.0, background=-jnp.inf)
    assert float(none.background_importance()) == -np.inf
    assert float(none.background_importance(jnp.asarray(-1.0))) == -np.inf  # either sign
    assert float(none.background_importance(jnp.asarray(0.0))) == 0.0  # importance off
    np.testing.assert_allclose(float(Importance(global_weight=2.0, background=-3.0)
                                     .background_importance()), -6.0)
    for p in (none, Importance(global_weight=0.0, background=-jnp.inf)):
        g = jax.grad(lambda p: jnp.sum(composite(
            jnp.full((2, 3), 0.5), jnp.full((2,), 0.5), importance=jnp.ones(2),
            background_importance=p.background_importance())) * p.global_weight)(p)
        assert np.isfinite(float(g.global_weight)) and np.isfinite(float(g.background))
    # W_global W_bg has slope W_bg at W_global = 0 as well (the off switch only changes the
    # value where W_bg = -inf)
    for g0 in (0.0, 1e-9, -1e-9):
        slope = jax.grad(lambda g: Importance(background=-3.0).background_importance(g))(g0)
        assert float(slope) == -3.0, g0


def test_a_python_int_computes_and_compiles_as_a_python_float():
    # found by a review: an int became a strong float (float64 under x64), which promoted
    # a float16 or float32 computation, and a Python float then a float32 array of it
    # compiled focus_weights twice
    from volshade.importance import _focus_weights

    center = jnp.asarray([3.0, 4.0], jnp.float16)
    assert focus_weights((4, 4), center=center, radius=2).dtype == jnp.float16
    assert focus_weights((4, 4), center=center, radius=2.0).dtype == jnp.float16
    compiled = sys.modules["volshade.importance"]._compiled_sample_importance
    ext = jnp.ones(5, jnp.float32)
    first, _ = sample_importance(Importance(extinction=1), extinction=ext)
    size = compiled._cached._cache_size()
    second, _ = sample_importance(Importance(extinction=jnp.float32(1.0)), extinction=ext)
    assert compiled._cached._cache_size() == size
    assert first.dtype == second.dtype == jnp.float32
    center = jnp.asarray([3.0, 4.0], jnp.float32)
    focus_weights((8, 8), center=center, radius=2.0, inside=0.5)
    size = _focus_weights._cache_size()
    focus_weights((8, 8), center=center, radius=jnp.float32(2.0), inside=jnp.float32(0.5))
    assert _focus_weights._cache_size() == size


def test_a_bool_direction_is_refused():
    with pytest.raises(TypeError, match="`view` must be a number or numbers, got a bool"):
        sample_importance(Importance(silhouette=1.0), normal=jnp.ones((4, 3)),
                          view=(True, False, False), gradient_magnitude=jnp.ones(4) / 2)
