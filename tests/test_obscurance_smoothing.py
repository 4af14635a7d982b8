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


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), True, "1"])
def test_smoothing_must_be_a_finite_number_at_least_zero(bad):
    with pytest.raises(ValueError, match="`smoothing` must be a finite number >= 0"):
        vs.ObscuranceParams(smoothing=bad)


def test_smoothing_accepts_numpy_numbers_and_blurs_integer_volumes_as_floats():
    for sigma in (np.float32(1.0), np.int64(1)):
        assert vs.ObscuranceParams(smoothing=sigma).smoothing == 1.0
    ints = jnp.arange(216, dtype=jnp.int32).reshape(6, 6, 6)
    blurred = _gaussian_smooth(ints, 1.0)
    assert jnp.issubdtype(blurred.dtype, jnp.floating)
    np.testing.assert_allclose(blurred, _gaussian_smooth(ints.astype(blurred.dtype), 1.0))
    assert float(jnp.max(blurred)) > 100
