r"""Clip shapes: the voxels a clip removes, and the voxels whose LAO it can change.

A clip is a solid placed in the volume (voxel index coordinates, ``(d, h, w)``
order) by its ``center`` and ``rotation`` (a rotation matrix whose columns are
the shape's local axes); the voxels whose centres lie inside it are removed
(opacity 0). This is the subtraction of the clipping mesh from the volume of
Titov et al. (section 3.2), but for the voxels on the surface: their eq. 1 keeps a
sample on the clipping surface visible; here a voxel centre on it, $\phi = 0$, is
removed (a sphere of radius 1 about a voxel centre removes 7 voxels, not 1; a
half-space through voxel centres, the layer on its plane). Every shape has a signed
distance $\phi(x)$ (voxels, negative inside, 1-Lipschitz; exact, but inside a
self-intersecting torus, ``major < minor``, where $|\phi|$ may be less than the
distance to the surface), from which both masks follow:

* **clipped**: $\phi(x) \le 0$ at the voxel centre;
* **affected** (the dilation shape, sections 3.3-3.4): the LAO of voxel $x$ reads
  trilinear samples at distances less than $R$ from $x$ (the last at
  $R - \frac32 \Delta s$), each from voxels at most $\sqrt 3$ from the sample
  (with weight 0 at exactly $\sqrt 3$), so it can change only if a clipped voxel
  lies within $R + \sqrt 3$ of $x$; as $\phi$ is 1-Lipschitz, every voxel with
  $\phi(x) \ge R + \sqrt 3$ (plus a margin for the rounding of $\phi$) keeps its
  unclipped LAO.

The paper computes the dilation as the Minkowski sum of the clipping mesh and a
sphere of radius $R$, in 2D on depth maps rendered from a clipping camera (a
rasterisation device, which limits it to meshes of at most two depth layers);
with a 1-Lipschitz signed distance it is a threshold, for any shape, convex or not.

The pose and sizes are array leaves: moving a clip does not recompile. They are
checked when the shape is built from known values and, when traced, wherever the
masks are computed (a rotation that is not orthonormal would break the 1-Lipschitz
bound). The masks are piecewise constant in them, so they get no gradient.
Distances are computed in float32 at least.

References:
    Titov, Kersten-Oertel, Drouin, "Contextual ambient occlusion", sections 3.2-3.4.
"""

import abc
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import safe_sqrt
from ._types import Array, ArrayLike, Bool, Float

# voxels: the rounding of phi must not make an affected voxel look safe; the relative
# part covers float32 coordinates of large volumes, far centres and large clips
_REACH_MARGIN, _REACH_RELATIVE_MARGIN = 1e-3, 64


def _orthonormal(rotation: Array) -> Array:
    """Whether ``rotation`` is a rotation (or reflection) matrix, to rounding."""
    xp, rotation = _checks.for_check(rotation)
    return xp.max(xp.abs(rotation.T @ rotation - xp.eye(3))) < 1e-5


def _pose(center, rotation, where: str) -> tuple[Array, Array]:
    center = _checks.float_leaf(center, "center", where)
    rotation = _checks.float_leaf(np.eye(3) if rotation is None else rotation, "rotation", where)
    if center.shape != (3,):
        raise ValueError(f"{where}: `center` must be 3 numbers (d, h, w) in voxels, got shape "
                         f"{center.shape}.")
    if rotation.shape != (3, 3):
        raise ValueError(f"{where}: `rotation` must be a 3x3 rotation matrix, got shape "
                         f"{rotation.shape}.")
    _checks.refuse(center, [(_checks.non_finite(center).any(), "`center` must be finite "
                             "(voxels).")], where, traced=False)
    _checks.refuse(rotation, [(_checks.non_finite(rotation).any(), "`rotation` must be "
                               "finite (NaN or inf in it)."),
                              (~_orthonormal(rotation), "`rotation` must be orthonormal (a "
                               "rotation matrix): the signed distance is exact only then.")],
                   where, traced=False)
    return center, rotation


def _positive(value, name: str, where: str) -> Array:
    value = _checks.float_leaf(value, name, where)
    _checks.refuse(value, [(_checks.not_positive(value),
                            f"`{name}` must be finite and > 0 (voxels).")], where, traced=False)
    return value


def _hypot(*components: Array) -> Array:
    """The Euclidean norm of the components, with a finite gradient at 0."""
    return safe_sqrt(sum(c * c for c in components))


def _lead(vector: Array, like: Array) -> Array:
    """``vector`` ``(3,)`` with leading unit axes to broadcast against ``like`` ``(..., 3)``."""
    return jnp.reshape(vector, (1,) * (like.ndim - 1) + (3,))


class Clip(eqx.Module):
    """A clip shape: ``center`` ``(3,)`` and ``rotation`` ``(3, 3)`` (columns: the
    local axes) in voxel index coordinates. Subclasses give the signed distance in
    the shape's local frame and name their size leaves in ``sizes``.

    Every shape is built with keyword arguments: ``center`` (3 numbers, voxels),
    ``rotation`` (optional 3x3 orthonormal matrix, default the identity) and its
    sizes (voxels, > 0).

    Raises:
        ValueError: a ``center`` that is not 3 finite numbers, a ``rotation`` that is
            not a 3x3 orthonormal matrix, a size that is not finite and > 0 (when
            known; traced values where the masks are computed); where a clip is used, a
            size that is not one number (three for ``BoxClip``'s ``half_size``): a
            batch of sizes is for vmap.
        TypeError: a value that is not a real number.
    """

    center: Float[Array, "3"]
    rotation: Float[Array, "3 3"]
    sizes = ()  # the names of the size leaves (voxels, > 0)
    size_shape = ()  # the shape of each, where a clip is used (a batch is for vmap)

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        why = "a clip's masks are piecewise constant in its pose and sizes"
        return dict.fromkeys(("center", "rotation", *self.sizes), why)

    def signed_distance(self, points: Float[Array, "*batch 3"]) -> Float[Array, "*batch"]:
        r"""Exact Euclidean signed distance $\phi$ (voxels) of ``points`` ``(..., 3)``
        to the shape's surface, negative inside."""
        where = f"volshade.{type(self).__name__}.signed_distance"
        points = _checks.as_float_array(points, "points", where)
        if points.ndim < 1 or points.shape[-1] != 3:
            raise ValueError(f"{where}: `points` must have shape (..., 3) (d, h, w in voxels), "
                             f"got {points.shape}.")
        clip = _widened(_checked(self))
        points = points.astype(jnp.promote_types(points.dtype, clip.center.dtype))
        local = (points - _lead(clip.center, points)) @ clip.rotation
        return clip._local_distance(local[..., 0], local[..., 1], local[..., 2])

    @abc.abstractmethod
    def _local_distance(self, u: Array, v: Array, w: Array) -> Array:
        r"""$\phi$ of points given by their coordinates along the shape's local axes
        (centre at the origin; any broadcastable shapes)."""


class SphereClip(Clip):
    """A ball of ``radius`` voxels around ``center``.

    Args:
        center: ``(3,)`` centre ``(d, h, w)`` in voxel index coordinates.
        radius: radius in voxels (> 0).
        rotation: optional ``(3, 3)`` orthonormal matrix, columns the local axes
            (default the identity; a ball is the same in any).

    Example:
        >>> clip = SphereClip(center=(8.0, 8.0, 8.0), radius=3.0)
        >>> float(clip.signed_distance(jnp.asarray([8.0, 8.0, 13.0])))
        2.0
    """

    radius: Float[Array, ""]
    sizes = ("radius",)

    def __init__(self, *, center: ArrayLike, radius: ArrayLike,
                 rotation: ArrayLike | None = None):
        where = "volshade.SphereClip"
        self.center, self.rotation = _pose(center, rotation, where)
        self.radius = _positive(radius, "radius", where)

    def _local_distance(self, u, v, w):
        return _hypot(u, v, w) - self.radius


class BoxClip(Clip):
    """A box of half-sizes ``half_size`` ``(3,)`` voxels along its local axes.

    Args:
        center: ``(3,)`` centre ``(d, h, w)`` in voxel index coordinates.
        half_size: half the box's edge along each local axis in voxels (> 0): one
            number (a cube) or three; ``(..., 3)`` builds a batch of boxes, for vmap
            (as a batch of sizes does for the other shapes).
        rotation: optional ``(3, 3)`` orthonormal matrix whose columns are the box's
            local axes (default the identity: edges along ``d``, ``h``, ``w``).
    """

    half_size: Float[Array, "3"]
    sizes = ("half_size",)
    size_shape = (3,)

    def __init__(self, *, center: ArrayLike, half_size: ArrayLike,
                 rotation: ArrayLike | None = None):
        where = "volshade.BoxClip"
        self.center, self.rotation = _pose(center, rotation, where)
        half_size = _checks.float_leaf(half_size, "half_size", where)
        if half_size.shape != () and half_size.shape[-1] != 3:
            raise ValueError(f"{where}: `half_size` must be one number or three (d, h, w), "
                             f"in voxels (a batch of boxes, for vmap: shape (..., 3)), got "
                             f"shape {half_size.shape}.")
        self.half_size = _positive(jnp.broadcast_to(half_size,
                                                    half_size.shape or (3,)),
                                   "half_size", where)

    def _local_distance(self, u, v, w):
        q = [jnp.abs(x) - h for x, h in zip((u, v, w), self.half_size, strict=True)]
        outside = _hypot(*(jnp.maximum(x, 0) for x in q))
        return outside + jnp.minimum(jnp.maximum(jnp.maximum(q[0], q[1]), q[2]), 0)


class TorusClip(Clip):
    """A torus around the local first axis: its tube (radius ``minor``) circles at
    ``major`` voxels from ``center`` in the plane of the other two axes (the concave
    clip of Titov et al., Figure 1). Its signed distance is 1-Lipschitz for any sizes
    and exact when ``major >= minor``.

    Args:
        center: ``(3,)`` centre ``(d, h, w)`` in voxel index coordinates.
        major: distance in voxels from ``center`` to the centre line of the tube (> 0).
        minor: radius of the tube in voxels (> 0).
        rotation: optional ``(3, 3)`` orthonormal matrix whose columns are the local
            axes, the first the torus's axis (default the identity: around ``d``).
    """

    major: Float[Array, ""]
    minor: Float[Array, ""]
    sizes = ("major", "minor")

    def __init__(self, *, center: ArrayLike, major: ArrayLike, minor: ArrayLike,
                 rotation: ArrayLike | None = None):
        where = "volshade.TorusClip"
        self.center, self.rotation = _pose(center, rotation, where)
        self.major = _positive(major, "major", where)
        self.minor = _positive(minor, "minor", where)

    def _local_distance(self, u, v, w):
        return _hypot(u, _hypot(v, w) - self.major) - self.minor


class HalfSpaceClip(Clip):
    """Everything on the side of the plane through ``center`` that the local first axis
    (``rotation[:, 0]``, by default ``+d``) points to: a cut-away.

    Args:
        center: ``(3,)`` a point ``(d, h, w)`` of the plane, in voxel index
            coordinates.
        rotation: optional ``(3, 3)`` orthonormal matrix whose first column is the
            plane's normal, pointing into the removed side (default the identity).
    """

    def __init__(self, *, center: ArrayLike, rotation: ArrayLike | None = None):
        self.center, self.rotation = _pose(center, rotation, "volshade.HalfSpaceClip")

    def _local_distance(self, u, v, w):
        return -jnp.broadcast_arrays(u, v, w)[0]


def _checked(clip: Clip) -> Clip:
    """``clip`` with its traced leaves checked at run time (known ones were checked when
    it was built): finite, sizes > 0, an orthonormal rotation; and, at once, sizes of
    one clip (built with a batch axis, a clip is for vmap: its sizes would broadcast
    against the voxel grid)."""
    where = f"volshade.{type(clip).__name__}"
    # leaves set with eqx.tree_at skip the constructor's dtype and shape checks: a bool
    # would pass as 0 or 1, an integer rotation fail deep inside
    for name in ("center", "rotation", *clip.sizes):
        value = getattr(clip, name)
        if _checks.holds_bool(value) or (eqx.is_array(value)
                                         and not jnp.issubdtype(value.dtype, jnp.floating)):
            raise TypeError(f"{where}: `{name}` must hold floating-point numbers, got "
                            f"{getattr(value, 'dtype', type(value).__name__)}; set it to a "
                            f"float array (or build the clip with its constructor).")
    for name, shape, what in (("center", (3,), "3 numbers (d, h, w) in voxels"),
                              ("rotation", (3, 3), "a 3x3 rotation matrix")):
        if jnp.shape(getattr(clip, name)) != shape:
            raise ValueError(f"{where}: `{name}` must be {what}, got shape "
                             f"{jnp.shape(getattr(clip, name))}; for a batch of clips, "
                             f"jax.vmap over them.")
    for name in clip.sizes:
        if jnp.shape(getattr(clip, name)) != clip.size_shape:
            raise ValueError(f"{where}: `{name}` must have shape {clip.size_shape} (voxels) "
                             f"where the clip is used, got {jnp.shape(getattr(clip, name))};"
                             f" for a batch of clips, jax.vmap over them.")
    leaves = [clip.center, clip.rotation, *(getattr(clip, name) for name in clip.sizes)]
    xp, *leaves = _checks.for_check(*leaves)
    finite = functools.reduce(xp.logical_and, [xp.all(xp.isfinite(x)) for x in leaves])
    positive = functools.reduce(xp.logical_and, [xp.all(x > 0) for x in leaves[2:]],
                                xp.asarray(True))
    return _checks.refuse(
        clip, [(~(finite & positive & _orthonormal(clip.rotation)),
                "the clip's leaves must be finite, its sizes > 0 and `rotation` orthonormal "
                "(a rotation matrix).")], where)


def _voxel_distances(shape: tuple[int, int, int], clip: Clip) -> Array:
    r"""$\phi$ at every voxel centre, in float32 at least (``clip`` checked)."""
    return _grid_distances(shape, _checked(clip))


def _widened(clip: Clip) -> Clip:
    """``clip`` with its array leaves in float32 at least, the dtype it computes in."""
    return jax.tree_util.tree_map(lambda x: _checks.at_least_float32(x) if eqx.is_array(x)
                                  else x, clip)


def _grid_distances(shape: tuple[int, int, int], clip: Clip) -> Array:
    r""":func:`_voxel_distances` of a checked clip. The local coordinates of the grid
    are sums of three broadcast 1-D terms, $\sum_k (x_k - c_k) R_{kj}$, so no
    ``(D, H, W, 3)`` array of points is built and multiplied."""
    clip = _widened(clip)
    offsets = [(jnp.arange(n, dtype=clip.center.dtype) - clip.center[k]).reshape(
        [n if a == k else 1 for a in range(3)]) for k, n in enumerate(shape)]
    local = [sum(offsets[k] * clip.rotation[k, j] for k in range(3)) for j in range(3)]
    return jnp.broadcast_to(clip._local_distance(*local), shape)


def _removed(distances: Array) -> Array:
    return distances <= 0


def _within_reach(distances: Array, radius, clip: Clip) -> Array:
    # phi rounds relative to the largest number it is computed from: the coordinates,
    # the centre and the sizes (a torus of major radius 1e7 rounds phi by half a voxel
    # in float32 wherever its tube passes, however small the volume)
    sizes = [jnp.max(jnp.abs(getattr(clip, name))) for name in clip.sizes]
    scale = max(distances.shape) + jnp.max(jnp.abs(clip.center)) + sum(sizes)
    margin = _REACH_MARGIN + _REACH_RELATIVE_MARGIN * jnp.finfo(distances.dtype).eps * scale
    return distances < jnp.asarray(radius, distances.dtype) + math.sqrt(3) + margin


def _shape_of(shape, where: str) -> tuple[int, int, int]:
    if np.ndim(shape) > 1:  # the volume itself (its repr would fill the screen)
        raise TypeError(f"{where}: `shape` must be 3 positive ints (D, H, W), got an array of "
                        f"shape {np.shape(shape)}; pass `volume.shape`.")
    try:
        shape = tuple(shape)
    except TypeError as err:
        raise TypeError(f"{where}: `shape` must be 3 positive ints (D, H, W), e.g. "
                        f"`volume.shape`, got {shape!r:.80}.") from err
    if any(isinstance(n, jax.Array) for n in shape):
        raise TypeError(f"{where}: `shape` must be Python ints (it sets array shapes), e.g. "
                        f"`volume.shape`, got JAX arrays.")
    if len(shape) != 3 or not all(isinstance(n, int | np.integer) and not isinstance(n, bool)
                                  and n >= 1 for n in shape):
        shown = repr(shape) if len(shape) <= 3 else f"{len(shape)} values"
        raise ValueError(f"{where}: `shape` must be 3 positive ints (D, H, W), got {shown}.")
    return tuple(int(n) for n in shape)


def _clip(clip: Clip, where: str) -> Clip:
    """``clip``, checked to be a clip shape, with its leaves given as Python numbers made
    arrays of the dtype the clip computes in (:func:`volshade._checks.strongly_typed`):
    the compiled functions are not compiled again for the same clip built with arrays
    (``radius=2.0``, then ``radius=jnp.float32(2.0)`` while the clip moves)."""
    if not isinstance(clip, Clip):
        raise TypeError(f"{where}: `clip` must be a volshade clip shape (SphereClip, BoxClip, "
                        f"TorusClip or HalfSpaceClip), got {type(clip).__name__}.")
    if not any(eqx.is_inexact_array(x) for x in jax.tree_util.tree_leaves(clip)):
        return clip  # every leaf replaced by a non-float (eqx.tree_at): _checked names it
    return _checks.strongly_typed(clip, _clip_dtype(clip))


def _clip_dtype(clip: Clip):
    """The dtype ``clip`` computes in: its floating leaves', float32 at least (a
    Python-number size beside float16 leaves would otherwise be rounded to float16
    before its check and its use)."""
    leaves = [x for x in jax.tree_util.tree_leaves(clip) if eqx.is_inexact_array(x)]
    return jnp.result_type(*leaves, jnp.float32)


def clip_mask(shape: tuple[int, int, int], clip: Clip) -> Bool[Array, "D H W"]:
    r"""The voxels ``clip`` removes: $\phi \le 0$ at their centres.

    Args:
        shape: the volume's ``(D, H, W)``.
        clip: a clip shape.

    Returns:
        ``(D, H, W)`` boolean, True where removed.

    Raises:
        ValueError: ``shape`` not 3 positive ints.
        TypeError: ``shape`` not a sequence, of JAX arrays, or the volume itself
            (pass ``volume.shape``); ``clip`` not a clip shape.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): a ``clip`` leaf
            that is not finite, a size that is not > 0 or a ``rotation`` that is not
            orthonormal (values set after it was built, e.g. with ``eqx.tree_at``, or
            traced).

    Example:
        >>> int(clip_mask((9, 9, 9), SphereClip(center=(4.0, 4.0, 4.0), radius=1.0)).sum())
        7
    """
    where = "volshade.clip_mask"
    return _compiled_mask(_shape_of(shape, where), _checked(_clip(clip, where)))


def affected_mask(shape: tuple[int, int, int], clip: Clip, *,
                  radius: Float[ArrayLike, ""]) -> Bool[Array, "D H W"]:
    r"""The voxels whose LAO of radius ``radius`` can differ with and without ``clip``:
    $\phi < R + \sqrt 3$ plus a rounding margin (at least $10^{-3}$ voxels; see the
    module docstring); the clipped voxels are among them.

    Args:
        shape: the volume's ``(D, H, W)``.
        clip: a clip shape.
        radius: the LAO radius $R$ in voxels (dynamic).

    Returns:
        ``(D, H, W)`` boolean.

    Raises:
        ValueError: ``shape`` not 3 positive ints, a non-scalar ``radius``.
        TypeError: ``shape`` not a sequence, of JAX arrays, or the volume itself
            (pass ``volume.shape``); ``clip`` not a clip shape, a non-numeric
            (or bool) ``radius``.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): ``radius`` not
            a finite number > 0; a bad ``clip`` leaf (as for :func:`clip_mask`).
    """
    return _affected_mask(shape, clip, radius, "volshade.affected_mask")


def _affected_mask(shape, clip, radius, where: str) -> Array:
    """:func:`affected_mask`, its errors naming ``where``."""
    clip = _clip(clip, where)
    # a Python number compiles as an array of the dtype it is compared in
    radius = _checks.strongly_typed(_checks.scalar(radius, "radius", where), _clip_dtype(clip))
    radius = _checks.refuse(radius, [(_checks.not_positive(radius),
                                      "`radius` must be a finite number > 0 (voxels).")], where)
    return _compiled_reach(_shape_of(shape, where), _checked(clip), radius)


def clip_opacity(alpha: Float[Array, "D H W"], clip: Clip) -> Float[Array, "D H W"]:
    """``alpha`` with the voxels ``clip`` removes set to 0 (same floating dtype;
    integer and bool volumes come back as floats, as every volume is read).

    Args:
        alpha: ``(D, H, W)`` opacities (NaN or inf is refused). The values are only
            kept or zeroed, so any finite volume works (an intensity volume too);
            :func:`~volshade.lao.lao` and :func:`~volshade.cao.contextual_ao` refuse
            opacities outside [0, 1] when they read the result.
        clip: a clip shape (:class:`SphereClip`, :class:`BoxClip`,
            :class:`TorusClip`, :class:`HalfSpaceClip`).

    Returns:
        ``(D, H, W)``: ``alpha``, 0 at the voxels whose centres lie inside ``clip``.

    Raises:
        ValueError: ``alpha`` not 3-D or not finite, a bad clip leaf.
        TypeError: ``clip`` not a clip shape; ``alpha`` not numbers.
    """
    where = "volshade.clip_opacity"
    alpha = _checks.volume(alpha, "alpha", where)
    return _compiled_clip_opacity(alpha, _checked(_clip(clip, where)))


# The public functions after their eager checks: one compiled program per shape and clip
# type, not an XLA program per operation (clip_opacity of a 32^3 volume, eager: the first
# call 1.0-2.0 s -> 0.12-0.22 s, later ones 8 -> 1.1-1.6 ms)
@eqx.filter_jit
def _compiled_mask(shape: tuple[int, int, int], clip: Clip) -> Array:
    return _removed(_grid_distances(shape, clip))


@eqx.filter_jit
def _compiled_reach(shape: tuple[int, int, int], clip: Clip, radius: Array) -> Array:
    return _within_reach(_grid_distances(shape, clip), radius, clip)


@eqx.filter_jit
def _compiled_clip_opacity(alpha: Array, clip: Clip) -> Array:
    return jnp.where(_compiled_mask(alpha.shape, clip), jnp.zeros_like(alpha), alpha)
