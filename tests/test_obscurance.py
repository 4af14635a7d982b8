"""Obscurances (Ruiz et al. 2008): exact agreement with a per-voxel march, corner phantom
properties, display controls, jit / vmap / grad and input errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_obscurance as ref
from helpers import check_grad_fd, temp_bytes

import volshade as vs
from volshade.directions import fibonacci, icosphere, icosphere_points
from volshade.obscurance import (
    RHO_FUNCTIONS,
    ObscuranceParams,
    _obscurance,
    obscurance,
    obscurance_shading,
    occluder_distances,
    threshold,
)
from volshade.saliency import opacity_factor

RHOS = tuple(RHO_FUNCTIONS)
DIRS12 = np.asarray(icosphere(0))
DIRS42 = np.asarray(icosphere(1))


def random_volume(shape, seed, *, levels=None):
    rng = np.random.default_rng(seed)
    if levels:  # many ties: exercises "strictly greater"
        return rng.integers(0, levels, size=shape).astype(np.float64)
    return rng.random(shape)


def corner(n, thickness=2):
    """Corner phantom: opacity 1 on three walls (d: white, h: green, w: blue), 0 elsewhere."""
    alpha = np.zeros((n, n, n))
    colors = np.zeros((n, n, n, 3))
    for axis, rgb in ((0, (1.0, 1.0, 1.0)), (1, (0.0, 1.0, 0.0)), (2, (0.0, 0.0, 1.0))):
        idx = [slice(None)] * 3
        idx[axis] = slice(0, thickness)
        alpha[tuple(idx)] = 1.0
        colors[tuple(idx)] = rgb
    return jnp.asarray(alpha), jnp.asarray(colors)


# ------------------------------------------------------------------ agreement with reference


def assert_same_distances(fast, want):
    """Same occluders (inf pattern, step counts); lengths equal up to the last bit of |s|."""
    np.testing.assert_array_equal(np.isinf(fast), np.isinf(want))
    np.testing.assert_allclose(fast, want, rtol=1e-15, atol=0)


@pytest.mark.parametrize(("shape", "seed", "levels", "dirs"), [
    ((12, 12, 12), 0, None, DIRS12), ((12, 12, 12), 0, None, DIRS42),
    ((9, 13, 11), 1, 4, DIRS42), ((16, 7, 10), 2, 2, DIRS12)])
def test_distances_match_reference_exactly(shape, seed, levels, dirs):
    vol = random_volume(shape, seed, levels=levels)
    fast = np.asarray(occluder_distances(jnp.asarray(vol), directions=dirs))
    assert_same_distances(fast, ref.occluder_distances(vol, dirs))


def test_distances_arbitrary_directions_and_axis_aligned():
    vol = random_volume((10, 12, 9), 3, levels=3)
    dirs = np.concatenate([np.asarray(fibonacci(17)), np.eye(3), -np.eye(3),
                           [[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0], [0.3, -0.9, 0.0]]])
    fast = np.asarray(occluder_distances(jnp.asarray(vol), directions=dirs))
    assert_same_distances(fast, ref.occluder_distances(vol, dirs))


def test_distances_match_reference_for_42_directions_and_an_oblique_one():
    vol = random_volume((9, 12, 7), 9, levels=4)
    dirs = np.concatenate([np.asarray(DIRS42), [[0.2, -1.0, 0.7]]])
    fast = occluder_distances(jnp.asarray(vol), directions=dirs)
    assert_same_distances(np.asarray(fast), ref.occluder_distances(vol, dirs))


@pytest.mark.parametrize("shape", [(11, 2, 3), (3, 17, 2), (1, 9, 13), (13, 1, 1)])
def test_distances_match_reference_in_thin_volumes(shape):
    # thin axes make a cyclic column wrap onto many digital lines
    vol = random_volume(shape, 8, levels=3)
    dirs = np.concatenate([np.asarray(DIRS42), np.asarray(fibonacci(9)), [[1.0, 1.0, -1.0]]])
    fast = np.asarray(occluder_distances(jnp.asarray(vol), directions=dirs))
    assert_same_distances(fast, ref.occluder_distances(vol, dirs))


@pytest.mark.parametrize(("rho", "dirs"), [(rho, DIRS42) for rho in RHOS] + [("sqrt", DIRS12)])
def test_obscurance_matches_reference(rho, dirs):
    vol = random_volume((12, 12, 12), 4)
    got = obscurance(jnp.asarray(vol), directions=dirs, d_max=5.5, rho=rho)
    want = ref.obscurance(vol, dirs, 5.5, rho)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-13)


@pytest.mark.parametrize("rho", ["linear", "sqrt"])
def test_colour_bleeding_matches_per_voxel_reference(rho):
    vol = random_volume((6, 7, 5), 5, levels=3)
    colors = np.random.default_rng(6).random((6, 7, 5, 3))
    amb = (0.9, 0.8, 0.7)
    got = obscurance(jnp.asarray(vol), directions=DIRS12, d_max=3.0, rho=rho,
                     colors=jnp.asarray(colors), ambient=amb)
    want = ref.obscurance(vol, DIRS12, 3.0, rho, colors=colors, ambient=amb)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-13)


def test_per_voxel_reference_agrees_with_vectorised_reference():
    vol = random_volume((5, 6, 4), 7, levels=3)
    dists = ref.occluder_distances(vol, DIRS12)
    for n in range(len(DIRS12)):
        q = ref.occluder_index(vol, DIRS12, n)
        np.testing.assert_array_equal(q[..., 0] >= 0, np.isfinite(dists[n]))


# ------------------------------------------------------------------ analytic cases


@pytest.mark.parametrize("rho", RHOS)
def test_no_occluder_gives_exactly_one(rho):
    # Same shapes and options as the reference tests, so the compiled programs are reused.
    vol = jnp.full((12, 12, 12), 0.3)  # ties never occlude
    out = obscurance(vol, directions=DIRS42, d_max=4.0, rho=rho)
    assert bool(jnp.all(out == 1.0))
    if rho in ("linear", "sqrt"):
        rgb = obscurance(jnp.full((6, 7, 5), 0.3), directions=DIRS12, d_max=4.0, rho=rho,
                         colors=jnp.zeros((6, 7, 5, 3)))
        assert bool(jnp.all(rgb == 1.0))


def test_single_direction_floor_analytic():
    vol = jnp.zeros((10, 4, 4)).at[8:].set(1.0)
    dirs = np.array([[1.0, 0.0, 0.0]])
    out = obscurance(vol, directions=dirs, d_max=6.0, rho="linear")
    d = np.arange(10)
    want = np.where(8 - d <= 6, (8 - d) / 6.0, 1.0)
    want[8:] = 1.0  # wall voxels: nothing denser ahead
    np.testing.assert_allclose(np.asarray(out[:, 1, 2]), want, atol=1e-15)


def test_diagonal_distance_is_steps_times_step_length():
    vol = jnp.zeros((6, 6, 6)).at[5, 5, 5].set(1.0)
    d = occluder_distances(vol, directions=np.array([[1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(float(d[0, 2, 2, 2]), 3 * np.sqrt(3.0), rtol=1e-15)
    assert float(d[0, 2, 2, 3]) == np.inf


def test_direction_with_an_exact_ratio_follows_its_documented_line():
    # found by a review: (3, 4, 0) was normalised before s = l / |l_a| was taken, so
    # s_d = 0.7499999999999999 and o_d(2) = floor(1.9999999999999998) = 1, not 2: the
    # line from (0, 0, 0) missed the occluder at (2, 2, 0), two steps of 1.25 away.
    # ((0.6, 0.8, 0) is not among these: its ratio in binary is 0.7499999999999999.)
    vol = jnp.zeros((3, 3, 1)).at[2, 2, 0].set(1.0)
    for direction in ([3.0, 4.0, 0.0], [0.75, 1.0, 0.0], [3 * 2.0**100, 4 * 2.0**100, 0.0]):
        dist = occluder_distances(vol, directions=np.array([direction]))
        assert float(dist[0, 0, 0, 0]) == 2.5
        ao = obscurance(vol, directions=np.array([direction]), d_max=2.5, rho="ao")
        assert float(ao[0, 0, 0]) == 0.0


def test_integer_directions_match_reference_exactly():
    # every direction whose ratios are exact in binary (halves, quarters) hits
    # the rounding boundaries floor(k + 1/2) of its digital lines
    vol = random_volume((9, 17, 8), 21, levels=3)
    dirs = np.array([v for v in np.ndindex(9, 9, 9) if any(v)], float) - 4.0
    dirs = dirs[np.any(dirs != 0, axis=1) & np.isin(np.max(np.abs(dirs), 1), (2, 4))]
    fast = np.asarray(occluder_distances(jnp.asarray(vol), directions=dirs))
    assert_same_distances(fast, ref.occluder_distances(vol, dirs))


def test_user_callable_rho_and_dtype():
    vol = jnp.asarray(random_volume((8, 8, 8), 8), jnp.float32)
    square = lambda d, dm: (d / dm) ** 2  # noqa: E731
    got = obscurance(vol, directions=DIRS12, d_max=4.0, rho=square)
    assert got.dtype == jnp.float32
    # the reference with the same callable: the float32 values, exactly in float64, give
    # the same occluders (same comparisons), so only the rounding of d and rho differs
    dists = ref.occluder_distances(np.asarray(vol, np.float64), DIRS12)
    occluded = dists <= 4.0
    want = np.where(occluded, square(np.where(occluded, dists, 4.0), 4.0), 1.0).mean(0)
    assert 0.5 < occluded.mean() < 1 and np.ptp(want) > 0.5  # rho matters here
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-6)
    # white occluders under a white ambient: colour bleeding is the grey value per channel
    rgb = obscurance(vol, directions=DIRS12, d_max=4.0, colors=jnp.ones((8, 8, 8, 3), jnp.float32))
    assert rgb.dtype == jnp.float32 and rgb.shape == (8, 8, 8, 3)
    np.testing.assert_allclose(
        np.asarray(rgb), np.repeat(ref.obscurance(np.asarray(vol, np.float64), DIRS12, 4.0,
                                                  "sqrt")[..., None], 3, -1), rtol=0, atol=1e-6)
    rgb_square = obscurance(vol, directions=DIRS12, d_max=4.0, rho=square,
                            colors=jnp.ones((8, 8, 8, 3), jnp.float32))
    np.testing.assert_allclose(np.asarray(rgb_square), np.repeat(want[..., None], 3, -1), rtol=0,
                               atol=1e-6)


def test_a_user_rho_that_is_not_finite_or_elementwise_is_refused():
    # found by a review: sqrt(2 - d) gave NaN beyond 2 voxels, silently
    vol = jnp.zeros((6, 6, 6)).at[3:].set(1.0)
    bad_rho = lambda d, dm: jnp.sqrt(2.0 - d)  # noqa: E731
    with pytest.raises(ValueError, match=r"`rho\(d, d_max\)` returned NaN or inf"):
        obscurance(vol, directions=DIRS12, d_max=4.0, rho=bad_rho)
    traced = jax.jit(lambda v, dm: obscurance(v, directions=DIRS12, d_max=dm, rho=bad_rho))
    with pytest.raises(Exception, match=r"`rho\(d, d_max\)` returned NaN or inf"):
        jax.block_until_ready(traced(vol, 4.0))
    assert bool(jnp.all(jnp.isfinite(traced(vol, 1.5))))  # finite where it is used
    # the shape quoted is that of the `d` the rho was given (the volume's axes reordered)
    with pytest.raises(ValueError, match=r"the shape of `d`, here \(\d+, \d+, \d+\)"):
        obscurance(jnp.zeros((3, 11, 7)), directions=DIRS12, d_max=3.0, rho=lambda d, m: d[0])


class _PowerRho(eqx.Module):
    """rho = (d / d_max)^p with a differentiable exponent."""

    p: jax.Array

    def __call__(self, d, d_max):
        return (d / d_max) ** self.p


@pytest.mark.filterwarnings("ignore:A JAX array is being set as static")  # equinox's, first
def test_rho_with_array_leaves_is_traced_and_gets_gradients():
    # found by a review: a rho Module (unhashable) crashed as jit's static argument
    vol = jnp.asarray(random_volume((8, 8, 8), 3))
    kw = dict(directions=DIRS12, d_max=4.0)
    np.testing.assert_array_equal(obscurance(vol, rho=_PowerRho(jnp.asarray(0.5)), **kw),
                                  obscurance(vol, rho="sqrt", **kw))

    def total(p):
        return jnp.sum(obscurance(vol, rho=_PowerRho(p), **kw))

    check_grad_fd(total, jnp.asarray(0.7))
    # one compile per rho, reused: splitting rho at each call made a new static key
    # each time for a pytree rho (found reading the change)
    for rho in (_PowerRho(jnp.asarray(0.5)), jax.tree_util.Partial(lambda d, dm: d / dm)):
        obscurance(vol, rho=rho, **kw)
        compiled = _obscurance._cache_size()
        obscurance(vol, rho=rho, **kw)
        assert _obscurance._cache_size() == compiled
    with pytest.raises(TypeError, match="`rho` is static here .* must be hashable"):
        ObscuranceParams(rho=_PowerRho(jnp.asarray(0.5)))
    with pytest.raises(TypeError, match="`rho` is static here"):
        vs.SaliencyModulation(rho=_PowerRho(jnp.asarray(0.5)))


def test_parameter_modules_take_a_callable_rho():
    vol = vs.data.phantom("shells", shape=10)
    tf = vs.transfer.preset("shells")
    square = lambda d, dm: (d / dm) ** 2  # noqa: E731
    got = ObscuranceParams(d_max=4.0, level=0, rho=square)(vol, tf)
    np.testing.assert_array_equal(got, obscurance(tf.opacity(vol), directions=DIRS12,
                                                  d_max=4.0, rho=square))
    assert not np.array_equal(got, ObscuranceParams(d_max=4.0, level=0)(vol, tf))
    factor = vs.SaliencyModulation(d_max=4.0, level=0, size=3, rho=square)(vol, tf)
    np.testing.assert_array_equal(factor, opacity_factor(
        vs.saliency(obscurance(tf.opacity(vol), directions=DIRS12, d_max=4.0, rho=square),
                    size=3), threshold=0.2))
    for module in (ObscuranceParams, vs.SaliencyModulation):
        with pytest.raises(ValueError, match="unknown rho 'cubic'"):
            module(rho="cubic")


# ------------------------------------------------------------------ corner phantom


@pytest.fixture(scope="module")
def corner_results():
    # 12^3 and 42 directions, as the reference tests: their compiled grey programs are
    # reused. The probes below lie 2 voxels from the walls they see and 7 (> d_max) from
    # the others
    alpha, colors = corner(12)
    out = {rho: obscurance(alpha, directions=DIRS42, d_max=4.0, rho=rho) for rho in RHOS}
    rgb = obscurance(alpha, directions=DIRS42, d_max=4.0, rho="sqrt", colors=colors)
    return out, rgb


def test_corner_green_bleeding(corner_results):
    _, rgb = corner_results
    r, g, b = (float(c) for c in rgb[8, 3, 8])  # next to the green wall only
    assert g > r and g > b
    r, g, b = (float(c) for c in rgb[8, 8, 3])  # next to the blue wall only
    assert b > r and b > g


def test_corner_darker_than_wall_middle(corner_results):
    grey, rgb = corner_results
    for rho in ("sqrt", "linear", "exponential", "ao"):
        assert float(grey[rho][2, 2, 2]) < float(grey[rho][2, 8, 8])
    assert float(rgb[2, 2, 2].sum()) < float(rgb[2, 8, 8].sum())


def test_sqrt_lighter_than_all_or_nothing_everywhere(corner_results):
    grey, _ = corner_results
    assert bool(jnp.all(grey["sqrt"] >= grey["ao"]))
    assert bool(jnp.all(grey["sqrt"] >= grey["linear"]))
    assert bool(jnp.any(grey["sqrt"] > grey["ao"]))


def test_larger_d_max_is_darker():
    alpha, _ = corner(12)  # the corner above's program: d_max is its argument
    small = obscurance(alpha, directions=DIRS42, d_max=4.0, rho="ao")
    large = obscurance(alpha, directions=DIRS42, d_max=12.0, rho="ao")
    assert bool(jnp.all(large <= small))


# ------------------------------------------------------------------ transformations


def test_jit_equals_eager_and_one_compilation_for_all_d_max():
    vol = jnp.asarray(random_volume((10, 10, 10), 9))
    f = jax.jit(lambda v, dm: obscurance(v, directions=DIRS12, d_max=dm, rho="sqrt"))
    for dm in (2.0, 7.5, 300.0):
        np.testing.assert_array_equal(np.asarray(f(vol, dm)),
                                      np.asarray(obscurance(vol, directions=DIRS12, d_max=dm)))
    assert f._cache_size() == 1


def test_vmap_equals_stacked():
    vols = jnp.asarray(random_volume((3, 8, 8, 8), 10))
    dms = jnp.array([2.0, 4.0, 9.0])
    f = lambda v, dm: obscurance(v, directions=DIRS12, d_max=dm, rho="exponential")
    batched = jax.jit(jax.vmap(f))(vols, dms)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(f(vols[i], dms[i])),
                                   rtol=0, atol=1e-15)


@pytest.mark.parametrize("rho", ["linear", "exponential", "sqrt"])
def test_grad_d_max_matches_finite_differences(rho):
    vol = jnp.asarray(random_volume((8, 8, 8), 11))

    def f(dm):
        return jnp.sum(obscurance(vol, directions=DIRS12, d_max=dm, rho=rho) ** 2)

    g = check_grad_fd(f, jnp.asarray(4.3))
    assert float(g) < 0  # larger d_max -> lower rho of each occluded direction


def test_grad_colours_and_ambient_match_finite_differences():
    vol = jnp.asarray(random_volume((6, 6, 6), 12, levels=3))
    colors = jnp.asarray(np.random.default_rng(13).random((6, 6, 6, 3)))
    w = jnp.asarray(np.random.default_rng(14).random((6, 6, 6, 3)))
    check_grad_fd(lambda c: jnp.sum(w * obscurance(vol, directions=DIRS12, d_max=3.0, colors=c)),
                  colors)
    check_grad_fd(lambda a: jnp.sum(w * obscurance(vol, directions=DIRS12, d_max=3.0,
                                                   colors=colors, ambient=a)),
                  jnp.array([0.9, 0.5, 0.2]))


def test_reverse_mode_memory_does_not_grow_with_the_directions():
    # found by a review: each direction's distances and colours were kept for the
    # reverse pass (162 directions of 256^3: 31 GB for the gradient w.r.t. d_max). A
    # compiled program's buffer plan, not a timing: 12 against 42 directions, 16^3
    spec = jax.ShapeDtypeStruct((16, 16, 16), jnp.float32)
    colors = jax.ShapeDtypeStruct((16, 16, 16, 3), jnp.float32)

    def grad_temp_bytes(level):
        dirs = icosphere_points(level)
        grad = jax.grad(lambda d, c, a: jnp.sum(obscurance(a, directions=dirs, d_max=d,
                                                           colors=c)), (0, 1))
        return temp_bytes(grad, jax.ShapeDtypeStruct((), jnp.float32), colors, spec)

    few, many = grad_temp_bytes(0), grad_temp_bytes(1)
    assert many <= 1.1 * few, (few, many)


def test_memory_holds_one_direction_group_at_a_time():
    # the frame of each of the six direction groups (the volume transposed, tiled 2 x 2,
    # and the colours transposed) was made outside the loop over the group's directions,
    # and each group summed into its own accumulator: XLA made all six frames and
    # accumulators before marching the first group, 41 volumes of temporaries (67 with
    # colours) at 32^3; frames made per direction and colours gathered as given, 18 (34);
    # one running sum, 13 (19). A compiled program's buffer plan, not a timing
    n = 32
    spec = jax.ShapeDtypeStruct((n, n, n), jnp.float32)
    colors = jax.ShapeDtypeStruct((n, n, n, 3), jnp.float32)
    volume = 4 * n**3
    plain = temp_bytes(lambda a: obscurance(a, directions=DIRS12, d_max=8.0), spec)
    bleeding = temp_bytes(lambda a, c: obscurance(a, directions=DIRS12, d_max=8.0, colors=c),
                          spec, colors)
    assert plain <= 20 * volume, plain / volume
    assert bleeding <= 28 * volume, bleeding / volume
    # reverse mode w.r.t. d_max, with colours and a cotangent that is not constant: 98
    # volumes at first, 87 with the frames made per direction, 72 with the running sum,
    # 53 with each direction's tile tied to the direction (not kept from the forward pass)
    grad = jax.grad(lambda d, a, c: jnp.sum(jnp.sin(
        obscurance(a, directions=DIRS12, d_max=d, colors=c))))
    reverse = temp_bytes(grad, jax.ShapeDtypeStruct((), jnp.float32), spec, colors)
    assert reverse <= 62 * volume, reverse / volume


def test_grad_density_is_zero_and_finite_at_hard_cases():
    f = jax.jit(jax.grad(lambda v: jnp.sum(obscurance(v, directions=DIRS12, d_max=3.0))))
    for vol in (jnp.zeros((6, 6, 6)), jnp.ones((6, 6, 6)), corner(6)[0],
                jnp.zeros((6, 6, 6)).at[2, 2, 2].set(1.0)):
        g = f(vol)
        assert bool(jnp.all(g == 0))
    # the corner's d_max Jacobian, per voxel (1/L) sum over occluded directions of
    # d/dd_max sqrt(d / d_max) = -sqrt(d / d_max) / (2 d_max). At d_max = 1 the nearest
    # occluder (|s| = 1.18 voxels for icosphere(0)) is out of reach: exactly 0; d_max = 3
    # lies between the distances 2.35 and 3.53, where O is smooth in d_max
    vol = corner(6)[0]
    o = jax.jit(lambda dm: obscurance(vol, directions=DIRS12, d_max=dm))
    jac = jax.jit(jax.jacrev(o))
    d = np.asarray(occluder_distances(vol, directions=DIRS12))
    for d_max in (1.0, 3.0):
        want = -np.sum(np.where(d <= d_max, np.sqrt(d / d_max) / (2 * d_max), 0), 0) / len(d)
        got = np.asarray(jac(d_max))
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)
        fd = (np.asarray(o(d_max + 1e-6)) - np.asarray(o(d_max - 1e-6))) / 2e-6
        np.testing.assert_allclose(got, fd, rtol=0, atol=1e-8)
    assert np.count_nonzero(got) > 0  # d_max = 3 reaches the walls


# ------------------------------------------------------------------ display controls


def test_threshold_values_and_binary_limit():
    o = jnp.array([0.0, 0.1, 0.2, 0.5, 0.8, 0.9, 1.0])
    np.testing.assert_allclose(np.asarray(threshold(o, 0.2, 0.8)),
                               [0, 0, 0, 0.5, 1, 1, 1], atol=1e-15)
    np.testing.assert_array_equal(np.asarray(threshold(o, 0.5, 0.5)), [0, 0, 0, 1, 1, 1, 1])
    np.testing.assert_array_equal(np.asarray(threshold(o, 0.0, 1.0)), np.asarray(o))
    g = jax.grad(lambda lo: jnp.sum(threshold(o, lo, 0.5)))(0.5)
    assert np.isfinite(float(g))
    check_grad_fd(lambda lo: jnp.sum(threshold(o, lo, 0.85) ** 2), jnp.asarray(0.15))
    assert threshold(o.astype(jnp.float32), 0.2, 0.8).dtype == jnp.float32
    with pytest.raises(TypeError, match="threshold: `low`"):  # not parsed from a string
        threshold(o, "0.2", 0.8)


def test_obscurance_shading_blinn_phong():
    n = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    light = jnp.array([0.0, 1.0, 1.0])
    view = jnp.array([0.0, 0.0, 1.0])
    obs = jnp.array([0.5, 1.0, 1.0, 1.0])
    shade = jax.jit(obscurance_shading)
    out = shade(n, light, view, obs, k_d=0.7, k_s=0.3, shininess=4.0)
    half = np.array([0.0, 1.0, 1.0 + np.sqrt(2.0)])
    nh = (half / np.linalg.norm(half))[2]
    want0 = (0.7 / np.sqrt(2.0) + 0.3 * nh**4) * 0.5
    np.testing.assert_allclose(np.asarray(out), [want0, 0.0, 0.0, 2 * want0], rtol=1e-14)
    rgb = shade(n, light, view, jnp.ones((4, 3)) * obs[:, None], k_d=0.7, k_s=0.3, shininess=4.0)
    np.testing.assert_allclose(np.asarray(rgb), np.asarray(out)[:, None] * np.ones(3), rtol=1e-14)
    jac = jax.jit(jax.jacrev(lambda x: obscurance_shading(x, light, view, obs, k_s=0.5)))(n)
    assert bool(jnp.all(jnp.isfinite(jac)))  # the zero normal's row too
    for row in (0, 1, 3):  # the others against central differences
        check_grad_fd(lambda x, row=row: obscurance_shading(x, light, view, obs, k_s=0.5)[row],
                      n, h=1e-6, n_dirs=2)
    # two-sided: the normal pointing away from the light is lit as the one towards it
    both = obscurance_shading(n, light, view, obs, k_d=0.7, k_s=0.3, shininess=4.0,
                              two_sided=True)
    np.testing.assert_allclose(np.asarray(both), [want0, 2 * want0, 0.0, 2 * want0], rtol=1e-14)
    with pytest.raises(TypeError, match="two_sided"):
        obscurance_shading(n, light, view, obs, two_sided="yes")


# ------------------------------------------------------------------ float32 against float64


def float32_exact(x):
    """``x`` rounded to float32, in float64: both precisions then compare the same values
    (strictly greater, below low, at or above high) and differ only in their arithmetic."""
    return np.asarray(np.asarray(x, np.float32), np.float64)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_density_sums_in_float32(dtype):
    # found by a review: the sum over 162 directions in bfloat16 was off by up to 9e-3;
    # the same (rounded) densities in float32 differ only by the output's rounding
    vol = jnp.asarray(random_volume((12, 12, 12), 5), dtype)
    dirs = icosphere(2)
    got = obscurance(vol, directions=dirs, d_max=9.0)
    assert got.dtype == dtype
    want = obscurance(vol.astype(jnp.float32), directions=dirs, d_max=9.0)
    np.testing.assert_allclose(np.asarray(got, np.float32), want, rtol=0,
                               atol=float(jnp.finfo(dtype).eps) / 2)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_density_keeps_the_colours_given(dtype):
    # found by a review: colours and ambient were cast to the density's dtype before
    # their [0, 1] check and the float32 sum, so 1.003 passed as 1 and every colour lost
    # digits; the same (rounded) densities in float32 differ only by the output's rounding
    vol = jnp.asarray(random_volume((8, 8, 8), 7), dtype)
    colors = np.random.default_rng(8).random((8, 8, 8, 3))
    ambient = (0.9, 0.8, 0.7)
    got = obscurance(vol, directions=DIRS12, d_max=4.0, colors=colors, ambient=ambient)
    assert got.dtype == dtype
    want = obscurance(vol.astype(jnp.float32), directions=DIRS12, d_max=4.0,
                      colors=colors.astype(np.float32), ambient=ambient)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want.astype(dtype)))
    for kwargs in (dict(colors=np.full((8, 8, 8, 3), 1.003)),
                   dict(colors=colors, ambient=(1.003, 1.0, 1.0))):
        with pytest.raises(ValueError, match="must lie in"):
            obscurance(vol, directions=DIRS12, d_max=4.0, **kwargs)
    # a bool is no colour (found by a review: it passed as 0 or 1)
    with pytest.raises(TypeError, match="`ambient` must be a number or numbers, got a bool"):
        obscurance(vol, directions=DIRS12, d_max=4.0, colors=colors, ambient=(True, 1.0, 1.0))


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_density_keeps_d_max(dtype):
    # found by a review: d_max was cast to the density's dtype, so in bfloat16 19.06 became
    # 19.0 and missed an occluder 11 sqrt(3) = 19.05 voxels away, and in float16 1e5 was
    # refused as not finite
    vol = jnp.zeros((12, 12, 12), dtype).at[11, 11, 11].set(1.0)
    diagonal = np.array([[1.0, 1.0, 1.0]])
    assert float(obscurance(vol, directions=diagonal, d_max=19.06, rho="ao")[0, 0, 0]) == 0.0
    far = obscurance(vol, directions=diagonal, d_max=1e5, rho="linear")
    np.testing.assert_allclose(float(far[0, 0, 0]), 11 * np.sqrt(3.0) / 1e5, rtol=1e-2)
    # and occluder_distances measures as obscurance does (it returned 19.125 in bfloat16,
    # so that `d <= 19.06` said unoccluded where obscurance said occluded)
    dist = occluder_distances(vol, directions=diagonal)
    assert dist.dtype == jnp.float32
    assert float(dist[0, 0, 0, 0]) == np.float32(11 * np.sqrt(np.float32(3.0)))


@pytest.mark.parametrize("rho", ["exponential", "sqrt"])
def test_obscurance_float32_agrees_with_float64(rho):
    # 12^3 and 42 directions, as the reference tests: their float64 grey program is reused
    vol = float32_exact(random_volume((12, 12, 12), 15))
    colors = float32_exact(np.random.default_rng(16).random((12, 12, 12, 3)))
    amb = (0.9, 0.8, 0.7)
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        v = jnp.asarray(vol, dtype)
        grey = obscurance(v, directions=DIRS42, d_max=jnp.asarray(4.5, dtype), rho=rho)
        rgb = obscurance(v, directions=DIRS42, d_max=jnp.asarray(4.5, dtype), rho=rho,
                         colors=jnp.asarray(colors, dtype), ambient=amb)
        assert grey.dtype == dtype and rgb.dtype == dtype
        out[dtype] = (np.asarray(grey, np.float64), np.asarray(rgb, np.float64))
    for lo, hi in zip(out[jnp.float32], out[jnp.float64], strict=True):
        assert np.ptp(hi) > 0.3
        np.testing.assert_allclose(lo, hi, rtol=0, atol=2e-6)
    # and float64 is the reference's value
    np.testing.assert_allclose(out[jnp.float64][0], ref.obscurance(vol, DIRS42, 4.5, rho),
                               rtol=0, atol=1e-13)


def test_threshold_and_shading_float32_agree_with_float64():
    rng = np.random.default_rng(17)
    obs = float32_exact(rng.random((6, 7, 5)))
    obs[0, 0, :3] = np.float32(0.25), np.float32(0.75), 1.0  # exactly at low / high
    normal = float32_exact(rng.standard_normal((6, 7, 5, 3)))
    normal[1, 1] = 0.0  # a zero normal
    light, view = np.array([0.3, 0.2, 0.9]), np.array([0.9, 0.1, 0.3])
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        o = threshold(jnp.asarray(obs, dtype), np.float32(0.25), np.float32(0.75))
        grey = obscurance_shading(jnp.asarray(normal, dtype), light, view, o, k_d=0.7,
                                  k_s=0.4, shininess=12.0)
        rgb = obscurance_shading(jnp.asarray(normal, dtype), light, view,
                                 jnp.stack([o, o ** 2, 1 - o], -1), k_d=0.7, k_s=0.4,
                                 shininess=12.0)
        assert o.dtype == grey.dtype == rgb.dtype == dtype
        out[dtype] = [np.asarray(x, np.float64) for x in (o, grey, rgb)]
    lo, hi = out[jnp.float32], out[jnp.float64]
    # the thresholds: 0 up to low, 1 at or above high, the same in both precisions
    np.testing.assert_array_equal(lo[0] == 0, obs <= 0.25)
    np.testing.assert_array_equal(hi[0] == 0, obs <= 0.25)
    np.testing.assert_array_equal(lo[0] == 1, obs >= 0.75)
    np.testing.assert_array_equal(hi[0] == 1, obs >= 0.75)
    for a, b in zip(lo, hi, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    assert np.all(hi[1][1, 1] == 0) and np.all(lo[1][1, 1] == 0)  # zero normal: dark


# ------------------------------------------------------------------ errors


def test_errors():
    vol = jnp.zeros((4, 4, 4))
    with pytest.raises(ValueError, match="density.*3 dimensions"):
        obscurance(jnp.zeros((4, 4)), directions=DIRS12, d_max=2.0)
    with pytest.raises(ValueError, match="d_max"):
        obscurance(vol, directions=DIRS12, d_max=0.0)
    with pytest.raises(ValueError, match="d_max"):
        obscurance(vol, directions=DIRS12, d_max=-1)
    with pytest.raises(ValueError, match="d_max"):  # concrete arrays: at trace time too
        obscurance(vol, directions=DIRS12, d_max=np.array(-1.0))
    assert ObscuranceParams(level=4).level == 4  # icosphere levels 0-4
    with pytest.raises(ValueError, match="level"):
        ObscuranceParams(level=5)
    half = obscurance(vol, directions=DIRS12, d_max=jnp.asarray(2.0, jnp.bfloat16))
    np.testing.assert_array_equal(half, obscurance(vol, directions=DIRS12, d_max=2.0))
    for not_a_number in (True, "2"):
        with pytest.raises(TypeError, match="d_max"):
            obscurance(vol, directions=DIRS12, d_max=not_a_number)
    with pytest.raises(ValueError, match="unknown rho 'cubic'.*'sqrt'"):
        obscurance(vol, directions=DIRS12, d_max=2.0, rho="cubic")
    with pytest.raises(ValueError, match=r"directions.*\(L, 3\)"):
        obscurance(vol, directions=np.zeros((0, 3)), d_max=2.0)
    with pytest.raises(ValueError, match="zero vector"):
        obscurance(vol, directions=np.zeros((2, 3)), d_max=2.0)
    # a direction in huge or tiny numbers is that direction (its norm would overflow to
    # inf, a zero direction marched nowhere, or underflow to 0, refused as zero)
    wall = jnp.zeros((4, 4, 4)).at[3].set(1.0)
    for scale in (1e200, 1e-200):
        np.testing.assert_array_equal(
            occluder_distances(wall, directions=np.array([[scale, 0.0, 0.0]]))[0, :, 0, 0],
            [3.0, 2.0, 1.0, np.inf])
    with pytest.raises(ValueError, match="colors"):
        obscurance(vol, directions=DIRS12, d_max=2.0, colors=jnp.zeros((4, 4, 4)))
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda d: obscurance(vol, directions=d, d_max=2.0))(jnp.asarray(DIRS12))
    with pytest.raises(TypeError, match="icosphere_points"):
        jax.jit(lambda v: obscurance(v, directions=icosphere(0), d_max=2.0))(vol)
    inside = jax.jit(lambda v: obscurance(v, directions=icosphere_points(0), d_max=2.0))(vol)
    np.testing.assert_array_equal(inside, obscurance(vol, directions=icosphere(0), d_max=2.0))
    with pytest.raises(ValueError, match="`density` contains NaN or inf"):
        obscurance(vol.at[1, 1, 1].set(jnp.nan), directions=DIRS12, d_max=2.0)
    with pytest.raises(Exception, match="d_max"):
        jax.jit(lambda dm: obscurance(vol, directions=DIRS12, d_max=dm))(-1.0)
    with pytest.raises(ValueError, match="low"):
        threshold(vol, 0.8, 0.2)
    with pytest.raises(ValueError, match="obscurance"):
        obscurance_shading(jnp.ones((2, 3)), jnp.ones(3), jnp.ones(3), jnp.ones((3,)))
    with pytest.raises(ValueError, match="`ambient` contains NaN"):
        obscurance(vol, directions=DIRS12, d_max=2.0, colors=jnp.zeros((4, 4, 4, 3)),
                   ambient=(jnp.nan, 1.0, 1.0))
    for name, light, view in (("light", [jnp.nan, 0.0, 1.0], [0.0, 0.0, 1.0]),
                              ("view", [0.0, 0.0, 1.0], [jnp.inf, 0.0, 1.0])):
        with pytest.raises(ValueError, match=f"`{name}` contains NaN or inf"):
            obscurance_shading(jnp.ones((2, 3)), jnp.asarray(light), jnp.asarray(view),
                               jnp.ones(2))


def test_colour_bleeding_with_the_ao_rho_is_the_grey_obscurance_times_the_ambient():
    # rho = 0 for every occluder within reach: the occluders' colours drop out (a review
    # found the colour-bleeding render pixel-identical to the grey one, as eq. 3 says)
    rng = np.random.default_rng(40)
    density = jnp.asarray(rng.random((10, 10, 10)) > 0.7, jnp.float64)
    colors = jnp.asarray(rng.random((10, 10, 10, 3)))
    ambient = jnp.asarray([0.9, 0.5, 0.2])
    rgb = obscurance(density, directions=DIRS12, d_max=4.0, rho="ao", colors=colors,
                     ambient=ambient)
    grey = obscurance(density, directions=DIRS12, d_max=4.0, rho="ao")
    assert 0 < float(jnp.mean(grey)) < 1  # partly occluded: the test compares something
    np.testing.assert_allclose(np.asarray(rgb), np.asarray(grey)[..., None] * np.asarray(ambient),
                               atol=1e-14)
