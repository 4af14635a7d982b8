import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import check_grad_fd, check_grads_fd, run_with_user_xla_flags, strongly_typed

import volshade as vs
from volshade.camera import Camera, box_half_extent, intersect_box
from volshade.render import march, n_samples, save_png
from volshade.shading import Phong, blinn_phong
from volshade.transfer import TransferFunction, preset


def _constant_tf(alpha0, color=(0.2, 0.6, 1.0), dtype=jnp.float64):
    return TransferFunction.from_points([(0.0, *color, alpha0), (1.0, *color, alpha0)], dtype=dtype)


def _path_through_box(camera, shape, spacing):
    """Each ray's (entry, exit) parameters through the volume's box, by the slab method in
    NumPy (independent of the renderer's own intersection): the box of voxel cells,
    centred at the origin, longest side 1."""
    origins, dirs = (np.asarray(a, np.float64) for a in camera.rays())
    extent = np.asarray(shape, float) * np.asarray(spacing, float)
    half = extent / extent.max() / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        lo, hi = (-half - origins) / dirs, (half - origins) / dirs
    near = np.max(np.where(dirs == 0, -np.inf, np.minimum(lo, hi)), axis=-1)
    far = np.min(np.where(dirs == 0, np.inf, np.maximum(lo, hi)), axis=-1)
    outside = np.any((dirs == 0) & (np.abs(origins) > half), axis=-1)
    return np.where(outside, 0.0, np.maximum(near, 0.0)), np.where(outside, 0.0, far)


def _ortho_along_h(image_shape=(6, 6), width=1.5):
    # Azimuth 0, elevation 0: parallel rays along -h.
    return Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=image_shape,
                        projection="orthographic", width=width)


def _smooth_volume(n=10, seed=0):
    rng = np.random.default_rng(seed)
    x = np.linspace(-1, 1, n)
    d, h, w = np.meshgrid(x, x, x, indexing="ij")
    c = rng.uniform(-0.3, 0.3, 3)
    vol = np.exp(-((d - c[0]) ** 2 + (h - c[1]) ** 2 + (w - c[2]) ** 2) * 2.5)
    return jnp.asarray(vol)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_empty_volume_renders_background_exactly(dtype):
    bg = (0.25, 0.5, 0.75)
    img = march(jnp.zeros((8, 9, 10), dtype), preset("grey"), Camera.orbit(image_shape=(7, 5)),
                background=bg, shading="phong")
    assert img.dtype == dtype
    np.testing.assert_array_equal(img[..., :3], np.broadcast_to(np.asarray(bg, dtype), (7, 5, 3)))
    np.testing.assert_array_equal(img[..., 3], 0)


@pytest.mark.parametrize("step", [0.3, 1.0, 1.7])
def test_uniform_slab_matches_beer_lambert(step):
    alpha0 = 0.1
    tau = -np.log1p(-alpha0)
    shape, spacing = (8, 12, 10), (1.0, 1.5, 0.8)
    color = np.array([0.2, 0.6, 1.0])
    img = march(jnp.full(shape, 0.5), _constant_tf(alpha0), _ortho_along_h(), spacing=spacing,
                step=step)
    # Rays along h that hit the box cross it completely: 12 voxels of 1.5 mm.
    t0, t1 = _path_through_box(_ortho_along_h(), shape, spacing)
    hit = t1 > t0
    assert hit.sum() > 0 and (~hit).sum() > 0
    expected_alpha = 1 - np.exp(-tau * shape[1] * spacing[1])
    np.testing.assert_allclose(np.asarray(img[..., 3])[hit], expected_alpha, atol=1e-5)
    np.testing.assert_allclose(np.asarray(img[..., :3])[hit],
                               np.broadcast_to(expected_alpha * color, (hit.sum(), 3)), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(img[..., 3])[~hit], 0)


# rays of many lengths (and misses) in one image: the march sorts them into groups of
# similar length (81 rays: 3 copies of the longest pad the last group; one ray: one
# group) and marches each only as far as its longest ray, in chunks
@pytest.mark.parametrize("image_shape", [(9, 9), (1, 1), (2, 3)])
def test_uniform_slab_oblique_rays_match_path_lengths(image_shape):
    alpha0, shape = 0.05, (10, 10, 10)
    cam = Camera.orbit(azimuth=33.0, elevation=21.0, image_shape=image_shape,
                       fov=30.0 if image_shape != (1, 1) else 5.0)
    img = march(jnp.full(shape, 0.5), _constant_tf(alpha0), cam, step=0.7)
    t0, t1 = _path_through_box(cam, shape, (1, 1, 1))
    path_mm = np.maximum(t1 - t0, 0) * 10.0
    np.testing.assert_allclose(img[..., 3], 1 - (1 - alpha0) ** path_mm, atol=1e-5)


def test_opacity_correction_converges_as_step_shrinks():
    vol = _smooth_volume(12)
    tf = TransferFunction.from_points([(0.0, 0.1, 0.2, 0.3, 0.0), (0.5, 1.0, 0.5, 0.2, 0.2),
                                       (1.0, 1.0, 1.0, 1.0, 0.6)])
    cam = Camera.orbit(azimuth=20.0, elevation=15.0, image_shape=(10, 10))
    steps = [2.0, 1.0, 0.5, 0.25]
    finest = march(vol, tf, cam, step=0.0625)
    errors = [float(jnp.max(jnp.abs(march(vol, tf, cam, step=s) - finest))) for s in steps]
    assert all(a > b for a, b in zip(errors, errors[1:], strict=False)), errors
    assert errors[-1] < 0.2 * errors[0]


def test_gradient_wrt_transfer_function_matches_finite_differences():
    vol = _smooth_volume(8)
    # control values inside (0, 1), so that the differences stay in the valid range
    tf = TransferFunction.from_points([(0.0, 0.1, 0.2, 0.3, 0.05), (0.5, 0.95, 0.5, 0.2, 0.3),
                                       (1.0, 0.9, 0.9, 0.95, 0.7)])
    cam = Camera.orbit(azimuth=25.0, elevation=10.0, image_shape=(6, 6))
    weights = jnp.asarray(np.random.default_rng(3).random((6, 6, 4)))

    # both fields' gradients, and the losses differenced, from one compiled program
    def loss(colors, opacities):
        t = eqx.tree_at(lambda t: (t.colors, t.opacities), tf, (colors, opacities))
        return jnp.sum(weights * march(vol, t, cam, step=0.5, shading="phong"))

    grads = check_grads_fd(jax.jit(jax.value_and_grad(loss, (0, 1))),
                            (tf.colors, tf.opacities), (0, 1), rtol=1e-4)
    for g in grads:
        assert float(jnp.max(jnp.abs(g))) > 0


@pytest.mark.slow
def test_jit_vmap_grad_of_march():
    vol = _smooth_volume(8)
    tf = preset("grey")
    cam = Camera.orbit(azimuth=10.0, image_shape=(5, 4))
    eager = march(vol, tf, cam)
    jitted_march = eqx.filter_jit(march)
    jitted = jitted_march(vol, tf, cam)
    np.testing.assert_allclose(jitted, eager, atol=1e-12)
    # vmap over volumes and over cameras; grads w.r.t. the volume and the camera.
    # every batch element equals its own render (a loop), not just one of them
    scales = (1.0, 0.5, 0.8)
    batched = jax.jit(jax.vmap(lambda v: march(v, tf, cam)))(jnp.stack([s * vol for s in scales]))
    for i, s in enumerate(scales):
        np.testing.assert_allclose(batched[i], jitted_march(s * vol, tf, cam), atol=1e-12)
    azimuths = (10.0, 50.0, -70.0)
    cams = jax.vmap(lambda a: Camera.orbit(azimuth=a, image_shape=(5, 4)))(jnp.array(azimuths))
    per_cam = eqx.filter_jit(eqx.filter_vmap(lambda c: march(vol, tf, c)))(cams)
    np.testing.assert_allclose(per_cam[0], eager, atol=1e-12)
    for i, a in enumerate(azimuths):
        np.testing.assert_allclose(
            per_cam[i], jitted_march(vol, tf, Camera.orbit(azimuth=a, image_shape=(5, 4))),
            atol=1e-12)
    assert not np.allclose(per_cam[1], per_cam[2], atol=1e-3)
    # both gradients from one backward pass (two programs took twice as long to compile)
    g, g_cam = jax.jit(jax.grad(lambda v, a: jnp.sum(march(
        v, tf, Camera.orbit(azimuth=a, image_shape=(5, 4)), shading="phong")), (0, 1)))(
        vol, 20.0)
    assert np.all(np.isfinite(g)) and float(jnp.sum(jnp.abs(g))) > 0
    assert np.isfinite(g_cam)


@pytest.mark.slow
def test_gradient_wrt_camera_matches_finite_differences():
    # d(image)/d(azimuth, elevation) and d(image)/d(eye), perspective and orthographic,
    # against central differences in float64 (the rays depend on the camera)
    vol = _smooth_volume(8)
    tf = TransferFunction.from_points([(0.0, 0.1, 0.2, 0.3, 0.05), (0.5, 0.95, 0.5, 0.2, 0.3),
                                       (1.0, 0.9, 0.9, 0.95, 0.7)])
    weights = jnp.asarray(np.random.default_rng(4).random((5, 4, 4)))

    def by_angles(angles):
        cam = Camera.orbit(azimuth=angles[0], elevation=angles[1], image_shape=(5, 4))
        return jnp.sum(weights * march(vol, tf, cam, step=0.5, shading="phong"))

    def by_eye(eye):
        cam = Camera(eye, jnp.zeros(3), jnp.asarray([1.0, 0.0, 0.0]), jnp.asarray(30.0),
                     jnp.asarray(0.9), image_shape=(5, 4), projection="orthographic")
        return jnp.sum(weights * march(vol, tf, cam, step=0.5))

    g = check_grad_fd(by_angles, jnp.asarray([25.0, 10.0]), rtol=1e-4)
    assert np.all(np.abs(np.asarray(g)) > 1e-6)
    g = check_grad_fd(by_eye, jnp.asarray([0.6, 1.9, 0.9]), rtol=1e-4)
    assert float(jnp.max(jnp.abs(g))) > 1e-6


def _blinn_phong_reference(color, gradient, light, view, ambient, ka, kd, ks, n):
    # the module docstring of volshade.shading, written out in NumPy
    color, gradient, light, view, ambient = map(np.asarray, (color, gradient, light, view, ambient))
    norm = np.linalg.norm(gradient, axis=-1, keepdims=True)
    normal = np.where(norm > 0, -gradient / np.where(norm > 0, norm, 1), 0)
    half = (light + view) / np.linalg.norm(light + view, axis=-1, keepdims=True)
    n_l = np.abs(np.sum(normal * light, axis=-1, keepdims=True))
    n_h = np.abs(np.sum(normal * half, axis=-1, keepdims=True))
    return color * (ka * ambient + kd * n_l) + ks * n_h ** n


def test_blinn_phong_matches_the_documented_formula():
    # I = c (ka A + kd |N.L|) + ks |N.H|^n with N = -g/|g|, H = (L+V)/|L+V|: random
    # samples with N.L of both signs (two-sided: |N.L|), a zero gradient (ambient only),
    # grey and RGB ambient, specular on and off
    rng = np.random.default_rng(7)
    m = 64

    def unit(x):
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    color = rng.uniform(0, 1, (m, 3))
    gradient = rng.normal(size=(m, 3)) * rng.uniform(0.1, 5, (m, 1))
    gradient[0] = 0.0
    light, view = unit(rng.normal(size=(m, 3))), unit(rng.normal(size=(m, 3)))
    light[1] = unit(gradient[1])  # N.L = -1 exactly: the diffuse term is kd, not 0
    n_l = np.sum(-unit(gradient[1:]) * light[1:], axis=-1)
    assert (n_l < -0.2).sum() > 5 and (n_l > 0.2).sum() > 5
    for ambient in (rng.uniform(0, 1, (m, 1)), rng.uniform(0, 1, (m, 3))):
        for ka, kd, ks, n in ((0.3, 0.6, 0.0, 10.0), (0.2, 0.7, 0.5, 7.0), (0.0, 1.0, 0.0, 1.0)):
            got = blinn_phong(*map(jnp.asarray, (color, gradient, light, view, ambient)),
                              Phong(ambient=ka, diffuse=kd, specular=ks, shininess=n))
            expected = _blinn_phong_reference(color, gradient, light, view, ambient, ka, kd, ks, n)
            np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(np.asarray(got[0]), color[0] * ka * ambient[0], atol=1e-15)
            np.testing.assert_allclose(np.asarray(got[1]),
                                       color[1] * (ka * ambient[1] + kd)
                                       + ks * abs(np.dot(light[1], unit(light[1] + view[1]))) ** n,
                                       rtol=1e-12)


@pytest.mark.parametrize("azimuth, elevation", [(0.0, 0.0), (30.0, 20.0), (180.0, 0.0)])
def test_phong_render_of_a_ramp_along_h_matches_hand_computation(azimuth, elevation):
    # a volume linear along h has normals +-h everywhere (the regression gradient is exact
    # in direction, also at the edges); with a constant transfer function every sample has
    # colour s = c (ka + kd x) + ks x^n, x = |N.V| = |cos e cos a| (headlight: L = V = H),
    # so the image is s times the accumulated opacity, and c times it unshaded
    shape = (6, 8, 6)
    color = np.array([0.2, 0.6, 1.0])
    tf = _constant_tf(0.15, color=tuple(color))
    ramp = jnp.broadcast_to(jnp.linspace(0.0, 1.0, shape[1])[None, :, None], shape)
    cam = Camera.orbit(azimuth=azimuth, elevation=elevation, image_shape=(7, 7),
                       projection="orthographic", width=1.0)
    x = abs(np.cos(np.deg2rad(elevation)) * np.cos(np.deg2rad(azimuth)))
    render = eqx.filter_jit(march)
    plain = np.asarray(render(ramp, tf, cam, step=0.6))
    alpha = plain[..., 3:]
    assert alpha[3, 3, 0] > 0.3 and (alpha[..., 0] == 0).any()
    np.testing.assert_allclose(plain[..., :3], color * alpha, atol=1e-12)
    for ka, kd, ks, n in ((0.35, 0.65, 0.0, 24.0), (0.1, 0.5, 0.4, 3.0)):
        phong = Phong(ambient=ka, diffuse=kd, specular=ks, shininess=n)
        for vol in (ramp, 1.0 - ramp):  # N.V = -x and +x: two-sided
            lit = np.asarray(render(vol, tf, cam, step=0.6, shading="phong", phong=phong))
            s = color * (ka + kd * x) + ks * x ** n
            np.testing.assert_allclose(lit[..., 3:], alpha, atol=1e-12)
            np.testing.assert_allclose(lit[..., :3], s * alpha, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("shading", ["none", "phong"])
def test_no_nan_gradients_on_edge_volumes(shading):
    tf = TransferFunction.from_points([(0.0, 1, 1, 1, 0.0), (1.0, 1, 1, 1, 1.0)])
    cam = Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(3, 3))

    @jax.jit
    def image_and_derivatives(vol, t):
        # one forward and one batched backward pass (jax.jacrev's, for the volume and the
        # transfer function together; the gradient of the sum is the sum of the rows)
        img, pullback = jax.vjp(lambda v, u: march(v, u, cam, shading=shading), vol, t)
        rows = jnp.eye(img.size, dtype=img.dtype).reshape(img.size, *img.shape)
        jac, jac_tf = jax.vmap(pullback)(rows)
        g_tf = jax.tree.map(lambda j: jnp.sum(j, axis=0), jac_tf)
        return img, jac, jac_tf, g_tf

    corner = jnp.zeros((5, 5, 5)).at[0, 0, 0].set(1.0)
    for vol in (jnp.zeros((5, 5, 5)), jnp.ones((5, 5, 5)), corner, jnp.ones((1, 1, 1))):
        for leaf in jax.tree.leaves(image_and_derivatives(vol, tf)):
            assert np.all(np.isfinite(leaf))
            # bounded too: a constant volume's rounding noise once became unit normals
            # with derivatives of 1e16
            assert np.all(np.abs(leaf) < 1e3)


@pytest.mark.parametrize("name, units", [("shells", 1e20), ("shells", 1e30), ("corner", 3e38)])
def test_a_volume_in_huge_units_keeps_its_normals(name, units):
    # float32: |gradient|^2 overflows above 1e19, which would leave every sample without
    # a normal (Phong's ambient term only); the corner's walls at 3e38 give a gradient of
    # 1.5e38, whose reciprocal XLA on a CPU flushed to 0 (no normal either). (Tiny units
    # fail earlier: jnp.interp takes control points closer than about 1e-14 in float32
    # as one point.)
    vol = vs.data.phantom(name, shape=12)
    points = [(0.0, 1, 1, 1, 0.0), (0.5, 1, 0.8, 0.6, 0.4), (1.0, 1, 1, 1, 0.9)]
    cam = Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(8, 8))
    images = [march(vol * scale, TransferFunction.from_points(
        [(x * scale, *rest) for x, *rest in points], dtype=jnp.float32), cam, shading="phong")
        for scale in (1.0, units)]
    np.testing.assert_allclose(images[1], images[0], atol=1e-5)


def test_constant_volumes_have_no_normal():
    # whatever the constant value, an opaque constant volume has no gradient, so Phong
    # gives the ambient term only (not random full-strength normals)
    tf = _constant_tf(1.0)
    cam = Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(6, 6))
    images = [march(jnp.full((6, 6, 6), v), tf, cam, shading="phong") for v in (0.0, 0.3, 1.0)]
    for img in images[1:]:
        np.testing.assert_array_equal(np.asarray(img), np.asarray(images[0]))


def test_fully_opaque_volume_shows_its_colour():
    tf = _constant_tf(1.0, color=(0.3, 0.4, 0.5))
    img = march(jnp.ones((4, 4, 4)), tf, _ortho_along_h(width=0.5), background=(1, 1, 1))
    np.testing.assert_allclose(img[2, 2], [0.3, 0.4, 0.5, 1.0], atol=1e-12)


def test_opaque_volume_leaves_missed_rays_and_the_space_behind_it_empty():
    # rays that miss the box and samples past the exit have length 0, hence opacity 0,
    # even where the nearest voxel's opacity is exactly 1
    tf = _constant_tf(1.0, color=(0.3, 0.4, 0.5))
    cam = Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=(6, 6),
                       projection="orthographic", width=1.5)
    img = np.asarray(march(jnp.ones((8, 8, 8)), tf, cam, background=(1.0, 1.0, 1.0)))
    t0, t1 = _path_through_box(cam, (8, 8, 8), (1, 1, 1))
    hit = t1 > t0
    assert hit.any() and not hit.all()
    np.testing.assert_array_equal(img[~hit], [[1.0, 1.0, 1.0, 0.0]] * int((~hit).sum()))
    np.testing.assert_allclose(img[hit], [[0.3, 0.4, 0.5, 1.0]] * int(hit.sum()), atol=1e-12)
    one_voxel = jnp.zeros((8, 8, 8)).at[0, 0, 0].set(1.0)  # clamped to by past-exit samples
    tf01 = TransferFunction.from_points([(0.0, 0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0, 0.0),
                                         (1.0, 1.0, 0.0, 0.0, 1.0)])
    far = march(one_voxel, tf01, Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(16, 16)))
    assert int(jnp.sum(far[..., 3] > 0.5)) <= 4


def test_ambient_volume_scales_unlit_colour():
    tf = _constant_tf(0.2)
    vol = jnp.full((6, 6, 6), 0.5)
    cam = _ortho_along_h(width=0.5)
    plain = march(vol, tf, cam)
    half = march(vol, tf, cam, ambient=jnp.full((6, 6, 6), 0.5))
    np.testing.assert_allclose(half[..., :3], 0.5 * plain[..., :3], atol=1e-12)
    tint = np.array([1.0, 0.0, 0.5])
    rgb = march(vol, tf, cam, ambient=jnp.asarray(np.ones((6, 6, 6, 3)) * tint))
    np.testing.assert_allclose(rgb[..., :3], np.asarray(plain[..., :3]) * tint, atol=1e-12)


def test_bad_input_errors(tmp_path):
    tf, cam = preset("grey"), Camera.orbit(image_shape=(4, 4))
    for name in ("azimuth", "elevation", "distance"):   # not a bare error from jnp.stack
        with pytest.raises(ValueError, match=f"`{name}` must be a scalar.*list of cameras"):
            Camera.orbit(**{name: jnp.asarray([10.0, 20.0])})
    with pytest.raises(ValueError, match="3 dimensions"):
        march(jnp.zeros((4, 4)), tf, cam)
    with pytest.raises(TypeError, match="dtype"):
        march(jnp.zeros((4, 4, 4), jnp.complex64), tf, cam)
    with pytest.raises(ValueError, match="empty"):
        march(jnp.zeros((0, 4, 4)), tf, cam)
    with pytest.raises(Exception, match="NaN or inf"):
        march(jnp.full((4, 4, 4), jnp.nan), tf, cam)
    with pytest.raises(Exception, match="NaN or inf"):
        eqx.filter_jit(march)(jnp.zeros((4, 4, 4)).at[1, 1, 1].set(jnp.inf), tf, cam)
    with pytest.raises(ValueError, match="step"):
        march(jnp.zeros((4, 4, 4)), tf, cam, step=0.0)
    with pytest.raises(ValueError, match="spacing"):
        march(jnp.zeros((4, 4, 4)), tf, cam, spacing=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="unknown shading 'gouraud'"):
        march(jnp.zeros((4, 4, 4)), tf, cam, shading="gouraud")
    with pytest.raises(ValueError, match="unknown composition"):
        march(jnp.zeros((4, 4, 4)), tf, cam, composition="mip")
    with pytest.raises(ValueError, match="ambient"):
        march(jnp.zeros((4, 4, 4)), tf, cam, ambient=jnp.zeros((4, 4, 5)))
    with pytest.raises(Exception, match="`background` contains NaN or inf"):
        march(jnp.zeros((4, 4, 4)), tf, cam, background=(jnp.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="background"):
        march(jnp.zeros((4, 4, 4)), tf, cam, background=(0.0, 0.0))
    with pytest.raises(Exception, match=r"`opacity_scale` must be >= 0"):
        march(jnp.zeros((4, 4, 4)), tf, cam, opacity_scale=jnp.full((4, 4, 4), -1.0))
    with pytest.raises(TypeError, match="TransferFunction"):
        march(jnp.zeros((4, 4, 4)), "grey", cam)
    with pytest.raises(Exception, match="outside the transfer function's control points"):
        march(jnp.full((4, 4, 4), 255.0), tf, cam)  # e.g. a uint8 volume, not normalised
    unsorted = eqx.tree_at(lambda t: t.points, tf, tf.points[::-1])
    with pytest.raises(Exception, match="strictly increasing"):
        march(jnp.zeros((4, 4, 4)), unsorted, cam)
    with pytest.raises(ValueError, match="image_shape"):
        Camera.orbit(image_shape=(0, 4))
    with pytest.raises(ValueError, match="projection"):
        Camera.orbit(projection="fisheye")
    with pytest.raises(ValueError, match="NaN"):
        save_png(tmp_path / "x.png", jnp.full((2, 2, 3), jnp.nan))


def test_cameras_with_no_image_are_refused():
    eye, up, zero = jnp.asarray([2.0, 0.0, 0.0]), jnp.asarray([1.0, 0.0, 0.0]), jnp.zeros(3)

    def f32(*values):
        return jnp.asarray(values if len(values) > 1 else values[0], jnp.float32)

    bad = [
        (lambda: Camera(zero, zero, up, jnp.asarray(30.0), jnp.asarray(1.0)), "must differ"),
        (lambda: Camera(eye, zero, up, jnp.asarray(30.0), jnp.asarray(1.0)), "parallel"),
        (lambda: Camera(eye, zero, zero, jnp.asarray(30.0), jnp.asarray(1.0)), "non-zero"),
        (lambda: Camera.orbit(distance=0.0), "distance"),
        (lambda: Camera.orbit(distance=-1.0), "distance"),
        (lambda: Camera.orbit(fov=0.0), "fov"),
        (lambda: Camera.orbit(fov=180.0), "fov"),
        (lambda: Camera.orbit(width=0.0, projection="orthographic"), "width"),
        # found by a review: the other projection's parameter was ignored without a word
        (lambda: Camera.orbit(fov=40.0, projection="orthographic"),
         "Camera.orbit: `fov` does not apply to orthographic views .* set "
         "projection='perspective'"),
        (lambda: Camera.orbit(width=1.0), "`width` does not apply to perspective views"),
        # found by a review: lengths whose square is subnormal in float32, which the rays'
        # normalisation flushes to zero (every pixel got the same ray, or a zero one)
        (lambda: Camera(f32(1e-20, 0, 0), f32(0, 0, 0), f32(0, 1, 0), f32(30), f32(1)),
         "must differ"),
        (lambda: Camera(f32(2, 0, 0), f32(0, 0, 0), f32(1, 1e-20, 0), f32(30), f32(1)),
         "parallel"),
    ]
    for make, match in bad:
        with pytest.raises(ValueError, match=match):
            make()
    # traced values (a fit over the camera) are checked when rays are made
    rays = jax.jit(lambda fov: Camera.orbit(fov=fov, image_shape=(2, 2)).rays())
    assert rays(30.0)[1].shape == (2, 2, 3)
    with pytest.raises(Exception, match=r"`fov` must lie in \(0, 180\)"):
        rays(-30.0)
    # a traced negative distance would look from the other side, silently
    eye_at = jax.jit(lambda d: Camera.orbit(distance=d, image_shape=(2, 2)).eye)
    with pytest.raises(Exception, match="`distance` must be > 0"):
        jax.block_until_ready(eye_at(-1.0))
    looking_up = jax.jit(lambda u: Camera(eye, zero, u, jnp.asarray(30.0), jnp.asarray(1.0),
                                          image_shape=(2, 2)).rays())
    with pytest.raises(Exception, match="parallel"):
        looking_up(up)
    for elevation in (90.0, -90.0, 89.95):  # looking along d is not degenerate
        assert np.all(np.isfinite(Camera.orbit(elevation=elevation, image_shape=(2, 2)).rays()[1]))
    # nor is a short view whose square is still a normal float32
    near = Camera(f32(1e-18, 0, 0), f32(0, 0, 0), f32(0, 1, 0), f32(30), f32(1),
                  image_shape=(2, 2)).rays()[1]
    assert len(np.unique(np.asarray(near).reshape(-1, 3), axis=0)) == 4


def test_camera_from_a_view_direction():
    for azimuth, elevation in ((30.0, 20.0), (-120.0, -45.0), (0.0, 90.0), (77.0, -90.0)):
        orbit = Camera.orbit(azimuth=azimuth, elevation=elevation, image_shape=(4, 4))
        view = (orbit.eye - orbit.target) / jnp.linalg.norm(orbit.eye - orbit.target)
        cam = Camera.from_view(view, image_shape=(4, 4))
        np.testing.assert_allclose(np.asarray(cam.eye), np.asarray(orbit.eye), atol=1e-12)
        if abs(elevation) < 90:  # along d the azimuth (the image's roll) is taken as 0
            np.testing.assert_allclose(np.asarray(cam.rays()[1]), np.asarray(orbit.rays()[1]),
                                       atol=1e-12)
    # a view in voxel index space, with 4 x 1 x 1 mm voxels: (1, 1, 0) is arctan 4 above h
    cam = Camera.from_view(jnp.array([1.0, 1.0, 0.0]), spacing=(4.0, 1.0, 1.0))
    eye = np.asarray(cam.eye - cam.target)
    np.testing.assert_allclose(np.degrees(np.arctan2(eye[0], eye[1])), np.degrees(np.arctan(4.0)),
                               rtol=1e-12)
    assert abs(eye[2]) < 1e-12
    with pytest.raises(ValueError, match="spacing"):
        Camera.from_view(jnp.array([1.0, 1.0, 0.0]), spacing=(4.0, -1.0, 1.0))
    # directions in huge or tiny numbers (|view|^2 overflows or underflows in float32;
    # above 8.5e37 the reciprocal of the largest component is subnormal, flushed to 0 on
    # a CPU: the view became the zero vector, azimuth and elevation 0)
    for scale in (1e20, 1e-20, 6e37):
        view = jnp.asarray([3.0, 0.0, 4.0], jnp.float32) * scale
        eye = np.asarray(Camera.from_view(view, image_shape=(2, 2)).eye)
        np.testing.assert_allclose(eye, [1.5, 0.0, 2.0], atol=1e-6)
    # along d the azimuth is undefined: taken as 0, with a zero (finite) gradient, also
    # just beside the axis, where |v_hw|^2 underflows (the rays carry both angles)
    rays = jax.jit(jax.jacrev(lambda v: Camera.from_view(v, image_shape=(2, 2)).rays()[1]))
    for view in ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 1e-3, 0.0], [1.0, 1e-200, 0.0]):
        assert np.all(np.isfinite(rays(jnp.asarray(view))))
    assert np.all(np.isfinite(rays(jnp.asarray([1.0, 1e-20, 0.0], jnp.float32))))
    # lists and an int image size are accepted, as elsewhere in the API
    cam = Camera(eye=[2.0, 0.0, 0.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0], fov=30.0,
                 width=1.0, image_shape=5)
    assert cam.image_shape == (5, 5) and cam.rays()[0].shape == (5, 5, 3)


def test_camera_geometry_and_png(tmp_path):
    cam = Camera.orbit(azimuth=0.0, elevation=0.0, image_shape=(3, 5), distance=2.0)
    forward, right, up = cam.basis()
    np.testing.assert_allclose(forward, [0, -1, 0], atol=1e-7)
    np.testing.assert_allclose(up, [1, 0, 0], atol=1e-7)
    np.testing.assert_allclose(right, [0, 0, -1], atol=1e-7)
    origins, dirs = cam.rays()
    np.testing.assert_allclose(jnp.linalg.norm(dirs, axis=-1), 1.0, rtol=1e-6)
    assert float(dirs[0, 2, 0]) > 0 > float(dirs[2, 2, 0])  # row 0 looks up
    top = Camera.orbit(elevation=90.0, image_shape=(3, 3))
    assert np.all(np.isfinite(top.rays()[1]))
    np.testing.assert_allclose(top.basis()[0], [-1, 0, 0], atol=1e-6)
    assert n_samples((10, 10, 10), (1, 1, 1), 1.0) == 19
    for step in (1e-30, 5e-324):  # more samples than a march can index: named, not an MLIR error
        with pytest.raises(ValueError, match="`step` = .* samples per ray"):
            n_samples((10, 10, 10), (1, 1, 1), step)
    save_png(tmp_path / "img.png", jnp.ones((4, 6, 4)) * 0.5)
    from skimage import io

    img = io.imread(tmp_path / "img.png")
    assert img.shape == (4, 6, 3) and int(img[0, 0, 0]) in (127, 128)
    save_png(tmp_path / "slice.png", jnp.linspace(0, 1, 12).reshape(3, 4))  # e.g. an AO slice
    grey = io.imread(tmp_path / "slice.png")
    assert grey.shape == (3, 4) and grey[0, 0] == 0 and grey[-1, -1] == 255
    with pytest.raises(ValueError, match=r"must be \(H, W\), \(H, W, 3\) or"):
        save_png(tmp_path / "x.png", jnp.ones((2, 2, 2)))
    # an 8-bit image is refused, not clipped to 0 and 1 of 255
    with pytest.raises(TypeError, match="integers of dtype uint8; convert them with .*img_as_"):
        save_png(tmp_path / "x.png", np.full((2, 2, 3), 255, np.uint8))
    save_png(tmp_path / "bf16.png", jnp.full((2, 2, 3), 0.5, jnp.bfloat16))  # a float, written
    assert int(io.imread(tmp_path / "bf16.png")[0, 0, 0]) in (127, 128)
    save_png(tmp_path / "mask.png", np.array([[True, False]]))  # a mask: True is white
    np.testing.assert_array_equal(io.imread(tmp_path / "mask.png"), [[255, 0]])
    with pytest.raises(TypeError, match="real numbers in"):
        save_png(tmp_path / "x.png", np.full((2, 2), 0.5 + 0j))
    with pytest.raises(ValueError, match="empty"):
        save_png(tmp_path / "x.png", np.zeros((0, 4, 3)))
    save_png(tmp_path / "upper.PNG", jnp.ones((2, 2, 3)))
    for other in ("x.jpg", "x"):  # scikit-image would write a JPEG, or fail unnamed
        with pytest.raises(ValueError, match=r"`path` must end in \.png, got .*skimage"):
            save_png(tmp_path / other, jnp.ones((2, 2, 3)))
    assert not (tmp_path / "x.jpg").exists()


def test_intersect_box_matches_the_numpy_slab_method():
    # the renderer's clipping against the independent NumPy version, for rays that hit,
    # miss, graze and run parallel to faces (axis-aligned views)
    shape, spacing = (8, 12, 10), (1.0, 1.5, 0.8)
    half = box_half_extent(shape, spacing)[0]
    for azimuth, elevation in ((0.0, 0.0), (90.0, 0.0), (33.0, 21.0), (-140.0, 65.0)):
        cam = Camera.orbit(azimuth=azimuth, elevation=elevation, image_shape=(9, 11))
        t0, t1 = intersect_box(*cam.rays(), half)
        want0, want1 = _path_through_box(cam, shape, spacing)
        hit = want1 > want0
        assert hit.any() and not hit.all()
        np.testing.assert_array_equal(np.asarray(t1 > t0), hit)
        np.testing.assert_allclose(np.asarray(t0)[hit], want0[hit], atol=1e-12)
        np.testing.assert_allclose(np.asarray(t1)[hit], want1[hit], atol=1e-12)


def test_pre_classification_equals_post_for_a_linear_transfer_function():
    """Trilinear interpolation commutes with a classification that is linear in the
    value: constant colour, opacity linear over the volume's values. Then the
    opacity-weighted colours interpolate to the same colour and opacity."""
    vol = _smooth_volume(9, seed=2)
    tf = TransferFunction.from_points([(0.0, 0.3, 0.7, 0.2, 0.05), (1.0, 0.3, 0.7, 0.2, 0.85)])
    cam = Camera.orbit(azimuth=35.0, elevation=-20.0, image_shape=(7, 6))
    rng = np.random.default_rng(7)
    extras = {"ambient": jnp.asarray(rng.uniform(0.3, 1.0, (*vol.shape, 3))),
              "opacity_scale": jnp.asarray(rng.uniform(0.0, 2.0, vol.shape)),
              "focus": vs.focus_weights((7, 6), center=(3.0, 2.0), radius=2.5)}
    # (no importance without Phong: it reads the pre-classified samples and the intensity
    # as the last case does, and shades as the first)
    for kw in ({"shading": "none"}, {"shading": "phong"},
               {"composition": "importance", "shading": "phong",
                "importance": vs.Importance(intensity=2.0, gradient=1.0), **extras}):
        post = march(vol, tf, cam, step=0.4, **kw)
        pre = march(vol, tf, cam, step=0.4, classification="pre", **kw)
        np.testing.assert_allclose(pre, post, atol=1e-13)
        assert float(jnp.max(pre[..., 3])) > 0.3


def _labels():
    """A white cube (label 1.0) in air (0); the transfer function has a green class at
    0.5, between air and the cube's label."""
    vol = jnp.zeros((10, 10, 10)).at[3:7, 3:7, 3:7].set(1.0)
    tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (0.4, 0, 0, 0, 0.0),
                                       (0.5, 0.1, 0.9, 0.1, 1.0), (0.6, 0.1, 0.9, 0.1, 1.0),
                                       (0.7, 1, 1, 1, 1.0), (1.0, 1, 1, 1, 1.0)])
    return vol, tf


def test_pre_classification_renders_labels_in_their_own_colours():
    vol, tf = _labels()
    cam = Camera.orbit(azimuth=30.0, elevation=25.0, image_shape=(16, 16))
    post = np.asarray(march(vol, tf, cam, step=0.25))
    pre = np.asarray(march(vol, tf, cam, step=0.25, classification="pre"))
    # post-classification passes through the green class where the cube meets the air
    assert np.max(post[..., 1] - post[..., 0]) > 0.3
    # pre-classification draws only the cube's white over the black background: grey
    # levels, R = G = B, and the cube is seen (opaque in the middle)
    np.testing.assert_allclose(pre[..., 1], pre[..., 0], atol=1e-12)
    np.testing.assert_allclose(pre[..., 2], pre[..., 0], atol=1e-12)
    assert pre[8, 8, 3] > 0.99 and pre[8, 8, 0] > 0.99


def test_pre_classification_jit_vmap_and_gradients():
    # a blob in exactly empty space: opacity 0 (the first control point) at half the
    # voxels, where the interpolated colour is 0 / 0
    vol = jnp.maximum(_smooth_volume(8, seed=4) - 0.05, 0) / 0.95
    assert 0.2 < float(jnp.mean(vol == 0)) < 0.8
    tf = TransferFunction.from_points([(0.0, 0.1, 0.2, 0.3, 0.0), (0.5, 0.95, 0.5, 0.2, 0.3),
                                       (1.0, 0.9, 0.9, 0.95, 0.7)])
    cam = Camera.orbit(azimuth=25.0, elevation=10.0, image_shape=(5, 5))
    weights = jnp.asarray(np.random.default_rng(5).random((5, 5, 4)))

    def render(v, t):
        return march(v, t, cam, step=0.5, shading="phong", classification="pre")

    eager = render(vol, tf)
    # (this transfer function is not linear: pre- and post-classification differ)
    assert not np.allclose(eager, march(vol, tf, cam, step=0.5, shading="phong"), atol=1e-3)
    np.testing.assert_allclose(eqx.filter_jit(render)(vol, tf), eager, atol=1e-13)
    scales = (1.0, 0.6)
    batched = jax.jit(jax.vmap(lambda v: render(v, tf)))(jnp.stack([s * vol for s in scales]))
    for i, s in enumerate(scales):
        np.testing.assert_allclose(batched[i], render(s * vol, tf), atol=1e-12)
    # gradients w.r.t. the control values and the volume, finite where the opacity is 0;
    # the opacities are differenced from 0.05 up, inside [0, 1]. All three, and the losses
    # differenced, from one compiled program
    def loss(v, colors, opacities):
        t = eqx.tree_at(lambda t: (t.colors, t.opacities), tf, (colors, opacities))
        return jnp.sum(weights * render(v, t))

    value_and_grad = jax.jit(jax.value_and_grad(loss, (0, 1, 2)))
    g_vol, g_colors, _ = check_grads_fd(value_and_grad, (vol, tf.colors, tf.opacities), (1,),
                                         rtol=1e-4)
    g_opacities = check_grads_fd(value_and_grad, (vol, tf.colors, tf.opacities.at[0].set(0.05)),
                                  (2,), rtol=1e-4)[2]
    for g in (g_colors, g_opacities):
        assert float(jnp.max(jnp.abs(g))) > 0
    assert np.all(np.isfinite(g_vol)) and float(jnp.sum(jnp.abs(g_vol))) > 0


_VOXEL_CENTRE_SCENES = """
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import volshade as vs

rng = np.random.default_rng(9)
vol = rng.uniform(0, 1, (3, 3, 7))
vol[rng.uniform(size=vol.shape) < 0.3] = 0
tf = vs.TransferFunction(jnp.asarray([0.0, 1.0]), jnp.asarray([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3]]),
                         jnp.asarray([1.0, 0.02]), step0=2.0)
cam = vs.Camera.orbit(azimuth=90, elevation=0, distance=2.0, image_shape=(5, 4),
                      projection="orthographic", width=0.85)
scenes = [vs.Scene(volume=jnp.asarray(vol), transfer=tf, spacing=(2.0, 1.0, 1.0), step=1.0,
                   classification=classification, shading="phong",
                   ambient="none" if ambient is None else "volume",
                   ambient_volume=None if ambient is None else jnp.asarray(ambient))
          for classification, ambient in (("pre", None),
                                          ("post", rng.uniform(size=(3, 3, 7, 3))))]
"""


@pytest.mark.slow
def test_samples_on_voxel_centres_read_their_own_voxel_with_the_default_xla_build():
    # found by a review: the centre row of this image samples the plane d = 1 at index
    # coordinates within an ulp of 1; XLA on a CPU recomputed each sample's point in every
    # fusion reading it, LLVM contracted some copies into fused multiply-adds, and a
    # multi-channel sample (pre-classified, an RGB ambient, the gradient of Phong) took its
    # voxel from one copy and its weights from another: it read the slice d = 0 (0.28 of
    # opacity off). The suite's own XLA flags hide this, so the renders run in a
    # subprocess with the user's, and are checked against the same renders here.
    printed = run_with_user_xla_flags(
        _VOXEL_CENTRE_SCENES + "for scene in scenes:\n"
                               "    print(*np.asarray(vs.render(scene, cam)).ravel().tolist())\n")
    setup: dict = {}
    exec(_VOXEL_CENTRE_SCENES, setup)
    want = np.concatenate([np.asarray(vs.render(scene, setup["cam"])).ravel()
                           for scene in setup["scenes"]])
    # to 1e-6, not to rounding: the exact index of the plane is 1 - 1.1e-16, a builds' point
    # may round to either side, and next to an opaque voxel (opacity 1 at value 0) the
    # correction to a half step, 1 - (1 - alpha)^0.5, turns an ulp of opacity into 1e-8
    # (7e-10 in a pixel); reading the wrong voxel is an error of 0.28
    np.testing.assert_allclose(np.asarray(printed, dtype=np.float64), want, rtol=0, atol=1e-6)


def test_classification_option_is_checked_and_scenes_pass_it_on():
    vol, tf = _labels()
    cam = Camera.orbit(azimuth=30.0, image_shape=(6, 6))
    with pytest.raises(ValueError, match="classification"):
        march(vol, tf, cam, classification="before")
    with pytest.raises(ValueError, match="classification"):
        vs.Scene(volume=vol, transfer=tf, classification="pre-")
    scene = vs.Scene(volume=vol, transfer=tf, classification="pre", shading="phong")
    # the camera and Phong's defaults strongly typed, as the render makes them: the march
    # runs the render's compiled march (one compilation, not two)
    cam, phong = strongly_typed((cam, Phong()))
    np.testing.assert_array_equal(vs.render(scene, cam), march(vol, tf, cam, classification="pre",
                                                               shading="phong", phong=phong))


def test_an_eager_render_compiles_once_and_still_refuses_bad_values_at_once():
    # the march and the shared volumes are compiled once per structure: an eager call
    # with other values (volume, camera pose, Phong coefficients) reuses them, also when
    # a coefficient given as a Python number (a weakly typed leaf) comes back as a
    # float32 array (from a fit, say)
    from volshade.render import _march_view, _shared_volumes

    tf = preset("shells")
    scene = vs.Scene(volume=vs.data.phantom("shells", shape=8), transfer=tf, shading="phong",
                     phong=Phong(diffuse=0.5))
    cam = Camera.orbit(azimuth=30.0, elevation=20.0, image_shape=(4, 5))
    first = vs.render(scene, cam)
    sizes = (_march_view._cached._cache_size(), _shared_volumes._cached._cache_size())
    other = eqx.tree_at(lambda s: (s.volume, s.phong.diffuse), scene,
                        (scene.volume * 0.5, jnp.float32(0.7)))
    moved = Camera.orbit(azimuth=75.0, elevation=-10.0, image_shape=(4, 5))
    second = vs.render(other, moved)
    assert (_march_view._cached._cache_size(), _shared_volumes._cached._cache_size()) == sizes
    np.testing.assert_allclose(second, eqx.filter_jit(vs.render)(other, moved), atol=1e-6)
    assert not np.allclose(first, second)
    # values known at the call are still refused with a ValueError, not at run time
    same = eqx.tree_at(lambda c: c.target, moved, moved.eye)
    with pytest.raises(ValueError, match="`eye` and `target` must differ"):
        vs.render(scene, same)


@pytest.mark.parametrize("box_mm, dtype", [(41.0, jnp.float32), (49.0, jnp.float64)])
def test_an_opaque_sample_keeps_the_identity_slope_whatever_the_box(box_mm, dtype):
    # found by a review: a whole segment's ratio step / step0 was formed as
    # (step / scale) * scale / step0, which rounds 1 to 1 - ulp for these boxes, and at
    # opacity 1 the correction's slope for a ratio below 1 is 0: the gradient vanished
    tf = preset("shells")
    tf = eqx.tree_at(lambda t: t.opacities, tf, tf.opacities.at[7].set(1.0).at[8].set(1.0))
    cam = Camera.orbit(azimuth=30, elevation=20, distance=1.8, image_shape=(8, 8))
    weights = jax.random.normal(jax.random.PRNGKey(0), (8, 8, 4), jnp.float64)
    vol = vs.data.phantom("shells", shape=14)

    def loss(opacity, vol, spacing):
        t = eqx.tree_at(lambda t: t.opacities, tf, tf.opacities.at[8].set(opacity))
        scene = vs.Scene(volume=vol, transfer=t, spacing=spacing, step=1.0)
        return jnp.sum(vs.render(scene, cam) * weights)

    spacing = box_mm / 14
    got = jax.grad(loss)(jnp.asarray(1.0, dtype), vol.astype(dtype), spacing)
    x64 = vol.astype(jnp.float64)
    h = 1e-6                                                  # from below, into [0, 1]
    one_sided = (3 * loss(1.0, x64, spacing) - 4 * loss(1.0 - h, x64, spacing)
                 + loss(1.0 - 2 * h, x64, spacing)) / (2 * h)
    assert abs(float(one_sided)) > 1e-3
    np.testing.assert_allclose(float(got), float(one_sided), rtol=1e-3 if dtype == jnp.float32
                               else 1e-6)
