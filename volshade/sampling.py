"""Trilinear sampling of volumes at arbitrary points.

Conventions: points are in *voxel index* coordinates ``(d, h, w)``: voxel
``(i, j, k)`` has its centre at ``(i, j, k)``. Physical positions (mm) map to
index coordinates by dividing by the voxel spacing, which is how anisotropic
spacing is honoured. Two boundary rules are defined:

* ``"constant"``: the volume is surrounded by zeros, so values fade linearly to
  0 over the voxel beyond the outermost centres (half the edge value at the cell
  faces, 0 one voxel out; an opacity volume is empty outside; used by ambient
  occlusion and obscurances).
* ``"nearest"``: points outside take the value of the closest voxel (used by
  the renderer inside the box of voxel cells, so a uniform volume samples as a
  uniform medium right up to its faces).
"""

import jax
import jax.numpy as jnp
from jax.scipy.ndimage import map_coordinates

from . import _checks
from ._types import Array, Float

__all__ = ["trilinear"]

_MODES = {"constant": "constant", "nearest": "nearest"}


def trilinear(
    volume: Float[Array, "D H W *C"],
    points: Float[Array, "*batch 3"],
    *,
    mode: str = "constant",
) -> Array:
    """Trilinearly interpolate ``volume`` at ``points`` (voxel index coordinates).

    Args:
        volume: ``(D, H, W)`` scalar volume, or ``(D, H, W, C)`` with C channels
            interpolated independently.
        points: ``(..., 3)`` positions ``(d, h, w)`` in voxel index units.
        mode: boundary rule, ``"constant"`` (zero outside) or ``"nearest"``.

    Returns:
        ``(...)`` values, or ``(..., C)`` for a multi-channel volume, in the dtype
        of ``volume`` (integer and bool volumes: JAX's default float).

    Raises:
        ValueError: ``volume`` is not 3-D or 4-D or is empty, ``points`` does not end in 3,
            ``mode`` is unknown, or ``volume`` or ``points`` holds NaN or inf (at run
            time, an ``EquinoxRuntimeError``, when they are traced).
        TypeError: ``volume`` or ``points`` not real numbers (e.g. a complex dtype).

    Example:
        >>> vol = jnp.arange(8.0).reshape(2, 2, 2)
        >>> float(trilinear(vol, jnp.array([0.5, 0.5, 0.5])))
        3.5
    """
    where = "volshade.sampling.trilinear"
    scipy_mode = _checks.option(mode, _MODES, "mode", where)
    volume = _checks.as_float_array(volume, "volume", where)
    points = _checks.as_float_array(points, "points", where)
    if volume.ndim not in (3, 4) or 0 in volume.shape:
        raise ValueError(f"{where}: `volume` must be (D, H, W) or (D, H, W, C), not empty, "
                         f"got shape {volume.shape}.")
    if points.ndim < 1 or points.shape[-1] != 3:
        raise ValueError(f"{where}: `points` must have shape (..., 3), got {points.shape}.")
    volume = _checks.finite(volume, "volume", where)
    # The check passes traced points through a conditional, which XLA stores once: every
    # read of them then sees one value. Points computed in the caller's jit would otherwise
    # be recomputed in each fusion reading them, some copies contracted into fused
    # multiply-adds, and a channel of a point within an ulp of a voxel centre could take
    # its voxel from one copy and its weights from another (the render march's lax.cond;
    # tests/test_sampling_gradient.py).
    points = _checks.finite(points, "points", where)
    return _trilinear(volume, points, scipy_mode)


def _trilinear(volume: Array, points: Array, mode: str) -> Array:
    """:func:`trilinear` without its checks, for callers whose volume and points are
    checked already (the renderer's march)."""
    # coordinates in at least float32: half precision cannot even hold index 257
    work = jnp.promote_types(volume.dtype, jnp.float32)
    points = points.astype(work)

    def scalar(vol: Array) -> Array:
        coords = [points[..., i] for i in range(3)]
        out = map_coordinates(vol.astype(work), coords, order=1, mode=mode, cval=0.0)
        return out.astype(volume.dtype)

    if volume.ndim == 3:
        return scalar(volume)
    return jnp.moveaxis(jax.vmap(scalar, in_axes=-1)(volume), 0, -1)
