r"""Obscurances, rho functions and colour bleeding (Ruiz et al. 2008).

The obscurance of a voxel $p$ is the average over a set of $L$ directions of a
function $\rho$ of the distance to the first occluder along each direction,
the discrete, full-sphere volumetric form (vicinity shading, Stewart 2003) of
the hemisphere integral of eq. (1), section 2.1:

$$ O(p) = \frac{1}{L} \sum_{l=1}^{L} \rho(d_l(p)), $$

with $\rho = 1$ where no occluder lies within $d_{max}$.

With colours (spectral obscurances, colour bleeding, eq. 3) each direction
contributes the occluder's colour $R(q_l)$ weighted by $\rho$, and a white (or
user-given) ambient colour where nothing occludes:

$$ W(p) = \frac{1}{L} \sum_{l} \begin{cases} \rho(d_l)\, R(q_l) & \text{occluded} \\
   c_{amb} & \text{otherwise.} \end{cases} $$

**Digital lines (section 3.1).** For a direction $l$ let $a$ be its major axis
($|l_a|$ largest, the first axis on ties) and $b < c$ the other two. In the
*frame* of the direction, axis $a$ comes first and is flipped when $l_a < 0$, so
that the direction is $s = (1, s_b, s_c)$ with $s = l / |l_a|$. The offsets
$o_b(i) = \lfloor i s_b + 1/2 \rfloor$ and $o_c(i) = \lfloor i s_c + 1/2 \rfloor$
($i = 0 \dots N_a - 1$, the frame coordinate along $a$) define the parallel
digital lines $\{(i,\ u + o_b(i),\ v + o_c(i))\}_i$ for integer $(u, v)$: every
voxel lies on exactly one of them (the Bresenham sweep of the paper). Walking a
line $t$ steps from $p = (i, j, k)$ reaches $(i + t,\ j + o_b(i+t) - o_b(i),\
k + o_c(i+t) - o_c(i))$, and the distance is defined as

$$ d = t \cdot |s| = t \sqrt{1 + s_b^2 + s_c^2} \quad \text{(voxels)}, $$

the step count times the length of the major-axis-normalised direction.
A voxel $q$ occludes $p$ when $q$ lies strictly after $p$ on $p$'s line and
its density is *strictly greater* than the density of $p$; the occluder is the
first such voxel. Densities are whatever the caller passes: raw intensities
(transfer-function independent) or opacities from a transfer function.

**Cost independent of $d_{max}$.** Each direction's lines are sheared into
axis-aligned columns: slice $i$ of the frame is shifted cyclically by
$(-o_b(i), -o_c(i))$, so the columns hold exactly the volume's voxels, a column
holding one run of positions per digital line it wraps onto (a padded shear holding whole lines
would be up to four times the volume for diagonal directions, 3.2 times on
average over 162 directions, and costs as many times more to search);
and the "first strictly greater value ahead" of every column position is found
with a sparse table of running maxima and binary lifting, $O(n \log n)$ per
column of length $n$, vectorised over all columns. The search is unbounded
(the whole column; an answer past the end of the voxel's own run means no
occluder), so $d_{max}$ enters only through $\rho$ and the cut-off
$d \le d_{max}$: it is a dynamic (traceable, differentiable) scalar, and
neither the cost nor the compiled program depends on it.

**Derivatives.** $O$ is differentiable in $d_{max}$ (through $\rho$; the
cut-off itself is piecewise constant), in the colours and the ambient colour.
With respect to the density the occluder search is piecewise constant: its
derivative is zero almost everywhere, and it is not propagated.

References:
    Ruiz, Boada, Viola, Bruckner, Feixas, Sbert: Obscurance-based volume
    rendering framework. Volume and Point-Based Graphics 2008 (eq. 1-3, sections 2.1,
    3.1, 3.2).
    Stewart: Vicinity shading for enhanced perception of volumetric data. IEEE
    Visualization 2003.
    Méndez, Sbert, Catá: Real-time obscurances with color bleeding. SCCG 2003.
"""

import functools
import math
import numbers
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import quotient, safe_div, safe_normalize, safe_pow, safe_sqrt
from ._types import Array, ArrayLike, Float
from .directions import _check_level, icosphere_points

__all__ = [
    "RHO_FUNCTIONS",
    "obscurance",
    "occluder_distances",
    "threshold",
    "obscurance_shading",
    "ObscuranceParams",
]


def _rho_ao(d: Array, d_max: Array) -> Array:
    return jnp.zeros_like(d)


def _rho_linear(d: Array, d_max: Array) -> Array:
    # (all three by `quotient`: the slope -d / d_max^2 of the plain quotient rule
    # overflows float32 for d_max below about 1e-19 voxels, and the unoccluded
    # directions' discarded rho(d_max, d_max) would multiply that inf by 0)
    return quotient(d, d_max)


def _rho_exponential(d: Array, d_max: Array) -> Array:
    return -jnp.expm1(-quotient(d, d_max))


def _rho_sqrt(d: Array, d_max: Array) -> Array:
    return safe_sqrt(quotient(d, d_max))


#: The rho functions of section 3.2 (Figure 3), called as ``rho(d, d_max)`` for
#: occluded directions (``0 < d <= d_max``): ``"ao"`` all-or-nothing (ambient
#: occlusion, 0), ``"linear"`` $d/d_{max}$, ``"exponential"`` $1 - e^{-d/d_{max}}$
#: and ``"sqrt"`` $\sqrt{d/d_{max}}$.
RHO_FUNCTIONS: dict[str, Callable[[Array, Array], Array]] = {
    "ao": _rho_ao,
    "linear": _rho_linear,
    "exponential": _rho_exponential,
    "sqrt": _rho_sqrt,
}


# ----------------------------------------------------------------------------------------
# Digital lines: frames, shear and the first-greater search (shared with saliency.py).


class _Group(NamedTuple):
    """Directions sharing a major axis and sign, with their static shear tables."""

    axis: int  # major axis a
    sign: int  # +1 or -1
    index: np.ndarray  # (Lg,) positions in the caller's direction array
    off_b: np.ndarray  # (Lg, Na) int32 offsets o_b(i)
    off_c: np.ndarray  # (Lg, Na)
    step: np.ndarray  # (Lg,) |s|, voxels per step
    cosine: np.ndarray  # (Lg,) |l_a| / |l|, projected area of one column
    range_b: int  # max over the group of max(o_b) - min(o_b)
    range_c: int


def _direction_array(directions: object, name: str, where: str) -> np.ndarray:
    """Concrete ``(L, 3)`` directions as float64 numpy (they set the traced program),
    each divided by its largest absolute component, which is then exactly 1: the
    digital lines read $s = l / |l_a|$ off them without rounding (a unit vector
    would not give it: (3, 4, 0) normalised and divided by 0.8 has
    $s_d = 0.7499999999999999$, and $o_d(2) = 1$, not 2)."""
    rows = "V" if name == "viewpoints" else "L"  # (as the docstrings name them)
    an = "a" if rows == "V" else "an"
    if directions is None:
        raise TypeError(f"{where}: `{name}` must be {an} ({rows}, 3) array of directions, "
                        f"got None.")
    try:
        given = np.asarray(directions)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError) as err:
        raise TypeError(
            f"{where}: `{name}` must be concrete (numpy or a JAX array outside `jit`), not "
            f"traced: the directions set the sweep. Close over them instead of passing "
            f"them as a jit argument, and inside a jitted function build them with NumPy, "
            f"e.g. `volshade.directions.icosphere_points(1)` (jnp arrays made under `jit` are "
            f"traced)."
        ) from err
    except (TypeError, ValueError) as err:
        raise TypeError(f"{where}: `{name}` must be {an} ({rows}, 3) array of directions, "
                        f"got {type(directions).__name__}.") from err
    if np.iscomplexobj(given):  # converted, they would have lost their imaginary part
        raise TypeError(f"{where}: `{name}` must be real ({rows}, 3) directions, got complex "
                        f"numbers.")
    # converted to float64, a string would parse and a bool pass as 1 (also beside
    # numbers, which NumPy promotes to float)
    real = jnp.issubdtype(given.dtype, jnp.floating) or jnp.issubdtype(given.dtype, jnp.integer)
    if (given.size and not real) or _checks.holds_bool(directions):
        got = f"dtype {given.dtype}" if not real or given.dtype == np.bool_ else "a bool"
        raise TypeError(f"{where}: `{name}` must be {an} ({rows}, 3) array of real numbers, got "
                        f"{got}.")
    dirs = given.astype(np.float64)
    if dirs.ndim == 0:
        raise TypeError(
            f"{where}: `{name}` must be {an} ({rows}, 3) array of directions, got the number "
            f"{directions!r}: the sweep needs the directions themselves; use e.g. "
            f"`volshade.directions.icosphere_points(1)` (42 directions; levels 0, 1, 2 give "
            f"the paper's 12, 42, 162).")
    if dirs.ndim != 2 or dirs.shape[1] != 3 or dirs.shape[0] == 0:
        raise ValueError(
            f"{where}: `{name}` must have shape ({rows}, 3) with {rows} >= 1 (d, h, w) "
            f"directions, got "
            f"shape {dirs.shape}; use e.g. `volshade.directions.icosphere(1)` (42 directions)."
        )
    if not np.all(np.isfinite(dirs)):
        raise ValueError(f"{where}: `{name}` contains NaN or inf.")
    # no norm is taken: that of a direction given in huge or tiny numbers would
    # overflow (a zero direction, marched nowhere) or underflow
    scale = np.max(np.abs(dirs), axis=1, keepdims=True)
    if np.any(scale == 0):
        raise ValueError(f"{where}: `{name}` contains a zero vector; every direction must "
                         f"have a non-zero length.")
    return dirs / scale


def _other_axes(axis: int) -> tuple[int, int]:
    b, c = (ax for ax in range(3) if ax != axis)
    return b, c


def _line_groups(dirs: np.ndarray, shape: tuple[int, int, int]) -> list[_Group]:
    """Group directions (largest absolute component 1, as :func:`_direction_array`
    gives them) by (major axis, sign) and tabulate their digital lines."""
    axes = np.argmax(np.abs(dirs), axis=1)
    groups = []
    for axis in range(3):
        b, c = _other_axes(axis)
        n_a = shape[axis]
        i = np.arange(n_a, dtype=np.float64)
        for sign in (1, -1):
            sel = np.nonzero((axes == axis) & (np.sign(dirs[:, axis]) == sign))[0]
            if sel.size == 0:
                continue
            s_b, s_c = dirs[sel, b], dirs[sel, c]  # |l_a| = 1
            off_b = np.floor(i[None, :] * s_b[:, None] + 0.5).astype(np.int32)
            off_c = np.floor(i[None, :] * s_c[:, None] + 0.5).astype(np.int32)
            step = np.sqrt(1.0 + s_b**2 + s_c**2)
            groups.append(_Group(
                axis=axis, sign=sign, index=sel, off_b=off_b, off_c=off_c,
                step=step, cosine=1.0 / step,
                range_b=int(np.max(off_b.max(1) - off_b.min(1))),
                range_c=int(np.max(off_c.max(1) - off_c.min(1))),
            ))
    return groups


def _to_frame(x: Array, axis: int, sign: int) -> Array:
    """Volume (D, H, W, ...) -> direction frame (N_a, N_b, N_c, ...)."""
    b, c = _other_axes(axis)
    rest = tuple(range(3, x.ndim))
    x = jnp.transpose(x, (axis, b, c, *rest))
    return jnp.flip(x, axis=0) if sign < 0 else x


def _from_frame(x: Array, axis: int, sign: int) -> Array:
    """Inverse of :func:`_to_frame` (leading batch axes not allowed)."""
    if sign < 0:
        x = jnp.flip(x, axis=0)
    b, c = _other_axes(axis)
    perm = (axis, b, c)
    inverse = tuple(perm.index(k) for k in range(3))
    return jnp.transpose(x, (*inverse, *range(3, x.ndim)))


def _shear(x: Array, off_b: Array, off_c: Array, range_b: int, range_c: int,
           fill: float) -> Array:
    """Frame volume (Na, Nb, Nc) -> columns (Na, Nb + Rb, Nc + Rc): column (u, v)
    holds the digital line through (0, u - max o_b, v - max o_c); ``fill`` outside."""
    n_a, n_b, n_c = x.shape
    pad = jnp.pad(x, ((0, 0), (range_b, range_b), (range_c, range_c)), constant_values=fill)
    start_b = range_b - jnp.max(off_b) + off_b
    start_c = range_c - jnp.max(off_c) + off_c

    def one(slice_, sb, sc):
        return jax.lax.dynamic_slice(slice_, (sb, sc), (n_b + range_b, n_c + range_c))

    return jax.vmap(one)(pad, start_b, start_c)


def _tile(frame: Array) -> Array:
    """The frame tiled twice along b and c (four volumes), as :func:`_wrap` reads it:
    each slice's cyclic shift is then one window."""
    return jnp.tile(frame, (1, 2, 2))


def _wrap(tiled: Array, off_b: Array, off_c: Array) -> Array:
    """Cyclic columns of a frame volume ``x``, with no padding: ``C[i, u, v] = x[i, (u +
    o_b(i)) mod N_b, (v + o_c(i)) mod N_c]``, from ``tiled = _tile(x)``."""
    n_b, n_c = tiled.shape[1] // 2, tiled.shape[2] // 2

    def one(slice_, sb, sc):
        return jax.lax.dynamic_slice(slice_, (sb, sc), (n_b, n_c))

    return jax.vmap(one)(tiled, jnp.remainder(off_b, n_b), jnp.remainder(off_c, n_c))


def _unwrap(columns: Array, off_b: Array, off_c: Array) -> Array:
    """Inverse of :func:`_wrap`: ``x[i, j, k] = C[i, (j - o_b(i)) mod N_b, (k - o_c(i)) mod
    N_c]``."""
    return _wrap(_tile(columns), -off_b, -off_c)


def _segment_ends(off: Array, n: int) -> Array:
    r"""``(N_a, n)``: for column position ``(i, u)`` of :func:`_wrap`, the first frame
    slice after ``i`` where column ``u`` has wrapped onto another line (or ``N_a``).

    Entry ``(i, u)`` holds the voxel ``(u + o(i)) mod n`` of its slice, on the digital
    line through it while the wrap count $\lfloor (u + o(i)) / n \rfloor$ stays the same;
    ``o`` is monotone, so the line's voxels in a column are one run of positions.
    """
    n_a = off.shape[0]
    wraps = jnp.floor_divide(jnp.arange(n)[None, :] + off[:, None], n)
    position = jax.lax.broadcasted_iota(jnp.int32, wraps.shape, 0)
    changes = jnp.where(wraps[1:] != wraps[:-1], position[1:], n_a)
    first_after = jax.lax.cummin(changes, axis=0, reverse=True)
    return jnp.concatenate([first_after, jnp.full((1, n), n_a, first_after.dtype)])


def _line_ends(off_b: Array, off_c: Array, n_b: int, n_c: int) -> Array:
    """``(N_a, N_b, N_c)``: for every position of the cyclic columns, the first position
    past the end of its own digital line (wrapping along b or along c ends it)."""
    return jnp.minimum(_segment_ends(off_b, n_b)[:, :, None],
                       _segment_ends(off_c, n_c)[:, None, :])


def _shift_up(y: Array, s: int, fill: Array) -> Array:
    """``y[i + s]`` along the first axis, ``fill`` past the end."""
    n = y.shape[0]
    if s >= n:
        return jnp.full_like(y, fill)
    return jnp.concatenate([y[s:], jnp.full((s, *y.shape[1:]), fill, y.dtype)])


def _first_greater_steps(x: Array) -> Array:
    """Per position ``i`` of each column (along the first axis): the smallest ``t >= 1``
    with ``x[i + t] > x[i]``, or 0 when none exists.

    Sparse table $M_k[i] = \\max x[i+1 .. i+2^k]$ built by doubling, then binary
    lifting from the largest level down: ``pos`` grows by $2^k$ while the next
    $2^k$ values are all ``<= x[i]``. $O(n \\log n)$ for a column of length $n$,
    whatever the distance of the answer.
    """
    n = x.shape[0]
    n_levels = max(0, math.ceil(math.log2(n))) if n > 1 else 0
    neg = jnp.asarray(-jnp.inf, x.dtype)
    levels = []
    m = _shift_up(x, 1, neg)
    for k in range(n_levels):
        levels.append(m)
        if k + 1 < n_levels:
            m = jnp.maximum(m, _shift_up(m, 2**k, neg))
    iota = jax.lax.broadcasted_iota(jnp.int32, x.shape, 0)
    pos = jnp.zeros(x.shape, jnp.int32)
    for k in reversed(range(n_levels)):
        idx = jnp.minimum(iota + pos, n - 1)
        ahead = jnp.take_along_axis(levels[k], idx, axis=0)
        pos = jnp.where(ahead <= x, pos + 2**k, pos)
    target = iota + pos + 1
    return jnp.where(target < n, pos + 1, 0)


def _frame_steps(volume: Array, axis: int, sign: int, off_b: Array, off_c: Array) -> Array:
    """Steps to the occluder of every voxel along one direction (0: none), in the frame
    of the direction's group (``axis``, ``sign``; :func:`_to_frame`).

    The first greater value ahead is searched in the whole cyclic column; where it
    lies past the end of the voxel's own line (the column wrapped to another line),
    there is no occluder.
    """
    # The frame and its tiles are made here, for each direction, not once per group
    # outside the loop over its directions: XLA then made every group's (five volumes a
    # group, six groups) before marching the first, 43 volumes of temporaries against 20
    # (64^3, 42 directions), in the same time. `+ 0 * off_b[0]` (which adds 0) ties the
    # tiles to the direction: the scan's reverse mode moved them, depending only on the
    # volume, out of the loop and kept every group's from the forward pass (with
    # colours, 73 volumes against 54).
    frame = _to_frame(volume, axis, sign)
    n_b, n_c = frame.shape[1], frame.shape[2]
    tiled = _tile(frame + (0 * off_b[0]).astype(frame.dtype))
    # the columns run along the first axis: laid out along the contiguous last axis
    # instead (two transposes per direction), the whole obscurance measured 1.6-1.7x
    # slower on a CPU (64^3, 128^3, 42 directions) and 1.23x slower on an H200 (256^3,
    # 162 directions: 0.190 s against 0.154 s)
    steps = _first_greater_steps(_wrap(tiled, off_b, off_c))
    target = jax.lax.broadcasted_iota(jnp.int32, steps.shape, 0) + steps
    on_line = target < _line_ends(off_b, off_c, n_b, n_c)
    return _unwrap(jnp.where(on_line, steps, 0), off_b, off_c)


def _occluder_index(steps: Array, off_b: Array, off_c: Array) -> tuple[Array, Array, Array]:
    """Frame coordinates of the occluder (clipped into range where ``steps == 0``)."""
    n_a, n_b, n_c = steps.shape
    i = jax.lax.broadcasted_iota(jnp.int32, steps.shape, 0)
    j = jax.lax.broadcasted_iota(jnp.int32, steps.shape, 1)
    k = jax.lax.broadcasted_iota(jnp.int32, steps.shape, 2)
    tgt = jnp.minimum(i + steps, n_a - 1)
    qj = jnp.clip(j + off_b[tgt] - off_b[i], 0, n_b - 1)
    qk = jnp.clip(k + off_c[tgt] - off_c[i], 0, n_c - 1)
    return tgt, qj, qk


def _volume_index(frame_index: tuple[Array, Array, Array], axis: int,
                  sign: int) -> tuple[Array, Array, Array]:
    """Frame coordinates ``(i, j, k)`` (:func:`_to_frame`) as the volume's ``(d, h, w)``.

    The index arrays have the frame's shape (as :func:`_occluder_index` gives them): the
    frame's first axis, of length ``i.shape[0]``, is the one a negative ``sign`` flips.
    """
    i, j, k = frame_index
    if sign < 0:
        i = i.shape[0] - 1 - i
    b, c = _other_axes(axis)
    by_axis = {axis: i, b: j, c: k}
    return by_axis[0], by_axis[1], by_axis[2]


# ----------------------------------------------------------------------------------------
# Public API.


def _d_max(d_max: ArrayLike, dtype, where: str) -> Array:
    """``d_max`` as a scalar array: refused at once when concrete, at run time when
    traced (``_checks.refuse``)."""
    arr = _checks.scalar(d_max, "d_max", where, unit="voxels", dtype=dtype)
    return _checks.refuse(arr, _d_max_problems(arr), where)


def _d_max_problems(d_max: Array) -> list[tuple[Array, str]]:
    """The checks on ``d_max`` for :func:`volshade._checks.refuse`."""
    return [(~(jnp.isfinite(d_max) & (d_max > 0)),
             "`d_max` must be a finite distance > 0 (voxels).")]


def _gaussian_smooth(volume: Float[Array, "D H W"], sigma: float,
                     where: str = "volshade.ObscuranceParams") -> Float[Array, "D H W"]:
    """Separable Gaussian blur of a volume, as ``skimage.filters.gaussian(volume, sigma,
    mode="nearest", truncate=4.0, preserve_range=True)`` computes it, but traceable
    (the density may depend on transfer-function parameters under ``jit``).

    Args:
        volume: ``(D, H, W)`` values.
        sigma: standard deviation in voxels (static, > 0, at most the longest side of
            ``volume``); the kernel is truncated at ``4 sigma`` and normalised, and the
            edges are extended (``"nearest"``).
        where: the caller, named in errors.
    """
    volume = _checks.as_working_float(volume, "volume", where)
    # a sigma beyond the volume's longest side blurs every line to nearly its two edge
    # values, and one of 1e9 voxels would make a kernel of 8e9 taps (out of memory):
    # refused by name rather than computed
    longest = max(volume.shape)
    if sigma > longest:
        raise ValueError(f"{where}: `smoothing` ({sigma:g} voxels) must be at most the "
                         f"volume's longest side, {longest} voxels (a wider Gaussian blurs "
                         f"the density to its edge values).")
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel = jnp.asarray(kernel / kernel.sum(), volume.dtype)[None, None, :]
    for axis in range(3):
        # one 1-D convolution along `axis`, over the edge-extended lines
        lines = jnp.moveaxis(volume, axis, -1)
        shape = lines.shape
        padded = jnp.pad(lines.reshape(-1, 1, shape[-1]), ((0, 0), (0, 0), (radius, radius)),
                         mode="edge")
        out = jax.lax.conv_general_dilated(padded, kernel, (1,), "VALID",
                                           precision=jax.lax.Precision.HIGHEST)
        volume = jnp.moveaxis(out.reshape(shape), -1, axis)
    return volume


def _rho_fn(rho: str | Callable, where: str, *, static: bool = False) -> Callable:
    """The rho function named or given. ``static``: for a Module's static field, which
    compiles it in and must hash it (a callable holding arrays cannot be)."""
    if not callable(rho):
        return _checks.option(rho, RHO_FUNCTIONS, "rho", where)
    if static:
        try:
            hash(rho)
        except TypeError as err:
            raise TypeError(
                f"{where}: `rho` is static here (compiled in), so it must be hashable; "
                f"{type(rho).__name__} is not (a callable holding arrays, such as an "
                f"equinox Module with a parameter, cannot be). Pass a function, or "
                f"compute vs.obscurance(..., rho=...), which traces such a rho, and use "
                f"it as the scene's ambient_volume.") from err
    return rho


def occluder_distances(
    density: Float[Array, "D H W"],
    *,
    directions: Float[ArrayLike, "L 3"],
) -> Float[Array, "L D H W"]:
    r"""Distance to the first occluder of every voxel along every direction.

    The search of :func:`obscurance` without a cut-off: for direction $l$ and
    voxel $p$, the distance $d = t |s|$ (voxels) to the first voxel strictly
    after $p$ on $p$'s digital line whose density is strictly greater than
    $\text{density}(p)$ (section 3.1; definitions in the module docstring), and
    $+\infty$ where there is none. Computing these once lets any $d_{max}$ and
    $\rho$ be applied afterwards.

    Args:
        density: ``(D, H, W)`` intensities or opacities (any finite values).
        directions: ``(L, 3)`` concrete directions ``(d, h, w)`` (of any length).

    Returns:
        ``(L, D, H, W)`` distances in voxels, ``inf`` where unoccluded, in the dtype
        of ``density``, float32 at least (as :func:`obscurance` measures them).

    Raises:
        ValueError / TypeError: see :func:`obscurance`.

    Example:
        >>> vol = jnp.zeros((4, 4, 4)).at[3].set(1.0)
        >>> d = occluder_distances(vol, directions=jnp.array([[1.0, 0.0, 0.0]]))
        >>> float(d[0, 0, 0, 0]), float(d[0, 3, 0, 0])
        (3.0, inf)
    """
    where = "volshade.occluder_distances"
    density = jax.lax.stop_gradient(_checks.volume(density, "density", where))
    dirs = _direction_array(directions, "directions", where)
    return _occluder_distances(density, _static_dirs(dirs))


def _static_dirs(dirs: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    """Directions as a hashable static argument of the jitted cores."""
    return tuple(tuple(float(x) for x in row) for row in dirs)


@functools.partial(jax.jit, static_argnames=("dirs",))
def _occluder_distances(density: Array, dirs: tuple) -> Array:
    dirs = np.asarray(dirs)
    # distances in float32 at least, as :func:`obscurance` measures them: a half-precision
    # distance (19.05 as 19.125 in bfloat16) would disagree with it at some d_max
    dtype = _checks.at_least_float32(density).dtype
    out = jnp.zeros((dirs.shape[0], *density.shape), dtype)
    for g in _line_groups(dirs, density.shape):
        def one(tables, g=g):
            off_b, off_c, step = tables
            steps = _frame_steps(density, g.axis, g.sign, off_b, off_c)
            dist = jnp.where(steps > 0, steps.astype(dtype) * step, jnp.inf)
            return _from_frame(dist, g.axis, g.sign)

        dists = jax.lax.map(one, (jnp.asarray(g.off_b), jnp.asarray(g.off_c),
                                  jnp.asarray(g.step, dtype)))
        out = out.at[g.index].set(dists)
    return out


def obscurance(
    density: Float[Array, "D H W"],
    *,
    directions: Float[ArrayLike, "L 3"],
    d_max: Float[ArrayLike, ""],
    rho: str | Callable[[Array, Array], Array] = "sqrt",
    colors: Float[Array, "D H W 3"] | None = None,
    ambient: Float[ArrayLike, "3"] | None = None,
) -> Float[Array, "D H W"] | Float[Array, "D H W 3"]:
    r"""Obscurance (eq. 1) or colour-bleeding obscurance (eq. 3) of every voxel.

    $$ O(p) = \frac{1}{L} \sum_l \rho(d_l, d_{max}), \qquad
       W(p) = \frac{1}{L} \sum_l \big[\, o_l\, \rho(d_l, d_{max})\, R(q_l)
              + (1 - o_l)\, c_{amb} \big], $$

    where $d_l$ is the distance (voxels, $t |s|$ along the digital line) to the
    first voxel $q_l$ whose density is strictly greater than $p$'s, and
    $o_l = [d_l \le d_{max}]$; unoccluded directions give $\rho = 1$ (grey) or
    the ambient colour (colour bleeding, the paper's white "ambient colour
    constant", section 3.1). The full sphere of directions is averaged with equal
    weights (the volumetric form of Stewart's vicinity shading; the $\cos\theta$
    hemisphere weighting of eq. 1 needs surface normals, which a voxel of a volume
    does not have). The cost is $O(L\, N \log N_a)$ for $N$ voxels, independent
    of ``d_max``; see the module docstring for the digital lines and the search.

    Args:
        density: ``(D, H, W)`` densities compared by the visibility test: raw
            intensities (transfer-function independent) or opacities.
        directions: ``(L, 3)`` directions ``(d, h, w)``, e.g.
            ``volshade.directions.icosphere(0|1|2)`` (12, 42, 162); concrete (they set
            the traced program), of any length.
        d_max: maximum occluder distance in voxels, a scalar > 0; dynamic and
            differentiable (through $\rho$; the cut-off $d \le d_{max}$ is piecewise
            constant). An occluder at exactly ``d_max`` counts; distances are whole
            multiples of a direction's step, so a ``d_max`` computed as one sits on the
            cut-off, where float32 and float64 may round either way: choose it
            between multiples.
        rho: ``"ao"``, ``"linear"``, ``"exponential"``, ``"sqrt"`` (section 3.2, see
            :data:`RHO_FUNCTIONS`) or a callable ``rho(d, d_max)`` evaluated
            elementwise on occluded directions ($0 < d \le d_{max}$); the array
            leaves of a callable pytree (an equinox Module with a parameter) are
            traced, so they get gradients.
        colors: optional ``(D, H, W, 3)`` diffuse colours $R$ in $[0, 1]$ (e.g. the
            transfer function's colour of each voxel); turns on colour bleeding. With
            ``rho="ao"`` (0 for every occluder within reach) the occluders' colours drop
            out: $W$ is the grey obscurance times ``ambient``.
        ambient: ``(3,)`` colour in $[0, 1]$ of unoccluded directions, for colour
            bleeding only (``None``: white; the average reflectivity in Méndez et al.).

    Returns:
        ``(D, H, W)`` obscurance in $[0, 1]$ (for rho in $[0, 1]$), or
        ``(D, H, W, 3)`` RGB with colours, in the dtype of ``density``.

    Raises:
        ValueError: ``density`` not 3-D or empty, ``colors`` not ``(D, H, W, 3)``,
            ``ambient`` without ``colors``, ``directions`` not ``(L, 3)`` with
            ``L >= 1`` or containing zero vectors, unknown ``rho`` or a ``rho`` whose
            result does not have the distances' shape, a concrete ``d_max <= 0``.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time)
            (``jax.jit`` may report it as a ``JaxRuntimeError`` carrying the same
            message): NaN/inf in ``density``, ``colors`` outside $[0, 1]$ or NaN, a
            traced ``d_max`` that is not a finite number > 0, a callable ``rho`` that
            returns NaN or inf.
        TypeError: non-numeric inputs, an int or traced ``directions``.

    Noisy densities (MRI, CT) speckle the obscurance: the strict "greater than"
    test flips between neighbouring voxels of nearly equal density. Smooth the
    density first (e.g. ``skimage.filters.gaussian``), as
    ``experiments/corner_colour_bleeding.py`` does.

    References:
        Ruiz, Boada, Viola, Bruckner, Feixas, Sbert: Obscurance-based volume
        rendering framework. Volume and Point-Based Graphics 2008, eq. (1)-(3),
        sections 2.1-3.2.

    Example:
        >>> from volshade.directions import icosphere
        >>> vol = jnp.zeros((16, 16, 16)).at[:2].set(1.0)        # a floor at small d
        >>> dirs = icosphere(1)
        >>> obs = obscurance(vol, directions=dirs, d_max=8.0, rho="sqrt")
        >>> bool(obs[3, 8, 8] < obs[12, 8, 8])
        True
    """
    where = "volshade.obscurance"
    density = _checks.volume(density, "density", where)
    rho_fn = _rho_fn(rho, where)
    dirs = _direction_array(directions, "directions", where)
    # in the dtype of the distances and the sum (_obscurance): a half-precision d_max
    # would be rounded (bfloat16: 19.06 -> 19.0) or overflow (float16: 1e5)
    work = _checks.at_least_float32(density).dtype
    d_max = _d_max(d_max, work, where)
    bleeding = colors is not None
    if bleeding:
        # checked as given, then in the sum's dtype: rounded to a half-precision
        # density's dtype first, 1.003 would pass as 1 and every colour lose digits
        colors = _checks.as_float_array(colors, "colors", where)
        if colors.shape != (*density.shape, 3):
            raise ValueError(f"{where}: `colors` must have shape {(*density.shape, 3)} "
                             f"(D, H, W, RGB) to match `density`, got {colors.shape}.")
        reflectances = "(RGB reflectances); rescale it"
        colors = _checks.finite(colors, "colors", where, unit_range=True,
                                hint=reflectances).astype(work)
        ambient = (1.0, 1.0, 1.0) if ambient is None else ambient
        ambient = _checks.numbers(ambient, "ambient", where)
        if ambient.shape != (3,):
            raise ValueError(f"{where}: `ambient` must be an RGB triple, shape (3,), got "
                             f"{ambient.shape}.")
        ambient = _checks.finite(ambient, "ambient", where, unit_range=True,
                                 hint=reflectances).astype(work)
    elif ambient is not None:
        raise ValueError(f"{where}: `ambient` is the colour of unoccluded directions for "
                         f"colour bleeding and needs `colors`; pass `colors` or drop it.")
    # a rho with array leaves (an equinox Module with a parameter) is traced through
    # them, so they get gradients; the rest of it is compiled in
    rho_arrays, rho_rest = eqx.partition(rho_fn, eqx.is_array)
    if not jax.tree_util.tree_leaves(rho_arrays):
        rho_rest = rho_fn  # as given: partition would rebuild a pytree rho at every call
    out = _obscurance(density, d_max, colors, ambient if bleeding else None, rho_arrays,
                      dirs=_static_dirs(dirs), rho_rest=_Static(rho_rest, rho_fn))
    if callable(rho):
        # the named rho functions are finite on (0, d_max]; a user's may not be
        out = _checks.refuse(out, [(_checks.holds_non_finite(out),
                                    "`rho(d, d_max)` returned NaN or inf for some distance "
                                    "0 < d <= d_max; make it finite there.")], where)
    return out


class _Static:
    """A static argument of jit: hashed and compared as ``value`` where that can be
    hashed, else by the identity of ``owner``, the rho it came from (so the same rho
    reuses its compiled program, and each other one compiles its own)."""

    def __init__(self, value: Any, owner: Any):
        self.value, self.owner = value, owner
        try:
            self._key = (True, hash(value))
        except TypeError:
            self._key = (False, id(owner))

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, _Static) or self._key != other._key:
            return False
        return self.value == other.value if self._key[0] else self.owner is other.owner


@functools.partial(jax.jit, static_argnames=("dirs", "rho_rest"))
def _obscurance(density: Array, d_max: Array, colors: Array | None, ambient: Array | None,
                rho_arrays: Any, *, dirs: tuple, rho_rest: _Static) -> Array:
    rho_fn = eqx.combine(rho_arrays, rho_rest.value)
    dirs = np.asarray(dirs)
    # the search compares the density as given; distances, rho and the sum over the
    # directions are in float32 at least (a half-precision sum of 162 terms is off by
    # 1e-3 to 1e-2)
    dtype = _checks.at_least_float32(density).dtype
    d_max = d_max.astype(dtype)
    bleeding = colors is not None
    if bleeding:
        colors, ambient = colors.astype(dtype), ambient.astype(dtype)
    search = jax.lax.stop_gradient(density)
    total = jnp.zeros((*density.shape, 3) if bleeding else density.shape, dtype)

    for g in _line_groups(dirs, density.shape):
        def body(acc, tables, g=g):
            off_b, off_c, step = tables
            steps = _frame_steps(search, g.axis, g.sign, off_b, off_c)
            dist = steps.astype(dtype) * step
            occluded = (steps > 0) & (dist <= d_max)
            safe_dist = jnp.where(occluded, dist, d_max)
            value = jnp.asarray(rho_fn(safe_dist, d_max), dtype)
            if value.shape == ():  # a constant rho
                value = jnp.broadcast_to(value, safe_dist.shape)
            if value.shape != safe_dist.shape:
                raise ValueError(
                    f"volshade.obscurance: `rho(d, d_max)` must return one value "
                    f"per distance (elementwise: the shape of `d`, here {safe_dist.shape}, "
                    f"the volume's axes reordered along the direction's lines), got shape "
                    f"{value.shape}.")
            if not bleeding:
                return acc + jnp.where(occluded, value, jnp.ones_like(value)), None
            # gathered from the colours as given, not from a copy in the frame's axis
            # order: XLA made every group's copy (three volumes each) before the first
            # group's march
            hit = colors[_volume_index(_occluder_index(steps, off_b, off_c), g.axis, g.sign)]
            amb = jnp.broadcast_to(ambient, hit.shape)
            contrib = jnp.where(occluded[..., None], value[..., None] * hit, amb)
            return acc + contrib, None

        # one running sum through the groups, not a sum per group: XLA made all six
        # groups' accumulators (and, in reverse mode, their transposed cotangents) at
        # once; chained in the data, one is alive at a time (64^3: 5 volumes fewer in
        # the forward, 15 with colours, 15-17 in reverse mode)
        acc0 = _to_frame(total, g.axis, g.sign)
        # rematerialised in reverse mode: each direction's distances and gathered colours
        # would otherwise be kept, some 3-5 volumes per direction (162 directions of a
        # 256^3 volume: 31 GB for the gradient w.r.t. d_max; now 20 volumes of
        # temporaries, 25 with colours, for any L)
        acc, _ = jax.lax.scan(jax.checkpoint(body), acc0,
                              (jnp.asarray(g.off_b), jnp.asarray(g.off_c),
                               jnp.asarray(g.step, dtype)))
        total = _from_frame(acc, g.axis, g.sign)
    return (total / jnp.asarray(dirs.shape[0], dtype)).astype(density.dtype)


def threshold(
    obscurance: Float[Array, "*shape"],
    low: Float[ArrayLike, ""],
    high: Float[ArrayLike, ""],
) -> Float[Array, "*shape"]:
    r"""The *low* / *high* display controls of section 5.1.

    $$ O' = \begin{cases} 0 & O < low \\ \dfrac{O - low}{high - low} & low \le O < high
        \\ 1 & O \ge high \end{cases} $$

    Values below ``low`` become 0 (black), values at or above ``high`` become 1
    (unobscured), and the band between is stretched linearly onto $[0, 1]$
    (continuous; the paper's "linear distribution"). The paper adds "(preserving
    their original value)", which could also be read as keeping $O$ unchanged
    between the thresholds; that reading jumps at both of them, so the stretch is
    used. ``low == high`` gives a binary map. ``low`` and ``high`` may be traced and
    are differentiable; the division is safe (no NaN gradient when ``low == high``).

    Args:
        obscurance: obscurance values of any shape (grey or RGB), nominally in [0, 1].
        low: lower threshold, scalar.
        high: upper threshold, scalar, ``>= low``.

    Returns:
        Array of the input's shape and dtype, in [0, 1].

    Raises:
        ValueError: non-scalar thresholds.
        TypeError: a bool or non-numeric threshold.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            ``low > high``, NaN/inf thresholds or obscurance.

    References:
        Ruiz et al. 2008, section 5.1.

    Example:
        >>> [round(x, 6) for x in threshold(jnp.array([0.1, 0.5, 0.9]), 0.2, 0.8).tolist()]
        [0.0, 0.5, 1.0]
    """
    where = "volshade.threshold"
    obscurance = _checks.finite(_checks.as_float_array(obscurance, "obscurance", where),
                                "obscurance", where)
    dtype = obscurance.dtype
    # a bool is refused, not read as 0 or 1 (as ObscuranceParams refuses it)
    given = low, high
    low, high = (_checks.scalar(v, name, where, dtype=dtype)
                 for v, name in ((low, "low"), (high, "high")))
    if all(isinstance(v, int | float) for v in given) and given[0] > given[1]:
        raise ValueError(f"{where}: `low` must be <= `high`, got low={given[0]}, "
                         f"high={given[1]}.")
    # checked on the input, which the output always uses (a check on `low` alone
    # would be compiled away where every value is above `high`)
    xp, lo, hi = _checks.for_check(low, high)
    obscurance = _checks.refuse(obscurance, [
        (~xp.isfinite(lo) | ~xp.isfinite(hi), "`low` and `high` must be finite."),
        (lo > hi, "`low` must be <= `high`.")], where)
    return _threshold(obscurance, low, high)


@jax.jit
def _threshold(obscurance: Array, low: Array, high: Array) -> Array:
    """:func:`threshold` after its checks, one compiled program (op by op, a first eager
    call compiled a program per operation: 0.85 s, now 0.21-0.23 s, for a 32^3 volume)."""
    ramp = safe_div(obscurance - low, high - low)
    out = jnp.where(obscurance < low, jnp.zeros_like(ramp), ramp)
    return jnp.where(obscurance >= high, jnp.ones_like(ramp), out)


def obscurance_shading(
    normal: Float[Array, "*batch 3"],
    light: Float[ArrayLike, "*batch 3"],
    view: Float[ArrayLike, "*batch 3"],
    obscurance: Float[Array, "*batch"] | Float[Array, "*batch 3"],
    *,
    k_d: Float[ArrayLike, ""] = 1.0,
    k_s: Float[ArrayLike, ""] = 0.0,
    shininess: Float[ArrayLike, ""] = 32.0,
    two_sided: bool = False,
) -> Float[Array, "*batch"] | Float[Array, "*batch 3"]:
    r"""Blinn-Phong lighting scaled by the obscurance, eq. (5) of section 5.1.

    $$ I(x) = \big(k_d \max(N \cdot L, 0) + k_s \max(N \cdot H, 0)^n\big)\, O(x),
       \qquad H = \frac{L + V}{|L + V|}. $$

    ``normal``, ``light`` and ``view`` are normalised here (a gradient can be
    passed as the normal); a zero vector stays zero, so a voxel with a zero
    normal gets $I = 0$, with finite gradients. Cosines are clamped at 0 (no
    light from behind), or with ``two_sided`` taken as $|N \cdot L|$ and
    $|N \cdot H|$, as :class:`volshade.Scene`'s ``shading="obscurance"`` does: a
    gradient's sign depends on the classification (a bright object and the same
    object classified from its dark side have opposite gradients), so a one-sided
    rule would leave one of them black. $0^n$ is 0 with a zero gradient. The
    defaults (diffuse only, ``shininess`` 32, one-sided; the paper gives no values)
    are this function's; a scene takes its :class:`volshade.Phong` coefficients
    instead (``diffuse`` 0.65, ``specular`` 0.25, ``shininess`` 24), two-sided.

    Args:
        normal: ``(..., 3)`` surface normals (or gradients), ``(d, h, w)``.
        light: ``(3,)`` or ``(..., 3)`` direction towards the light.
        view: ``(3,)`` or ``(..., 3)`` direction towards the viewer.
        obscurance: ``(...)`` grey or ``(..., 3)`` RGB obscurance, in [0, 1].
        k_d: diffuse coefficient (>= 0).
        k_s: specular coefficient (>= 0).
        shininess: Phong exponent $n$ (> 0).
        two_sided: light both sides of the surface (static; default ``False``, the
            paper's form).

    Returns:
        ``(...)`` or ``(..., 3)`` intensity, in the dtype of ``normal``.

    Raises:
        ValueError: vectors whose last axis is not 3 or that do not broadcast against
            ``normal``; non-scalar coefficients.
        TypeError: ``two_sided`` not True or False, non-numeric inputs.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            NaN or inf in ``normal``, ``light``, ``view``, ``obscurance`` or the
            coefficients; ``obscurance`` outside [0, 1]; ``k_d < 0``, ``k_s < 0``,
            ``shininess <= 0``.

    References:
        Ruiz et al. 2008, eq. (5).

    Example:
        >>> n = jnp.array([[0.0, 0.0, 1.0]])
        >>> obscurance_shading(n, n[0], n[0], jnp.array([0.5]), k_d=1.0, k_s=0.0).tolist()
        [0.5]
    """
    where = "volshade.obscurance_shading"
    normal = _checks.finite(_checks.as_float_array(normal, "normal", where), "normal", where)
    dtype = normal.dtype
    if normal.ndim < 1 or normal.shape[-1] != 3:
        raise ValueError(f"{where}: `normal` must have shape (..., 3), got {normal.shape}.")
    vectors = {}
    for name, vec in (("light", light), ("view", view)):
        vec = _checks.as_float_array(vec, name, where).astype(dtype)
        if vec.ndim < 1 or vec.shape[-1] != 3 or not _checks.broadcasts(vec.shape, normal.shape):
            raise ValueError(f"{where}: `{name}` must have shape (3,) or one that "
                             f"broadcasts to `normal`'s {normal.shape}, got {vec.shape}.")
        vectors[name] = _checks.finite(vec, name, where)
    light, view = vectors["light"], vectors["view"]
    obscurance = _checks.finite(_checks.as_float_array(obscurance, "obscurance", where),
                                "obscurance", where, unit_range=True,
                                hint="(an obscurance: see `threshold`)").astype(dtype)
    batch = normal.shape[:-1]
    if obscurance.shape not in (batch, (*batch, 3)):
        raise ValueError(f"{where}: `obscurance` must have shape {batch} (grey) or "
                         f"{(*batch, 3)} (RGB) to match `normal`, got {obscurance.shape}.")
    coefficients = {name: _checks.scalar(v, name, where, dtype=dtype)
                    for v, name in ((k_d, "k_d"), (k_s, "k_s"), (shininess, "shininess"))}
    xp, *values = _checks.for_check(*coefficients.values())
    known = dict(zip(coefficients, values, strict=True))
    problems = [(~xp.isfinite(v), f"`{name}` contains NaN or inf.") for name, v in known.items()]
    problems += [(known[name] < 0, f"`{name}` must be >= 0 (a negative coefficient "
                                   f"gives negative light).") for name in ("k_d", "k_s")]
    problems.append((~(known["shininess"] > 0), "`shininess` must be > 0."))
    two_sided = _checks.flag(two_sided, "two_sided", where)
    # checked on the result: a check on a coefficient would be folded away with its term
    # (the specular one, when every N.H is a known 0)
    shaded = _compiled_shading(normal, light, view, obscurance, *coefficients.values(),
                               two_sided)
    return _checks.refuse(shaded, problems, where)


def _obscurance_shading(normal, light, view, obscurance, k_d, k_s, shininess,
                        two_sided: bool = False):
    """:func:`obscurance_shading` without its checks, for the renderer's per-sample
    shader (whose inputs come from a checked volume: a run-time check at every step of
    the march would cost a host round trip on a GPU)."""
    dtype = normal.dtype
    batch = normal.shape[:-1]
    light = jnp.broadcast_to(light, normal.shape)
    view = jnp.broadcast_to(view, normal.shape)
    n = safe_normalize(normal)
    light_dir = safe_normalize(light)
    half = safe_normalize(light_dir + safe_normalize(view))
    cosine = jnp.abs if two_sided else (lambda c: jnp.maximum(c, 0))
    n_dot_l = cosine(jnp.sum(n * light_dir, axis=-1))
    n_dot_h = cosine(jnp.sum(n * half, axis=-1))
    k_d, k_s, shininess = (jnp.asarray(v, dtype) for v in (k_d, k_s, shininess))
    local = k_d * n_dot_l + k_s * safe_pow(n_dot_h, shininess)
    return local * obscurance if obscurance.shape == batch else local[..., None] * obscurance


# an eager call compiles one program, not one per operation
_compiled_shading = jax.jit(_obscurance_shading, static_argnums=7)


_DENSITIES = ("opacity", "intensity")


def _static_number(value):
    """A real number, or a concrete scalar array of one, as a Python float (a NumPy
    scalar or an array as a static field would make equinox warn, and compare by
    identity); anything else is left for the check."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_):
        return float(value)
    if (isinstance(value, np.ndarray | jax.Array) and not isinstance(value, jax.core.Tracer)
            and value.shape == () and (jnp.issubdtype(value.dtype, jnp.floating)
                                       or jnp.issubdtype(value.dtype, jnp.integer))):
        return float(value)
    return value


def _check_smoothing(smoothing: float, where: str) -> None:
    """Refuse a ``smoothing`` that is not a finite number >= 0 (after
    :func:`_static_number`)."""
    if not isinstance(smoothing, float):  # a bool, a string, a traced or non-scalar array
        raise TypeError(f"{where}: `smoothing` must be a number (Gaussian sigma in voxels, "
                        f"static), got {smoothing!r:.80}.")
    if not (math.isfinite(smoothing) and smoothing >= 0):
        raise ValueError(f"{where}: `smoothing` must be a finite number >= 0 (Gaussian "
                         f"sigma in voxels, static), got {smoothing!r}.")


def _d_max_without_gradient(rho) -> dict[str, str]:
    """``{"d_max": why}`` where ``rho`` makes the obscurance a step in ``d_max``."""
    if isinstance(rho, str) and rho == "ao":
        return {"d_max": "with rho='ao' an occluder counts 1 at any distance up to d_max, "
                         "so the obscurance is a step in d_max; a graded rho ('sqrt', "
                         "'linear', 'exponential') makes it differentiable"}
    return {}


class ObscuranceParams(eqx.Module):
    r"""Obscurance settings for a :class:`volshade.Scene` (``ambient="obscurance"``).

    ``d_max``, ``low`` and ``high`` are differentiable leaves (``d_max`` but with
    ``rho="ao"``, a step in it); the rest is static.

    Attributes:
        d_max: maximum occluder distance in voxels.
        low, high: display thresholds (:func:`threshold`; 0 and 1 leave values as they
            are). Where the density rises into an object (measured data, or after
            ``smoothing``), the denser voxels behind a surface occlude up to half of
            its directions at short distances, where rho is small: the obscurance at
            surfaces is well below 1 (0.31 at the median over the Colin27 skin
            voxels, head preset, 42 directions, d_max 32; 0.69 at a flat face of a
            solid blurred by one voxel), so ``shading="obscurance"``, which scales all
            the lighting by it, renders surfaces darker than ``"phong"``. ``high`` at
            0.5 to 0.7 gives flat surfaces their brightness back and darkens only
            creases and cavities (the paper's Figure 1 uses low/high 0/1, 0.4/0.6,
            0.6/0.7).
        rho: name of a rho function (:data:`RHO_FUNCTIONS`) or a callable
            ``rho(d, d_max)``, as for :func:`obscurance` (static: a new function
            compiles again; it must be hashable, so one holding arrays is refused).
        level: icosphere level of the directions, 0 to 4: 0, 1, 2 for the paper's 12,
            42, 162 (3 and 4 give 642 and 2562).
        color_bleeding: tint by the occluders' transfer-function colours (eq. 3): a
            voxel's own colour or, with ``smoothing``, the opacity-weighted mean colour
            of the neighbourhood its smoothed density comes from,
            $G * (\alpha c) / G * \alpha$ (so a voxel that occludes only through
            the smoothing takes the colour of the material near it). A voxel with no
            opacity (and, with ``smoothing``, none near it), which can occlude only
            with ``density="intensity"``, tints like the ambient white: it reflects
            nothing of its own, and the colour a transfer function gives invisible
            values (black, in every preset) would darken its neighbours. That switch
            from white to a colour, as opacity appears, is a step the gradient
            w.r.t. the opacities does not see.
        density: what occludes: ``"opacity"`` (transfer-function opacity) or
            ``"intensity"`` (raw values, transfer-function independent).
        smoothing: standard deviation in voxels of a Gaussian applied to the density
            before the occluder search (0: none). The strict "greater than" test
            on a noisy density (the MRI head's skin) flips between neighbouring
            voxels and draws the voxel grid on smooth surfaces as striations; a
            sigma of about 1 voxel removes them. The search is not differentiated,
            so this changes only which voxels occlude.

    Raises:
        ValueError: an unknown ``rho`` or ``density``; ``level`` outside 0-4;
            ``smoothing`` not a finite number >= 0.
        TypeError: non-numeric (or bool) ``d_max``, ``low``, ``high`` or
            ``smoothing``; ``level`` not an int; ``color_bleeding`` not a bool.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): ``d_max`` not
            a finite number > 0, NaN or inf in ``low`` or ``high``, ``low > high``;
            traced values are checked when a render computes the obscurance.
    """

    d_max: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.ObscuranceParams", "d_max"), default=32.0)
    low: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.ObscuranceParams", "low"), default=0.0)
    high: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.ObscuranceParams", "high"), default=1.0)
    rho: str | Callable[[Array, Array], Array] = eqx.field(
        static=True, default="sqrt", converter=_checks.python_scalar)
    level: int = eqx.field(static=True, default=1, converter=_checks.python_scalar)
    color_bleeding: bool = eqx.field(static=True, default=False,
                                     converter=_checks.python_scalar)
    density: str = eqx.field(static=True, default="opacity", converter=_checks.python_scalar)
    smoothing: float = eqx.field(static=True, default=0.0, converter=_static_number)

    def __check_init__(self):
        where = "volshade.ObscuranceParams"
        _check_smoothing(self.smoothing, where)
        _rho_fn(self.rho, where, static=True)
        if self.density not in _DENSITIES:
            raise ValueError(f"{where}: unknown density {self.density!r}; valid values are "
                             f"{', '.join(map(repr, _DENSITIES))}.")
        _check_level(self.level, where)
        _checks.flag(self.color_bleeding, "color_bleeding", where)
        d_max, low, high = self.d_max, self.low, self.high
        # values are checked here when known (built eagerly; leaves may carry a batch
        # axis for vmap); traced ones where they are used
        _checks.refuse(d_max, _d_max_problems(d_max), where, traced=False)
        _checks.refuse(low, [(~(jnp.isfinite(low) & jnp.isfinite(high)),
                              "`low` and `high` must be finite."),
                             (low > high, "`low` must be <= `high`.")], where, traced=False)

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        return _d_max_without_gradient(self.rho)

    def __call__(self, volume: Float[Array, "D H W"], transfer) -> Array:
        """Thresholded obscurance of ``volume`` classified by ``transfer``: ``(D, H, W)``,
        or ``(D, H, W, 3)`` with colour bleeding."""
        # (the intensity alone, without colours, needs no classification: the volume may
        # then lie outside the transfer function's range)
        classify = self.density == "opacity" or self.color_bleeding
        alpha = transfer.opacity(volume) if classify else None
        # the smoothed opacity is both the density and the colours' weight: blurred once
        weight = None if alpha is None else self._smooth(alpha)
        density = weight if self.density == "opacity" else self._smooth(volume)
        colors = (self._reflectances(alpha, weight, transfer.color(volume))
                  if self.color_bleeding else None)
        obs = obscurance(density, directions=icosphere_points(self.level), d_max=self.d_max,
                         rho=self.rho, colors=colors)
        return threshold(obs, self.low, self.high)

    def _smooth(self, volume: Array) -> Array:
        return _gaussian_smooth(volume, self.smoothing) if self.smoothing > 0 else volume

    def _reflectances(self, alpha: Array, weight: Array, colors: Array) -> Array:
        """Each voxel's diffuse colour $R(q)$ as an occluder (see ``color_bleeding``), from
        its opacity, the smoothed opacity ``weight`` and its transfer-function colour."""
        if self.smoothing > 0:
            weighted = jnp.stack([self._smooth(alpha * colors[..., c]) for c in range(3)],
                                 axis=-1)
            colors = safe_div(weighted, weight[..., None])
        return jnp.where(weight[..., None] > 0, colors, jnp.ones_like(colors))
