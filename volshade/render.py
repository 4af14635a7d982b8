r"""Ray marching: camera rays -> samples -> classification -> shading -> composition.

Each pixel's ray is clipped against the box of voxel cells and sampled at a
fixed step $\Delta s$ (mm). The number of samples is static
(``ceil(box diagonal / step) + 1``); sample $k$ stands for the segment
$[t_0 + k\Delta s,\, \min(t_0 + (k+1)\Delta s, t_1)]$ and sits at its midpoint,
so the segment lengths add up exactly to the ray's path through the box and a
uniform medium reproduces Beer--Lambert, $T = e^{-\tau \ell}$. Samples past
the exit point have length 0, hence opacity 0. Intensities are interpolated
trilinearly with the ``"nearest"`` boundary rule (uniform right up to the
faces) and classified after interpolation (``classification="post"``), or the
voxels are classified first and their opacity-weighted colours
$(\alpha_0 c, \alpha_0)$ interpolated (``"pre"``, for label volumes, whose
interpolated values would pass through the classes between two labels;
Wittenbrink, Malzbender and Goss 1998). Opacities are corrected to each
segment's length (:meth:`volshade.TransferFunction.opacity`).

The march is a ``lax.scan`` over samples carrying all rays of a group at once, in
chunks of 16 samples, rematerialised in reverse mode a chunk at a time
(``jax.checkpoint``), so memory for gradients is one compositing state per chunk plus
one chunk's intermediates, not every intermediate. The rays are marched in four groups of
similar length, each only as far as its longest ray reaches: a chunk past that is
skipped (it would change nothing).

:func:`march` is :func:`medium` (the checks and the volumes every view shares:
the gradient volume, the ambient and opacity-scale volumes) followed by
:func:`march_view` (one camera's rays), so that several views of one scene
(:func:`volshade.render` with a sequence of cameras) share that work.
"""

import math
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import correct_opacity, log1m, safe_div, scaled_down, tiny
from ._types import Array, Float
from .camera import Camera, box_half_extent, intersect_box
from .composition import COMPOSITORS, Compositor, Sample
from .gradient import regression_gradient
from .importance import Importance, _sample_importance, normalized_gradient_magnitude
from .sampling import _trilinear
from .shading import SHADERS, Phong, Shader
from .transfer import TransferFunction


def n_samples(shape: tuple[int, int, int], spacing, step: float) -> int:
    """Static number of samples per ray: the box diagonal over the step, plus one.

    Raises:
        ValueError: more samples than a march can index (``2**31 - 1``).
    """
    diagonal = float(np.linalg.norm(np.asarray(shape) * np.asarray(spacing)))
    ratio = diagonal / step
    if not ratio < np.iinfo(np.int32).max - 1:
        raise ValueError(f"volshade.render: `step` = {step!r} gives {ratio:.3g} samples per ray "
                         f"(the volume's diagonal, {diagonal:.4g} mm, over the step), more "
                         f"than a march can index (2**31 - 1); use a step of about half the "
                         f"voxel size, e.g. {float(np.min(spacing)) / 2:.3g}.")
    return math.ceil(ratio) + 1


def march(
    volume: Float[Array, "D H W"],
    transfer: TransferFunction,
    camera: Camera,
    *,
    spacing=(1.0, 1.0, 1.0),
    step: float = 0.5,
    shading: str = "none",
    phong: Phong | None = None,
    ambient: Array | None = None,
    composition: str = "standard",
    background=(0.0, 0.0, 0.0),
    opacity_scale: Float[Array, "D H W"] | None = None,
    importance: Importance | None = None,
    focus: Float[Array, "H W"] | None = None,
    classification: str = "post",
) -> Float[Array, "H W 4"]:
    """Render a volume by front-to-back ray marching.

    Args:
        volume: ``(D, H, W)`` intensities (the transfer function's domain).
        transfer: classification of intensities into colour and opacity.
        camera: the view.
        spacing: voxel size ``(sd, sh, sw)`` in mm.
        step: sample distance in mm (static: it sets the number of samples).
        shading: ``"none"``, ``"phong"`` or ``"obscurance"`` (see :mod:`volshade.shading`).
        phong: Blinn--Phong coefficients (default :class:`~volshade.shading.Phong`).
        ambient: optional ``(D, H, W)`` or ``(D, H, W, 3)`` ambient factor in
            [0, 1] (ambient occlusion, obscurance), sampled trilinearly.
        composition: compositor name (see :data:`volshade.composition.COMPOSITORS`).
        background: RGB colour behind the volume, in [0, 1] (checked where known).
        opacity_scale: optional ``(D, H, W)`` factor $f \\ge 0$, sampled trilinearly;
            each sample's reference opacity becomes $\\min(1, f \\alpha_0)$ before
            the step correction (saliency-driven modulation).
        importance: weights of the importance measures for
            ``composition="importance"`` (default :class:`~volshade.importance.Importance`,
            all weights 0, which equals standard compositing). Each sample's
            importance is measured on the fly (:func:`~volshade.importance.sample_importance`)
            from its intensity, extinction, normalised gradient magnitude, normal,
            the view (= light, a headlight) and the optical depth in front of it;
            the silhouette darkening scales its colour. An opaque sample's
            extinction is infinite; it is capped at ``-log(tiny) / step0`` (so
            ln(1 + tau) is about 4.5 in float32 and 6.6 in float64 for 1 mm).
        focus: optional ``(H, W)`` per-ray global weights (focus plus context,
            :func:`~volshade.importance.focus_weights`), for ``composition="importance"``.
        classification: ``"post"`` (default): classify each sample's interpolated
            intensity. ``"pre"``: classify the voxels and interpolate the
            opacity-weighted colour $\alpha_0 c$ and the opacity $\alpha_0$, the
            colour being their quotient (0 where $\alpha_0 = 0$). Use ``"pre"`` for
            label volumes (each value a class, like the ``"corner"`` phantom's
            walls): post-classification renders the classes that lie between two
            labels' values where they meet (or meet the air). For a transfer
            function whose opacity is linear and colour constant over the
            volume's values the two are equal.

    Returns:
        ``(H, W, 4)``: RGB with the background blended in, and the accumulated
        opacity; the dtype of ``volume``, or float32 for a half-precision
        (``float16``/``bfloat16``) volume, which is rendered in float32 (its values
        convert exactly; compositing hundreds of samples in half precision would not
        be accurate to a grey level).

    Raises:
        ValueError / TypeError: bad shapes, dtypes, options or sizes; NaN or inf
            in ``volume``, ``ambient`` or ``background``, a known ``background``
            outside [0, 1], a negative
            ``opacity_scale``, transfer-function control values out of order or
            outside [0, 1], or ``phong`` or ``importance`` values outside their
            domains (raised when the data is seen: at run time for traced values);
            ``phong`` given to a shading that does not read it (``"none"``), or
            ``importance`` or ``focus`` to standard compositing (they would be
            ignored); a ``camera``, ``phong`` or ``importance`` of another type.
    """
    shared = medium(volume, transfer, spacing=spacing, step=step, shading=shading,
                    phong=phong, ambient=ambient, composition=composition,
                    background=background, opacity_scale=opacity_scale,
                    importance=importance, classification=classification)
    # a PNG would clip a colour outside [0, 1] silently. Checked here and where a Scene is
    # built, on known values (not in `medium`): a fit may converge to 0 or 1 with a
    # rounding error either side, and its scene must still render
    _checks.in_unit_range(shared.background, "background", "volshade.render",
                          hint=BACKGROUND_HINT, traced=False)
    return march_view(shared, camera, focus)


class Medium(NamedTuple):
    """What every view of a render shares: the checked volume and transfer function,
    the shading and compositing choices, the ambient and opacity-scale volumes and the
    gradient volume (and its normalised magnitude, for importance compositing)."""

    volume: Array
    transfer: TransferFunction
    spacing: tuple[float, float, float]
    step: float
    shader: Shader
    compositor: Compositor
    phong: Phong
    ambient: Array | None
    opacity_scale: Array | None
    importance: Importance | None
    background: Array
    gradient: Array | None
    magnitude: Array | None
    classified: Array | None


# what "`background` must lie in [0, 1]" is followed by (Scene says it too)
BACKGROUND_HINT = "(an RGB colour)"
_CLASSIFICATIONS = {"post": "classify interpolated intensities",
                    "pre": "interpolate classified voxels (opacity-weighted colours)"}


def medium(
    volume, transfer, *, spacing, step, shading, phong, ambient, composition, background,
    opacity_scale, importance, classification="post",
) -> Medium:
    """The view-independent part of :func:`march` (same arguments): its checks, and
    the gradient volume when the shading or the compositing needs it."""
    where = "volshade.render"
    volume = _checks.as_working_float(volume, "volume", where)
    _checks.check_ndim(volume, 3, "volume", where, "(D, H, W)")  # finite: with the transfer
    spacing = _checks.spacing(spacing, where)
    step = _checks.positive_float(step, "step", where)
    shader = _checks.option(shading, SHADERS, "shading", where)
    comp = _checks.option(composition, COMPOSITORS, "composition", where)
    _checks.option(classification, _CLASSIFICATIONS, "classification", where)
    dtype = volume.dtype
    if ambient is not None:
        ambient = _checks.as_float_array(ambient, "ambient", where).astype(dtype)
        if ambient.shape[:3] != volume.shape or ambient.ndim not in (3, 4) or (
                ambient.ndim == 4 and ambient.shape[-1] != 3):
            raise ValueError(f"{where}: `ambient` must have shape {volume.shape} or "
                             f"{(*volume.shape, 3)}, got {ambient.shape}.")
        ambient = _checks.finite(ambient, "ambient", where)
    if opacity_scale is not None:
        opacity_scale = _checks.volume(opacity_scale, "opacity_scale", where,
                                       non_negative=True, hint="(a factor on opacity)")
        if opacity_scale.shape != volume.shape:
            raise ValueError(f"{where}: `opacity_scale` must have shape {volume.shape}, "
                             f"got {opacity_scale.shape}.")
        opacity_scale = opacity_scale.astype(dtype)
    if not isinstance(transfer, TransferFunction):
        raise TypeError(f"{where}: `transfer` must be a volshade.TransferFunction, got "
                        f"{type(transfer).__name__}.")
    transfer, volume = transfer._checked(volume, where)
    background = _checks.numbers(background, "background", where).astype(dtype)
    if background.shape != (3,):
        raise ValueError(f"{where}: `background` must be an RGB triple, shape (3,), got "
                         f"{background.shape}.")
    background = _checks.finite(background, "background", where)
    measured = composition == "importance"
    # as a Scene does: parameters the render would not read are refused, or it would
    # look as if they had no effect
    for value, kind, used, name, wanted in (
            (phong, Phong, shader.needs_gradient, "phong", "shading='phong' or 'obscurance'"),
            (importance, Importance, measured, "importance", "composition='importance'")):
        if value is not None and not isinstance(value, kind):
            raise TypeError(f"{where}: `{name}` must be a volshade.{kind.__name__}, got "
                            f"{type(value).__name__}.")
        if value is not None and not used:
            raise ValueError(f"{where}: `{name}` is read only with {wanted}; pass that, or "
                             f"leave `{name}` out.")
    phong = Phong() if phong is None else phong
    if shader.needs_gradient:  # the lit shaders, which read the Phong coefficients
        phong = phong.checked()
    gradient, magnitude, classified = _shared_volumes(
        volume, transfer, spacing, gradient=shader.needs_gradient or measured,
        magnitude=measured, classified=classification == "pre")
    return Medium(
        volume=volume, transfer=transfer, spacing=spacing, step=step, shader=shader,
        compositor=comp, phong=phong, ambient=ambient, opacity_scale=opacity_scale,
        importance=(Importance() if importance is None else _checks.refuse(
            importance.checked(), importance._non_finite(), where)) if measured else None,
        background=background, gradient=gradient, magnitude=magnitude,
        classified=classified)


@eqx.filter_jit
def _shared_volumes(volume: Array, transfer: TransferFunction, spacing, *, gradient: bool,
                    magnitude: bool, classified: bool
                    ) -> tuple[Array | None, Array | None, Array | None]:
    """The volumes :func:`medium` computes (each when asked for): the gradient (over its
    largest component), its normalised magnitude and the pre-classified
    ``(alpha0 c, alpha0)``; compiled once per structure, for eager calls."""
    grad = mag = rgba = None
    if gradient:
        grad = regression_gradient(volume, spacing=spacing, size=3)
        # normals need only its direction and the importance its scaled magnitude: over
        # its largest component, a volume in tiny or huge units keeps its normals
        # (|g|^2 would underflow or overflow, and safe_normalize give no normal). Both
        # are scale-invariant, so the factor is held constant (scaled_down)
        peak = jnp.max(jnp.abs(grad))
        grad = scaled_down(grad, jnp.where(peak > 0, peak, jnp.ones_like(peak)))
    if magnitude:
        mag = normalized_gradient_magnitude(grad)
    if classified:
        color, alpha0 = transfer._rgba(volume)
        rgba = jnp.concatenate([alpha0[..., None] * color, alpha0[..., None]], axis=-1)
    return grad, mag, rgba


def march_view(shared: Medium, camera: Camera, focus: Array | None = None
               ) -> Float[Array, "H W 4"]:
    """The per-view part of :func:`march`: ``camera``'s rays through ``shared`` (what
    :func:`medium` returns), with optional ``(H, W)`` ``focus`` weights; returns the
    ``(H, W, 4)`` image."""
    if not isinstance(camera, Camera):
        raise TypeError(f"volshade.render: `camera` must be a volshade.Camera, got "
                        f"{type(camera).__name__}.")
    focus = _checked_focus(shared, camera.image_shape, focus)
    # known degenerate values are refused now, with a ValueError; traced ones by the
    # compiled march, at run time
    _checks.refuse(camera, camera._degenerate(), "volshade.Camera", traced=False)
    return _march_view(shared, camera, focus)


def march_views(shared: Medium, cameras: Sequence[Camera], focus: Array | None = None
                ) -> Float[Array, "N H W 4"]:
    """:func:`march_view` of each of ``cameras``, which must share one structure (image
    shape, projection, and the shapes and dtypes of their values), by one compiled loop
    over their stacked values (``jax.lax.map``): many views compile as one. ``focus``
    (``(H, W)``) weighs every view alike. Returns the ``(N, H, W, 4)`` images."""
    structures = {_structure(cam) for cam in cameras}
    if len(structures) != 1:
        raise ValueError(f"volshade.render: `cameras` must share one structure (image "
                         f"shape, projection, shapes and dtypes of their values), got "
                         f"{len(structures)}; march them one by one (march_view).")
    # known degenerate values are refused here, naming the camera; inside the loop they
    # would be traced, and refused at run time without the index
    for i, cam in enumerate(cameras):
        try:
            _checks.refuse(cam, cam._degenerate(), "volshade.Camera", traced=False)
        except ValueError as err:
            raise ValueError(f"volshade.render: `camera[{i}]`: {err}") from None
    focus = _checked_focus(shared, cameras[0].image_shape, focus)
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *cameras)
    return _march_views(shared, stacked, focus)


def _structure(camera: Camera) -> tuple:
    """What must match for cameras to share a compiled march: the pytree structure
    (static fields included) and each leaf's shape and dtype (a leaf may be a Python
    float, set with eqx.tree_at)."""
    return (jax.tree_util.tree_structure(camera),
            tuple((jnp.shape(x), jnp.result_type(x)) for x in jax.tree_util.tree_leaves(camera)))


def _checked_focus(shared: Medium, image_shape: tuple[int, int], focus: Array | None
                   ) -> Array | None:
    """``focus`` weights in the volume's dtype, refused unless finite, of the image's
    shape and with importance-aware composition."""
    where = "volshade.render"
    if focus is None:
        return None
    focus = _checks.finite(_checks.as_float_array(focus, "focus", where).astype(
        shared.volume.dtype), "focus", where)
    if focus.shape != tuple(image_shape):
        raise ValueError(f"{where}: `focus` must have the camera's image shape "
                         f"{tuple(image_shape)}, got {focus.shape}.")
    if shared.importance is None:
        raise ValueError(f"{where}: `focus` weights need composition='importance'.")
    return focus


@eqx.filter_jit
def _march_views(shared: Medium, cameras: Camera, focus: Array | None) -> Array:
    """:func:`_march_view` of each of the stacked ``cameras``. Compiled here, once per
    structure: an eager ``lax.map`` over a closure made on each call traced and
    compiled its loop again on every call (a turntable of three 16^2 views of a 24^3
    volume: 4.4-4.7 s a call, against 11-15 ms now)."""
    return jax.lax.map(lambda camera: _march_view(shared, camera, focus), cameras)


# Rays are marched in groups of similar length, each only as far as its longest ray
# reaches, in chunks of steps: a chunk past that is skipped whole. A box's rays differ
# in length (corner, edge, centre, missed), and a march of every ray over the full
# diagonal spent 74% of its samples outside the box (the head at 2 mm, Phong and LAO,
# 2-core CPU: a 128^2 render 0.43 -> 0.25 s, a 96^2 render with its gradient 0.71 ->
# 0.37 s). A skipped step would have had length 0, opacity 0 and changed nothing, bit
# for bit, so the images are those of the full march up to rounding (the head:
# identical; elsewhere XLA may fuse the grouped program's arithmetic otherwise, a few
# float32 ulps).
_RAY_GROUPS = 4
_CHUNK = 16


@eqx.filter_jit
def _march_view(shared: Medium, camera: Camera, focus: Array | None) -> Array:
    """:func:`march_view` after its checks, compiled once per structure: called
    eagerly (a notebook's ``vs.render(scene, camera)``), the march would otherwise be
    traced and compiled again on every call (its loop body is a new closure each time)
    and every operation around it compiled on its own."""
    volume, spacing = shared.volume, shared.spacing
    dtype = volume.dtype
    half_extent, scale = box_half_extent(volume.shape, spacing)
    half_extent = half_extent.astype(dtype)
    origins, directions = jax.tree.map(lambda a: a.astype(dtype), camera.rays())
    image_shape = origins.shape[:-1]
    t_near, t_far = intersect_box(origins, directions, half_extent)
    hit = t_far > t_near
    length = jnp.where(hit, t_far - t_near, 0).reshape(-1)
    t_near = jnp.where(hit, t_near, 0)  # a missed ray may carry t = +-max: keep positions finite
    # the rays by length, in equal groups (padded with copies of the longest, which
    # cost no chunk more and are dropped)
    n_rays = length.shape[0]
    groups = min(_RAY_GROUPS, n_rays)
    order = jnp.argsort(length)
    order = jnp.concatenate([order, jnp.broadcast_to(order[-1:], (-n_rays % groups,))])

    def grouped(x: Array) -> Array:
        x = x.reshape(n_rays, *x.shape[len(image_shape):])[order]
        return x.reshape(groups, -1, *x.shape[1:])

    rays = [grouped(x) for x in (origins, directions, t_near, length)]
    rays.append(None if focus is None else grouped(focus))
    images = jax.lax.map(lambda group: _march_rays(shared, half_extent, scale, *group), rays)
    images = images.reshape(-1, 4)[:n_rays]
    return jnp.zeros_like(images).at[order[:n_rays]].set(images, unique_indices=True) \
        .reshape(*image_shape, 4)


def _march_rays(shared: Medium, half_extent: Array, scale: float, origins: Array,
                directions: Array, t_near: Array, length: Array, focus: Array | None
                ) -> Array:
    """The ``(N, 4)`` images of ``N`` rays that enter the box (of ``half_extent``, in
    units of ``scale`` mm, :func:`~volshade.camera.box_half_extent`) at ``t_near`` and
    cross it over ``length`` (0 for a miss), marched in chunks of :data:`_CHUNK` steps
    as far as the longest of them reaches."""
    volume, transfer, spacing, comp = shared.volume, shared.transfer, shared.spacing, \
        shared.compositor
    dtype = volume.dtype
    measured = shared.importance is not None
    batch = origins.shape[:-1]
    bg = jnp.broadcast_to(shared.background, (*batch, 3))
    dt = jnp.asarray(shared.step / scale, dtype)
    full_ratio = jnp.asarray(shared.step / transfer.step0, dtype)
    to_index = jnp.asarray(scale / np.asarray(spacing), dtype)
    ambient, opacity_scale, gradient = shared.ambient, shared.opacity_scale, shared.gradient
    eye_dir = -directions
    # Optical depth of an opaque sample is infinite; capping it at -log(tiny) keeps the
    # importance measures finite (a weight of 0 times inf would be NaN). Transmittance
    # below `tiny` is 0 in this dtype anyway.
    max_depth = -jnp.log(tiny(volume))

    def point(k, seg):
        """Sample ``k``'s point (in a segment of length ``seg``) in voxel index coordinates."""
        t_mid = t_near + k * dt + 0.5 * seg
        return (origins + t_mid[..., None] * directions + half_extent[None]) \
            * to_index[None] - 0.5

    def body(carry, k):
        state, depth = carry
        seg = jnp.clip(length - k * dt, 0, dt)
        # The point is computed in a conditional (always taken): its result is stored
        # once, and every sampling reads it. Computed in the body, XLA on a CPU
        # recomputed it in each fusion that reads it (every gather of a multi-channel
        # volume, and the weights), LLVM contracted some copies into fused multiply-adds
        # and not others, and at a point within an ulp of a voxel centre one copy's floor
        # chose the voxels and another's the weights: the sample read the neighbouring
        # voxel. (An optimization_barrier does not stop that on a CPU, and a carried point
        # would be stored for every step in reverse mode; the conditional is recomputed
        # from k there, with the rest of the checkpointed body.)
        index = jax.lax.cond(k >= 0, lambda: point(k, seg), lambda: jnp.zeros((*batch, 3), dtype))
        if shared.classified is None:
            value = _trilinear(volume, index, "nearest")
            color, alpha0 = transfer._rgba(value)
        else:  # pre-classified: the intensity is read only for the importance measures
            weighted = _trilinear(shared.classified, index, "nearest")
            alpha0 = weighted[..., 3]
            color = safe_div(weighted[..., :3], alpha0[..., None])
            value = _trilinear(volume, index, "nearest") if measured else None
        if opacity_scale is not None:
            alpha0 = jnp.minimum(alpha0 * _trilinear(opacity_scale, index, "nearest"), 1)
        # a whole segment's ratio as step / step0, not (step / scale) * scale / step0: that
        # rounds 1 to 1 - ulp for some boxes (41 mm in float32), and at opacity 1 a ratio
        # below 1 has the slope 0, not the identity's 1 (correct_opacity)
        ratio = jnp.where(seg < dt, seg * scale / transfer.step0, full_ratio)
        alpha = correct_opacity(alpha0, ratio)
        amb = jnp.ones((*batch, 1), dtype) if ambient is None else \
            _trilinear(ambient, index, "nearest").reshape(*batch, -1)
        grad = None if gradient is None else _trilinear(gradient, index, "nearest")
        shaded = shared.shader.fn(color, grad, eye_dir, eye_dir, amb, shared.phong)
        sample_imp = None
        if measured:
            tau = jnp.minimum(-log1m(alpha0), max_depth) / transfer.step0
            sample_imp, darkening = _sample_importance(
                shared.importance,
                {"intensity": value, "extinction": tau, "optical_depth": depth,
                 "gradient_magnitude": _trilinear(shared.magnitude, index, "nearest")},
                {"normal": -grad, "view": eye_dir, "light": eye_dir}, focus)
            shaded = shaded * darkening[..., None]
            depth = depth + tau * seg * scale
        state = comp.step(state, Sample(alpha[..., None] * shaded, alpha, sample_imp))
        return (state, depth), None

    reach = jnp.max(length)

    def chunk(carry, first):
        # past the longest ray every step has length 0 (and so opacity 0): the chunk
        # would change nothing, and is skipped
        steps = first + jnp.arange(_CHUNK, dtype=dtype)
        return jax.lax.cond(first * dt < reach, lambda c: jax.lax.scan(body, c, steps)[0],
                            lambda c: c, carry), None

    carry = (comp.init(batch, dtype), jnp.zeros(batch, dtype))
    n_chunks = -(-n_samples(volume.shape, spacing, shared.step) // _CHUNK)
    firsts = jnp.arange(0, n_chunks * _CHUNK, _CHUNK, dtype=dtype)
    # rematerialised in reverse mode a chunk at a time: the state at each chunk's start
    # is kept, and one chunk's intermediates while it is differentiated (checkpointing
    # each step kept a state per step, and its gradient took 1.5x as long)
    (state, _), _ = jax.lax.scan(jax.checkpoint(chunk), carry, firsts)
    bg_importance = shared.importance.background_importance(focus) if measured else 0
    return comp.finish(state, bg, jnp.broadcast_to(jnp.asarray(bg_importance, dtype), batch))


def save_png(path, image: Float[Array, "H W C"]) -> None:
    """Write an ``(H, W, 3)`` or ``(H, W, 4)`` image in [0, 1] as an 8-bit RGB PNG, or an
    ``(H, W)`` one (a slice of an ambient-occlusion volume) as an 8-bit grey PNG.

    Values above 1 (added-up highlights) are clipped to white and values below 0 to
    black when written; the alpha channel is dropped, since the background is already
    blended in. A boolean mask is written white where True.

    Args:
        path: the ``.png`` file to write (for other formats, write the image with
            ``skimage.io.imsave``).
        image: ``(H, W)``, ``(H, W, 3)`` or ``(H, W, 4)`` floats (or bools).

    Raises:
        ValueError: a path that does not end in ``.png``; another shape, an empty
            image, NaN or inf.
        TypeError: an integer image (convert it with ``skimage.util.img_as_float``)
            or one that is not real numbers.
    """
    from skimage import io, util

    if not str(path).lower().endswith(".png"):
        # scikit-image would pick the format from the extension (a JPEG for .jpg) or
        # fail without one
        raise ValueError(f"volshade.save_png: `path` must end in .png, got {str(path)!r}; "
                         f"write other formats with skimage.io.imsave.")

    img = np.asarray(image)
    if not (img.ndim == 2 or img.ndim == 3 and img.shape[-1] in (3, 4)):
        raise ValueError(f"volshade.save_png: `image` must be (H, W), (H, W, 3) or "
                         f"(H, W, 4), got {img.shape}.")
    if img.size == 0:
        raise ValueError(f"volshade.save_png: `image` is empty, shape {img.shape}.")
    if img.dtype == np.bool_:  # a mask: True is white
        img = img.astype(np.float32)
    if np.issubdtype(img.dtype, np.integer):
        # np.clip(img, 0, 1) would turn an 8-bit white 255 into 1 of 255
        raise TypeError(f"volshade.save_png: `image` must be in [0, 1] (a render), got "
                        f"integers of dtype {img.dtype}; convert them with "
                        f"skimage.util.img_as_float, or write them with skimage.io.imsave.")
    if not jnp.issubdtype(img.dtype, jnp.floating):
        raise TypeError(f"volshade.save_png: `image` must hold real numbers in [0, 1], got "
                        f"dtype {img.dtype}.")
    if not np.all(np.isfinite(img)):
        raise ValueError("volshade.save_png: `image` contains NaN or inf.")
    pixels = img if img.ndim == 2 else img[..., :3]
    io.imsave(str(path), util.img_as_ubyte(np.clip(pixels, 0, 1)), check_contrast=False)
