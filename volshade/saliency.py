r"""Obscurance saliency, viewpoint saliency and saliency-driven opacity (Ruiz et al. 2008).

Voxel saliency (section 4, eq. 4) is the magnitude of the obscurance gradient,
estimated by 4D linear regression (Neumann et al. 2000) over a $5^3$ (or $3^3$)
neighbourhood with distance weights $w(k) = |\mathbf{x}(k)|$, scaled to $[0, 1]$
by its maximum over the volume:

$$ S(p) = \frac{\sqrt{A^2 + B^2 + C^2}}{\max_q \sqrt{A_q^2 + B_q^2 + C_q^2}}. $$

Here $(A, B, C)$ is :func:`volshade.gradient.regression_gradient`: eq. 4's sums
$\sum_k w(k) O(k) x_i(k)$, each divided by $\sum_k w(k) x_i(k)^2$. With equal
spacing on the three axes that divisor is one common factor, which the scaling by
the maximum removes, so $S$ is eq. 4's. With unequal spacing each axis has its own
divisor, which makes $(A, B, C)$ the gradient in mm (exact for linear fields away from
the border, see :func:`~volshade.gradient.regression_gradient`);
eq. 4's raw sums would weigh the long axis more, and $S$ differs from them there.

Viewpoint saliency (section 5.2, eq. 6) sums the voxel saliency weighted by the
visibility of each voxel from the viewpoint, $S(v) = \sum_p S(p) V(p)$. Here
$V(p)$ is the transmittance from $p$ to the outside of the volume towards an
orthographic viewer in direction $v$, accumulated along the same digital lines
as the obscurance sweep (:mod:`volshade.obscurance`): with $q_1, q_2, \dots$ the
voxels after $p$ on its line in direction $v$,

$$ V(p) = \prod_{t \ge 1} \big(1 - \alpha'(q_t)\big), \qquad
   \alpha' = 1 - (1 - \alpha)^{|s|}, $$

where the opacities (given per voxel length) are corrected to the line's step
length $|s| = |v| / |v_a| \in [1, \sqrt 3]$ voxels. The digital line stands in
for a ray through voxel centres: nearest-voxel sampling, no interpolation. This
is the approximation; it is exact for axis-aligned viewpoints.

Viewpoints are unit vectors pointing *from the volume towards the viewer*,
axis order ``(d, h, w)``, e.g. ``volshade.directions.icosphere(1)`` (42).
"""

import functools
import numbers
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import correct_opacity, safe_div
from ._types import Array, ArrayLike, Float
from .directions import _check_level, icosphere_points
from .gradient import _WEIGHTS, _check_size, _magnitude, regression_gradient
from .obscurance import (
    _check_smoothing,
    _d_max_problems,
    _d_max_without_gradient,
    _direction_array,
    _gaussian_smooth,
    _line_groups,
    _rho_fn,
    _shear,
    _shift_up,
    _static_dirs,
    _static_number,
    _to_frame,
    obscurance,
)

__all__ = [
    "saliency",
    "viewpoint_saliency",
    "projected_area",
    "most_salient_view",
    "least_salient_view",
    "modulate_opacity",
    "opacity_factor",
    "SaliencyModulation",
]


def saliency(
    obscurance: Float[Array, "D H W"] | Float[Array, "D H W C"],
    *,
    size: int = 5,
    spacing: float | tuple[float, float, float] = 1.0,
    weighting: str = "distance",
) -> Float[Array, "D H W"]:
    r"""Voxel saliency: the scaled magnitude of the obscurance gradient (eq. 4, section 4).

    $S(p) = |\nabla O(p)| / \max_q |\nabla O(q)|$, with $\nabla O$ from
    :func:`volshade.gradient.regression_gradient` (exact for linear fields, but in
    the outer ``size // 2`` layers of the volume, which are edge-extended). For
    a multi-channel (e.g. RGB colour-bleeding) obscurance the magnitude is the
    Frobenius norm over channels and components. A constant field gives exactly 0
    everywhere (the central differences cancel exactly); where the maximum
    magnitude is 0 the result is 0.

    Args:
        obscurance: ``(D, H, W)`` or ``(D, H, W, C)`` obscurance field.
        size: regression neighbourhood edge, 5 (the paper's) or 3 voxels.
        spacing: voxel size ``(sd, sh, sw)`` in mm, or one number.
        weighting: regression weights, ``"distance"`` (the paper's $w(k) = |x(k)|$),
            ``"inverse_distance"`` or ``"uniform"``.

    Returns:
        ``(D, H, W)`` saliency in $[0, 1]$, in the input dtype.

    Raises:
        ValueError: wrong rank, empty, bad ``size``/``weighting``/``spacing``.
        TypeError: a traced ``spacing`` or ``size`` (static: they set the kernel).
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            NaN or inf in ``obscurance``.

    References:
        Ruiz et al. 2008, eq. (4); Neumann, Csébfalvi, König, Gröller: Gradient
        estimation in volume data using 4D linear regression. CGF 19(3), 2000.

    Example:
        >>> obs = jnp.linspace(0.0, 1.0, 8)[:, None, None] * jnp.ones((8, 8, 8))
        >>> float(saliency(obs)[4, 4, 4])
        1.0
    """
    where = "volshade.saliency"
    _check_size(size, where)
    _checks.spacing(spacing, where)
    _checks.option(weighting, _WEIGHTS, "weighting", where)
    arr = _checks.finite(_checks.as_float_array(obscurance, "obscurance", where),
                         "obscurance", where)
    if arr.ndim not in (3, 4):
        raise ValueError(f"{where}: `obscurance` must have shape (D, H, W) or (D, H, W, C), "
                         f"got {arr.shape}; for a batch, use `jax.vmap`.")
    if arr.ndim == 4 and arr.shape[-1] == 0:
        raise ValueError(f"{where}: `obscurance` must have at least one channel, got "
                         f"shape {arr.shape}.")
    _checks.check_ndim(arr, arr.ndim, "obscurance", where, "(D, H, W) or (D, H, W, C)")
    # in float32 at least: a half-precision gradient overflows where the voxels are
    # small (float16 at 4 nm: inf / inf in the scaling), though the result does not
    # depend on the scale
    work = _checks.at_least_float32(arr)
    channels = [work] if work.ndim == 3 else [work[..., c] for c in range(work.shape[-1])]
    grads = [regression_gradient(ch, spacing=spacing, size=size, weighting=weighting)
             for ch in channels]
    return _scaled_magnitude(grads).astype(arr.dtype)


@jax.jit
def _scaled_magnitude(gradients: list[Array]) -> Array:
    """Eq. 4's magnitude of the channels' gradients, scaled to [0, 1], as one compiled
    program (op by op, an eager call compiled about a dozen: first :func:`saliency` of
    a 32^3 volume 1.2 s, now 0.7-0.9 s)."""
    return _magnitude(jnp.concatenate(gradients, axis=-1), scaled=True)


_VISIBILITY = {
    "transmittance": lambda trans, alpha: trans,
    "contribution": lambda trans, alpha: trans * alpha,
}


def _work_dtype(saliency: Array, opacity: Array):
    """The dtype a saliency and an opacity volume are combined in: the wider of theirs,
    float32 at least. Neither rounds the other: a bfloat16 saliency mask would turn an
    opacity of 0.999 into 1 (transmittance 0), a bfloat16 opacity a saliency of 0.1999
    into the threshold 0.2; half precision summed over a view is 1.7 % off at 16^3."""
    return jnp.result_type(saliency.dtype, opacity.dtype, jnp.float32)


def _check_pair(saliency, opacity, where):
    """Both volumes checked and in their :func:`_work_dtype`, that of the result too.

    The saliency may be unscaled or masked, but not negative: a gradient magnitude never
    is, and a negative one would make a view that hides it the most salient."""
    saliency = _checks.volume(saliency, "saliency", where, non_negative=True,
                              hint="(a gradient magnitude, e.g. from `vs.saliency`)")
    opacity = _checks.volume(opacity, "opacity", where, unit_range=True)
    if saliency.shape != opacity.shape:
        raise ValueError(f"{where}: `saliency` and `opacity` must have the same (D, H, W) "
                         f"shape, got {saliency.shape} and {opacity.shape}.")
    dtype = _work_dtype(saliency, opacity)
    return saliency.astype(dtype), opacity.astype(dtype)


def _per_view(
    opacity: Array, dirs: np.ndarray,
    reduce: Callable[[Array, Array | None, Array], Array],
    extra: Array | None = None,
) -> Array:
    """Apply ``reduce(columns_alpha, columns_extra, cosine) -> scalar`` to the sheared
    columns of every viewpoint; columns run from the volume towards the viewer."""
    dtype = opacity.dtype
    out = jnp.zeros((dirs.shape[0],), dtype)
    for g in _line_groups(dirs, opacity.shape):
        frame_alpha = _to_frame(opacity, g.axis, g.sign)
        frame_extra = _to_frame(extra, g.axis, g.sign) if extra is not None else None

        def one(tables, frame_alpha=frame_alpha, frame_extra=frame_extra, g=g):
            off_b, off_c, step, cosine = tables
            alpha = correct_opacity(
                _shear(frame_alpha, off_b, off_c, g.range_b, g.range_c, 0.0), step)
            cols_extra = (None if frame_extra is None else
                          _shear(frame_extra, off_b, off_c, g.range_b, g.range_c, 0.0))
            return reduce(alpha, cols_extra, cosine)

        # (checkpointed: reverse mode would otherwise keep every view's sheared columns,
        # 150 volumes for 12 views at 32^3 and 650 for 42; recomputed, 55 and 87)
        values = jax.lax.map(jax.checkpoint(one),
                             (jnp.asarray(g.off_b), jnp.asarray(g.off_c),
                              jnp.asarray(g.step, dtype), jnp.asarray(g.cosine, dtype)))
        out = out.at[g.index].set(values)
    return out


def _sequential_products() -> bool:
    """Whether the transmittance along columns is a ``lax.scan`` over slices (a CPU) or
    ``lax.cumprod`` (elsewhere). XLA lowers ``cumprod`` to an associative scan of strided
    slices, which on a CPU measured 18x slower than the scan (64 x 128^2 columns; the
    whole viewpoint saliency of 42 views 4.0x faster at 64^3, 4.3x at 96^3). On a GPU
    the scan would be one small kernel per slice, so ``cumprod`` is kept there. The
    choice follows the default backend, not the device of the data."""
    return jax.default_backend() == "cpu"


def _visible_sum(alpha: Array, weights: Array, visibility: Callable, sequential: bool
                 ) -> Array:
    r"""$\sum_p w(p)\, \mathrm{vis}(T(p), \alpha(p))$ over columns along axis 0,
    $T(p)$ the product of $1 - \alpha$ over the positions after $p$ (towards the viewer)."""
    if not sequential:
        inclusive = jax.lax.cumprod(1 - alpha, axis=0, reverse=True)
        trans = _shift_up(inclusive, 1, jnp.ones((), alpha.dtype))
        return jnp.sum(weights * visibility(trans, alpha))

    def step(carry, slices):
        trans, total = carry
        a, w = slices
        return (trans * (1 - a), total + w * visibility(trans, a)), None

    init = (jnp.ones(alpha.shape[1:], alpha.dtype), jnp.zeros(alpha.shape[1:], alpha.dtype))
    (_, total), _ = jax.lax.scan(step, init, (alpha, weights), reverse=True)
    return jnp.sum(total)


@functools.partial(jax.jit, static_argnames=("dirs", "visibility", "sequential"))
def _viewpoint_sums(saliency: Array, opacity: Array, *, dirs: tuple, visibility: str,
                    sequential: bool) -> Array:
    vis_fn = _VISIBILITY[visibility]

    def reduce(alpha, cols_saliency, cosine):
        total = _visible_sum(alpha, cols_saliency, vis_fn, sequential)
        # a composite is a value per pixel, and a line stands for |v_a| voxel^2 of the
        # image plane (1 to 1/sqrt(3)): unweighted, a sum over lines would count an
        # oblique view's pixels up to sqrt(3) times over
        return cosine * total if visibility == "contribution" else total

    # the caller gives both in their _work_dtype
    return _per_view(opacity, np.asarray(dirs), reduce, saliency)


@functools.partial(jax.jit, static_argnames=("dirs",))
def _projected_area(mask: Array, *, dirs: tuple) -> Array:
    def reduce(alpha, _, cosine):
        return cosine * jnp.sum(jnp.any(alpha > 0, axis=0)).astype(alpha.dtype)

    # in float32 at least (the caller's mask is), so that the cosine is not rounded to
    # half precision before it scales the count, and the area does not overflow float16
    return _per_view(mask, np.asarray(dirs), reduce)


def viewpoint_saliency(
    saliency: Float[Array, "D H W"],
    opacity: Float[Array, "D H W"],
    viewpoints: Float[ArrayLike, "V 3"],
    *,
    visibility: str = "transmittance",
    per_area: bool = False,
) -> Float[Array, " V"]:
    r"""Viewpoint saliency $S(v) = \sum_p S(p) V(p)$ (eq. 6, section 5.2) for each viewpoint.

    $V(p)$ is the transmittance from voxel $p$ to the viewer (module docstring).
    ``visibility="transmittance"`` uses it as is, the paper's visibility: a sum over
    voxels, a volume integral. Where the opacity per step is high its visible layer
    is one step of the digital line thick, 1 voxel on axis-aligned views and up to
    $\sqrt 3$ on diagonal ones, so an opaque surface scores up to $\sqrt 3$ times
    more seen obliquely (an opaque ball: 1.41 along ``(1, 1, 0)`` and 1.72 along
    ``(1, 1, 1)``, against 1.01 and 1.02 at opacity 0.05). ``"contribution"`` has
    no such bias: it is the saliency composited front to back as an image, summed
    over the image plane (voxel$^2$), $\sum_{\text{lines}} |v_a| \sum_p \alpha'(p)
    V(p) S(p)$, each line standing for $|v_a|$ voxel$^2$ of the image (the opaque
    ball's scores from the 42 views of ``icosphere(1)`` differ by 2.6%); empty
    voxels count for nothing. Use it for surfaces. With ``per_area=True`` the sum is
    divided by :func:`projected_area` (the most salient view per unit of projected
    area, Figure 6 f-g); a viewpoint that sees an empty volume gets 0.

    On measured data, restrict the saliency to what should be looked at (e.g.
    ``saliency * (opacity > 0)``, and 0 near faces where the scan is cut). The
    obscurance varies in the air around an object and jumps where the data ends, and
    both carry saliency: on Colin27 (3 mm voxels, ``head`` preset, 42 directions,
    ``d_max`` 16) 37% of it lies in voxels without opacity, and the most salient of 42
    views looks down at the crown (``"transmittance"``) or in from the left and 30
    degrees below, at the cut neck (``"contribution"``).

    Args:
        saliency: ``(D, H, W)`` voxel saliency (:func:`saliency`).
        opacity: ``(D, H, W)`` opacities in [0, 1] per voxel length.
        viewpoints: ``(V, 3)`` concrete directions from the volume towards the viewer
            (``d, h, w``), e.g. ``volshade.directions.icosphere(1)``.
        visibility: ``"transmittance"`` or ``"contribution"``.
        per_area: divide by the projected area.

    Returns:
        ``(V,)`` viewpoint saliencies in the wider dtype of the two volumes, float32 at
        least: a sum over a view exceeds float16's range (65504) from a few thousand
        visible salient voxels on.

    Raises:
        ValueError: shapes differ, bad ``viewpoints``, unknown ``visibility``.
        TypeError: non-numeric volumes; ``viewpoints`` traced (they must be concrete),
            a number or complex; ``visibility`` not a string; ``per_area`` not a bool.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            opacity outside [0, 1], a negative saliency, NaN or inf in either volume.

    References:
        Ruiz et al. 2008, eq. (6); Lee, Varshney, Jacobs: Mesh saliency. SIGGRAPH 2005.

    Example:
        >>> from volshade.directions import icosphere
        >>> sal = jnp.zeros((8, 8, 8)).at[1, 4, 4].set(1.0)
        >>> alpha = jnp.zeros((8, 8, 8)).at[4:].set(1.0)   # a wall hides d >= 4 from +d
        >>> s = viewpoint_saliency(sal, alpha, jnp.array([[-1.0, 0, 0], [1.0, 0, 0]]))
        >>> [float(x) for x in s]
        [1.0, 0.0]
    """
    return _viewpoint_saliency(saliency, opacity, viewpoints, visibility, per_area,
                               "volshade.viewpoint_saliency")[0]


def _viewpoint_saliency(saliency, opacity, viewpoints, visibility, per_area, where):
    """:func:`viewpoint_saliency` with errors naming ``where``; also returns the
    normalised ``(V, 3)`` viewpoints as NumPy."""
    _checks.option(visibility, _VISIBILITY, "visibility", where)
    per_area = _checks.flag(per_area, "per_area", where)
    saliency, opacity = _check_pair(saliency, opacity, where)
    dirs = _direction_array(viewpoints, "viewpoints", where)
    static = _static_dirs(dirs)
    total = _viewpoint_sums(saliency, opacity, dirs=static, visibility=visibility,
                            sequential=_sequential_products())
    if per_area:
        total = safe_div(total, _projected_area(_nonempty(opacity, 0), dirs=static))
    return total, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _nonempty(opacity: Array, level: Array) -> Array:
    """The mask of voxels above ``level``, as 0 and 1 in the dtype of ``opacity``."""
    return jnp.where(opacity > level, jnp.ones_like(opacity), jnp.zeros_like(opacity))


def projected_area(
    opacity: Float[Array, "D H W"],
    viewpoints: Float[ArrayLike, "V 3"],
    *,
    level: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, " V"]:
    r"""Projected area (voxel$^2$) of the non-empty part of the volume seen from each viewpoint.

    The pixels of the orthographic projection are the digital lines of the
    viewpoint's sweep; a pixel is visible when some voxel on its line has
    opacity greater than ``level``. Each line covers $|v_a|$ voxel$^2$ of the
    image plane (a unit voxel face perpendicular to the major axis $a$,
    projected along $v$), so the area is $|v_a| \cdot$ (number of visible lines).

    Args:
        opacity: ``(D, H, W)`` opacities in [0, 1].
        viewpoints: ``(V, 3)`` concrete directions towards the viewer.
        level: opacity in [0, 1) above which a voxel counts as non-empty.

    Returns:
        ``(V,)`` areas in voxel$^2$, in the dtype of ``opacity``, float32 at least (an
        area of 256 x 256 voxels exceeds float16's range).

    Raises:
        ValueError: ``opacity`` not 3-D or empty; a non-scalar ``level``;
            ``viewpoints`` not of shape ``(V, 3)`` with ``V >= 1``, or holding NaN, inf
            or a zero vector.
        TypeError: non-numeric inputs (or a bool ``level``); ``viewpoints`` traced
            (they must be concrete), a number or complex.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN or inf in
            ``opacity`` or ``level``, ``opacity`` outside [0, 1], ``level`` outside
            [0, 1).

    Example:
        >>> alpha = jnp.zeros((8, 8, 8)).at[2:4, 2:6, 2:6].set(1.0)
        >>> [float(a) for a in projected_area(alpha, jnp.array([[1.0, 0, 0], [0, 1.0, 0]]))]
        [16.0, 8.0]
    """
    where = "volshade.projected_area"
    opacity = _checks.volume(opacity, "opacity", where, unit_range=True)
    level = _checks.scalar(level, "level", where)
    # An opacity cannot exceed 1, so a level of 1 or more leaves every view empty, and
    # one below 0 counts empty voxels: both are refused rather than answered with 0.
    level = _checks.refuse(level, [
        (~jnp.isfinite(level), "`level` must be a finite opacity (0 counts every voxel "
                               "with any opacity)."),
        ((level < 0) | (level >= 1), "`level` must be an opacity in [0, 1) (0 counts "
                                     "every voxel with any opacity).")], where)

    # The mask of non-empty voxels is swept (opacity correction keeps 0 and 1 fixed).
    dirs = _static_dirs(_direction_array(viewpoints, "viewpoints", where))
    # compared in float32 at least: a float16 level of 0.9999 would round to 1
    work = _checks.at_least_float32(opacity)
    return _projected_area(_nonempty(work, level.astype(work.dtype)), dirs=dirs)


def _select(saliency, opacity, viewpoints, per_area, visibility, pick, where):
    values, dirs = _viewpoint_saliency(saliency, opacity, viewpoints, visibility, per_area,
                                       where)
    return jnp.asarray(dirs, values.dtype)[pick(values)]


def most_salient_view(
    saliency: Float[Array, "D H W"],
    opacity: Float[Array, "D H W"],
    viewpoints: Float[ArrayLike, "V 3"],
    *,
    per_area: bool = False,
    visibility: str = "transmittance",
) -> Float[Array, "3"]:
    """The viewpoint (unit ``(3,)`` direction towards the viewer) of largest
    :func:`viewpoint_saliency` (Figure 6 b; ``per_area=True``: Figure 6 f).

    For the index use ``jnp.argmax(viewpoint_saliency(...))``. Arguments as in
    :func:`viewpoint_saliency`; ties go to the first viewpoint. The direction is in
    voxel index space: ``Camera.from_view(view, spacing=...)`` looks along it.

    Raises:
        ValueError: ``saliency`` or ``opacity`` not 3-D or empty, or of different
            shapes; ``viewpoints`` not of shape ``(V, 3)`` with ``V >= 1``, or holding
            NaN, inf or a zero vector; an unknown ``visibility``.
        TypeError: non-numeric inputs; ``viewpoints`` traced (they must be concrete),
            a number or complex; ``per_area`` not a bool; ``visibility`` not a string.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN or inf in
            ``saliency`` or ``opacity``, ``opacity`` outside [0, 1].

    Example:
        >>> sal = jnp.zeros((8, 8, 8)).at[1, 4, 4].set(1.0)
        >>> alpha = jnp.zeros((8, 8, 8)).at[4:].set(1.0)
        >>> most_salient_view(sal, alpha, jnp.array([[-1.0, 0, 0], [1.0, 0, 0]])).tolist()
        [-1.0, 0.0, 0.0]
    """
    return _select(saliency, opacity, viewpoints, per_area, visibility, jnp.argmax,
                   "volshade.most_salient_view")


def least_salient_view(
    saliency: Float[Array, "D H W"],
    opacity: Float[Array, "D H W"],
    viewpoints: Float[ArrayLike, "V 3"],
    *,
    per_area: bool = False,
    visibility: str = "transmittance",
) -> Float[Array, "3"]:
    """The viewpoint of smallest :func:`viewpoint_saliency` (Figure 6 d); see
    :func:`most_salient_view`, whose errors it raises."""
    return _select(saliency, opacity, viewpoints, per_area, visibility, jnp.argmin,
                   "volshade.least_salient_view")


def modulate_opacity(
    opacity: Float[Array, "D H W"],
    saliency: Float[Array, "D H W"],
    *,
    threshold: Float[ArrayLike, ""] = 0.2,
    multiply: bool = True,
    boost_top: float | None = None,
) -> Float[Array, "D H W"]:
    r"""Saliency-driven opacity modulation (section 5.2, Figures 6 c/e/g and 7).

    $$ \alpha' = \begin{cases} 0 & S < \text{threshold} \\
        \min\big(1,\ b\, \alpha\, S^{m}\big) & \text{otherwise} \end{cases}
       \qquad b = \begin{cases} 2 & S \ge 1 - \text{boost\_top} \\ 1 & \text{else} \end{cases} $$

    with $m = 1$ when ``multiply`` (the opacity times the saliency, Figure 6) and
    $m = 0$ otherwise (opacity preserved above the threshold, Figure 7 b). The
    paper uses the threshold 0.2 only with $m = 0$ (Figure 7); Figure 6 multiplies
    without one (``threshold=0``). The defaults combine the two: multiplied, and cut
    at 0.2.
    ``boost_top`` doubles the opacity of the most salient voxels, those whose
    scaled saliency is in the top ``boost_top`` fraction of the range [0, 1]
    (Figure 7 c); the doubled opacity is clipped to 1 (documented clip).

    Args:
        opacity: ``(D, H, W)`` opacities in [0, 1].
        saliency: ``(D, H, W)`` saliency in [0, 1] (:func:`saliency`).
        threshold: saliency below which voxels become transparent, in [0, 1] (0.2 in
            the paper's Figure 7; 0 for its Figure 6); dynamic.
        multiply: multiply the opacity by the saliency.
        boost_top: ``None`` (no boost) or a fraction in (0, 1].

    Returns:
        ``(D, H, W)`` opacities in [0, 1], in the dtype of ``opacity``.

    Raises:
        ValueError: shapes differ, ``boost_top`` outside (0, 1], non-scalar ``threshold``.
        TypeError: ``multiply`` not a bool, a traced ``boost_top``.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            ``opacity``, ``saliency`` or ``threshold`` outside [0, 1], NaN/inf in
            either volume or in ``threshold``.

    Example:
        >>> a = jnp.full((1, 1, 3), 0.5)
        >>> s = jnp.array([[[0.1, 0.5, 1.0]]])
        >>> modulate_opacity(a, s, boost_top=0.1).tolist()
        [[[0.0, 0.25, 1.0]]]
    """
    where = "volshade.modulate_opacity"
    opacity = _checks.volume(opacity, "opacity", where, unit_range=True)
    saliency = _saliency_volume(saliency, where)
    if saliency.shape != opacity.shape:
        raise ValueError(f"{where}: `saliency` and `opacity` must have the same shape, got "
                         f"{saliency.shape} and {opacity.shape}.")
    dtype = _work_dtype(saliency, opacity)
    return _opacity_factor(saliency.astype(dtype), threshold, multiply, boost_top, where,
                           opacity=opacity.astype(dtype)).astype(opacity.dtype)


def opacity_factor(
    saliency: Float[Array, "D H W"],
    *,
    threshold: Float[ArrayLike, ""] = 0.2,
    multiply: bool = True,
    boost_top: float | None = None,
) -> Float[Array, "D H W"]:
    r"""The factor $f$ of :func:`modulate_opacity`, $\alpha' = \min(1, f\,\alpha)$.

    $f = 0$ where $S <$ ``threshold``, else $b\, S^m$ ($b$, $m$ as in
    :func:`modulate_opacity`). The renderer multiplies interpolated opacities by it.
    Errors as :func:`modulate_opacity`'s; an integer ``saliency`` (a 0/1 mask) is taken
    as float.
    """
    where = "volshade.saliency.opacity_factor"
    saliency = _saliency_volume(saliency, where)
    # compared in float32 at least, as modulate_opacity does: in bfloat16, 1 - boost_top
    # would round (0.9 to 0.8984) and double other voxels than there
    return _opacity_factor(_checks.at_least_float32(saliency), threshold, multiply,
                           boost_top, where).astype(saliency.dtype)


def _saliency_volume(saliency, where: str) -> Array:
    """``saliency`` checked as a ``(D, H, W)`` volume of finite values in [0, 1]."""
    return _checks.volume(saliency, "saliency", where, unit_range=True,
                          hint="(a scaled saliency: `vs.saliency` divides "
                               "by its maximum)")


def _opacity_factor(saliency, threshold, multiply, boost_top, where: str, *,
                    opacity=None) -> Array:
    r""":func:`opacity_factor`, its errors naming ``where`` (the function called); with
    ``opacity``, the modulated opacity $\min(1, f\,\alpha)$ instead."""
    boost_top = _boost_top(boost_top, where)
    multiply = _checks.flag(multiply, "multiply", where)
    threshold = _checks.scalar(threshold, "threshold", where)
    xp, known = _checks.for_check(threshold)
    threshold = _checks.refuse(threshold.astype(saliency.dtype),
                               _threshold_problems(xp, known), where)
    return _modulated(saliency, threshold, multiply, boost_top, opacity)


def _threshold_problems(xp, threshold) -> list[tuple[Array, str]]:
    """``(is_bad, message)`` for a saliency threshold: finite and in [0, 1], where the
    saliency lies (above 1 every voxel would become transparent)."""
    return [(~xp.isfinite(threshold), "`threshold` must be a finite saliency level (0.2 "
                                      "in the paper)."),
            ((threshold < 0) | (threshold > 1), "`threshold` must be a saliency level in "
                                                "[0, 1] (0.2 in the paper).")]


@functools.partial(jax.jit, static_argnums=(2, 3))
def _modulated(saliency, threshold, multiply, boost_top, opacity):
    """The factor (``opacity`` None) or the modulated opacity, after the checks: one
    compiled program (op by op, a first eager :func:`modulate_opacity` of a 32^3
    volume compiled a dozen: 0.50 s, now 0.22-0.30 s)."""
    factor = saliency if multiply else jnp.ones_like(saliency)
    if boost_top is not None:
        top = saliency >= 1 - jnp.asarray(boost_top, saliency.dtype)
        factor = jnp.where(top, 2 * factor, factor)
    factor = jnp.where(saliency < threshold, jnp.zeros_like(factor), factor)
    return factor if opacity is None else jnp.minimum(opacity * factor, 1)


def _boost_top(value, where: str) -> float | None:
    """``boost_top`` (static): ``None`` or a real fraction in (0, 1]."""
    if value is None:
        return None
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{where}: `boost_top` sets which voxels are doubled and must be a "
                        f"static number, not a traced value; close over it instead.")
    value = _static_number(value)     # a concrete scalar array as the number
    if (isinstance(value, bool) or not isinstance(value, numbers.Real)
            or not 0 < value <= 1):
        raise ValueError(f"{where}: `boost_top` must be None or a fraction in (0, 1] (the "
                         f"top fraction of saliency whose opacity is doubled), got {value!r}.")
    return float(value)


class SaliencyModulation(eqx.Module):
    """Saliency-driven opacity modulation for a :class:`volshade.Scene` (section 5.2).

    The scene's obscurance (grey, of the transfer-function opacity) gives the
    saliency (:func:`saliency`), and the renderer multiplies every sample's
    opacity by :func:`volshade.saliency.opacity_factor` of it. ``threshold`` and
    ``d_max`` are array leaves (changing them does not recompile); the rest is
    static. ``d_max`` gets a gradient (but with ``multiply=False`` or ``rho="ao"``,
    where the factor is a step in it); ``threshold`` does not (the factor is a step
    at the threshold, so its derivative there is 0 almost everywhere).

    Attributes:
        threshold: saliency below which voxels become transparent, in [0, 1]
            (default 0.2).
        d_max: obscurance distance in voxels (default 32).
        rho: the obscurance's rho: a :data:`volshade.obscurance.RHO_FUNCTIONS` name
            (default ``"sqrt"``) or a callable ``rho(d, d_max)``, as for
            :func:`~volshade.obscurance.obscurance` (static: hashable, so one holding
            arrays is refused).
        level: icosphere level of the obscurance directions, 0 to 4 (default 1: 42).
        size: regression neighbourhood of the saliency, 5 (default) or 3.
        multiply: multiply the opacity by the saliency (default True).
        boost_top: ``None`` (default) or the top fraction of the saliency range whose
            opacity is doubled (:func:`modulate_opacity`).
        smoothing: standard deviation in voxels of a Gaussian applied to the opacity
            before the occluder search (0, the default: none), as in
            :class:`~volshade.obscurance.ObscuranceParams`: on noisy measured data the
            strict "greater than" test draws the voxel grid into the obscurance, and
            its gradient, the saliency, takes it up.

    Raises:
        ValueError / TypeError: a ``threshold`` not in [0, 1], a bad ``d_max``, an
            unknown ``rho``, a ``level`` outside 0-4, a ``size`` other than 3 or 5, a
            ``multiply`` that is not a bool, a ``boost_top`` outside (0, 1], a
            ``smoothing`` that is not a finite number >= 0.
    """

    threshold: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.SaliencyModulation", "threshold"), default=0.2)
    d_max: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.SaliencyModulation", "d_max"), default=32.0)
    rho: str | Callable[[Array, Array], Array] = eqx.field(
        static=True, default="sqrt", converter=_checks.python_scalar)
    level: int = eqx.field(static=True, default=1, converter=_checks.python_scalar)
    size: int = eqx.field(static=True, default=5, converter=_checks.python_scalar)
    multiply: bool = eqx.field(static=True, default=True, converter=_checks.python_scalar)
    boost_top: float | None = eqx.field(static=True, default=None, converter=_static_number)
    smoothing: float = eqx.field(static=True, default=0.0, converter=_static_number)

    def __check_init__(self):
        where = "volshade.SaliencyModulation"
        _check_smoothing(self.smoothing, where)
        _rho_fn(self.rho, where, static=True)
        _check_level(self.level, where)
        _check_size(self.size, where)
        _boost_top(self.boost_top, where)
        _checks.flag(self.multiply, "multiply", where)
        threshold, d_max = self.threshold, self.d_max
        # values are checked here when known (built eagerly; leaves may carry a batch
        # axis for vmap); traced ones where they are used
        _checks.refuse(threshold, _threshold_problems(jnp, threshold), where, traced=False)
        _checks.refuse(d_max, _d_max_problems(d_max), where, traced=False)

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        steps = {"threshold": "the opacity factor is a step at the threshold"}
        if not self.multiply:
            steps["d_max"] = ("with multiply=False the opacity factor takes the values 0, 1 "
                              "and 2 only, a step in the saliency")
        return {**steps, **_d_max_without_gradient(self.rho)}

    def __call__(self, volume: Float[Array, "D H W"], transfer,
                 spacing: float | tuple[float, float, float] = 1.0) -> Float[Array, "D H W"]:
        """The opacity factor volume for ``volume`` classified by ``transfer``, with
        voxels of ``spacing`` mm (the scene's) for the saliency's regression gradient."""
        density = transfer.opacity(volume)
        if self.smoothing > 0:
            density = _gaussian_smooth(density, self.smoothing, "volshade.SaliencyModulation")
        obs = obscurance(density, directions=icosphere_points(self.level), d_max=self.d_max,
                         rho=self.rho)
        # the saliency computed here lies in [0, 1]: no value check in the renderer's trace
        return _opacity_factor(saliency(obs, size=self.size, spacing=spacing),
                               self.threshold, self.multiply, self.boost_top,
                               "volshade.SaliencyModulation")
