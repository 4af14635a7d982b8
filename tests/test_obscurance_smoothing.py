"""ObscuranceParams(smoothing=sigma): the density is blurred as scikit-image blurs it
before the occluder search, and the result is that of the plain pipeline on it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.filters import gaussian

import volshade as vs
from volshade.directions import icosphere_points
from volshade.obscurance import _gaussian_smooth
from volshade.saliency import opacity_factor

RNG = np.random.default_rng(5)


@pytest.mark.parametrize("sigma", [0.4, 1.0, 2.3])
def test_gaussian_smooth_matches_scikit_image(sigma):
    x = RNG.random((9, 12, 7))
    want = gaussian(x, sigma=sigma, mode="nearest", truncate=4.0, preserve_range=True)
    np.testing.assert_allclose(_gaussian_smooth(jnp.asarray(x), sigma), want, atol=1e-12)
    got32 = jax.jit(lambda v: _gaussian_smooth(v, sigma))(jnp.asarray(x, jnp.float32))
    assert got32.dtype == jnp.float32
    np.testing.assert_allclose(got32, want, atol=1e-6)


def test_smoothing_blurs_the_density_before_the_search():
    vol = vs.data.phantom("shells", shape=14)
    tf = vs.transfer.preset("shells")
    params = vs.ObscuranceParams(d_max=6.0, level=0, low=0.1, high=0.9, smoothing=1.0)
    # (the blur itself is checked against scikit-image above; here the same blur feeds
    # the search, whose strict comparisons would amplify round-off between two blurs)
    smooth = _gaussian_smooth(tf.opacity(vol), 1.0)
    obs = vs.obscurance(smooth, directions=icosphere_points(0), d_max=6.0, rho="sqrt")
    np.testing.assert_allclose(params(vol, tf), vs.threshold(obs, 0.1, 0.9), atol=1e-9)
    plain = vs.ObscuranceParams(d_max=6.0, level=0, low=0.1, high=0.9)(vol, tf)
    assert float(jnp.max(jnp.abs(plain - params(vol, tf)))) > 0.05


def test_saliency_modulation_smooths_the_same_way():
    vol = vs.data.phantom("shells", shape=14)
    tf = vs.transfer.preset("shells")
    params = vs.SaliencyModulation(d_max=6.0, level=0, size=3, smoothing=1.0)
    obs = vs.obscurance(_gaussian_smooth(tf.opacity(vol), 1.0), directions=icosphere_points(0),
                        d_max=6.0, rho="sqrt")
    want = opacity_factor(vs.saliency(obs, size=3), threshold=0.2)
    np.testing.assert_allclose(params(vol, tf), want, atol=1e-9)
    plain = vs.SaliencyModulation(d_max=6.0, level=0, size=3)(vol, tf)
    assert float(jnp.max(jnp.abs(plain - want))) > 0.05


@pytest.mark.parametrize("module", [vs.ObscuranceParams, vs.SaliencyModulation])
@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), True, "1"])
def test_smoothing_must_be_a_finite_number_at_least_zero(bad, module):
    # a number out of range is a bad value; a bool or a string, not a number at all
    error, what = ((ValueError, "a finite number >= 0") if isinstance(bad, float)
                   else (TypeError, "a number"))
    with pytest.raises(error, match=f"{module.__name__}: `smoothing` must be {what}"):
        module(smoothing=bad)


def test_smoothing_accepts_numpy_numbers_and_blurs_integer_volumes_as_floats():
    for sigma in (np.float32(1.0), np.int64(1), jnp.asarray(1.0), np.asarray(1)):
        kept = vs.ObscuranceParams(smoothing=sigma).smoothing
        assert type(kept) is float and kept == 1.0
    ints = jnp.arange(216, dtype=jnp.int32).reshape(6, 6, 6)
    blurred = _gaussian_smooth(ints, 1.0)
    assert jnp.issubdtype(blurred.dtype, jnp.floating)
    np.testing.assert_allclose(blurred, _gaussian_smooth(ints.astype(blurred.dtype), 1.0))
    assert float(jnp.max(blurred)) > 100


def _corner_transfer(empty_rgb):
    """The corner phantom with ``empty_rgb`` where the opacity is 0: the air and the wall
    of value 0.5 (its others, 0.75 and 1, are opaque)."""
    return vs.TransferFunction.from_points([(0.0, *empty_rgb, 0.0), (0.6, *empty_rgb, 0.0),
                                            (0.7, 0.1, 0.8, 0.1, 1.0), (1.0, 1, 1, 1, 1.0)])


@pytest.mark.parametrize("kind", [dict(smoothing=1.0), dict(density="intensity"),
                                  dict(smoothing=1.0, density="intensity")])
def test_bleeding_ignores_the_colour_of_what_has_no_opacity(kind):
    # smoothing, or intensity as the density, lets voxels without opacity occlude; the
    # colour a transfer function gives them is invisible and must not tint
    vol = vs.data.phantom("corner", shape=14)
    params = vs.ObscuranceParams(d_max=6.0, level=0, color_bleeding=True, **kind)
    black, white = (params(vol, _corner_transfer(c)) for c in ((0, 0, 0), (1, 1, 1)))
    np.testing.assert_array_equal(black, white)
    # they do occlude: the same pipeline with their black reflectance is darker
    density = _corner_transfer((0, 0, 0)).opacity(vol) if "density" not in kind else vol
    if "smoothing" in kind:
        density = _gaussian_smooth(density, 1.0)
    dark = vs.obscurance(density, directions=icosphere_points(0), d_max=6.0,
                         colors=_corner_transfer((0, 0, 0)).color(vol))
    assert float(jnp.max(black - dark)) > 0.05


def test_smoothed_bleeding_takes_the_opacity_weighted_mean_colour():
    vol = vs.data.phantom("corner", shape=14)
    tf = vs.transfer.preset("corner")
    params = vs.ObscuranceParams(d_max=6.0, level=0, color_bleeding=True, smoothing=1.0)
    alpha, colors = np.asarray(tf.opacity(vol)), np.asarray(tf.color(vol))
    blur = lambda x: gaussian(x, sigma=1.0, mode="nearest", truncate=4.0,  # noqa: E731
                              preserve_range=True)
    weight = blur(alpha)
    mean = np.stack([blur(alpha * colors[..., c]) for c in range(3)], axis=-1)
    reflect = np.where(weight[..., None] > 0, mean / np.where(weight > 0, weight, 1)[..., None],
                       1.0)
    # (the same blur of the density feeds the search, as above)
    want = vs.obscurance(_gaussian_smooth(tf.opacity(vol), 1.0),
                         directions=icosphere_points(0), d_max=6.0, colors=jnp.asarray(reflect))
    np.testing.assert_allclose(params(vol, tf), want, atol=1e-6)  # (float32 phantom)
    # the gradient reaches the wall colours and opacities through the weighted mean
    grads = jax.grad(lambda t: jnp.sum(params(vol, t)))(tf)
    assert np.all(np.isfinite(grads.colors)) and np.any(grads.colors != 0)
    assert np.all(np.isfinite(grads.opacities)) and np.any(grads.opacities != 0)


def test_intensity_density_without_colours_needs_no_classification():
    # a volume beyond the transfer function's control points: only the colours and the
    # opacity density would classify it
    vol = 2 * vs.data.phantom("shells", shape=10)
    params = vs.ObscuranceParams(d_max=4.0, level=0, density="intensity")
    np.testing.assert_array_equal(params(vol, vs.transfer.preset("shells")),
                                  vs.obscurance(vol, directions=icosphere_points(0), d_max=4.0))
    with pytest.raises(ValueError, match="outside the transfer function's control points"):
        vs.ObscuranceParams(d_max=4.0, level=0, density="intensity", color_bleeding=True)(
            vol, vs.transfer.preset("shells"))


@pytest.mark.parametrize("module", ["obscurance", "saliency"])
def test_smoothing_wider_than_the_volume_is_refused(module):
    # `volshade render --smoothing 1e9` ran out of memory (a kernel of 8e9 taps) with a
    # message that did not name the option; a sigma beyond the longest side is refused
    vol = jnp.zeros((6, 8, 5))
    tf = vs.transfer.preset("grey")
    make = (lambda s: vs.ObscuranceParams(d_max=2.0, level=0, smoothing=s)) if module == \
        "obscurance" else (lambda s: vs.SaliencyModulation(d_max=2.0, level=0, smoothing=s))
    where = "ObscuranceParams" if module == "obscurance" else "SaliencyModulation"
    with pytest.raises(ValueError, match=rf"volshade.{where}: `smoothing` \(1e\+09 voxels\) "
                                         rf"must be at most the volume's longest side, 8"):
        make(1e9)(vol, tf)
    assert make(8.0)(vol, tf).shape[:3] == vol.shape
