"""Direction sets: unit vectors, the documented counts, and an even cover of the sphere."""

import jax
import numpy as np
import pytest

from volshade import directions as vdirs


def _nearest_angles(points):
    """Angle from every direction to its nearest other one."""
    cos = np.clip(points @ points.T, -1, 1)
    np.fill_diagonal(cos, -1)
    return np.arccos(cos.max(axis=1))


def _ks_uniform(x):
    """Kolmogorov-Smirnov distance of the sample ``x`` from U[-1, 1]."""
    x, n = np.sort(x), len(x)
    cdf, i = (x + 1) / 2, np.arange(1, n + 1)
    return max(np.max(i / n - cdf), np.max(cdf - (i - 1) / n))


def _check_unit_and_distinct(points, n):
    assert points.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1, rtol=0, atol=1e-14)
    assert len(np.unique(np.round(points, 9), axis=0)) == n  # no direction twice


@pytest.mark.parametrize("level, n", [(0, 12), (1, 42), (2, 162)])
def test_icosphere_is_an_even_symmetric_set(level, n):
    points = np.asarray(vdirs.icosphere(level))
    _check_unit_and_distinct(points, n)  # 10 * 4**level + 2
    # every direction's opposite is in the set, so the mean is 0
    gap = np.linalg.norm(points[:, None] + points[None], axis=-1).min(axis=1)
    np.testing.assert_allclose(gap, 0, atol=1e-14)
    np.testing.assert_allclose(points.mean(axis=0), 0, atol=1e-15)
    # nearly equal spacing: measured max/min nearest-neighbour angle 1.0, 1.0, 1.035
    # (a uniform random set of 42 or 162: about 15)
    nearest = _nearest_angles(points)
    assert nearest.max() / nearest.min() < 1.1


def test_icosphere_level_0_is_the_icosahedron():
    # 12 vertices, each with 5 neighbours at the edge angle arccos(1/sqrt(5))
    points = np.asarray(vdirs.icosphere(0))
    cos = points @ points.T
    np.testing.assert_array_equal(np.sum(np.isclose(cos, 1 / np.sqrt(5), atol=1e-14), axis=1), 5)
    np.testing.assert_allclose(_nearest_angles(points), np.arccos(1 / np.sqrt(5)), rtol=1e-14)


@pytest.mark.parametrize("level", [0, 2])
def test_icosphere_points_is_icosphere_in_numpy(level):
    points = vdirs.icosphere_points(level)
    assert isinstance(points, np.ndarray) and points.dtype == np.float64
    assert not points.flags.writeable  # a cached array, shared by every caller
    np.testing.assert_array_equal(points, np.asarray(vdirs.icosphere(level)))


@pytest.mark.parametrize("n", [1, 2, 7, 16])
def test_fibonacci_counts_and_unit_norms(n):
    _check_unit_and_distinct(np.asarray(vdirs.fibonacci(n)), n)


def test_fibonacci_covers_the_sphere_evenly():
    # on a uniform sphere each coordinate is uniform on [-1, 1] (Archimedes); the spiral
    # steps the first one evenly. Measured: KS 5e-4, 6e-3, 6e-3, |mean| 1.3e-5,
    # nearest-neighbour max/min 1.13; a uniform random set: KS ~0.03, |mean| ~0.02, ~20
    n = 1000
    points = np.asarray(vdirs.fibonacci(n))
    _check_unit_and_distinct(points, n)
    assert _ks_uniform(points[:, 0]) == pytest.approx(0.5 / n)
    assert max(_ks_uniform(points[:, k]) for k in (1, 2)) < 0.01
    assert np.linalg.norm(points.mean(axis=0)) < 1e-3
    nearest = _nearest_angles(points)
    assert nearest.max() / nearest.min() < 1.2


def test_random_polar_is_uniform_on_the_sphere():
    # uniform in cos(theta), not theta: every coordinate is U[-1, 1]. With this key the
    # KS distances are 0.011, 0.010, 0.019 (bound 2/sqrt(n) = 0.032, p ~ 1e-3); theta
    # uniform instead gives 0.11 on the polar axis
    n = 4000
    points = np.asarray(vdirs.random_polar(n, key=jax.random.key(0)))
    _check_unit_and_distinct(points, n)
    assert max(_ks_uniform(points[:, k]) for k in range(3)) < 2 / np.sqrt(n)
    assert np.linalg.norm(points.mean(axis=0)) < 0.05  # measured 0.013


def test_random_polar_depends_on_the_key_only():
    same = [np.asarray(vdirs.random_polar(16, key=jax.random.key(3))) for _ in range(2)]
    np.testing.assert_array_equal(same[0], same[1])
    other = np.asarray(vdirs.random_polar(16, key=jax.random.key(4)))
    assert np.all(np.any(other != same[0], axis=1))
    # a legacy uint32 key is a key too
    assert vdirs.random_polar(5, key=jax.random.PRNGKey(0)).shape == (5, 3)


@pytest.mark.parametrize("call, error, match", [
    (lambda: vdirs.icosphere(-1), ValueError, "`level` must be >= 0"),
    (lambda: vdirs.icosphere(5), ValueError, "`level` must be <= 4"),
    (lambda: vdirs.icosphere(1.0), TypeError, "`level` must be a Python int"),
    (lambda: vdirs.icosphere(True), TypeError, "`level` must be a Python int"),
    (lambda: vdirs.icosphere_points(-1), ValueError, "icosphere_points: `level` must be >= 0"),
    (lambda: vdirs.fibonacci(0), ValueError, "`n` must be >= 1"),
    (lambda: vdirs.fibonacci(2.5), TypeError, "`n` must be a Python int"),
    (lambda: vdirs.random_polar(0, key=jax.random.key(0)), ValueError, "`n` must be >= 1"),
    (lambda: vdirs.random_polar("3", key=jax.random.key(0)), TypeError,
     "`n` must be a Python int"),
    (lambda: vdirs.random_polar(3, key=0), TypeError, "`key` must be one jax.random key"),
    (lambda: vdirs.random_polar(3, key=None), TypeError, "`key` must be one jax.random key"),
])
def test_bad_arguments_name_the_argument(call, error, match):
    with pytest.raises(error, match=match):
        call()
