import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd
from jax.flatten_util import ravel_pytree

from volshade import transfer
from volshade.transfer import IntervalFeature, TransferFunction, feature_opacities


def _tf(dtype=jnp.float64):
    return TransferFunction.from_points(
        [(0.0, 0, 0, 0, 0.0), (0.5, 1, 0, 0, 0.4), (1.0, 0, 0, 1, 0.8)], dtype=dtype)


def test_piecewise_linear_values():
    tf = _tf()
    x = jnp.array([0.0, 0.25, 0.5, 0.75, 1.0])  # outside [0, 1]: refused (below)
    np.testing.assert_allclose(tf.opacity(x), [0, 0.2, 0.4, 0.6, 0.8])
    np.testing.assert_allclose(tf.color(jnp.array(0.75)), [0.5, 0, 0.5])


@pytest.mark.parametrize("dtype, unit, refused", [
    (jnp.float32, 1e-12, False), (jnp.float32, 1e-15, True), (jnp.float64, 1e-15, False),
    (jnp.float64, 1e-32, True), (jnp.float32, 1e20, False)])
def test_points_closer_than_the_interpolations_resolution_are_refused(dtype, unit, refused):
    # found by a review: jnp.interp takes gaps under an absolute 1.4e-14 (float32) for
    # steps, so points 1e-15 apart classified 0.25 of the way as the first point
    tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (unit, 1, 0.5, 0, 1.0),
                                       (2 * unit, 0, 0, 1, 0.0)])
    x = np.asarray([0.0, 0.25, 0.5, 1.0, 1.5, 2.0])
    volume = jnp.asarray(x * unit, dtype)
    if refused:
        with pytest.raises(ValueError, match=r"`points` must lie more than .* apart in "
                                             f"{jnp.dtype(dtype).name}.*rescale"):
            tf.opacity(volume)
        return
    np.testing.assert_allclose(tf.opacity(volume), np.interp(x, [0, 1, 2], [0, 1, 0]),
                               rtol=1e-6, atol=1e-6)


def test_opacity_correction_matches_extinction():
    tf = _tf()
    x = jnp.linspace(0, 1, 9)
    for step in (0.25, 1.0, 3.0):
        np.testing.assert_allclose(tf.opacity(x, step=step),
                                   1 - np.exp(-tf.extinction(x) * step), rtol=1e-12, atol=1e-15)


def test_transfer_function_under_jit_vmap_grad():
    tf = _tf()
    x = jnp.linspace(0, 1, 5)
    np.testing.assert_allclose(jax.jit(lambda t, v: t.opacity(v, step=0.5))(tf, x),
                               tf.opacity(x, step=0.5))
    opacities = jnp.stack([tf.opacities, 2 * tf.opacities / 3])
    batch = jax.jit(jax.vmap(lambda o: TransferFunction(tf.points, tf.colors, o).opacity(x)))(
        opacities)
    for got, o in zip(batch, opacities, strict=True):
        np.testing.assert_allclose(got, TransferFunction(tf.points, tf.colors, o).opacity(x),
                                   rtol=0, atol=1e-15)
    np.testing.assert_allclose(batch[0], [0, 0.2, 0.4, 0.6, 0.8], rtol=1e-15)  # not all zero
    g = jax.jit(jax.grad(lambda t: jnp.sum(t.opacity(x, step=2.0))))(tf)
    assert np.all(np.isfinite(g.opacities)) and np.all(np.isfinite(g.points))
    assert float(jnp.sum(jnp.abs(g.opacities))) > 0


def test_gradient_wrt_control_points_and_values_matches_finite_differences():
    # d/d(points, colors, opacities) of opacity (corrected), extinction and colour at
    # values between the control points, against central differences in float64
    tf = TransferFunction.from_points([(0.0, 0.1, 0.2, 0.3, 0.05), (0.3, 0.9, 0.5, 0.2, 0.4),
                                       (0.55, 0.4, 0.7, 0.6, 0.2), (1.0, 0.3, 0.8, 0.9, 0.7)])
    x = jnp.asarray(np.random.default_rng(0).uniform(0.02, 0.98, 40))
    w = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (40, 5)))

    fields = ("points", "colors", "opacities")
    flat, unravel = ravel_pytree([getattr(tf, field) for field in fields])

    # the three fields as one vector: one program and one gradient (one of each per field
    # before), checked along 4 random directions within each field, so that an error in one
    # field is not hidden by the larger derivatives of another
    @jax.jit
    def loss(values):
        t = eqx.tree_at(lambda t: [getattr(t, field) for field in fields], tf, unravel(values))
        return (jnp.sum(w[:, 0] * t.opacity(x, step=2.0)) + jnp.sum(w[:, 1] * t.extinction(x))
                + jnp.sum(w[:, 2:] * t.color(x)))

    rng = np.random.default_rng(2)
    directions = [ravel_pytree([rng.standard_normal(getattr(tf, f).shape) * (f == field)
                                for f in fields])[0] for field in fields for _ in range(4)]
    grads = unravel(check_grad_fd(loss, flat, directions=jnp.stack(directions)))
    for field, g in zip(fields, grads, strict=True):
        assert float(jnp.min(jnp.abs(g))) > 1e-3, (field, g)  # every control value matters
    # analytically: at x between p0 and p1 the opacity is a0 + (a1 - a0) (x - p0) / (p1 - p0),
    # so d/dp0 = (a1 - a0) (x - p1) / (p1 - p0)^2 and d/dp1 = -(a1 - a0) (x - p0) / (p1 - p0)^2
    g = jax.grad(lambda p: TransferFunction(p, tf.colors, tf.opacities).opacity(
        jnp.asarray(0.2)))(tf.points)
    np.testing.assert_allclose(g, [-(0.4 - 0.05) * (0.3 - 0.2) / 0.3 ** 2,
                                   -(0.4 - 0.05) * 0.2 / 0.3 ** 2, 0, 0], rtol=1e-12)


def test_from_points_errors():
    with pytest.raises(ValueError, match="strictly increasing"):
        TransferFunction.from_points([(0.5, 0, 0, 0, 0), (0.2, 0, 0, 0, 0)])
    with pytest.raises(ValueError, match="rows"):
        TransferFunction.from_points([(0.5, 0, 0, 0)])
    with pytest.raises(ValueError, match="of 5 numbers each"):
        TransferFunction.from_points([(0.0, 0, 0, 0, 0), (1.0, 1, 1, 1)])
    # converted, a complex opacity would lose its imaginary part
    for points in ([(0.0, 0, 0, 0, 0), (1.0, 1, 1, 1, 0.2 + 0.5j)], [(0.0, 0, 0, 0, "a")]):
        with pytest.raises(TypeError, match="from_points: `points` must be rows of 5 real"):
            TransferFunction.from_points(points)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        TransferFunction.from_points([(0.0, 0, 0, 0, 1.5)])
    with pytest.raises(ValueError, match="NaN"):
        TransferFunction.from_points([(np.nan, 0, 0, 0, 0.5)])
    with pytest.raises(ValueError, match="colors"):
        TransferFunction(jnp.zeros(2), jnp.zeros((3, 3)), jnp.zeros(2))
    with pytest.raises(ValueError, match="step0"):
        TransferFunction(jnp.zeros(1), jnp.zeros((1, 3)), jnp.zeros(1), step0=0.0)


def test_control_values_are_checked_however_the_function_is_built():
    points, colors = jnp.asarray([0.0, 0.5, 1.0]), jnp.full((3, 3), 0.5)
    with pytest.raises(ValueError, match="strictly increasing"):
        TransferFunction(points[::-1], colors, jnp.full(3, 0.5))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        TransferFunction(points, colors, jnp.asarray([0.0, 1.5, 0.5]))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        TransferFunction(points, colors.at[0, 0].set(-0.1), jnp.full(3, 0.5))
    x = jnp.linspace(0, 1, 5)
    tf = TransferFunction(points, colors, jnp.full(3, 0.5))
    # traced values (a fit) and eqx.tree_at skip __check_init__: checked when used
    traced = jax.jit(lambda o: TransferFunction(points, colors, o).opacity(x))
    np.testing.assert_allclose(traced(jnp.full(3, 0.5)), 0.5)
    with pytest.raises(Exception, match=r"`opacities` must lie in \[0, 1\]"):
        traced(jnp.asarray([0.0, 1.5, 0.5]))
    unsorted = eqx.tree_at(lambda t: t.points, tf, points[::-1])
    for method in (unsorted.opacity, unsorted.color, unsorted.extinction, unsorted):
        with pytest.raises(Exception, match="strictly increasing"):
            method(x)


def test_presets_and_unknown_preset():
    for name in transfer.PRESETS:
        tf = transfer.preset(name)
        op = tf.opacity(jnp.linspace(0, 1, 50))
        assert float(op.min()) >= 0 and float(op.max()) <= 1
    with pytest.raises(ValueError, match="unknown transfer-function preset 'bone'.*'grey'"):
        transfer.preset("bone")


def test_features():
    tf = _tf()
    vol = jnp.linspace(0, 1, 27).reshape(3, 3, 3)
    ops = feature_opacities(vol, [IntervalFeature(0.0, 0.5), tf], base=tf)
    assert ops.shape == (2, 3, 3, 3)
    expected_low = np.where(np.asarray(vol) <= 0.5, np.asarray(tf.opacity(vol)), 0)
    np.testing.assert_allclose(ops[0], expected_low)
    np.testing.assert_allclose(ops[1], tf.opacity(vol))
    with pytest.raises(ValueError, match="base"):
        feature_opacities(vol, [IntervalFeature(0.0, 0.5)])
    with pytest.raises(ValueError, match="empty"):
        feature_opacities(vol, [])
    with pytest.raises(ValueError, match="finite `low` < `high`"):
        IntervalFeature(0.5, 0.5)
    # finite, as a render requires of every scene parameter
    for low, high in ((0.5, np.inf), (-np.inf, 0.5), (np.nan, 0.5)):
        with pytest.raises(ValueError, match="need finite `low` < `high`"):
            IntervalFeature(low, high)


def test_interval_features_with_a_batch_axis_or_traced_bounds():
    tf = _tf()
    vol = jnp.linspace(0, 1, 27).reshape(3, 3, 3)
    # one feature per setting, then vmap
    batched = IntervalFeature([0.0, 0.5], [0.5, 1.0])
    ops = jax.vmap(lambda f: f.opacity(vol, tf))(batched)
    for i, (low, high) in enumerate(((0.0, 0.5), (0.5, 1.0))):
        np.testing.assert_array_equal(ops[i], IntervalFeature(low, high).opacity(vol, tf))
    with pytest.raises(ValueError, match="finite `low` < `high`"):
        IntervalFeature([0.0, 0.5], [0.5, 0.4])
    # bounds traced under jit (even in a list) are checked where they are used
    lists = jax.jit(lambda low, high: IntervalFeature([low], [high]))(0.0, 0.5)
    np.testing.assert_array_equal(lists.low, [0.0])
    select = eqx.filter_jit(lambda low, high: IntervalFeature(low, high).opacity(vol, tf))
    np.testing.assert_array_equal(select(jnp.asarray(0.0), jnp.asarray(0.5)), ops[0])
    for low, high in ((0.6, 0.5), (jnp.nan, 0.5)):
        with pytest.raises(eqx.EquinoxRuntimeError,
                           match="IntervalFeature: need finite `low` < `high`"):
            jax.block_until_ready(select(jnp.asarray(low), jnp.asarray(high)))


def test_values_outside_the_control_points_are_refused():
    # a 0-255 volume through a [0, 1] transfer function would be one solid blob
    tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (1.0, 1, 1, 1, 0.5)])
    for method in (tf.opacity, tf.color, tf.extinction, tf):
        with pytest.raises(Exception, match="outside the transfer function's control points"):
            method(jnp.asarray([0.0, 0.5, 255.0]))
    np.testing.assert_allclose(tf.opacity(jnp.asarray([0.0, 1.0])), [0.0, 0.5])  # ends inclusive


def test_an_empty_array_is_classified_as_empty():
    # an elementwise map: no value is outside the points (a minimum of nothing raised)
    tf = _tf()
    for empty in (jnp.zeros((0, 4, 4)), jnp.zeros((0,))):
        assert tf.opacity(empty).shape == empty.shape
        assert jax.jit(lambda v: tf.color(v))(empty).shape == (*empty.shape, 3)
        assert tf.extinction(empty).shape == empty.shape
        assert [x.shape for x in tf(empty)] == [(*empty.shape, 3), empty.shape]


def test_a_negative_or_non_finite_step_is_refused():
    tf = _tf()
    x = jnp.asarray([0.25, 0.5])
    np.testing.assert_array_equal(tf.opacity(x, step=0.0), [0.0, 0.0])  # no length, no opacity
    for step in (-1.0, jnp.nan, jnp.inf):
        for method in (tf.opacity, tf):
            with pytest.raises(ValueError, match="`step` must be a finite segment length"):
                method(x, step=step)
        with pytest.raises(Exception, match="`step` must be a finite segment length"):
            jax.block_until_ready(jax.jit(lambda s: tf.opacity(x, step=s))(step))
    # one length per value, or one for all (it was a raw broadcasting error)
    np.testing.assert_allclose(tf.opacity(x, step=[1.0, 0.0])[1], 0.0)
    for method in (tf.opacity, tf):
        with pytest.raises(ValueError, match=r"`step` must be one length or broadcast to the "
                                             r"volume's shape \(2,\), got shape \(3,\)"):
            method(x, step=[1.0, 2.0, 3.0])


def test_float32_volumes_are_classified_in_float32_whatever_the_control_values_dtype():
    # float32(0.3) > 0.3 and float32(0.4) > 0.4 in float64: the range check and the
    # interval ends compare in the volume's dtype, as the interpolation does
    tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (0.3, 1, 1, 1, 0.5)])
    assert tf.points.dtype == jnp.float64
    np.testing.assert_allclose(tf.opacity(jnp.asarray([0.0, 0.3], jnp.float32)), [0.0, 0.5])
    wide = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (1.0, 1, 1, 1, 1.0)])
    feature = IntervalFeature(0.2, 0.4)
    for dtype in (jnp.float32, jnp.float64):
        assert float(feature.opacity(jnp.asarray([0.4], dtype), wide)[0]) == pytest.approx(0.4)


def test_integer_bool_and_list_volumes_are_classified_as_their_values():
    # the interpolation runs in the volume's dtype: an int32 volume would truncate every
    # opacity and colour in [0, 1] to 0, silently
    tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (1.0, 0.6, 0.4, 0.2, 0.5),
                                       (3.0, 1, 1, 1, 0.8)])
    values = np.array([0, 1, 2, 3])
    expected = tf(jnp.asarray(values, float))
    for volume in (values.astype(np.int32), values.astype(np.uint8), values.tolist()):
        color, alpha = tf(volume)
        np.testing.assert_allclose(alpha, expected[1], rtol=1e-15)
        np.testing.assert_allclose(color, expected[0], rtol=1e-15)
        np.testing.assert_allclose(tf.opacity(volume), expected[1], rtol=1e-15)
        np.testing.assert_allclose(tf.color(volume), expected[0], rtol=1e-15)
        np.testing.assert_allclose(tf.extinction(volume),
                                   tf.extinction(jnp.asarray(values, float)), rtol=1e-15)
        np.testing.assert_allclose(IntervalFeature(0.5, 2.5).opacity(volume, tf),
                                   [0.0, 0.5, 0.65, 0.0], rtol=1e-15)
    np.testing.assert_allclose(tf.opacity(jnp.array([False, True])), [0.0, 0.5])
    # half precision is classified in float32, by an interval alone and among features
    # alike: float16(0.1) = 0.099976 lies below an interval starting at 0.1 (in float16
    # the end would round to the same 0.099976 and take it in)
    half = jnp.asarray([0.1, 0.5], jnp.float16).reshape(1, 1, 2)
    interval = IntervalFeature(0.1, 1.0)
    wide = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (1.0, 1, 1, 1, 1.0)])
    np.testing.assert_array_equal(interval.opacity(half, wide).ravel(), [0.0, 0.5])
    np.testing.assert_array_equal(feature_opacities(half, [interval], base=wide).ravel(),
                                  [0.0, 0.5])
    with pytest.raises(TypeError, match="`volume` must have a real floating or integer dtype"):
        tf.opacity(jnp.array([1j]))
