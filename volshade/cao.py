r"""Contextual ambient occlusion: LAO under a moving clip, recomputed only where it can change.

Titov et al. observe that clipping changes the LAO of few voxels: those within
reach of a removed one. So the LAO of the unclipped volume is computed once
($V_{PAO}$, their step 1), and for every position of the clip only the affected
voxels (:func:`~volshade.clip.affected_mask`, their dilation maps) are marched
again, on the clipped opacity (their steps 4-5); every other voxel keeps its
unclipped value, which *is* its LAO under the clip, since none of the voxels it
reads were removed. The result equals :func:`~volshade.lao.lao` of the clipped
opacity (to rounding), at a fraction of the cost when the clip is small against
the volume.

Here the affected voxels are gathered into bricks of ``brick_size`` and only the
bricks holding one are marched (``volshade.lao``'s bricked march: compacted,
vmapped groups of padded windows; the empty slots of the last group are marched
too, and a group is at most an eighth of the bricks); when more than half of the
bricks are affected
the whole clipped volume is marched instead, which is then cheaper. The clip's pose
is traced, so a moving clip never recompiles; under ``jax.vmap`` (a batch of poses)
the poses run one after another, each marching only its own bricks.

Two parts of the paper are not needed here: its clipped voxels get AO = 1
(category a) and its clipping test anti-aliases the opacity at the clip's surface
(eq. 5); here the clipped voxels get the AO that a full recompute gives them (the
renderer does not show them, but they are interpolated at the cut), and the clip
removes whole voxels, as :func:`~volshade.clip.clip_opacity` does.

Gradients: the marched bricks differentiate as :func:`~volshade.lao.lao` does
(opacity, radius, offset, weights); the other voxels take the gradient of
``unclipped`` itself, which is their gradient under the clip too when ``unclipped``
is computed from the same opacity inside the differentiated function. The clip's
pose gets none (the masks are piecewise constant).

References:
    Titov, Kersten-Oertel, Drouin, "Contextual ambient occlusion", section 3 (eq. 2-3).
"""

import functools

import equinox as eqx
import jax.numpy as jnp
from jax import lax

from . import _checks
from ._types import ArrayLike, Float, Volume
from .clip import (
    Clip,
    _affected_mask,
    _checked,
    _clip,
    _removed,
    _voxel_distances,
    _within_reach,
)
from .lao import (
    _MAX_ACTIVE_FRACTION,
    _bricked,
    _bricks_holding,
    _marchers,
    _one_at_a_time,
    _prepare,
    _unoccluded,
)

_WHERE = "volshade.contextual_ao"


def contextual_ao(
    alpha: Volume,
    *,
    clip: Clip,
    unclipped: Volume,
    directions: Float[ArrayLike, "L 3"] | int,
    radius: Float[ArrayLike, ""],
    offset: Float[ArrayLike, ""] = 1.0,
    samples: int = 16,
    weights: Float[ArrayLike, " L"] | None = None,
    opacity_correction: bool = False,
    brick_size: int = 8,
    max_radius: float | None = None,
) -> Volume:
    r"""LAO of ``alpha`` with the voxels inside ``clip`` removed, marching only the
    bricks the clip can change (Titov et al., section 3).

    Equals ``lao(clip_opacity(alpha, clip), ...)`` to rounding, provided ``unclipped``
    is ``lao(alpha, ...)`` with the same parameters (computed once, reused for every
    position of the clip).

    Args:
        alpha: ``(D, H, W)`` opacities in ``[0, 1]``, unclipped.
        clip: the clip shape (:mod:`volshade.clip`); the voxels inside it are removed.
        unclipped: ``(D, H, W)`` LAO of ``alpha`` without the clip, with the
            parameters given here ($V_{PAO}$ of the paper). To differentiate, compute
            it inside the differentiated function: voxels outside the marched bricks
            take its gradient (zero for a precomputed array).
        directions, radius, offset, samples, weights, opacity_correction, max_radius:
            as for :func:`~volshade.lao.lao`.
        brick_size: edge (voxels) of the bricks that are marched or kept whole (default 8).

    Returns:
        ``(D, H, W)`` AO in ``[0, 1]``, in the dtype of ``alpha`` (computed in float32
        at least: half precision is widened for the march and the result rounded).

    Raises:
        ValueError: ``unclipped`` of another shape than ``alpha``, ``brick_size < 1``,
            and every error of :func:`~volshade.lao.lao`.
        TypeError: ``clip`` not a clip shape.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            ``unclipped`` not finite or outside ``[0, 1]``.

    References:
        Titov, Kersten-Oertel, Drouin, "Contextual ambient occlusion".

    Example:
        >>> alpha = jnp.zeros((16, 16, 16)).at[4:12, 4:12, 4:12].set(0.3)
        >>> kw = dict(directions=12, radius=3.0, samples=6)
        >>> before = vs.lao(alpha, **kw)
        >>> clip = vs.SphereClip(center=(4.0, 4.0, 4.0), radius=3.0)
        >>> after = contextual_ao(alpha, clip=clip, unclipped=before, **kw)
        >>> bool(jnp.allclose(after, vs.lao(vs.clip_opacity(alpha, clip), **kw), atol=1e-6))
        True
    """
    clip = _clip(clip, _WHERE)
    brick_size = _checks.positive_int(brick_size, "brick_size", _WHERE)
    p = _prepare(alpha, directions=directions, radius=radius, offset=offset, samples=samples,
                 weights=weights, opacity_correction=opacity_correction,
                 brick_size=brick_size, max_radius=max_radius, where=_WHERE)
    unclipped = _checks.as_float_array(unclipped, "unclipped", _WHERE)
    if unclipped.shape != p.alpha.shape:
        raise ValueError(f"{_WHERE}: `unclipped` must be the LAO of `alpha`, of its shape "
                         f"{p.alpha.shape}, got {unclipped.shape}.")
    unclipped = _checks.finite(unclipped, "unclipped", _WHERE, unit_range=True,
                               hint="(an AO volume: `volshade.lao(alpha, ...)`)")
    return _contextual(p.alpha, unclipped.astype(p.alpha.dtype), clip, p.directions,
                       p.weights, p.radius, p.offset, pad=p.pad, samples=p.samples,
                       correction=p.correction, brick_size=brick_size,
                       max_active=_MAX_ACTIVE_FRACTION).astype(p.dtype)


@eqx.filter_jit
def _contextual(alpha, unclipped, clip, dirs, weights, radius, offset, *, pad, samples,
                correction, brick_size, max_active):
    """The validated computation, compiled once per shape and static options."""
    one = functools.partial(_contextual_one, pad=pad, samples=samples, correction=correction,
                            brick_size=brick_size, max_active=max_active)
    return _one_at_a_time(one)(alpha, unclipped, clip, dirs, weights, radius, offset)


def _contextual_one(alpha, unclipped, clip, dirs, weights, radius, offset, *, pad, samples,
                    correction, brick_size, max_active):
    """:func:`_contextual` for one clip."""
    if samples == 1:  # eq. 2 with M = 1: an empty product, clip or not
        return _unoccluded(alpha, unclipped, _checked(clip), dirs, weights, radius, offset)
    distances = _voxel_distances(alpha.shape, clip)
    clipped = jnp.where(_removed(distances), jnp.zeros_like(alpha), alpha)

    march, dense = _marchers(pad, dirs, weights, radius, offset, samples, correction)

    def sparse(clipped):
        ao, skipped = _bricked(clipped, active, pad, brick_size, march)
        return jnp.where(skipped, unclipped, ao)

    active = _bricks_holding(_within_reach(distances, radius, clip), brick_size)
    return lax.cond(jnp.mean(active) <= max_active, sparse, dense, clipped)


def affected_fraction(shape: tuple[int, int, int], clip: Clip, *, radius: float,
                      brick_size: int = 8) -> float:
    """The fraction of the bricks that hold a voxel the clip can change (a concrete
    number, for benchmarks and for choosing ``brick_size``): what
    :func:`contextual_ao` marches, up to one half, rounded up to whole groups of
    bricks (each at most an eighth of them); above, it marches the whole volume."""
    where = "volshade.cao.affected_fraction"
    brick_size = _checks.positive_int(brick_size, "brick_size", where)
    return float(jnp.mean(_bricks_holding(_affected_mask(shape, clip, radius, where),
                                          brick_size)))
