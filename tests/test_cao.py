"""Tests of volshade.cao: contextual AO equals a full LAO recompute under the clip, in
values (every clip shape, also moving under jit and vmap) and in gradients (w.r.t. the
opacity and the radius; the clip gets none)."""

import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade as vs
from volshade.cao import affected_fraction

RNG = np.random.default_rng(5)
ALPHA = jnp.asarray(RNG.uniform(0, 1, (24, 22, 26)) ** 3)
DIRS = vs.directions.icosphere(0)
KW = dict(directions=DIRS, radius=3.5, offset=0.5, samples=6)
ROTATION = np.linalg.qr(RNG.normal(size=(3, 3)))[0]
CLIPS = {
    "sphere": vs.SphereClip(center=(5.0, 6.0, 7.0), radius=3.5),
    "box": vs.BoxClip(center=(18.0, 9.0, 14.0), half_size=(3.0, 4.5, 2.0), rotation=ROTATION),
    "torus": vs.TorusClip(center=(12.0, 11.0, 13.0), major=4.0, minor=1.2, rotation=ROTATION),
    "half-space": vs.HalfSpaceClip(center=(20.0, 0.0, 0.0)),
}
# moving poses, in the vmapped and the forward-mode tests: a sphere at each centre
POSE_ALPHA = ALPHA[:12, :12, :12]
POSE_KW = dict(directions=DIRS, offset=0.5, samples=3, max_radius=4.0)
POSE_CENTRES = jnp.asarray([[2.0, 2.0, 2.0], [10.0, 3.0, 8.0], [40.0, 40.0, 40.0]])
POSE_RADII = jnp.asarray([3.5, 2.5, 3.0])
POSE_W = jnp.asarray(RNG.normal(size=POSE_ALPHA.shape))


def _pose_ao(alpha, radius, centre):
    clip = vs.SphereClip(center=centre, radius=3.0)
    return vs.contextual_ao(alpha, clip=clip, unclipped=vs.lao(alpha, radius=radius, **POSE_KW),
                            radius=radius, brick_size=4, **POSE_KW)


def _pose_loss(alpha, radius, centre):
    return jnp.sum(POSE_W * _pose_ao(alpha, radius, centre))


# one pose's value and gradient w.r.t. the opacity and the radius: one compiled program
# for both tests (a gradient of contextual AO traces and compiles in 2-3 s)
_pose_grad = jax.value_and_grad(_pose_loss, argnums=(0, 1))
_one_pose_grad = jax.jit(_pose_grad)


def _full(alpha, clip, **kw):
    """The reference: LAO of the clipped opacity, every voxel marched."""
    return vs.lao(vs.clip_opacity(alpha, clip), **kw)


@pytest.mark.parametrize("name", sorted(CLIPS))
def test_equals_a_full_recompute(name):
    clip = CLIPS[name]
    unclipped = vs.lao(ALPHA, **KW)
    got = vs.contextual_ao(ALPHA, clip=clip, unclipped=unclipped, brick_size=4, **KW)
    # the clip changes a part of the volume, and only that part is marched again
    full = _full(ALPHA, clip, **KW)
    assert 0.01 < float(jnp.mean(jnp.abs(full - unclipped) > 1e-9)) < 0.6
    assert 0 < affected_fraction(ALPHA.shape, clip, radius=3.5, brick_size=4) <= 0.5
    np.testing.assert_allclose(np.asarray(got), np.asarray(full), rtol=0, atol=1e-12)


def test_float32_weights_and_correction():
    alpha = ALPHA.astype(jnp.float32)
    weights = jnp.asarray(RNG.uniform(0.2, 2.0, DIRS.shape[0]), jnp.float32)
    kw = dict(KW, weights=weights, opacity_correction=True)
    clip = CLIPS["torus"]
    assert affected_fraction(alpha.shape, clip, radius=3.5, brick_size=4) <= 0.5  # sparse
    got = vs.contextual_ao(alpha, clip=clip, unclipped=vs.lao(alpha, **kw), brick_size=4, **kw)
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), np.asarray(_full(alpha, clip, **kw)), rtol=0,
                               atol=1e-6)


def test_the_reach_is_needed_and_enough_voxel_by_voxel():
    # bricks of one voxel, many samples, random directions: the voxels whose AO the clip
    # changes all lie in the affected mask, some of them farther than R from the clip (so
    # a reach of R alone would miss them), and marching only the mask gives the full AO
    alpha = ALPHA[:14, :14, :14]
    clip = vs.HalfSpaceClip(center=(9.0, 0.0, 0.0))
    # (one ray along d, which the half-space's removed voxels lie across)
    dirs = jnp.concatenate([jnp.asarray([[1.0, 0.0, 0.0]]),
                            vs.directions.random_polar(8, key=jax.random.key(4))])
    kw = dict(directions=dirs, radius=3.5, offset=0.5, samples=12)
    unclipped = vs.lao(alpha, **kw)
    full = _full(alpha, clip, **kw)
    changed = np.asarray(jnp.abs(full - unclipped) > 0)
    affected = np.asarray(vs.affected_mask(alpha.shape, clip, radius=3.5))
    assert np.all(affected[changed])
    distance = 9.0 - np.arange(14)[:, None, None] * np.ones((1, 14, 14))
    assert np.any(changed & (distance >= 3.5))
    got = vs.contextual_ao(alpha, clip=clip, unclipped=unclipped, brick_size=1, **kw)
    np.testing.assert_allclose(np.asarray(got), np.asarray(full), rtol=0, atol=1e-12)


def test_unclipped_from_other_paddings_and_bricks():
    # the unclipped AO may come from lao with bricks, another max_radius or a traced
    # radius (another padding): the same values, so the same result
    clip = CLIPS["sphere"]
    full = _full(ALPHA, clip, **KW)
    for unclipped in (vs.lao(ALPHA, **KW, brick_size=4), vs.lao(ALPHA, **KW, max_radius=9.0),
                      jax.jit(lambda r: vs.lao(ALPHA, **dict(KW, radius=r)))(3.5)):
        got = vs.contextual_ao(ALPHA, clip=clip, unclipped=unclipped, brick_size=4, **KW)
        np.testing.assert_allclose(np.asarray(got), np.asarray(full), rtol=0, atol=1e-12)


def test_traced_clips_are_checked_where_used():
    unclipped = vs.lao(ALPHA, **KW)

    def run(rotation, centre):
        clip = vs.BoxClip(center=centre, half_size=2.0, rotation=rotation)
        return vs.contextual_ao(ALPHA, clip=clip, unclipped=unclipped, **KW)

    fine = eqx.filter_jit(run)(jnp.eye(3), jnp.asarray([5.0, 5.0, 5.0]))
    clipped = vs.clip_opacity(ALPHA, vs.BoxClip(center=(5.0, 5.0, 5.0), half_size=2.0))
    np.testing.assert_allclose(np.asarray(fine), np.asarray(vs.lao(clipped, **KW)), rtol=0,
                               atol=1e-12)
    for rotation, centre in ((2 * jnp.eye(3), [5.0, 5.0, 5.0]), (jnp.eye(3), [5.0, jnp.nan, 5.0])):
        with pytest.raises(eqx.EquinoxRuntimeError, match="orthonormal"):
            jax.block_until_ready(eqx.filter_jit(run)(rotation, jnp.asarray(centre)))


def test_large_clip_marches_the_whole_volume_and_still_agrees():
    clip = vs.SphereClip(center=(12.0, 11.0, 13.0), radius=9.0)
    assert affected_fraction(ALPHA.shape, clip, radius=3.5) > 0.5  # the dense branch
    got = vs.contextual_ao(ALPHA, clip=clip, unclipped=vs.lao(ALPHA, **KW), **KW)
    np.testing.assert_allclose(np.asarray(got), np.asarray(_full(ALPHA, clip, **KW)),
                               rtol=0, atol=1e-12)


def test_hard_cases():
    unclipped = vs.lao(ALPHA, **KW)
    # a clip outside the volume removes nothing: the unclipped AO, exactly
    away = vs.SphereClip(center=(-20.0, -20.0, -20.0), radius=2.0)
    np.testing.assert_array_equal(
        np.asarray(vs.contextual_ao(ALPHA, clip=away, unclipped=unclipped, **KW)),
        np.asarray(unclipped))
    # a clip that removes everything: nothing occludes
    everything = vs.HalfSpaceClip(center=(-1.0, 0.0, 0.0))
    out = vs.contextual_ao(ALPHA, clip=everything, unclipped=unclipped, **KW)
    assert np.all(np.asarray(out) == 1.0)
    # one voxel, clipped or not; M = 1
    one = jnp.full((1, 1, 1), 0.7)
    kept = vs.SphereClip(center=(5.0, 5.0, 5.0), radius=1.0)
    assert float(vs.contextual_ao(one, clip=kept, unclipped=vs.lao(one, **KW), **KW)[0, 0, 0]) \
        == float(vs.lao(one, **KW)[0, 0, 0])
    m1 = dict(KW, samples=1)
    assert np.all(np.asarray(vs.contextual_ao(ALPHA, clip=CLIPS["box"],
                                              unclipped=vs.lao(ALPHA, **m1), **m1)) == 1.0)


def _axes(first):
    """An orthonormal matrix whose first column points along ``first``."""
    q, r = np.linalg.qr(np.column_stack([first, np.eye(3)[:, :2]]))
    return q * np.sign(np.diag(r))


# each shape at a traced pose, its sizes fixed: a clip moving through a 16^3 volume
MOVING = {
    "sphere": lambda centre, rotation: vs.SphereClip(center=centre, radius=2.0,
                                                     rotation=rotation),
    "box": lambda centre, rotation: vs.BoxClip(center=centre, half_size=(1.5, 2.0, 1.0),
                                               rotation=rotation),
    "torus": lambda centre, rotation: vs.TorusClip(center=centre, major=2.0, minor=0.8,
                                                   rotation=rotation),
    "half-space": lambda centre, rotation: vs.HalfSpaceClip(center=centre, rotation=rotation),
}


@pytest.mark.parametrize("name", sorted(MOVING))
def test_moving_clip_under_jit_and_vmap_never_recompiles(name):
    alpha, kw = ALPHA[:16, :16, :16], dict(KW, radius=2.5, samples=4)
    unclipped = vs.lao(alpha, **kw)
    traces = []

    @jax.jit
    def frame(centre, rotation):
        traces.append(1)
        return vs.contextual_ao(alpha, clip=MOVING[name](centre, rotation),
                                unclipped=unclipped, brick_size=4, **kw)

    # a pose at a corner (few bricks marched), one inside, one outside the volume (the
    # first local axis, a half-space's normal, pointing out of it)
    centres = jnp.asarray([[14.0, 1.0, 2.0], [8.0, 12.0, 4.0], [40.0, 40.0, 40.0]])
    rotations = jnp.asarray(np.stack([_axes([1.0, -1.0, -1.0]), ROTATION,
                                      _axes([1.0, 1.0, 1.0])]))
    clips = [MOVING[name](c, r) for c, r in zip(centres, rotations, strict=True)]
    full = [_full(alpha, clip, **kw) for clip in clips]
    assert 0 < affected_fraction(alpha.shape, clips[0], radius=2.5, brick_size=4) <= 0.5
    assert float(jnp.max(jnp.abs(full[0] - full[1]))) > 0.1  # the poses differ
    np.testing.assert_array_equal(np.asarray(full[2]), np.asarray(unclipped))
    frames = [frame(c, r) for c, r in zip(centres, rotations, strict=True)]
    assert len(traces) == 1
    batched = jax.vmap(frame)(centres, rotations)  # every pose is its own
    for i in range(len(full)):
        np.testing.assert_allclose(np.asarray(frames[i]), np.asarray(full[i]), rtol=0,
                                   atol=1e-12)
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(full[i]), rtol=0,
                                   atol=1e-12)


def test_clips_built_from_numbers_or_arrays_share_one_compile():
    # a size given as a Python number is a weakly typed leaf, and the same clip built
    # with arrays compiled contextual_ao (and clip_opacity) a second time, as a notebook
    # moving a clip from one kind of value to the other would
    cao, clip_module = (sys.modules[f"volshade.{m}"] for m in ("cao", "clip"))
    alpha, kw = ALPHA[:12, :12, :12].astype(jnp.float32), dict(KW, radius=2.5, samples=3)
    unclipped = vs.lao(alpha, **kw)
    dtype = jnp.result_type(float)  # the default float dtype: jnp.asarray(2.5) is weak too
    clips = [vs.TorusClip(center=(6.0, 5.0, 6.0), major=3.0, minor=1.0),
             vs.TorusClip(center=jnp.asarray([5.0, 6.0, 6.0], dtype),
                          major=jnp.asarray(2.5, dtype), minor=jnp.asarray(1.5, dtype))]
    compiled = [cao._contextual._cached, clip_module._compiled_clip_opacity._cached]
    sizes = None
    for clip in clips:
        got = vs.contextual_ao(alpha, clip=clip, unclipped=unclipped, brick_size=4, **kw)
        np.testing.assert_allclose(got, _full(alpha, clip, **kw), rtol=0, atol=1e-6)
        sizes = sizes or [f._cache_size() for f in compiled]
    assert [f._cache_size() for f in compiled] == sizes


@pytest.mark.slow
def test_gradients_equal_the_full_recompute_and_finite_differences():
    # unclipped computed inside the differentiated function: its gradient is that of
    # the voxels the clip cannot change, under the clip too
    clip = vs.SphereClip(center=(2.0, 2.0, 2.0), radius=3.0)
    alpha = ALPHA[:16, :16, :16]
    w = jnp.asarray(RNG.normal(size=alpha.shape))
    # random directions: no sample sits on a voxel boundary (a kink of the trilinear
    # interpolation, where central differences and the gradient may differ)
    kw = dict(KW, directions=vs.directions.random_polar(5, key=jax.random.key(2)),
              max_radius=5.0)
    kw.pop("radius")

    def contextual(alpha, radius, clip):
        unclipped = vs.lao(alpha, radius=radius, **kw)
        return jnp.sum(w * vs.contextual_ao(alpha, clip=clip, unclipped=unclipped,
                                            radius=radius, brick_size=4, **kw))

    def full(alpha, radius):
        return jnp.sum(w * _full(alpha, clip, radius=radius, **kw))

    assert 0 < affected_fraction(alpha.shape, clip, radius=3.5, brick_size=4) <= 0.5
    r = jnp.asarray(3.5)
    got = jax.jit(jax.grad(contextual, argnums=(0, 1, 2)))(alpha, r, clip)
    ref = jax.jit(jax.grad(full, argnums=(0, 1)))(alpha, r)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(ref[0]), rtol=0, atol=1e-10)
    np.testing.assert_allclose(float(got[1]), float(ref[1]), rtol=1e-10)
    assert float(jnp.max(jnp.abs(got[0]))) > 0
    # the masks are piecewise constant in the clip's pose and size: no gradient
    assert all(np.all(np.asarray(x) == 0) for x in jax.tree.leaves(got[2]))
    value, h = jax.jit(contextual), 1e-6
    fd = (value(alpha, r + h, clip) - value(alpha, r - h, clip)) / (2 * h)
    np.testing.assert_allclose(float(got[1]), float(fd), rtol=1e-4)


@pytest.mark.slow
def test_vmapped_poses_keep_their_values_and_gradients():
    # under vmap every pose is computed alone (a loop: each marches its own bricks), in
    # its value and in its gradient w.r.t. the opacity and the radius
    value, (d_alpha, d_radius) = jax.jit(jax.vmap(_pose_grad, in_axes=(None, 0, 0)))(
        POSE_ALPHA, POSE_RADII, POSE_CENTRES)
    for i in range(3):
        want_value, (want_alpha, want_radius) = _one_pose_grad(POSE_ALPHA, POSE_RADII[i],
                                                               POSE_CENTRES[i])
        np.testing.assert_allclose(float(value[i]), float(want_value), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(d_alpha[i]), np.asarray(want_alpha), rtol=0,
                                   atol=1e-12)
        np.testing.assert_allclose(float(d_radius[i]), float(want_radius), rtol=1e-10)
        assert float(jnp.max(jnp.abs(d_alpha[i]))) > 0


def test_bad_inputs_raise_clear_errors():
    unclipped = vs.lao(ALPHA, **KW)
    with pytest.raises(TypeError, match="`clip` must be a volshade clip shape"):
        vs.contextual_ao(ALPHA, clip=None, unclipped=unclipped, **KW)
    with pytest.raises(ValueError, match="`unclipped` must be the LAO of `alpha`"):
        vs.contextual_ao(ALPHA, clip=CLIPS["box"], unclipped=unclipped[1:], **KW)
    with pytest.raises(ValueError, match=r"`unclipped` must lie in \[0, 1\]"):
        vs.contextual_ao(ALPHA, clip=CLIPS["box"], unclipped=unclipped + 1, **KW)
    with pytest.raises(ValueError, match="volshade.contextual_ao: `radius`"):
        vs.contextual_ao(ALPHA, clip=CLIPS["box"], unclipped=unclipped, directions=DIRS,
                         radius=0.5, offset=1.0)
    with pytest.raises(ValueError, match="`brick_size` must be >= 1"):
        vs.contextual_ao(ALPHA, clip=CLIPS["box"], unclipped=unclipped, brick_size=0, **KW)
    # named for the function called (it named volshade.affected_mask)
    with pytest.raises(ValueError, match="volshade.cao.affected_fraction: `radius` must be"):
        affected_fraction(ALPHA.shape, CLIPS["box"], radius=float("nan"))


@pytest.mark.parametrize("samples", [6, 1])  # M = 1 takes no sample but checks as much
def test_bad_values_raise_under_jit(samples):
    kw = dict(KW, samples=samples, max_radius=4.0)
    alpha = jnp.full((8, 8, 8), 0.5)
    unclipped = vs.lao(alpha, **kw)
    f = eqx.filter_jit(lambda a, u, c, r: vs.contextual_ao(a, clip=c, unclipped=u,
                                                           **dict(kw, radius=r)))
    sphere = vs.SphereClip(center=(4.0, 4.0, 4.0), radius=2.0)
    radius = jnp.asarray(3.5)  # an array: traced by filter_jit, as the others
    with pytest.raises(eqx.EquinoxRuntimeError, match="`alpha` contains NaN or inf"):
        jax.block_until_ready(f(alpha.at[0, 0, 0].set(jnp.nan), unclipped, sphere, radius))
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`unclipped` must lie in \[0, 1\]"):
        jax.block_until_ready(f(alpha, unclipped + 1, sphere, radius))
    with pytest.raises(eqx.EquinoxRuntimeError, match="SphereClip: the clip's leaves must be "
                                                      "finite"):
        jax.block_until_ready(f(alpha, unclipped, eqx.tree_at(lambda c: c.center, sphere,
                                                               jnp.full(3, jnp.nan)), radius))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`radius` must be > `offset`"):
        jax.block_until_ready(f(alpha, unclipped, sphere, jnp.asarray(0.25)))


def test_scene_clips_the_render_and_the_lao_ambient():
    from volshade.scene import _lao_ambient

    vol = vs.data.phantom("shells", shape=16).astype(jnp.float64)
    tf = vs.transfer.preset("shells")
    params = vs.LocalAmbientOcclusion(3.0, directions=12, samples=5)
    clip = vs.SphereClip(center=(8.0, 8.0, 16.0), radius=7.0)
    scene = vs.Scene(volume=vol, transfer=tf, ambient="lao", lao=params, clip=clip,
                     shading="phong")
    np.testing.assert_allclose(np.asarray(_lao_ambient(scene)),
                               np.asarray(params(vs.clip_opacity(tf.opacity(vol), clip))),
                               atol=1e-12)
    camera = vs.Camera.orbit(azimuth=90, elevation=0, image_shape=(16, 16))
    render = eqx.filter_jit(vs.render)
    clipped = np.asarray(render(vs.Scene(volume=vol, transfer=tf, clip=clip), camera))
    whole = np.asarray(render(vs.Scene(volume=vol, transfer=tf), camera))
    assert clipped[..., 3].sum() < 0.95 * whole[..., 3].sum()
    # a clip that removes everything: nothing drawn (a sphere, as the clip above: the
    # same compiled render)
    gone = vs.Scene(volume=vol, transfer=tf, clip=vs.SphereClip(center=(8.0, 8.0, 8.0),
                                                               radius=100.0))
    assert np.all(np.asarray(render(gone, camera))[..., 3] == 0)
    with pytest.raises(ValueError, match="does not take `clip` into account"):
        vs.Scene(volume=vol, transfer=tf, ambient="obscurance", clip=clip)
    with pytest.raises(ValueError, match="does not take `clip` into account"):
        vs.Scene(volume=vol, transfer=tf, modulation="saliency", clip=clip)
    with pytest.raises(TypeError, match="`clip` must be a volshade clip shape"):
        vs.Scene(volume=vol, transfer=tf, clip="sphere")


def test_forward_mode_of_moving_poses_is_the_transpose_of_reverse_mode():
    # jax.jvp through contextual AO, vmapped over poses (each run alone, a loop): a tangent
    # in the opacity and the radius, against each pose's own gradient (<c, J t> = <J^T c, t>,
    # c the weights of _pose_loss)
    alpha = POSE_ALPHA
    t_alpha = jnp.asarray(RNG.normal(size=alpha.shape))
    tangents = jax.jit(jax.vmap(lambda r, x: jax.jvp(
        lambda a, r: _pose_ao(a, r, x), (alpha, r), (t_alpha, jnp.ones_like(r)))[1]))(
        POSE_RADII, POSE_CENTRES)
    for i in range(3):
        g_alpha, g_radius = _one_pose_grad(alpha, POSE_RADII[i], POSE_CENTRES[i])[1]
        want = float(jnp.vdot(g_alpha, t_alpha) + g_radius)
        np.testing.assert_allclose(float(jnp.vdot(POSE_W, tangents[i])), want, rtol=1e-12)
        # and the same as the full recompute's tangent
        clip = vs.SphereClip(center=POSE_CENTRES[i], radius=3.0)
        full = jax.jvp(lambda a, r, clip=clip: _full(a, clip, radius=r, **POSE_KW),
                       (alpha, POSE_RADII[i]), (t_alpha, jnp.ones_like(POSE_RADII[i])))[1]
        np.testing.assert_allclose(np.asarray(tangents[i]), np.asarray(full), rtol=0,
                                   atol=1e-12)
