"""Tests of volshade.clip: exact signed distances, the clipped and affected masks."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

import volshade as vs

RNG = np.random.default_rng(11)
ROTATION = np.linalg.qr(RNG.normal(size=(3, 3)))[0]
SHAPES = {
    "sphere": vs.SphereClip(center=(7.0, 8.5, 6.2), radius=4.3),
    "box": vs.BoxClip(center=(8.0, 7.0, 9.0), half_size=(2.5, 4.0, 1.5), rotation=ROTATION),
    "torus": vs.TorusClip(center=(8.0, 8.0, 8.0), major=4.5, minor=1.5, rotation=ROTATION),
    "half-space": vs.HalfSpaceClip(center=(8.0, 8.0, 8.0), rotation=ROTATION),
}


def _solid(name, points, clip=None):
    """Whether ``points`` (..., 3) lie inside the shape (``clip``, by default the one in
    ``SHAPES``), by its definition."""
    clip = SHAPES[name] if clip is None else clip
    local = (points - np.asarray(clip.center)) @ np.asarray(clip.rotation)
    if name == "sphere":
        return np.linalg.norm(local, axis=-1) <= float(clip.radius)
    if name == "box":
        return np.all(np.abs(local) <= np.asarray(clip.half_size), axis=-1)
    if name == "torus":
        ring = np.linalg.norm(local[..., 1:], axis=-1) - float(clip.major)
        return ring ** 2 + local[..., 0] ** 2 <= float(clip.minor) ** 2
    return local[..., 0] >= 0


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_signed_distance_is_the_distance_to_the_solid(name):
    # brute force: the distance from each probe to a fine grid of points of the solid
    # (outside) or of its complement (inside), within the grid's resolution
    step = 0.2
    axes = [np.arange(-1.0, 17.0 + step, step)] * 3
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = _solid(name, grid)
    probes = RNG.uniform(2.0, 14.0, (40, 3))
    phi = np.asarray(SHAPES[name].signed_distance(jnp.asarray(probes)))
    for x, value in zip(probes, phi, strict=True):
        other = grid[~inside] if _solid(name, x) else grid[inside]
        brute = np.min(np.linalg.norm(other - x, axis=-1))
        assert np.sign(value) == (-1 if _solid(name, x) else 1) or abs(value) < 1e-9
        assert abs(abs(value) - brute) <= step * np.sqrt(3), (name, x, value, brute)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_affected_voxels_hold_every_voxel_within_reach_of_a_clipped_one(name):
    shape, radius = (17, 16, 18), 3.3
    clipped = np.asarray(vs.clip_mask(shape, SHAPES[name]))
    assert 0 < clipped.sum() < clipped.size
    affected = np.asarray(vs.affected_mask(shape, SHAPES[name], radius=radius))
    assert np.all(affected[clipped])
    distance = ndimage.distance_transform_edt(~clipped)  # to the nearest clipped voxel
    # LAO at x reads voxels less than R + sqrt(3) away; those x must all be affected
    assert np.all(affected[distance < radius + np.sqrt(3)])
    # and the bound is not wastefully loose: few affected voxels are much farther
    assert np.mean(distance[affected] > radius + np.sqrt(3) + 1.5) < 0.05


def test_clip_opacity_and_mask_by_hand():
    mask = vs.clip_mask((9, 9, 9), vs.SphereClip(center=(4.0, 4.0, 4.0), radius=1.0))
    assert int(mask.sum()) == 7 and bool(mask[4, 4, 5]) and not bool(mask[4, 5, 5])
    alpha = jnp.full((9, 9, 9), 0.5, jnp.float32)
    out = vs.clip_opacity(alpha, vs.HalfSpaceClip(center=(6.0, 0.0, 0.0)))
    assert out.dtype == jnp.float32
    assert np.all(np.asarray(out[6:]) == 0) and np.all(np.asarray(out[:6]) == 0.5)
    flipped = vs.HalfSpaceClip(center=(6.0, 0.0, 0.0), rotation=-np.eye(3))
    assert np.all(np.asarray(vs.clip_opacity(alpha, flipped)[:7]) == 0)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_moving_a_clip_does_not_recompile_and_vmaps(name):
    traces = []

    def moved(centre, rotation):
        return eqx.tree_at(lambda c: (c.center, c.rotation), SHAPES[name], (centre, rotation))

    @jax.jit
    def removed(centre, rotation):
        traces.append(1)
        return vs.clip_mask((12, 12, 12), moved(centre, rotation))

    centres = np.asarray([[3.0, 3.0, 3.0], [6.0, 7.0, 5.0], [0.0, 0.0, 0.0]])
    rotations = np.stack([ROTATION, ROTATION.T, ROTATION @ ROTATION])
    grid = np.stack(np.meshgrid(*[np.arange(12.0)] * 3, indexing="ij"), -1)
    eager = []
    for c, r in zip(centres, rotations, strict=True):
        eager.append(np.asarray(vs.clip_mask((12, 12, 12), moved(c, r))))
        np.testing.assert_array_equal(eager[-1], _solid(name, grid, moved(c, r)))
    assert len({m.tobytes() for m in eager}) == 3 and 0 < eager[0].sum() < eager[0].size
    for c, r, want in zip(centres, rotations, eager, strict=True):
        np.testing.assert_array_equal(np.asarray(removed(c, r)), want)
    assert len(traces) == 1
    batched = jax.vmap(removed)(centres, rotations)
    for got, want in zip(batched, eager, strict=True):
        np.testing.assert_array_equal(np.asarray(got), want)


def _medial_margin(name, points):
    """A lower bound on the distance (voxels) from ``points`` to the shape's medial
    axis, where the nearest surface point is not unique and phi has a kink."""
    clip = SHAPES[name]
    local = (points - np.asarray(clip.center)) @ np.asarray(clip.rotation)
    if name == "sphere":  # the centre
        return np.linalg.norm(local, axis=-1)
    if name == "box":  # inside: where two faces are the nearest (half the gap bounds it)
        half = np.asarray(clip.half_size)
        faces = np.sort(np.concatenate([half - local, half + local], axis=-1), axis=-1)
        outside = np.any(np.abs(local) > half, axis=-1)
        return np.where(outside, np.inf, (faces[..., 1] - faces[..., 0]) / 2)
    if name == "torus":  # the tube's centre line, and the torus's axis
        rho = np.linalg.norm(local[..., 1:], axis=-1)
        return np.minimum(np.hypot(local[..., 0], rho - float(clip.major)), rho)
    return np.full(points.shape[:-1], np.inf)  # a half-space has none


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_signed_distance_gradient_is_a_unit_vector_to_the_nearest_surface_point(name):
    # off the medial axis phi is differentiable, its gradient has norm 1 (eikonal), and
    # a step of -phi along it lands on the surface: phi is the distance, not only a
    # 1-Lipschitz function with the right zero set
    clip = SHAPES[name]
    pool = np.random.default_rng(4).uniform(1.0, 15.0, (4000, 3))
    pool = pool[_medial_margin(name, pool) > 0.5]
    inside = _solid(name, pool)
    probes = jnp.asarray(np.concatenate([pool[inside][:20], pool[~inside][:20]]))
    assert probes.shape[0] == 40
    h = 1e-6

    @jax.jit  # one compiled program, not one per operation (twice as fast)
    def measured(p):
        phi, grad = clip.signed_distance(p), jax.vmap(jax.grad(clip.signed_distance))(p)
        fd = jnp.stack([(clip.signed_distance(p + e) - clip.signed_distance(p - e)) / (2 * h)
                        for e in h * jnp.eye(3)[:, None]], -1)
        return grad, fd, clip.signed_distance(p - phi[:, None] * grad)

    grad, fd, at_nearest = (np.asarray(x) for x in measured(probes))
    np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(grad, axis=-1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(at_nearest, 0.0, atol=1e-12)
    # at the centre (the medial axis of a sphere, and on a torus's axis) it stays finite
    g = jax.grad(clip.signed_distance)(jnp.asarray(clip.center))
    assert np.all(np.isfinite(np.asarray(g)))


def test_bad_clips_raise_clear_errors():
    with pytest.raises(ValueError, match="`radius` must be finite and > 0"):
        vs.SphereClip(center=(1.0, 2.0, 3.0), radius=0.0)
    with pytest.raises(ValueError, match="`center` must be 3 numbers"):
        vs.SphereClip(center=(1.0, 2.0), radius=1.0)
    for centre in ((np.nan, 0.0, 0.0), (0.0, np.inf, 0.0)):
        with pytest.raises(ValueError, match="`center` must be finite"):
            vs.HalfSpaceClip(center=centre)
    with pytest.raises(ValueError, match="orthonormal"):
        vs.BoxClip(center=(1.0, 2.0, 3.0), half_size=1.0, rotation=2 * np.eye(3))
    with pytest.raises(ValueError, match="`rotation` must be finite"):  # not "orthonormal"
        vs.BoxClip(center=(1.0, 2.0, 3.0), half_size=1.0, rotation=np.eye(3) * [np.nan, 1, 1])
    with pytest.raises(ValueError, match=r"`rotation` must be a 3x3"):
        vs.TorusClip(center=(1.0, 2.0, 3.0), major=2.0, minor=1.0, rotation=np.eye(2))
    with pytest.raises(ValueError, match="`half_size` must be finite and > 0"):
        vs.BoxClip(center=(1.0, 2.0, 3.0), half_size=(1.0, -1.0, 1.0))
    for shape in ((4, 4), (True, True, True)):
        with pytest.raises(ValueError, match=r"`shape` must be 3 positive ints"):
            vs.clip_mask(shape, SHAPES["sphere"])
    # found by a review: JAX scalars holding positive ints were refused as if they did not
    with pytest.raises(TypeError, match=r"`shape` must be Python ints .* got JAX arrays"):
        vs.affected_mask(tuple(jnp.array((4, 4, 4))), SHAPES["sphere"], radius=2.0)
    with pytest.raises(TypeError, match="`clip` must be a volshade clip shape"):
        vs.clip_opacity(jnp.ones((4, 4, 4)), "sphere")
    holed = jnp.ones((4, 4, 4)).at[0, 0, 0].set(jnp.nan)
    with pytest.raises(ValueError, match="NaN or inf"):  # eager: at once
        vs.clip_opacity(holed, SHAPES["sphere"])
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):  # traced: at run time
        eqx.filter_jit(vs.clip_opacity)(holed, SHAPES["sphere"])


def test_half_precision_clips_are_measured_in_float32():
    # bfloat16 cannot even count the voxels of a 300-voxel axis; the distances are
    # computed in float32 at least, so the masks are those of the float32 clip
    exact = vs.SphereClip(center=jnp.asarray([3.0, 150.0, 4.0], jnp.float32), radius=2.5)
    half = vs.SphereClip(center=jnp.asarray([3.0, 150.0, 4.0], jnp.bfloat16),
                         radius=jnp.asarray(2.5, jnp.bfloat16))
    for fn in (lambda c: vs.clip_mask((8, 300, 8), c),
               lambda c: vs.affected_mask((8, 300, 8), c, radius=2.0)):
        np.testing.assert_array_equal(np.asarray(fn(half)), np.asarray(fn(exact)))


def test_half_precision_leaves_keep_a_python_size_and_measure_points_in_float32():
    # found by a review: beside float16 leaves a Python-number radius was rounded to
    # float16 before its check and its use (1.9996 -> 2.0: 33 voxels removed, not 27;
    # 70000 -> inf, refused as not finite), and signed_distance of float16 points
    # computed in float16 (0.0 at a voxel the mask keeps)
    f16 = jnp.float16
    half = vs.SphereClip(center=jnp.full(3, 4, f16), radius=1.9996,
                         rotation=jnp.eye(3, dtype=f16))
    exact = vs.SphereClip(center=jnp.full(3, 4.0, jnp.float32), radius=1.9996)
    np.testing.assert_array_equal(np.asarray(vs.clip_mask((9, 9, 9), half)),
                                  np.asarray(vs.clip_mask((9, 9, 9), exact)))
    assert int(vs.clip_mask((9, 9, 9), half).sum()) == 27
    far = vs.SphereClip(center=jnp.full(3, 4, f16), radius=70000.0,
                        rotation=jnp.eye(3, dtype=f16))
    assert bool(vs.clip_mask((3, 3, 3), far).all())
    odd = vs.SphereClip(center=jnp.asarray([2.197, 2.87, 6.695], f16),
                        radius=jnp.asarray(3.588, f16), rotation=jnp.eye(3, dtype=f16))
    phi = odd.signed_distance(jnp.asarray([5.0, 5.0, 6.0], f16))
    assert phi.dtype == jnp.float32
    assert (float(phi) <= 0) == bool(vs.clip_mask((8, 8, 8), odd)[5, 5, 6])


def test_leaves_that_are_not_floats_are_refused():
    # found by a review: a bool beside numbers passed as 1, and leaves of another dtype
    # set with eqx.tree_at were never checked (a bool radius ran as 1, an integer
    # rotation failed deep inside)
    with pytest.raises(TypeError, match="`center` must be a real number"):
        vs.SphereClip(center=(True, 4.0, 4.0), radius=2.0)
    with pytest.raises(TypeError, match="`half_size` must be a real number"):
        vs.BoxClip(center=(4.0, 4.0, 4.0), half_size=(True, 2.0, 2.0))
    sphere = vs.SphereClip(center=(4.0, 4.0, 4.0), radius=2.0)
    plane = vs.HalfSpaceClip(center=(4.0, 0.0, 0.0))
    for clip, name in ((eqx.tree_at(lambda c: c.radius, sphere, jnp.asarray(True)), "radius"),
                       (eqx.tree_at(lambda c: c.rotation, plane, jnp.eye(3, dtype=jnp.int32)),
                        "rotation")):
        for use in (lambda c: vs.clip_mask((8, 8, 8), c),
                    lambda c: vs.affected_mask((8, 8, 8), c, radius=2.0),
                    lambda c: c.signed_distance(jnp.zeros(3))):
            with pytest.raises(TypeError, match=f"`{name}` must hold floating-point numbers"):
                use(clip)


def test_affected_mask_covers_the_rounding_of_large_float32_clips():
    # a torus of major radius 1e7 whose tube passes through a small volume: float32
    # rounds its phi by up to half a voxel there (the ulp of 1e7 is 1), so a margin
    # scaled by the volume and the centre alone left voxels within reach unmarked
    clip = vs.TorusClip(center=jnp.asarray([8.0, 8.0, 8.0], jnp.float32),
                        major=jnp.asarray(1e7, jnp.float32),
                        minor=jnp.asarray(1e7 - 10, jnp.float32),
                        rotation=jnp.eye(3, dtype=jnp.float32))
    shape = (16, 16, 16)
    assert clip.signed_distance(jnp.zeros(3, jnp.float32)).dtype == jnp.float32
    local = np.stack(np.meshgrid(*map(np.arange, shape), indexing="ij"), -1) - 8.0
    ring = np.hypot(local[..., 1], local[..., 2]) - float(clip.major)
    phi = np.hypot(local[..., 0], ring) - float(clip.minor)  # float64: exact to 1e-9
    for radius in (3.0, 4.0, 5.0):
        affected = np.asarray(vs.affected_mask(shape, clip, radius=radius))
        within = phi < radius + np.sqrt(3)
        assert 0 < within.sum() < within.size
        assert np.all(affected[within]), radius


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_signed_distance_refuses_bad_leaves_and_keeps_nan_points_nan(name):
    # found by a review: the sphere's and torus's square root took a NaN coordinate to
    # a finite "inside" distance, the public method checked no leaf, and a centre of the
    # wrong shape set with tree_at broadcast against the grid
    clip = SHAPES[name]
    phi = clip.signed_distance(jnp.asarray([[jnp.nan, 8.0, 8.0], [8.0, 8.0, 8.0]]))
    assert np.isnan(phi[0]) and np.isfinite(phi[1])
    with pytest.raises(ValueError, match="finite"):
        eqx.tree_at(lambda c: c.center, clip, jnp.full(3, jnp.nan)).signed_distance(
            jnp.zeros(3))
    with pytest.raises(Exception, match="finite"):
        jax.block_until_ready(eqx.filter_jit(lambda c, p: c.signed_distance(p))(
            eqx.tree_at(lambda c: c.center, clip, jnp.full(3, jnp.nan)), jnp.zeros(3)))
    with pytest.raises(ValueError, match=r"`points` must have shape \(\.\.\., 3\)"):
        clip.signed_distance(jnp.zeros((4, 2)))
    short = eqx.tree_at(lambda c: c.center, clip, jnp.asarray([2.0]))
    for use in (lambda c: vs.clip_mask((5, 5, 5), c), lambda c: c.signed_distance(jnp.zeros(3))):
        with pytest.raises(ValueError, match=r"`center` must be 3 numbers .* got shape \(1,\)"):
            use(short)


@pytest.mark.parametrize("make", [
    lambda dt, r: vs.SphereClip(center=jnp.zeros(3, dt), radius=jnp.asarray(2.0, dt),
                                rotation=r),
    lambda dt, r: vs.BoxClip(center=jnp.zeros(3, dt), half_size=jnp.asarray(2.0, dt),
                             rotation=r),
    lambda dt, r: vs.TorusClip(center=jnp.zeros(3, dt), major=jnp.asarray(3.0, dt),
                               minor=jnp.asarray(1.0, dt), rotation=r),
    lambda dt, r: vs.HalfSpaceClip(center=jnp.zeros(3, dt), rotation=r),
])
def test_every_clip_shape_keeps_its_leaves_dtype(make):
    # a float32 clip stays float32 under x64 (the box's half-sizes were cast to float64)
    clip = make(jnp.float32, jnp.eye(3, dtype=jnp.float32))
    assert {leaf.dtype for leaf in jax.tree.leaves(clip)} == {jnp.dtype(jnp.float32)}


def test_affected_mask_compiles_once_for_a_radius_given_as_a_number_or_an_array():
    # found by a review: a Python-number radius reached the compiled function weakly
    # typed, and the same radius as an array compiled it again
    import sys

    reach = sys.modules["volshade.clip"]._compiled_reach
    clip = vs.SphereClip(center=(4.0, 4.0, 4.0), radius=2.0)
    first = vs.affected_mask((8, 8, 8), clip, radius=2.0)
    size = reach._cached._cache_size()
    second = vs.affected_mask((8, 8, 8), clip, radius=jnp.asarray(2.0, clip.radius.dtype))
    assert reach._cached._cache_size() == size
    np.testing.assert_array_equal(np.asarray(first), np.asarray(second))
