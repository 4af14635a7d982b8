"""Fitting with optimistix: parameters recovered from targets made with known values.

LAO's gradient is a custom VJP (reverse mode only), so least-squares solvers get
``options=dict(jac="bwd")``: Jacobian products by reverse mode.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import volshade as vs

pytestmark = pytest.mark.slow

_BWD = {"jac": "bwd"}  # LAO has no forward-mode derivative


def test_levenberg_marquardt_recovers_the_lao_radius():
    rng = np.random.default_rng(0)
    alpha = jnp.zeros((12, 12, 12)).at[4:8, 3:9, 5:8].set(
        jnp.asarray(rng.uniform(0.2, 0.9, (4, 6, 3))))
    kw = dict(directions=vs.directions.fibonacci(6), samples=6, offset=0.5, max_radius=5.0)
    target = vs.lao(alpha, radius=3.3, **kw)

    def residuals(radius, args):
        return vs.lao(alpha, radius=radius, **kw) - target

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(residuals, solver, jnp.asarray(2.5), max_steps=60, options=_BWD)
    np.testing.assert_allclose(float(sol.value), 3.3, atol=1e-6)


def test_levenberg_marquardt_recovers_a_scene_parameter_from_an_image():
    # the LAO radius of a rendered scene, from the image alone
    vol = vs.data.phantom("shells", shape=12).astype(jnp.float64)
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(10, 10))
    scene = vs.Scene(volume=vol, transfer=vs.transfer.preset("shells"), shading="phong",
                     ambient="lao", lao=vs.LocalAmbientOcclusion(
                         2.0, offset=0.5, directions=6, samples=6, max_radius=5.0))

    def with_radius(radius):
        return eqx.tree_at(lambda s: s.lao.radius, scene, radius)

    target = vs.render(with_radius(jnp.asarray(3.0)), cam)

    def residuals(radius, args):
        return vs.render(with_radius(radius), cam) - target

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(residuals, solver, jnp.asarray(2.2), max_steps=60, options=_BWD)
    np.testing.assert_allclose(float(sol.value), 3.0, atol=1e-6)
