"""Tests of volshade.composition: standard and importance-aware compositing (Pinto & Freitas
2010)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_composition as ref
from helpers import check_grad_fd, temp_bytes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volshade.composition import (
    COMPOSITORS,
    ImportanceState,
    Sample,
    _importance_scan,
    _samples,
    _scan,
    _scan_in_place,
    composite,
    importance_finish,
    importance_init,
    importance_step,
    modulation,
    standard_init,
    standard_step,
)

jcomposite = jax.jit(composite)


def random_rays(n_rays, n_samples, *, seed=0, alpha=(0.05, 0.95), imp_scale=2.0):
    rng = np.random.default_rng(seed)
    a = rng.uniform(*alpha, (n_rays, n_samples))
    c = rng.uniform(0, 1, (n_rays, n_samples, 3)) * a[..., None]
    imp = rng.normal(0, imp_scale, (n_rays, n_samples))
    return c, a, imp


def scan_states(colors, alphas, importances):
    """All intermediate importance states of one batch of rays (front first)."""
    colors, alphas, importances = map(jnp.asarray, (colors, alphas, importances))
    state = importance_init(alphas.shape[:-1], alphas.dtype)
    xs = Sample(jnp.moveaxis(colors, -2, 0), jnp.moveaxis(alphas, -1, 0),
                jnp.moveaxis(importances, -1, 0))
    return jax.lax.scan(lambda s, x: (importance_step(s, x), s), state, xs)


# --------------------------------------------------------------------------- reference


def test_matches_reference_random():
    c, a, imp = random_rays(40, 12, seed=1)
    rng = np.random.default_rng(2)
    bg, bgi = rng.uniform(0, 1, 3), rng.normal(0, 2, 40)
    out = jcomposite(c, a, importance=imp, background=bg, background_importance=bgi)
    expected = np.stack([ref.importance(c[r], a[r], imp[r], bg, bgi[r]) for r in range(40)])
    np.testing.assert_allclose(out, expected, atol=1e-12)
    out = jcomposite(c, a, importance=imp, background=bg)
    expected = np.stack([ref.importance(c[r], a[r], imp[r], bg) for r in range(40)])
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_matches_reference_with_exact_zero_and_one_alphas():
    c, a, imp = random_rays(30, 10, seed=3)
    rng = np.random.default_rng(4)
    a = np.where(rng.uniform(size=a.shape) < 0.2, 0.0, a)
    a = np.where(rng.uniform(size=a.shape) < 0.1, 1.0, a)
    c = c * (a > 0)[..., None]
    out = jcomposite(c, a, importance=imp, background=np.array([0.2, 0.3, 0.4]))
    expected = np.stack([ref.importance(c[r], a[r], imp[r], [0.2, 0.3, 0.4]) for r in range(30)])
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_standard_matches_reference():
    c, a, _ = random_rays(20, 9, seed=5)
    out = jcomposite(c, a, background=np.array([1.0, 0.5, 0.0]))
    expected = np.stack([ref.standard(c[r], a[r], [1.0, 0.5, 0.0]) for r in range(20)])
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_accumulated_importance_matches_reference():
    c, a, imp = random_rays(10, 8, seed=6)
    final, _ = scan_states(c, a, imp)
    for r in range(10):
        c_ref, a_ref, i_ref, _ = ref.importance(c[r], a[r], imp[r], return_state=True)
        np.testing.assert_allclose(final.accumulated_importance[r], i_ref, atol=1e-12)
        np.testing.assert_allclose(final.opacity[r], a_ref, atol=1e-14)
        np.testing.assert_allclose(final.color[r], c_ref, atol=1e-12)


# --------------------------------------------------------------------------- properties


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_the_importance_offset_stays_at_most_zero(dtype):
    # ImportanceState's invariant delta = K - P <= 0, after every step: rounding could
    # otherwise take it above 0 (+0.40 in float32 without the clamp: found by mutation)
    for seed, scale in enumerate((1e-2, 1.0, 30.0, 1e3)):
        c, a, imp = random_rays(256, 32, seed=seed, alpha=(0.0, 1.0), imp_scale=scale)
        final, states = scan_states(*(np.asarray(x, dtype) for x in (c, a, imp)))
        assert float(jnp.max(states.importance_offset)) <= 0.0
        assert float(jnp.max(final.importance_offset)) <= 0.0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_zero_importance_equals_standard(dtype):
    c, a, _ = random_rays(64, 16, seed=7, alpha=(0.0, 1.0))
    c, a = jnp.asarray(c, dtype), jnp.asarray(a, dtype)
    bg = jnp.asarray([0.1, 0.7, 0.3], dtype)
    std = jcomposite(c, a, background=bg)
    imp = jcomposite(c, a, importance=jnp.zeros_like(a), background=bg)
    assert imp.dtype == dtype
    # m = 1 makes the step standard compositing up to the rounding of its weight
    # q = alpha_{i+1} T_i / alpha' (measured: 1.5 eps in float32, 2.5 eps in float64)
    atol = 8 * jnp.finfo(dtype).eps
    np.testing.assert_allclose(imp, std, rtol=0, atol=atol)
    # equal importances, whatever their level, also give standard compositing
    imp = jcomposite(c, a, importance=jnp.full_like(a, 7.5), background=bg)
    np.testing.assert_allclose(imp, std, rtol=0, atol=atol)


def test_opaque_samples_importance_is_max_and_modulations_multiply():
    # three opaque samples I_A < I_C < I_B (sec. III-A, eq. 5)
    i_a, i_c, i_b = 0.3, 1.1, 2.5
    one = jnp.ones(())
    s = importance_init((), jnp.float64)
    s = importance_step(s, Sample(jnp.array([1.0, 0, 0]), one, jnp.asarray(i_a)))
    m = modulation(s, i_b)                                   # two-sample case A, B
    m1 = modulation(s, i_c)
    s3 = importance_step(s, Sample(jnp.array([0, 1.0, 0]), one, jnp.asarray(i_c)))
    np.testing.assert_allclose(s3.accumulated_importance, i_c)
    m2 = modulation(s3, i_b)
    np.testing.assert_allclose(m, m2 * m1, rtol=1e-14)
    np.testing.assert_allclose(m, np.exp(i_a - i_b), rtol=1e-14)
    # the colour contribution of A is the same in both cases
    two = jcomposite(jnp.array([[1.0, 0, 0], [0, 0, 1.0]]), jnp.ones(2),
                    importance=jnp.array([i_a, i_b]))
    three = jcomposite(jnp.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), jnp.ones(3),
                      importance=jnp.array([i_a, i_c, i_b]))
    np.testing.assert_allclose(two[0], three[0], rtol=1e-14)
    np.testing.assert_allclose(two[0], m, rtol=1e-14)
    # accumulated importance of opaque samples is the maximum, in any order
    rng = np.random.default_rng(8)
    imps = rng.normal(0, 3, (20, 6))
    final, _ = scan_states(np.zeros((20, 6, 3)), np.ones((20, 6)), imps)
    np.testing.assert_allclose(final.accumulated_importance, imps.max(axis=1), rtol=1e-14)


@pytest.mark.parametrize("sample_importance", [-1e4, -3.0, 0.0, 3.0, 1e4])
def test_zero_opacity_sample_changes_nothing(sample_importance):
    c, a, imp = random_rays(16, 6, seed=9)
    base = jcomposite(c, a, importance=imp, background=np.array([0.5, 0.5, 0.5]),
                     background_importance=0.5)
    c2 = np.insert(c, 3, [0.0, 0.0, 0.0], axis=1)
    a2 = np.insert(a, 3, 0.0, axis=1)
    i2 = np.insert(imp, 3, sample_importance, axis=1)
    out = jcomposite(c2, a2, importance=i2, background=np.array([0.5, 0.5, 0.5]),
                    background_importance=0.5)
    np.testing.assert_allclose(out, base, atol=1e-14)
    # a colour given with it (not opacity-weighted) is not composited either (its weight
    # would be (1 - a) / m)
    c3 = np.insert(c, 3, [0.1, 0.8, 0.3], axis=1)
    out = jcomposite(c3, a2, importance=i2, background=np.array([0.5, 0.5, 0.5]),
                     background_importance=0.5)
    np.testing.assert_allclose(out, base, atol=1e-14)
    # where standard compositing adds it, as light emitted (composite's docstring)
    emitted = np.prod(1 - a[:, :3], axis=1)[:, None] * np.array([0.1, 0.8, 0.3])
    np.testing.assert_allclose(jcomposite(c3, a2)[:, :3], jcomposite(c2, a2)[:, :3] + emitted,
                               atol=1e-14)
    # also as the very first sample of a ray
    out = jcomposite(np.insert(c, 0, 0.0, axis=1), np.insert(a, 0, 0.0, axis=1),
                    importance=np.insert(imp, 0, sample_importance, axis=1),
                    background=np.array([0.5, 0.5, 0.5]), background_importance=0.5)
    np.testing.assert_allclose(out, base, atol=1e-14)


def test_accumulated_opacity_equals_standard():
    c, a, imp = random_rays(32, 20, seed=10, alpha=(0.0, 1.0), imp_scale=50.0)
    _, states = scan_states(c, a, imp)
    std = standard_init((32,), jnp.float64)
    for i in range(20):
        np.testing.assert_array_equal(states.transmittance[i], std.transmittance)
        std = standard_step(std, Sample(jnp.asarray(c[:, i]), jnp.asarray(a[:, i])))
    out = jcomposite(c, a, importance=imp)
    np.testing.assert_array_equal(out[:, 3], 1 - std.transmittance)


def test_importance_shift_invariance():
    c, a, imp = random_rays(16, 10, seed=11)
    bg = np.array([0.2, 0.9, 0.1])
    base = jcomposite(c, a, importance=imp, background=bg, background_importance=1.0)
    shifted = jcomposite(c, a, importance=imp + 123.0, background=bg, background_importance=124.0)
    np.testing.assert_allclose(shifted, base, atol=1e-10)


def test_more_important_sample_shows_through():
    # an opaque red front sample hides green in standard compositing, not with importance
    c = jnp.array([[1.0, 0, 0], [0, 1.0, 0]])
    a = jnp.array([1.0, 1.0])
    assert jcomposite(c, a)[1] == 0
    out = jcomposite(c, a, importance=jnp.array([0.0, 10.0]))
    np.testing.assert_allclose(out, [np.exp(-10), 1 - np.exp(-10), 0, 1], rtol=1e-12)


def test_background_importance_fades_volume():
    c, a, imp = random_rays(8, 6, seed=12)
    bg = np.array([0.3, 0.6, 0.9])
    none = jcomposite(c, a, importance=imp, background=bg)
    np.testing.assert_allclose(none[..., 3], jcomposite(c, a, background=bg)[..., 3], atol=1e-14)
    low = jcomposite(c, a, importance=imp, background=bg, background_importance=-1e4)
    np.testing.assert_allclose(low, none, atol=1e-14)
    high = jcomposite(c, a, importance=imp, background=bg, background_importance=1e4)
    np.testing.assert_allclose(high[..., :3], np.broadcast_to(bg, (8, 3)), atol=1e-14)
    np.testing.assert_allclose(high[..., 3], 0, atol=1e-14)
    alphas = [jcomposite(c, a, importance=imp, background=bg, background_importance=b)[..., 3]
              for b in (-2.0, 0.0, 2.0, 4.0, 8.0)]
    assert np.all(np.diff(np.stack(alphas), axis=0) <= 1e-15)


def test_a_tie_with_the_background_importance_takes_the_behind_side():
    # one opaque sample of importance 0 over a background of importance 0: K = I_bg, a
    # kink. Below it the background shows through its opacity (m = e^(K - I_bg)), above
    # it not (m = 1). The derivative is the side below, the one the steps take for a tie
    # K = I_s; jnp.minimum's mean slope (-0.6 here) was neither side's
    c = jnp.asarray([[0.5, 0.2, 0.1]])
    bg = jnp.ones(3)

    def loss(a, i):
        return jnp.sum(composite(c * a[:, None], a, importance=i, background=bg,
                                 background_importance=0.0))

    a, i, h = jnp.ones(1), jnp.zeros(1), 1e-6
    below = float((loss(a, i) - loss(a, i - h)) / h)
    above = float((loss(a, i + h) - loss(a, i)) / h)
    np.testing.assert_allclose([below, above], [-1.2, 0.0], atol=1e-5)  # sum(c) - sum(bg)
    g_i = float(jax.grad(loss, 1)(a, i)[0])
    np.testing.assert_allclose(g_i, -1.2, rtol=1e-12)
    # the modulation of a sample tied with K = I_s: the same side
    state = importance_step(importance_init((), jnp.float64),
                            Sample(c[0], jnp.asarray(1.0), jnp.asarray(0.0)))
    assert float(jax.grad(lambda s: modulation(state, s))(jnp.asarray(0.0))) == -1.0


def test_tends_to_coloured_mip_as_intensity_weight_grows():
    rng = np.random.default_rng(13)
    n_rays, n_samples = 256, 24
    intensity = rng.uniform(0, 1, (n_rays, n_samples))
    a = rng.uniform(0.3, 0.9, (n_rays, n_samples))
    colors = rng.uniform(0, 1, (n_rays, n_samples, 3))
    mip = np.take_along_axis(colors, intensity.argmax(axis=1)[:, None, None], axis=1)[:, 0]
    dists = []
    for weight in (0.0, 2.0, 8.0, 32.0, 128.0, 1024.0):
        rgba = jcomposite(colors * a[..., None], a, importance=weight * intensity)
        avg = rgba[:, :3] / rgba[:, 3:]
        dists.append(float(np.mean(np.abs(avg - mip))))
    assert all(d1 < d0 for d0, d1 in zip(dists, dists[1:], strict=False)), dists
    assert dists[-1] < 0.15 * dists[0], dists


# --------------------------------------------------------------------------- hard cases

HARD_CASES = {
    "alpha_zero": ([0.0, 0.0, 0.0], [1.0, 5.0, -2.0]),
    "alpha_one": ([1.0, 1.0, 1.0], [0.0, 3.0, 1.0]),
    "gap_up_1e4": ([0.5, 0.5, 0.7], [0.0, 1e4, 0.0]),
    "gap_down_1e4": ([0.5, 0.5, 0.7], [1e4, 0.0, 1e4]),
    "gap_opaque_1e4": ([1.0, 0.3, 1.0], [-1e4, 1e4, 0.0]),
    "all_transparent": ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    "single_opaque": ([0.0, 1.0, 0.0], [2.0, 1.0, 3.0]),
    "alternating": ([1.0, 0.0, 1.0], [0.0, 1e4, 5.0]),
    "negative": ([0.4, 0.9, 0.2], [-50.0, -3.0, -1e4]),
    "tiny_alpha_high_importance": ([0.9, 1e-7, 0.5], [0.0, 1e4, 0.0]),
}


def _hard_inputs(alphas, importances, dtype):
    a = jnp.asarray(alphas, dtype)
    base = jnp.asarray([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 1.0]], dtype)
    return base * a[:, None], a, jnp.asarray(importances, dtype)


def _loss(c, a, imp, bg, bgi):
    rgba = composite(c, a, importance=imp, background=bg, background_importance=bgi)
    return jnp.sum(rgba * jnp.broadcast_to(jnp.asarray([1.0, 2.0, 3.0, 4.0], rgba.dtype),
                                           rgba.shape))


_jit_grad = jax.jit(jax.grad(_loss, argnums=(0, 1, 2, 3, 4)))


@pytest.mark.parametrize("case", sorted(HARD_CASES))
@pytest.mark.parametrize("bg_importance", [None, -1e4, 0.0, 1e4])
def test_hard_cases(case, bg_importance):
    alphas, importances = HARD_CASES[case]
    results = {}
    for dtype in (jnp.float32, jnp.float64):
        c, a, imp = _hard_inputs(alphas, importances, dtype)
        bg = jnp.asarray([0.25, 0.5, 0.75], dtype)
        bgi = jnp.asarray(-jnp.inf if bg_importance is None else bg_importance, dtype)
        rgba = jcomposite(c, a, importance=imp, background=bg, background_importance=bgi)
        assert rgba.dtype == dtype
        assert np.all(np.isfinite(rgba)) and np.all(rgba >= 0) and np.all(rgba <= 1 + 1e-6)
        grads = _jit_grad(c, a, imp, bg, bgi)
        for g in grads:
            assert np.all(np.isfinite(g)), (case, dtype, grads)
        results[dtype] = np.asarray(rgba, np.float64)
        # eq. 8 literally, on the inputs as rounded to this dtype; in float64 it loses
        # about 1e4 eps against the 1e4 gaps in its accumulated importance I
        want = ref.importance(np.asarray(c, float), np.asarray(a, float), np.asarray(imp, float),
                              np.asarray(bg, float), float(bgi))
        np.testing.assert_allclose(results[dtype], want, rtol=0,
                                   atol=1e-6 if dtype == jnp.float32 else 1e-12)
    np.testing.assert_allclose(results[jnp.float32], results[jnp.float64], atol=1e-4)


@st.composite
def hard_rays(draw):
    n = 6
    # An opacity below float32's eps / 2 cannot change T = 1 in float32 (1 - alpha rounds to
    # 1), so an empty ray stays empty there and not in float64, and the accumulated importance
    # of such a sample (K = I - ln alpha) is kept in one dtype only: draw those as exact zeros.
    alpha = st.one_of(st.sampled_from([0.0, 1.0, 1e-6, 0.5]),
                      st.floats(0.0, 1.0, width=32).map(lambda x: x if x >= 6e-8 else 0.0))
    imp = st.one_of(st.sampled_from([-1e4, 0.0, 1e4, -30.0, 30.0]), st.floats(-5.0, 5.0, width=32))
    color = st.floats(0.0, 1.0, width=32)
    alphas = draw(st.lists(alpha, min_size=n, max_size=n))
    imps = draw(st.lists(imp, min_size=n, max_size=n))
    colors = draw(st.lists(st.tuples(color, color, color), min_size=n, max_size=n))
    bgi = draw(st.one_of(st.none(), imp))
    return np.asarray(colors) * np.asarray(alphas)[:, None], np.asarray(alphas), \
        np.asarray(imps), bgi




@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(hard_rays())
def test_hypothesis_hard_rays(ray):
    c, a, imp, bgi = ray
    results = {}
    for dtype in (jnp.float32, jnp.float64):
        args = [jnp.asarray(x, dtype) for x in (c, a, imp)]
        bg = jnp.asarray([0.3, 0.2, 0.1], dtype)
        b = jnp.asarray(-jnp.inf if bgi is None else bgi, dtype)
        rgba = np.asarray(jcomposite(args[0], args[1], importance=args[2], background=bg,
                                     background_importance=b))
        assert np.all(np.isfinite(rgba)) and np.all(rgba >= -1e-7) and np.all(rgba <= 1 + 1e-6)
        for g in _jit_grad(*args, bg, b):
            assert np.all(np.isfinite(g))
        results[dtype] = rgba.astype(np.float64)
    np.testing.assert_allclose(results[jnp.float32], results[jnp.float64], atol=1e-4)
    expected = ref.importance(c, a, imp, [0.3, 0.2, 0.1], -np.inf if bgi is None else bgi)
    np.testing.assert_allclose(results[jnp.float64], expected, atol=1e-9)


def _autodiff_loss(c, a, imp, bg, bgi):
    """:func:`_loss` through a plain ``lax.scan`` of ``importance_step``, differentiated by JAX
    (the renderer's path), against which the hand-written adjoint of ``composite`` is checked."""
    state = importance_init(a.shape[:-1], a.dtype)
    state = jax.lax.scan(lambda s, x: (importance_step(s, x), None), state,
                         _samples(c, a, imp))[0]
    rgba = importance_finish(state, bg, bgi)
    return jnp.sum(rgba * jnp.broadcast_to(jnp.asarray([1.0, 2.0, 3.0, 4.0], rgba.dtype),
                                           rgba.shape))


_jit_autodiff_grad = jax.jit(jax.grad(_autodiff_loss, argnums=(0, 1, 2, 3, 4)))


def _assert_grads_equal(got, expected, rtol):
    """Equal up to ``rtol`` relative to the largest entry (faint samples give gradients of
    1 / alpha, next to which rounding of O(1) entries differs)."""
    scale = max(1.0, *(float(jnp.max(jnp.abs(e))) for e in expected))
    for g, e in zip(got, expected, strict=True):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, e, rtol=rtol, atol=rtol * scale)


@pytest.mark.parametrize("case", sorted(HARD_CASES))
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_custom_vjp_equals_autodiff_of_step_on_hard_cases(case, dtype):
    alphas, importances = HARD_CASES[case]
    c, a, imp = _hard_inputs(alphas, importances, dtype)
    bg = jnp.asarray([0.25, 0.5, 0.75], dtype)
    for bgi in (-jnp.inf, -1e4, 0.0, 1e4):
        bgi = jnp.asarray(bgi, dtype)
        _assert_grads_equal(_jit_grad(c, a, imp, bg, bgi), _jit_autodiff_grad(c, a, imp, bg, bgi),
                            1e-12 if dtype == jnp.float64 else 1e-5)


def test_custom_vjp_equals_autodiff_of_step_random():
    c, a, imp = random_rays(48, 16, seed=20, alpha=(0.0, 1.0), imp_scale=4.0)
    rng = np.random.default_rng(21)
    a = np.where(rng.uniform(size=a.shape) < 0.15, 0.0, a)
    a = np.where(rng.uniform(size=a.shape) < 0.1, 1.0, a)
    imp = np.where(rng.uniform(size=imp.shape) < 0.1, 1e4, imp)
    imp[:, 5] = imp[:, 4]                                    # ties of importance
    c = c * (a > 0)[..., None]
    c, a, imp = map(jnp.asarray, (c, a, imp))
    bg = jnp.asarray([0.1, 0.6, 0.3])
    for bgi in (jnp.full(48, -jnp.inf), jnp.asarray(rng.normal(0, 3, 48))):
        _assert_grads_equal(_jit_grad(c, a, imp, bg, bgi), _jit_autodiff_grad(c, a, imp, bg, bgi),
                            1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_importance_forward_mode_equals_reverse_mode_on_hard_cases(dtype):
    # forward mode is JAX's through a scan of importance_step and reverse mode its
    # hand-written transpose: jax.jacfwd equals jax.jacrev (and is finite) on the hard
    # rays (opacities 0 and 1, importance gaps of 1e4), stacked as a batch of rays
    bg = jnp.asarray([0.25, 0.5, 0.75], dtype)
    rays = [_hard_inputs(*HARD_CASES[case], dtype) for case in sorted(HARD_CASES)]
    c, a, imp = (jnp.stack(x) for x in zip(*rays, strict=True))

    def f(c, a, imp, bgi):
        return composite(c, a, importance=imp, background=bg, background_importance=bgi)

    # both modes in one program, the background importance an argument: one compile for
    # the three of them
    jacobians = jax.jit(lambda *args: (jax.jacfwd(f, (0, 1, 2))(*args),
                                       jax.jacrev(f, (0, 1, 2))(*args)))
    for bgi in (-jnp.inf, 0.0, 1e4):
        fwd, rev = jacobians(c, a, imp, jnp.asarray(bgi, dtype))
        _assert_grads_equal(fwd, rev, 1e-12 if dtype == jnp.float64 else 1e-5)
        assert float(jnp.max(jnp.abs(fwd[2]))) > 1e-3  # the importances move the colour


@pytest.mark.parametrize("axes", [(0, None, 0), (None, 0, 0), (0, 0, None), (None, None, 0),
                                  (0, None, None)])
def test_importance_derivatives_under_vmap_of_some_arguments(axes):
    # vmapped over some inputs only, some outputs of the scan are not batched (over the
    # colours alone, the transmittance): their values and tangents must agree on that,
    # and the cotangent of an unbatched output is not counted once per element (found by
    # a review: a crash, and before forward mode a wrong gradient); against a loop
    rng = np.random.default_rng(31)
    full = (jnp.asarray(rng.uniform(0.05, 1, (2, 6, 9, 3))),
            jnp.asarray(rng.uniform(0.1, 0.8, (2, 6, 9))), jnp.asarray(rng.normal(size=(2, 6, 9))))
    args = tuple(x if ax is not None else x[0] for x, ax in zip(full, axes, strict=True))
    w = jnp.asarray(rng.normal(size=(6, 4)))

    def f(c, a, i):
        return jnp.sum(w * composite(c, a, importance=i))

    def element(b, *xs):
        return f(*(x[b] if ax is not None else x for x, ax in zip(xs, axes, strict=True)))

    ones = tuple(jnp.ones_like(x) for x in args)

    @jax.jit  # one program (eagerly, the loop's derivatives compiled about 80)
    def derivatives(*xs):
        grad = jax.grad(lambda *xs: jnp.sum(jnp.sin(jax.vmap(f, axes)(*xs))), (0, 1, 2))
        want = jax.grad(lambda *xs: sum(jnp.sin(element(b, *xs)) for b in range(2)), (0, 1, 2))
        tangent = jax.jvp(jax.vmap(f, axes), xs, ones)[1]
        looped = [jax.jvp(lambda *xs, b=b: element(b, *xs), xs, ones)[1] for b in range(2)]
        return grad(*xs), want(*xs), tangent, jnp.stack(looped)

    grad, want, tangent, looped = derivatives(*args)
    _assert_grads_equal(grad, want, 1e-12)
    np.testing.assert_allclose(tangent, looped, rtol=1e-12)


def test_custom_vjp_any_state_cotangent():
    # the adjoint of the scan for any cotangent of the final state (P and delta apart) and a
    # nonempty initial state, against JAX's reverse mode through importance_step
    rng = np.random.default_rng(22)
    n, s = 32, 10
    c, a, imp = random_rays(n, s, seed=23, alpha=(0.0, 1.0), imp_scale=3.0)
    a = np.where(rng.uniform(size=a.shape) < 0.2, np.where(rng.uniform(size=a.shape) < 0.5, 0, 1),
                 a)
    c, a, imp = map(jnp.asarray, (c, a, imp))
    init = ImportanceState(jnp.asarray(rng.uniform(0, 1, (n, 3))),
                           jnp.asarray(np.where(np.arange(n) % 2, rng.uniform(0, 1, n), 1.0)),
                           jnp.asarray(rng.normal(0, 2, n)), jnp.asarray(-rng.uniform(0, 2, n)))

    def plain(state, c, a, imp):
        return jax.lax.scan(lambda s, x: (importance_step(s, x), None), state,
                            _samples(c, a, imp))[0]

    out, vjp = jax.vjp(plain, init, c, a, imp)
    out2, vjp2 = jax.vjp(lambda *args: _importance_scan(*args, 1), init, c, a, imp)
    cot = ImportanceState(*(jnp.asarray(rng.normal(size=x.shape)) for x in out))
    for x, y in zip(jax.tree.leaves((out2, vjp2(cot))), jax.tree.leaves((out, vjp(cot))),
                    strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_faint_samples_on_empty_rays_have_finite_gradients(dtype):
    # opacities too small to change T = 1 (1 - alpha rounds to 1), below the visibility
    # floor (float32's sqrt(tiny), 1.1e-19: the step is empty) and above it
    faint = [1.4e-45, 1e-30, 1e-17, 1e-10] if dtype == jnp.float64 else [1e-19, 1e-12, 1e-9]
    for alpha in faint:
        a = jnp.asarray([0.0, alpha, 0.0, 0.6, alpha], dtype)
        c = jnp.asarray([[0.2, 0.3, 0.4]] * 5, dtype) * a[:, None]
        imp = jnp.asarray([-1e4, 1e4, -1e4, 0.0, 1e4], dtype)
        bg = jnp.asarray([0.3, 0.2, 0.1], dtype)
        for bgi in (-jnp.inf, 0.0):
            bgi = jnp.asarray(bgi, dtype)
            got = _jit_grad(c, a, imp, bg, bgi)
            for g in got:
                assert np.all(np.isfinite(g)), (alpha, got)
            if dtype == jnp.float64:
                _assert_grads_equal(got, _jit_autodiff_grad(c, a, imp, bg, bgi), 1e-12)


def test_transposed_importance_gradient_stores_no_more_than_twice_the_gradient():
    # a transposed VJP (how vs.fit built its forward mode before the compositor had one)
    # stored every backward step's non-linear values: 3.3x the gradient's temporaries
    # (found by a review); the backward step is checkpointed, and recomputed. A compiled
    # program's buffer plan, not a timing: 512 rays of 32 samples, float32
    spec = [jax.ShapeDtypeStruct(shape, jnp.float32) for shape in ((512, 32, 3), (512, 32),
                                                                    (512, 32))]

    def grad(c, a, i):
        return jax.grad(lambda c, a, i: jnp.sum(composite(c, a, importance=i)),
                        argnums=(0, 1, 2))(c, a, i)

    def transposed(c, a, i):
        out, vjp = jax.vjp(lambda a: composite(c, a, importance=i), a)
        return jax.linear_transpose(vjp, out)((jnp.ones_like(a),))[0]

    temp = [temp_bytes(f, *spec) for f in (grad, transposed)]
    assert temp[1] <= 2 * temp[0], temp


def test_grad_under_vmap_equals_batched_grad():
    c, a, imp = map(jnp.asarray, random_rays(6, 7, seed=24))
    bg, bgi = jnp.asarray([0.2, 0.4, 0.6]), jnp.asarray(0.5)
    batched = _jit_grad(c, a, imp, bg, bgi)
    per_ray = jax.jit(jax.vmap(jax.grad(_loss, argnums=(0, 1, 2)),
                               in_axes=(0, 0, 0, None, None)))(c, a, imp, bg, bgi)
    for x, y in zip(per_ray, batched[:3], strict=True):
        np.testing.assert_allclose(x, y, atol=1e-13)


def test_gradient_at_singular_points_is_exact_for_standard():
    # opacities 1, 0 and 1: the derivative of sum(T_i C_i) + 1 - prod(1 - a_j), written
    # as products (no division: exact at the ends), in the opacities and the colours
    c, a, _ = _hard_inputs([1.0, 0.0, 1.0], [0, 0, 0], jnp.float64)

    def by_products(c, a):
        rgb, t = jnp.zeros(3, a.dtype), jnp.ones((), a.dtype)
        for i in range(a.shape[0]):
            rgb, t = rgb + t * c[i], t * (1 - a[i])
        return jnp.sum(rgb) + 1 - t

    got = jax.grad(lambda c, a: jcomposite(c, a).sum(), argnums=(0, 1))(c, a)
    want = jax.grad(by_products, argnums=(0, 1))(c, a)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-14, atol=1e-15)


# Opacities at the ends of [0, 1] with the one-sided derivative that a fit sees there: a
# transparent sample behind a nonempty ray (equal and unequal importances), a transparent
# first sample of the importance of the samples behind it, and an opaque sample that ties
# the next sample's importance (K = I_s exactly; any opacity below 1 puts that sample
# behind). (A transparent sample that would lift K onto a later importance is a point
# where eq. 8 is not differentiable; a transparent first sample of another importance
# gets standard compositing's derivative, which misses the modulation its importance
# brings to the samples behind: see importance_step.)
ONE_SIDED_CASES = {
    "zero_behind_equal": ([0.5, 0.0, 0.5], [0.0, 0.0, 0.0], 1, None),
    "zero_behind_important": ([0.5, 0.0, 0.5], [0.0, 3.0, 1.0], 1, None),
    "zero_behind_unimportant": ([0.5, 0.0, 0.5], [2.0, -3.0, 1.0], 1, None),
    "zero_first_equal": ([0.0, 0.5, 0.5], [0.0, 0.0, 0.0], 0, None),
    "opaque_tie": ([1.0, 0.4, 1.0, 0.6], [2.0, 0.0, 3.0, 3.0], 2, None),
    # opaque ties on an opaque ray (y = a = 1 in eq. 8e), with a background importance
    "opaque_tie_on_opaque": ([1.0, 1.0, 0.0, 0.625, 0.145], [2.0, 0.0, 0.0, 1.0, 2.0], 0, 2.5),
}


@pytest.mark.parametrize("case", sorted(ONE_SIDED_CASES))
def test_gradients_at_alpha_zero_and_one_are_the_one_sided_derivatives(case):
    # The sample's colour is opacity-weighted, C_s = alpha_s c_s, so at alpha_s = 0 the
    # derivative also carries c_s: it was cut to 0 (and the empty ray's came out with the
    # wrong sign) when a transparent sample was skipped.
    alphas, importances, k, bgi = ONE_SIDED_CASES[case]
    bgi = -np.inf if bgi is None else bgi
    n = len(alphas)
    base = np.random.default_rng(30).uniform(0.1, 1.0, (n, 3))
    bg = [0.25, 0.5, 0.75]
    weights = np.asarray([1.0, 2.0, 3.0, 4.0])

    def reference(alpha_k):
        a = np.asarray(alphas, float)
        a[k] = alpha_k
        return float(ref.importance(base * a[:, None], a, importances, bg, bgi) @ weights)

    h = 1e-6 if alphas[k] == 0 else -1e-6                   # into [0, 1]
    expected = (-3 * reference(alphas[k]) + 4 * reference(alphas[k] + h)
                - reference(alphas[k] + 2 * h)) / (2 * h)

    def loss(a_k, grad_fn):
        a = jnp.asarray(alphas).at[k].set(a_k)
        c = jnp.asarray(base) * a[:, None]
        return grad_fn(c, a, jnp.asarray(importances), jnp.asarray(bg), jnp.asarray(bgi))

    for grad_fn in (_loss, _autodiff_loss):                 # composite's adjoint; autodiff
        got = jax.grad(loss)(jnp.asarray(float(alphas[k])), grad_fn)
        np.testing.assert_allclose(got, expected, rtol=1e-6, err_msg=grad_fn.__name__)


# --------------------------------------------------------------------------- transforms


def test_jit_equals_eager_and_vmap_equals_stack():
    c, a, imp = map(jnp.asarray, random_rays(6, 8, seed=14))
    bgi = jnp.linspace(-1.0, 1.0, 6)
    eager = composite(c, a, importance=imp, background_importance=bgi)
    jitted = jax.jit(composite)(c, a, importance=imp, background_importance=bgi)
    np.testing.assert_allclose(jitted, eager, atol=1e-14)
    vmapped = jax.vmap(lambda c, a, i, b: composite(c, a, importance=i, background_importance=b))(
        c, a, imp, bgi)
    stacked = jnp.stack([composite(c[r], a[r], importance=imp[r], background_importance=bgi[r])
                         for r in range(6)])
    np.testing.assert_allclose(vmapped, stacked, atol=1e-14)
    np.testing.assert_allclose(vmapped, eager, atol=1e-14)
    # batch-shape agnostic: (2, 3) rays give the same as 6 rays
    out = composite(c.reshape(2, 3, 8, 3), a.reshape(2, 3, 8), importance=imp.reshape(2, 3, 8),
                    background_importance=bgi.reshape(2, 3))
    np.testing.assert_allclose(out.reshape(6, 4), eager, atol=1e-14)


@pytest.mark.parametrize("wrt", ["colors", "alphas", "importance", "background_importance"])
def test_gradients_match_finite_differences(wrt):
    c, a, imp = map(jnp.asarray, random_rays(4, 6, seed=15, alpha=(0.1, 0.9)))
    bg = jnp.asarray([0.2, 0.4, 0.6])
    bgi = jnp.asarray([0.5, -0.5, 1.0, 0.0])
    args = {"colors": c, "alphas": a, "importance": imp, "background_importance": bgi}
    weights = jnp.asarray([[0.3, 0.5, 0.7, 1.1]])

    def f(x):
        kw = {**args, wrt: x}
        rgba = jcomposite(kw["colors"], kw["alphas"], importance=kw["importance"], background=bg,
                         background_importance=kw["background_importance"])
        return jnp.sum(rgba * weights)

    check_grad_fd(f, args[wrt], rtol=1e-4, n_dirs=4)


def test_standard_gradients_match_finite_differences():
    c, a, _ = map(jnp.asarray, random_rays(3, 5, seed=16))
    check_grad_fd(lambda a: jnp.sum(jcomposite(c, a, background=jnp.ones(3)) ** 2), a)


# --------------------------------------------------------------------------- interface


def test_compositor_interface():
    assert set(COMPOSITORS) == {"standard", "importance"}
    c, a, imp = map(jnp.asarray, random_rays(5, 7, seed=17))
    for name, comp in COMPOSITORS.items():
        state = comp.init((5,), jnp.float64)
        for i in range(7):
            state = comp.step(state, Sample(c[:, i], a[:, i], imp[:, i]))
        rgba = comp.finish(state, jnp.zeros(3), jnp.asarray(-jnp.inf))
        kw = {"importance": imp} if name == "importance" else {}
        np.testing.assert_allclose(rgba, jcomposite(c, a, **kw), atol=1e-14)
    assert isinstance(importance_init((2,), jnp.float32), ImportanceState)


def test_dtype_follows_input():
    c, a, imp = random_rays(2, 3)
    for dtype in (jnp.float32, jnp.float64):
        out = composite(jnp.asarray(c, dtype), jnp.asarray(a, dtype),
                        importance=jnp.asarray(imp, dtype))
        assert out.dtype == dtype
    assert composite(jnp.asarray(c, jnp.float32), jnp.asarray(a, jnp.float32)).dtype == jnp.float32


def test_float32_gradients_where_an_important_sample_takes_over():
    # p = m alpha_{i+1} / alpha' written as 1 - alpha_s (1 - m) / alpha' cancels where m is
    # small; a faint sample's gradients, scaled by 1 / alpha_s, came out O(1) wrong
    a = np.asarray([0.86, 1.0, 0.74, 0.28, 1e-7, 0.74])
    imp = np.asarray([-0.66, -0.66, -3.1, -3.1, 1e4, 1e4])
    c = np.random.default_rng(31).uniform(0, 1, (6, 3)) * a[:, None]
    bg = np.asarray([0.25, 0.5, 0.75])
    want = _jit_grad(*map(jnp.asarray, (c, a, imp, bg, 0.0)))
    for fn in (_jit_grad, _jit_autodiff_grad):
        got = fn(*(jnp.asarray(x, jnp.float32) for x in (c, a, imp, bg, 0.0)))
        for g, w in zip(got[:2], want[:2], strict=True):
            np.testing.assert_allclose(g, w, rtol=2e-3, atol=2e-3)


@pytest.mark.parametrize("faint", [1e-30, 1e-20, 1e-18])
def test_float32_and_float64_take_the_same_faint_samples(faint):
    # behind a red sample, a green one 100 above it in importance takes the colour however
    # faint it is (m = e^-100): both dtypes count opacities below float32's sqrt(tiny),
    # 1.1e-19, as empty (float64 took 1e-30 and 1e-20, float32 could not), and above it
    # both hand the ray to the green sample
    a = np.asarray([0.9, faint])
    c = np.asarray([[1.0, 0, 0], [0, 1.0, 0]]) * a[:, None]
    imp = np.asarray([0.0, 100.0])
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        args = [jnp.asarray(x, dtype) for x in (c, a, imp)]
        out[dtype] = np.asarray(composite(*args[:2], importance=args[2]), np.float64)
    np.testing.assert_allclose(out[jnp.float32], out[jnp.float64], rtol=1e-6, atol=1e-7)
    green = faint > 1.1e-19
    np.testing.assert_allclose(out[jnp.float64], [0, 0.9, 0, 0.9] if green else
                               [0.9, 0, 0, 0.9], atol=1e-7)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_is_composited_in_float32(dtype):
    # float16 has 2^-14 as its smallest normal number: composited in float16, an opacity of
    # 2e-3 made 1 / alpha'^2 overflow and the gradient NaN
    a = jnp.asarray([0.9, 2e-3, 0.5], dtype)
    imp = jnp.asarray([0.0, 1.0, 0.0], dtype)

    def loss(a, imp):
        c = a[:, None] * jnp.eye(3, dtype=a.dtype)
        return composite(c, a, importance=imp).astype(jnp.float32).sum()

    out = composite(a[:, None] * jnp.eye(3, dtype=dtype), a, importance=imp)
    assert out.dtype == dtype
    wide = [x.astype(jnp.float32) for x in (a, imp)]
    np.testing.assert_array_equal(out, composite(wide[0][:, None] * jnp.eye(3), wide[0],
                                                 importance=wide[1]).astype(dtype))
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))  # (eagerly: about 50 small programs)
    got, want = grad(a, imp), grad(*wide)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == dtype and np.all(np.isfinite(np.asarray(g, np.float32)))
        np.testing.assert_allclose(np.asarray(g, np.float32), w, rtol=1e-2, atol=1e-3)


def test_errors():
    c, a, imp = random_rays(2, 3)
    with pytest.raises(ValueError, match="colors"):
        composite(c[..., :2], a)
    with pytest.raises(ValueError, match="importance"):
        composite(c, a, importance=imp[:, :2])
    with pytest.raises(ValueError, match="background_importance"):
        composite(c, a, background_importance=1.0)
    with pytest.raises(ValueError, match="background"):
        composite(c, a, background=np.zeros(4))
    with pytest.raises(ValueError, match="`background` must be >= 0"):  # as colours are
        composite(c, a, background=[-1.0, 0.0, 0.0])
    with pytest.raises(TypeError, match="colors"):
        composite(c.astype(complex), a)
    with pytest.raises(ValueError, match="`alphas` contains NaN or inf"):
        composite(c, np.where(a > 0.5, np.nan, a))
    with pytest.raises(ValueError, match=r"`alphas` must lie in \[0, 1\]"):
        composite(c, a + 1.0)
    # negative light, known or traced (colours above alpha are fine: highlights)
    with pytest.raises(ValueError, match="`colors` must be >= 0"):
        composite(np.where(np.arange(3) == 2, -0.1, c), a)
    with pytest.raises(Exception, match="`colors` must be >= 0"):
        jax.block_until_ready(jax.jit(composite)(-c, a))
    assert np.isfinite(composite(2 * c, a)).all()
    with pytest.raises(ValueError, match="`importance` contains NaN or inf"):
        composite(c, a, importance=np.full_like(imp, np.inf))
    with pytest.raises(ValueError, match="`background_importance` must be finite or -inf"):
        composite(c, a, importance=imp, background_importance=np.inf)
    with pytest.raises(ValueError, match="importance"):
        importance_step(importance_init((), jnp.float32),
                        Sample(jnp.zeros(3, jnp.float32), jnp.zeros((), jnp.float32)))


@pytest.mark.parametrize("importance_aware", [False, True])
def test_traced_bad_samples_are_refused_at_run_time(importance_aware):
    # traced checks ride on the initial transmittance, which values and derivatives both
    # need (not on the samples, which they would copy); traced arrays are checked by float
    # reductions, NaN reported before the range. The gradient w.r.t. the colours alone,
    # and a JVP in them, do not read the colours: tied to the colours, as before, their
    # checks were dead code there, and NaN colours gave finite derivatives silently.
    c, a, imp = random_rays(64, 80, seed=6)

    def f(c, a, imp):
        return composite(c, a, importance=imp if importance_aware else None)

    def grad(c, a, imp):
        return jax.grad(lambda *x: jnp.sum(f(*x)), (0, 1))(c, a, imp)

    def grad_colors(c, a, imp):
        return jax.grad(lambda c: jnp.sum(f(c, a, imp)))(c)

    def jvp_colors(c, a, imp):
        return jax.jvp(lambda c: f(c, a, imp), (c,), (jnp.ones_like(c),))[1]

    bad_alpha = a.copy()
    bad_alpha[3, 5], bad_alpha[7, 9] = np.nan, 2.0
    cases = [((c, bad_alpha, imp), "`alphas` contains NaN or inf"),
             ((c, np.where(a > 0.9, 1.5, a), imp), r"`alphas` must lie in \[0, 1\]"),
             ((np.where(c > 0.9, np.inf, c), a, imp), "`colors` contains NaN or inf"),
             ((np.where(c > 0.9, -1e-30, c), a, imp), "`colors` must be >= 0")]
    if importance_aware:
        cases.append(((c, a, np.where(imp > 3, -np.inf, imp)), "`importance` contains NaN or inf"))
    for args, message in cases:
        for fn in (f, grad, grad_colors, jvp_colors):
            fn = jax.jit(fn)
            with pytest.raises(Exception, match=message):  # (wrapped in a JaxRuntimeError)
                jax.block_until_ready(fn(*args))
    np.testing.assert_allclose(jax.jit(f)(c, a, imp), f(c, a, imp), rtol=1e-14)


def test_standard_composite_in_forward_and_reverse_mode():
    # values come from the in-place loop, derivatives from the scan of the same steps
    c, a, _ = random_rays(3, 11, seed=7, alpha=(0.0, 1.0))
    bg = jnp.asarray([0.2, 0.4, 0.6])

    def f(c, a):
        return composite(c, a, background=bg)

    fwd, rev = jax.jacfwd(f, (0, 1))(c, a), jax.jacrev(f, (0, 1))(c, a)
    for x, y in zip(fwd, rev, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-15)
    value, tangent = jax.jvp(f, (c, a), (np.ones_like(c), np.zeros_like(a)))
    np.testing.assert_allclose(value, f(c, a), rtol=1e-14)
    # colours enter linearly, weighted by the transmittance in front of each sample
    t_front = np.cumprod(np.concatenate([np.ones((3, 1)), 1 - a[:, :-1]], 1), 1)
    np.testing.assert_allclose(tangent[:, :3], np.repeat(t_front.sum(1)[:, None], 3, 1),
                               rtol=1e-13)
    np.testing.assert_array_equal(tangent[:, 3], 0)


@pytest.mark.parametrize("n_samples", [0, 1, 7, 8, 9, 17])
@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_values_read_in_place_equal_the_scan(n_samples, batch):
    # a CPU computes values reading 8 or 4 samples per iteration where they lie, then the rest;
    # reverse mode and other platforms scan the samples moved in front. (The steps index
    # the batch as `...`: a batch of one axis, (2,), took the path of (2, 3).)
    rng = np.random.default_rng(n_samples)
    a = rng.uniform(0, 1, (*batch, n_samples))
    a = np.where(rng.uniform(size=a.shape) < 0.2, rng.integers(0, 2, a.shape), a)
    c = rng.uniform(0, 1, (*batch, n_samples, 3)) * a[..., None]
    imp = rng.normal(0, 3, (*batch, n_samples))
    for step, init, i in ((standard_step, standard_init, None),
                          (importance_step, importance_init, imp)):
        # both chunks and the scan in one program per step (three, and the scan's eager
        # pieces, before)
        @jax.jit
        def both_ways(s, c, a, i, step=step):
            in_place = [_scan_in_place(step, chunk, s, c, a, i) for chunk in (4, 8)]
            return in_place, _scan(step, s, _samples(c, a, i), 1)

        in_place, want = both_ways(init(batch, jnp.float64), c, a, i)
        for got in in_place:
            for x, y in zip(got, want, strict=True):
                np.testing.assert_allclose(x, y, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("importance_aware", [False, True])
def test_jaxpr_has_no_python_loop_over_samples(importance_aware):
    # the program does not grow with the number of samples (a loop, not one step each)
    sizes = []
    for n_samples in (64, 640):
        c, a, imp = random_rays(2, n_samples)
        jaxpr = str(jax.make_jaxpr(lambda c, a, i: composite(
            c, a, importance=i if importance_aware else None))(c, a, imp))
        assert "scan" in jaxpr
        sizes.append(jaxpr.count("\n"))
    assert sizes[0] == sizes[1]


def test_state_is_a_pytree_usable_by_eqx():
    s = importance_init((3,), jnp.float32)
    # empty rays: colour 0, transmittance 1, peak importance and offset 0
    want = ImportanceState(color=jnp.zeros((3, 3), jnp.float32),
                           transmittance=jnp.ones(3, jnp.float32),
                           peak_importance=jnp.zeros(3, jnp.float32),
                           importance_offset=jnp.zeros(3, jnp.float32))
    assert bool(eqx.tree_equal(s, want, typematch=True))
    assert len(jax.tree_util.tree_leaves(s)) == 4
    doubled = jax.tree_util.tree_map(lambda x: 2 * x + 1, s)
    assert isinstance(doubled, ImportanceState)
    np.testing.assert_array_equal(doubled.transmittance, 3.0)
    np.testing.assert_array_equal(doubled.color, 1.0)
    # nothing composited: the background, with alpha 0, whatever its importance
    bg = jnp.asarray([0.25, 0.5, 0.75], jnp.float32)
    for bgi in (-jnp.inf, 0.0, 5.0):
        rgba = importance_finish(s, bg, jnp.asarray(bgi, jnp.float32))
        np.testing.assert_allclose(rgba, np.tile([0.25, 0.5, 0.75, 0.0], (3, 1)), atol=1e-7)


def test_backgrounds_broadcast_to_the_rays():
    c, a, imp = random_rays(6, 5, seed=3)
    c, a, imp = (jnp.asarray(x).reshape(2, 3, *x.shape[1:]) for x in (c, a, imp))
    colour = jnp.array([0.2, 0.3, 0.4])
    for importance, bgi in ((None, None), (imp, jnp.array([[0.5], [-1.0]]))):
        want = composite(c, a, importance=importance,
                         background=jnp.broadcast_to(colour, (2, 3, 3)),
                         background_importance=None if bgi is None
                         else jnp.broadcast_to(bgi, (2, 3)))
        got = composite(c, a, importance=importance, background=colour.reshape(1, 1, 3),
                        background_importance=bgi)
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match=r"`background` must be an RGB colour that broadcasts "
                                         r"to the rays, \(\.\.\., 3\) = \(2, 3, 3\), got \(4, 3\)"):
        composite(c, a, background=jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"`background_importance` must broadcast to the rays"):
        composite(c, a, importance=imp, background_importance=jnp.zeros(2))


def test_an_eager_call_compiles_once():
    from volshade.composition import _composite

    c, a, imp = random_rays(4, 6, seed=4)
    for importance in (None, imp):
        composite(c, a, importance=importance)
        compiled = _composite._cache_size()
        composite(c + 0.0, a, importance=importance)  # new values, same shapes
        assert _composite._cache_size() == compiled


def test_unroll_changes_no_value_or_gradient_and_defaults_by_backend(monkeypatch):
    import volshade.composition as composition

    c, a, imp = random_rays(5, 11, seed=3)

    def loss(c, a, i, unroll):
        rgba = composite(c, a, importance=i, unroll=unroll)
        return jnp.sum(jnp.sin(3 * rgba)), rgba

    # the value and the gradient as one program per unroll
    value_and_grad = jax.jit(jax.value_and_grad(loss, (0, 1), has_aux=True), static_argnums=3)
    for importance in (None, imp):
        (_, want), grads = value_and_grad(c, a, importance, 1)
        for unroll in (None, 4):  # 4 leaves a remainder of 3 of the 11 samples
            (_, value), got_grads = value_and_grad(c, a, importance, unroll)
            np.testing.assert_allclose(value, want, rtol=1e-13, atol=1e-15)
            for got, ref_grad in zip(got_grads, grads, strict=True):
                np.testing.assert_allclose(got, ref_grad, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="`unroll` must be >= 1"):
        composite(c, a, unroll=0)
    with pytest.raises(TypeError, match="`unroll` must be a Python int"):
        composite(c, a, unroll=2.0)
    # the default: 1 on a CPU, 8 on other backends (timed on an H200)
    seen = []
    compiled = composition._composite

    def spy(*args, unroll):
        seen.append(unroll)
        return compiled(*args, unroll=unroll)

    monkeypatch.setattr(composition, "_composite", spy)
    for backend in ("cpu", "gpu"):
        monkeypatch.setattr(jax, "default_backend", lambda backend=backend: backend)
        composite(c, a)
    assert seen == [1, 8]


def test_a_traced_background_is_checked_in_a_gradient_of_the_samples():
    # found by a review: a traced background's check was tied to the background, which a
    # gradient w.r.t. the colours alone does not need, so it was left out and a NaN
    # background gave a gradient without a word
    c, a, imp = random_rays(4, 5, seed=1)
    standard = eqx.filter_jit(jax.grad(lambda c, bg: jnp.sum(composite(c, a, background=bg))))
    assert np.all(np.isfinite(standard(c, jnp.full(3, 0.5))))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`background` contains NaN or inf"):
        standard(c, jnp.asarray([jnp.nan, 0.0, 0.0]))
    aware = eqx.filter_jit(jax.grad(lambda c, bgi: jnp.sum(composite(
        c, a, importance=imp, background=jnp.ones(3), background_importance=bgi))))
    assert np.all(np.isfinite(aware(c, jnp.asarray(0.5))))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`background_importance` must be finite"):
        aware(c, jnp.asarray(jnp.inf))
