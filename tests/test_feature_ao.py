"""Tests of volshade.feature_ao: reference agreement of every merge, the properties that
motivate feature-driven AO, bricks, autodiff, the Module, the Scene, bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd, check_grads_fd, one_medium_written_twice
from reference_feature_ao import feature_ao_reference, merge_reference
from reference_lao import lao_reference

import volshade as vs
from volshade.feature_ao import MERGES, feature_labels

SHELLS_TF = vs.transfer.preset("shells")
# the three shells of the shells phantom, as intervals of its transfer function
SHELLS = [vs.IntervalFeature(0.2, 0.4), vs.IntervalFeature(0.5, 0.7),
          vs.IntervalFeature(0.8, 1.0)]
DIRS = vs.directions.icosphere(0)


def _shells(shape=16, dtype=jnp.float64):
    return vs.data.phantom("shells", shape=shape).astype(dtype)


def _blocks():
    """Thick nested blocks of the shells' three values, so that neighbourhoods of one
    feature, of several and of none all occur (the thin shells of a small phantom have
    no uniform neighbourhood)."""
    vol = np.zeros((14, 15, 13))
    vol[1:13, 1:14, 1:7] = 0.3
    vol[3:11, 3:12, 7:12] = 0.6
    vol[5:9, 5:10, 2:5] = 1.0
    vol[0:5, 11:15, 9:13] = 0.6  # a second feature touching two faces of the volume
    return jnp.asarray(vol, jnp.float64)


def _ramp_tf(opacities):
    """A transfer function whose opacity rises with the intensity (a feature of its own)."""
    points = jnp.linspace(0.0, 1.0, len(opacities))
    return vs.TransferFunction(points, jnp.ones((len(opacities), 3)), jnp.asarray(opacities))


def _regions(opacities):
    """Voxels whose 3^3 neighbourhood is one feature, mixed, or has no feature."""
    labels = np.asarray(feature_labels(jnp.asarray(opacities)))
    padded = np.pad(labels, 1, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (3, 3, 3))
    low, high = windows.min(axis=(-3, -2, -1)), windows.max(axis=(-3, -2, -1))
    uniform = (low == high) & (labels >= 0)
    empty = high < 0
    return uniform, ~uniform & ~empty, empty


# ----------------------------------------------------------------- reference agreement


@pytest.fixture(scope="module")
def blocks_reference():
    """The blocks volume, three features (the last two overlapping), their opacities and
    each feature's reference AO, computed once for every merge's test."""
    vol = _blocks()
    features = [*SHELLS[:2], _ramp_tf([0.0, 0.0, 0.0, 0.2, 0.6])]
    opacities = np.asarray(vs.transfer.feature_opacities(vol, features, base=SHELLS_TF))
    per_feature = np.stack([np.asarray(lao_reference(a, DIRS, 4.5, 0.5, 6)) for a in opacities])
    return vol, features, opacities, per_feature


@pytest.mark.parametrize("merge", sorted(MERGES))
def test_matches_voxel_by_voxel_reference(merge, blocks_reference):
    vol, features, opacities, per_feature = blocks_reference
    if merge == "neighbourhood":
        # every branch of the merge is exercised by this volume
        assert all(region.mean() > 0.05 for region in _regions(opacities))
    got = vs.feature_ao(vol, features=features, base=SHELLS_TF, directions=DIRS, radius=4.5,
                        offset=0.5, samples=6, merge=merge)
    assert got.shape == vol.shape and got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), merge_reference(per_feature, opacities, merge),
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("merge", ["max", "neighbourhood"])
def test_float32_matches_float64_reference(merge):
    vol = _shells(dtype=jnp.float32)
    got = vs.feature_ao(vol, features=SHELLS, base=SHELLS_TF, directions=DIRS, radius=5.0,
                        samples=8, merge=merge, opacity_correction=True, step=1.0)
    opacities = np.asarray(vs.transfer.feature_opacities(vol, SHELLS, base=SHELLS_TF, step=1.0))
    ref = feature_ao_reference(opacities, DIRS, 5.0, 1.0, 8, merge, opacity_correction=True)
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-6)


def test_step_corrects_the_feature_opacities():
    vol = _shells(12)
    kw = dict(features=SHELLS, base=SHELLS_TF, directions=DIRS, radius=4.0, samples=5,
              opacity_correction=True, merge="neighbourhood")
    got = vs.feature_ao(vol, step=2.5, **kw)
    opacities = np.asarray(vs.transfer.feature_opacities(vol, SHELLS, base=SHELLS_TF, step=2.5))
    np.testing.assert_allclose(np.asarray(opacities.max(axis=0)),
                               np.asarray(SHELLS_TF.opacity(vol, step=2.5)), atol=1e-15)
    ref = feature_ao_reference(opacities, DIRS, 4.0, 1.0, 5, "neighbourhood",
                               opacity_correction=True)
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-12)
    assert np.abs(np.asarray(got - vs.feature_ao(vol, **kw))).max() > 0.01


@pytest.mark.parametrize("merge", sorted(MERGES))
def test_merge_matches_reference_on_random_volumes(merge):
    rng = np.random.default_rng(3)
    shape = (3, 7, 6, 8)
    ao = rng.uniform(0, 1, shape)
    # sparse opacities, with whole blocks of one feature and empty blocks
    opacities = rng.uniform(0, 1, shape) * (rng.uniform(0, 1, shape) < 0.3)
    opacities[0, :3, :3, :4] = 0.8
    opacities[1:, :3, :3, :4] = 0.0
    opacities[:, 4:, 3:, 4:] = 0.0
    assert all(region.any() for region in _regions(opacities))
    got = vs.merge_feature_ao(jnp.asarray(ao), jnp.asarray(opacities), merge=merge)
    np.testing.assert_allclose(np.asarray(got), merge_reference(ao, opacities, merge),
                               rtol=0, atol=1e-14)


def test_merge_small_cases_by_hand():
    ao = jnp.stack([jnp.full((3, 3, 3), 0.9), jnp.full((3, 3, 3), 0.4)])
    opacities = jnp.zeros((2, 3, 3, 3)).at[0].set(0.5)
    # every voxel is feature 0: its own value, and the whole neighbourhood is uniform
    assert np.allclose(vs.merge_feature_ao(ao, opacities, merge="feature"), 0.9)
    assert np.allclose(vs.merge_feature_ao(ao, opacities, merge="neighbourhood"), 0.9)
    assert np.allclose(vs.merge_feature_ao(ao, opacities, merge="max"), 0.4)  # min visibility
    # one voxel of feature 1 (opacity 0.25) in the middle: every neighbourhood is mixed
    # and takes the opacity-weighted mean over its voxels inside the volume, all 27 for
    # the centre, 8 for a corner
    opacities = opacities.at[:, 1, 1, 1].set(jnp.asarray([0.0, 0.25]))
    out = vs.merge_feature_ao(ao, opacities, merge="neighbourhood")
    for index, n_first in (((1, 1, 1), 26), ((0, 0, 0), 7), ((2, 0, 2), 7), ((1, 0, 1), 17)):
        expected = (n_first * 0.5 * 0.9 + 0.25 * 0.4) / (n_first * 0.5 + 0.25)
        np.testing.assert_allclose(float(out[index]), expected, rtol=1e-12)
    # no feature anywhere: every merge is the maximum occlusion
    for merge in MERGES:
        assert np.allclose(vs.merge_feature_ao(ao, jnp.zeros_like(ao), merge=merge), 0.4)
    # ties go to the first feature
    tied = jnp.full_like(ao, 0.3)
    assert np.allclose(vs.merge_feature_ao(ao, tied, merge="feature"), 0.9)
    assert np.allclose(vs.merge_feature_ao(ao[::-1], tied, merge="feature"), 0.4)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_no_nan_in_jacrev_on_hard_opacities(dtype):
    # zero, tiny (down to the smallest normal), tied and opaque feature opacities: the
    # neighbourhood mean's derivative grows as 1 / (summed opacity) and must not overflow
    rng = np.random.default_rng(0)
    shape = (2, 5, 4, 6)
    tiny = float(jnp.finfo(dtype).tiny)
    opacities = rng.choice(np.asarray([0.0, tiny, 1e-30, 1e-12, 1e-7, 0.5, 1.0]), shape)
    opacities[:, 0] = 0.25  # ties
    ao = rng.uniform(0.05, 1.0, shape)
    ao_, op_ = jnp.asarray(ao, dtype), jnp.asarray(opacities, dtype)
    # a random cotangent: a NaN or inf in any row of the Jacobian shows in the product
    cotangent = jnp.asarray(rng.normal(size=shape[1:]), dtype)
    for merge in MERGES:
        _, vjp = jax.vjp(lambda a, o, m=merge: vs.merge_feature_ao(a, o, merge=m), ao_, op_)
        assert all(np.all(np.isfinite(np.asarray(g))) for g in vjp(cotangent))


# ----------------------------------------------------------------- properties


@pytest.mark.parametrize("merge", ["max", "feature"])
def test_one_feature_is_classic_lao(merge):
    vol = _shells()
    got = vs.feature_ao(vol, features=[SHELLS_TF], directions=DIRS, radius=5.0, samples=6,
                        merge=merge)
    classic = vs.lao(SHELLS_TF.opacity(vol), directions=DIRS, radius=5.0, samples=6)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(classic))


@pytest.mark.parametrize("merge", ["max", "feature"])
def test_never_darker_than_classic_lao(merge):
    # the features split the classified opacity, so each T_k sees fewer occluders than
    # classic AO (AO is monotone): no voxel gets darker, and the shells, which occlude
    # each other in classic AO, get lighter (the over-darkening of section 1)
    vol = _shells(24)
    features = [vs.IntervalFeature(0.0, 0.45), vs.IntervalFeature(0.45, 0.75),
                vs.IntervalFeature(0.75, 1.0)]
    assert np.allclose(np.asarray(vs.transfer.feature_opacities(vol, features, base=SHELLS_TF)
                                  .max(axis=0)), np.asarray(SHELLS_TF.opacity(vol)))
    fao = vs.feature_ao(vol, features=features, base=SHELLS_TF, directions=DIRS, radius=6.0,
                        samples=8, merge=merge)
    classic = vs.lao(SHELLS_TF.opacity(vol), directions=DIRS, radius=6.0, samples=8)
    gain = np.asarray(fao - classic)
    assert gain.min() >= -1e-12
    shells = np.asarray(vol) > 0
    assert gain[shells].mean() > 0.02


def test_a_feature_with_no_opacity_changes_nothing():
    vol = _shells()
    kw = dict(base=SHELLS_TF, directions=DIRS, radius=4.0, samples=6)
    nowhere = vs.IntervalFeature(0.42, 0.44)  # between the shells' values: empty
    assert float(jnp.max(nowhere.opacity(vol, SHELLS_TF))) == 0
    for merge in ("max", "neighbourhood"):
        with_it = vs.feature_ao(vol, features=[*SHELLS, nowhere], merge=merge, **kw)
        without = vs.feature_ao(vol, features=SHELLS, merge=merge, **kw)
        np.testing.assert_array_equal(np.asarray(with_it), np.asarray(without))


def test_empty_one_voxel_and_opaque_volumes():
    kw = dict(directions=DIRS, radius=3.0, samples=4)
    empty = vs.feature_ao(jnp.zeros((8, 8, 8)), features=SHELLS, base=SHELLS_TF, **kw)
    assert np.all(np.asarray(empty) == 1.0)
    # (offset 0.2: the first samples are close enough to read the voxel itself)
    one = vs.feature_ao(jnp.ones((1, 1, 1)), features=SHELLS, base=SHELLS_TF, offset=0.2, **kw)
    alone = vs.lao(SHELLS[2].opacity(jnp.ones((1, 1, 1)), SHELLS_TF), offset=0.2, **kw)
    assert one.shape == (1, 1, 1) and float(one[0, 0, 0]) == float(alone[0, 0, 0]) < 1

    opaque_tf = _ramp_tf([1.0, 1.0])

    def loss(radius):
        return jnp.sum(vs.feature_ao(jnp.ones((6, 6, 6)), features=[opaque_tf, opaque_tf],
                                     merge="neighbourhood", directions=DIRS, radius=radius,
                                     samples=4, opacity_correction=True))

    # the value from the program that the differences evaluate
    value_and_grad = jax.jit(jax.value_and_grad(loss, (0,)))
    assert float(value_and_grad(jnp.asarray(3.0))[0]) > 0
    check_grads_fd(value_and_grad, (jnp.asarray(3.0),), h=1e-5, n_dirs=1)


# ----------------------------------------------------------------- bricks


def _two_blobs():
    vol = np.zeros((24, 24, 24))
    vol[2:6, 3:7, 2:5] = 0.9        # feature "high"
    vol[16:21, 17:20, 15:20] = 0.3  # feature "low", far from the other
    return jnp.asarray(vol, jnp.float64)


FEATURES_2 = [vs.IntervalFeature(0.2, 0.4), vs.IntervalFeature(0.8, 1.0)]
TF_2 = _ramp_tf([0.0, 0.5, 0.9])


@pytest.mark.slow
def test_bricked_equals_unbricked_values_and_gradients():
    # bricks act on each feature's march, before the merge: one merge is enough
    vol, merge = _two_blobs(), "neighbourhood"

    def run(radius, brick_size):
        return vs.feature_ao(vol, features=FEATURES_2, base=TF_2, directions=DIRS,
                             radius=radius, samples=5, merge=merge, brick_size=brick_size,
                             max_radius=5.0)

    w = jnp.asarray(np.random.default_rng(1).uniform(size=vol.shape))

    def loss(radius, brick_size):
        ao = run(radius, brick_size)
        return jnp.sum(w * ao), ao

    # the AO itself from the same programs as the gradients
    grad = jax.jit(jax.value_and_grad(loss, has_aux=True), static_argnums=1)
    (bricked, ao_bricked), g_bricked = grad(3.5, 4)
    (full, ao_full), g_full = grad(3.5, None)
    np.testing.assert_allclose(float(bricked), float(full), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(ao_bricked), np.asarray(ao_full), rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(g_bricked), float(g_full), rtol=1e-10)
    assert float(g_full) != 0


# ----------------------------------------------------------------- transforms and autodiff


def test_jit_equals_eager_and_vmap_equals_a_loop():
    vols = jnp.stack([_shells(), _shells()[::-1, :, ::-1] * 0.9])
    fn = jax.jit(lambda v: vs.feature_ao(v, features=SHELLS, base=SHELLS_TF, directions=DIRS,
                                         radius=4.0, samples=5, merge="neighbourhood"))
    eager = [vs.feature_ao(v, features=SHELLS, base=SHELLS_TF, directions=DIRS, radius=4.0,
                           samples=5, merge="neighbourhood") for v in vols]
    assert not np.allclose(np.asarray(eager[0]), np.asarray(eager[1]))
    batched = jax.vmap(fn)(vols)
    for k in range(2):
        np.testing.assert_allclose(np.asarray(fn(vols[k])), np.asarray(eager[k]), atol=1e-12)
        np.testing.assert_allclose(np.asarray(batched[k]), np.asarray(eager[k]), atol=1e-12)


# ("feature" selects one T_k per voxel: its derivative is T_k's, which "max" exercises too;
# tests/test_transforms.py differentiates the merge itself)
@pytest.mark.parametrize("merge", ["max", "neighbourhood"])
def test_grads_vs_finite_differences(merge):
    vol = _shells(12)
    weight = jnp.asarray(np.random.default_rng(5).normal(size=vol.shape))

    def loss_radius_offset(p):
        return jnp.sum(weight * vs.feature_ao(
            vol, features=SHELLS, base=SHELLS_TF, directions=DIRS, radius=p[0], offset=p[1],
            samples=5, merge=merge, max_radius=6.0))

    g = check_grad_fd(jax.jit(loss_radius_offset), jnp.asarray([4.3, 0.7]), n_dirs=2)
    assert np.all(np.asarray(g) != 0)
    if merge != "neighbourhood":
        return

    # the control values of a transfer-function feature, through the merge with the most
    # arithmetic
    def loss_opacities(o):
        return jnp.sum(weight * vs.feature_ao(
            vol, features=[SHELLS[0], _ramp_tf(o)], base=SHELLS_TF, directions=DIRS,
            radius=4.0, samples=5, merge=merge))

    g = check_grad_fd(jax.jit(loss_opacities), jnp.asarray([0.05, 0.1, 0.3, 0.5]))
    assert float(jnp.max(jnp.abs(g))) > 0


def test_module_matches_function_and_differentiates():
    vol = _shells(12)
    params = vs.FeatureAmbientOcclusion(
        SHELLS, lao=vs.LocalAmbientOcclusion(4.0, directions=12, samples=5,
                                             opacity_correction=True), merge="feature")
    direct = vs.feature_ao(vol, features=SHELLS, base=SHELLS_TF, directions=params.lao.directions,
                           radius=4.0, samples=5, merge="feature", max_radius=8.0,
                           opacity_correction=True)
    np.testing.assert_array_equal(np.asarray(params(vol, base=SHELLS_TF)), np.asarray(direct))
    grads = eqx.filter_jit(eqx.filter_grad(
        lambda p: jnp.sum(p(vol, base=SHELLS_TF))))(params)
    # with the correction, a longer reach sees more of the shells: darker
    assert float(grads.lao.radius) < 0
    def at_offset(offset):
        moved = eqx.tree_at(lambda p: p.lao.offset, params, offset)
        return jnp.sum(moved(vol, base=SHELLS_TF))

    check_grad_fd(jax.jit(at_offset), jnp.asarray(1.0), h=1e-5, n_dirs=1)
    assert float(jnp.abs(grads.features[0].low)) == 0  # interval ends select: no gradient


def test_scene_renders_feature_ao_as_its_ambient_volume():
    vol = _shells(16)
    params = vs.FeatureAmbientOcclusion(
        SHELLS, lao=vs.LocalAmbientOcclusion(4.0, directions=12, samples=5))
    camera = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(12, 12))
    scene = vs.Scene(volume=vol, transfer=SHELLS_TF, ambient="feature_ao", feature_ao=params,
                     shading="phong")
    render = eqx.filter_jit(vs.render)
    image = render(scene, camera)
    ambient = params(vol, base=SHELLS_TF)
    same = render(vs.Scene(volume=vol, transfer=SHELLS_TF, ambient="volume",
                           ambient_volume=ambient, shading="phong"), camera)
    np.testing.assert_allclose(np.asarray(image), np.asarray(same), atol=1e-12)
    assert float(jnp.min(ambient)) < 0.9  # so the equality above is about something
    assert scene.plan()["ambient"] == "feature_ao"


# ----------------------------------------------------------------- bad input


@pytest.mark.parametrize("merge", sorted(MERGES))
def test_merge_refuses_bad_opacities_under_jit(merge):
    # "max" ignores the opacities: their run-time check was pruned under jit (found by
    # a review: a NaN opacity merged without an error)
    ao = jnp.full((2, 4, 4, 4), 0.5)
    merged = eqx.filter_jit(lambda a, o: vs.merge_feature_ao(a, o, merge=merge))
    for bad in (jnp.nan, 2.0):
        with pytest.raises(Exception, match="merge_feature_ao: `opacities`"):
            jax.block_until_ready(merged(ao, ao.at[0, 1, 2, 3].set(bad)))


def test_traced_bad_radius_is_refused_naming_feature_ao():
    # found by a review: under jit the loop's own check fired first, naming volshade.lao
    vol = _shells(8)
    features = [vs.IntervalFeature(0.2, 0.4), vs.IntervalFeature(0.8, 1.0)]
    base = vs.transfer.preset("shells")
    fn = eqx.filter_jit(lambda r: vs.feature_ao(vol, features=features, base=base,
                                                directions=DIRS, radius=r, samples=3))
    module = eqx.filter_jit(lambda r: vs.FeatureAmbientOcclusion(
        features, lao=vs.LocalAmbientOcclusion(r, directions=DIRS, samples=3))(vol, base=base))
    for call, name in ((fn, "volshade.feature_ao"), (module, "volshade.FeatureAmbientOcclusion")):
        for bad, why in ((jnp.nan, "`radius` finite"), (-1.0, "`radius` must be > `offset`")):
            with pytest.raises(eqx.EquinoxRuntimeError, match=f"{name}: .*{why}"):
                jax.block_until_ready(call(jnp.asarray(bad)))
    # and traced directions and weights (a review: their checks' results were unread, so
    # dropped under jit, and the march's own named volshade.lao)
    traced = eqx.filter_jit(lambda d, w: vs.feature_ao(vol, features=features, base=base,
                                                       directions=d, weights=w, radius=2.0,
                                                       samples=3))
    ones = jnp.ones(len(DIRS))
    for args, why in (((jnp.asarray(DIRS).at[0].set(jnp.nan), ones), "`directions` holds"),
                      ((jnp.asarray(DIRS), -ones), "`weights` must be finite, >= 0")):
        with pytest.raises(eqx.EquinoxRuntimeError, match=f"volshade.feature_ao: {why}"):
            jax.block_until_ready(traced(*args))


def test_bad_inputs_raise_clear_errors():
    vol = _shells(8)
    kw = dict(directions=DIRS, radius=3.0, samples=4)
    with pytest.raises(ValueError, match="features.*empty"):
        vs.feature_ao(vol, features=[], **kw)
    with pytest.raises(ValueError, match="unknown merge 'mean'.*'max'"):
        vs.feature_ao(vol, features=SHELLS, base=SHELLS_TF, merge="mean", **kw)
    with pytest.raises(ValueError, match="base="):
        vs.feature_ao(vol, features=SHELLS, **kw)
    with pytest.raises(ValueError, match="^volshade.feature_ao: unknown implementation 'cuda'"):
        vs.feature_ao(vol, features=SHELLS, base=SHELLS_TF, implementation="cuda", **kw)
    with pytest.raises(TypeError, match=r"features\[1\]"):
        vs.feature_ao(vol, features=[SHELLS_TF, "skull"], **kw)
    with pytest.raises(ValueError, match="radius.*offset"):
        vs.feature_ao(vol, features=[SHELLS_TF], directions=DIRS, radius=1.0, offset=2.0)
    with pytest.raises(ValueError, match="NaN or inf"):  # eager: at once
        vs.feature_ao(vol.at[1, 2, 3].set(jnp.nan), features=[SHELLS_TF], **kw)
    with pytest.raises(ValueError, match="shape of `ao`"):
        vs.merge_feature_ao(jnp.ones((2, 4, 4, 4)), jnp.ones((3, 4, 4, 4)))
    with pytest.raises(ValueError, match="`ao` must not be empty"):
        vs.merge_feature_ao(jnp.ones((0, 4, 4, 4)), jnp.ones((0, 4, 4, 4)))
    with pytest.raises(ValueError, match=r"\(F, D, H, W\)"):
        vs.merge_feature_ao(jnp.ones((4, 4, 4)), jnp.ones((4, 4, 4)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        vs.merge_feature_ao(jnp.full((1, 4, 4, 4), 1.5), jnp.ones((1, 4, 4, 4)))
    with pytest.raises(TypeError, match=r"list of features.*\[TransferFunction"):
        vs.feature_ao(vol, features=SHELLS_TF, **kw)
    with pytest.raises(TypeError, match=r"features.*list.*got float"):
        vs.feature_ao(vol, features=0.5, **kw)
    for step in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="`step` must be a finite number > 0"):
            vs.feature_ao(vol, features=SHELLS, base=SHELLS_TF, step=step, **kw)
    with pytest.raises(TypeError, match="`base` must be a volshade.TransferFunction"):
        vs.feature_ao(vol, features=SHELLS, base="shells", **kw)
    # a band written only over its own range names the feature and both fixes
    band = vs.TransferFunction.from_points([(0.2, 1, 0, 0, 0.0), (0.3, 1, 0, 0, 0.5),
                                            (0.4, 1, 0, 0, 0.0)])
    with pytest.raises(ValueError, match=r"^volshade.feature_ao: features\[1\]'s control points "
                                         r"span \[0.2, 0.4\], "
                                         r"but `volume` holds values in \[0, .*IntervalFeature"):
        vs.feature_ao(vol, features=[SHELLS_TF, band], **kw)
    with pytest.raises(Exception, match="outside the transfer function's control points"):
        jax.jit(lambda v: vs.feature_ao(v, features=[band], **kw))(vol)  # traced: at run time
    with pytest.raises(ValueError, match="features.*empty"):
        vs.FeatureAmbientOcclusion([])
    with pytest.raises(TypeError, match=r"features\[0\]"):
        vs.FeatureAmbientOcclusion([0.5])
    with pytest.raises(ValueError, match="unknown merge"):
        vs.FeatureAmbientOcclusion(SHELLS, merge="min")
    with pytest.raises(ValueError, match="ambient='feature_ao' needs"):
        vs.Scene(volume=vol, transfer=SHELLS_TF, ambient="feature_ao")


def test_scene_corrects_feature_opacities_to_the_voxel_step():
    # as for ambient="lao": with the opacity correction each feature's opacity is that of
    # a one-voxel step (2 mm voxels here), however the transfer function is written
    from volshade.scene import _feature_ao_ambient

    per_mm, per_half_mm = one_medium_written_twice()
    vol = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (10, 10, 10)))
    params = vs.FeatureAmbientOcclusion(
        [vs.IntervalFeature(0.0, 0.5), vs.IntervalFeature(0.5, 1.0)],
        lao=vs.LocalAmbientOcclusion(3.0, offset=0.5, directions=6, samples=4,
                                     opacity_correction=True))
    aos = [_feature_ao_ambient(vs.Scene(volume=vol, transfer=tf, ambient="feature_ao",
                                        feature_ao=params, spacing=(2.0, 2.0, 2.0)))
           for tf in (per_mm, per_half_mm)]
    np.testing.assert_allclose(np.asarray(aos[0]), np.asarray(aos[1]), atol=1e-12)
    np.testing.assert_allclose(np.asarray(aos[0]), np.asarray(params(vol, base=per_mm, step=2.0)),
                               atol=1e-12)
    assert np.abs(np.asarray(aos[0] - params(vol, base=per_mm))).max() > 0.01


def test_neighbourhood_merge_falls_back_below_the_dtypes_epsilon():
    """A float32 neighbourhood whose summed opacity is below float32's epsilon (but far
    above float64's) takes the "max" merge, as the reference does in that dtype."""
    ao = np.stack([np.full((3, 3, 3), 0.9), np.full((3, 3, 3), 0.4)]).astype(np.float32)
    opacities = np.zeros((2, 3, 3, 3), np.float32)
    opacities[0, 0, 0, 0] = opacities[1, 2, 2, 2] = 1e-9
    got = vs.merge_feature_ao(jnp.asarray(ao), jnp.asarray(opacities), merge="neighbourhood")
    np.testing.assert_array_equal(np.asarray(got)[1, 1, 1], np.float32(0.4))
    np.testing.assert_allclose(np.asarray(got), merge_reference(ao, opacities, "neighbourhood"),
                               rtol=0, atol=1e-7)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_merges_in_float32(dtype):
    # summed opacities of 3e-3 (above float16's epsilon, the fallback's bound): the mean's
    # derivative, of order 1 / sum^2, overflowed float16 and made every entry NaN
    ao = np.stack([np.full((4, 4, 4), 0.9), np.full((4, 4, 4), 0.4)])
    opacities = np.zeros((2, 4, 4, 4))
    opacities[0, 1, 1, 1], opacities[1, 1, 1, 2] = 2e-3, 1e-3

    def merged(ao, opacities):
        return vs.merge_feature_ao(ao, opacities, merge="neighbourhood")

    half = [jnp.asarray(x, dtype) for x in (ao, opacities)]
    wide = [x.astype(jnp.float32) for x in half]
    out = merged(*half)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, merged(*wide).astype(dtype))
    for g, w in zip(jax.grad(lambda *a: merged(*a).astype(jnp.float32).sum(), (0, 1))(*half),
                    jax.grad(lambda *a: merged(*a).sum(), (0, 1))(*wide), strict=True):
        assert g.dtype == dtype and np.all(np.isfinite(np.asarray(g, np.float32)))
        np.testing.assert_allclose(np.asarray(g, np.float32), np.asarray(w.astype(dtype),
                                                                         np.float32))


def test_an_eager_call_compiles_once():
    # the per-feature loop is compiled once per structure, not traced again per call
    from volshade.feature_ao import _merged

    vol, tf = vs.data.phantom("shells", shape=12), vs.transfer.preset("shells")
    features = [vs.IntervalFeature(0.2, 0.4), vs.IntervalFeature(0.5, 1.0)]
    module = vs.FeatureAmbientOcclusion(features, lao=vs.LocalAmbientOcclusion(
        3.0, directions=4, samples=4))
    for call in (lambda v: vs.feature_ao(v, features=features, base=tf, directions=4,
                                         radius=3.0, samples=4),
                 lambda v: module(v, base=tf)):
        first = call(vol)
        compiled = _merged._cached._cache_size()
        np.testing.assert_array_equal(call(vol + 0.0), first)
        assert _merged._cached._cache_size() == compiled
    # another radius (the same whole-number padding) and another offset: no new compile
    other = vs.feature_ao(vol, features=features, base=tf, directions=4, radius=2.6,
                          offset=0.5, samples=4)
    assert _merged._cached._cache_size() == compiled
    np.testing.assert_array_equal(other, vs.feature_ao(
        vol, features=features, base=tf, directions=vs.directions.fibonacci(4), radius=2.6,
        offset=0.5, samples=4))


def test_numpy_scalars_are_options_and_known_bad_values_raise_at_once():
    vol, tf = vs.data.phantom("shells", shape=8), vs.transfer.preset("shells")
    features = [vs.IntervalFeature(0.8, 1.0), vs.IntervalFeature(0.2, 0.4)]
    plain = dict(directions=6, radius=3.0, samples=4, brick_size=4, max_radius=5.0,
                 opacity_correction=True)
    numpy = dict(directions=np.int64(6), radius=np.float32(3.0), samples=np.int64(4),
                 brick_size=np.int64(4), max_radius=np.float32(5.0),
                 opacity_correction=np.bool_(True))
    np.testing.assert_array_equal(vs.feature_ao(vol, features=features, base=tf, **numpy),
                                  vs.feature_ao(vol, features=features, base=tf, **plain))
    for bad, match in ((dict(weights=-np.ones(6)), "`weights` must be finite, >= 0"),
                       (dict(radius=1.0, offset=2.0), "must be > `offset`")):
        with pytest.raises(ValueError, match=f"^volshade.feature_ao: .*{match}"):
            vs.feature_ao(vol, features=features, base=tf, **{**plain, **bad})
    module = vs.FeatureAmbientOcclusion(features, lao=vs.LocalAmbientOcclusion(
        3.0, directions=6, samples=4, max_radius=4.0))
    stepped = eqx.tree_at(lambda m: m.lao.radius, module, jnp.asarray(5.0))  # e.g. by a fit
    with pytest.raises(ValueError, match="^volshade.FeatureAmbientOcclusion: .*exceeds "
                                         "`max_radius`"):
        stepped(vol, base=tf)


def test_feature_labels_checks_its_input():
    # found by a review: a 3-D volume was read as (F, H, W), NaN made a voxel of opacity
    # 0.5 "no feature", and an empty or list input failed inside Python
    with pytest.raises(ValueError, match=r"feature_labels: `opacities` must have 4 dimensions"):
        feature_labels(jnp.ones((4, 4, 4)))
    with pytest.raises(ValueError, match="`opacities` must not be empty"):
        feature_labels(jnp.zeros((0, 2, 2, 2)))
    with pytest.raises(ValueError, match="`opacities` contains NaN"):
        feature_labels(jnp.array([jnp.nan, 0.5]).reshape(2, 1, 1, 1))
    with pytest.raises(ValueError, match=r"`opacities` must lie in \[0, 1\]"):
        feature_labels(jnp.array([2.0, 0.5]).reshape(2, 1, 1, 1))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`opacities` contains NaN"):
        eqx.filter_jit(feature_labels)(jnp.array([jnp.nan, 0.5]).reshape(2, 1, 1, 1))
    assert feature_labels([[[[0.5]]], [[[0.7]]]]).tolist() == [[[1]]]
