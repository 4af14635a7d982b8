r"""Local ambient occlusion (LAO) by ray marching, gather-free, exact and differentiable.

For the centre $x$ of every voxel, $L$ rays of length $R$ (the *radius*) are cast
in the directions $l$; along each, $M$ opacity samples $\alpha_i$ (trilinear,
zero outside the volume) are composited front to back (Hernell et al. 2007;
Ancel et al. 2010, section 3, eq. 3-4; Titov et al., eq. 2-3). The sum has $M$ terms,
as in Titov et al.'s eq. 2; Ancel et al.'s eq. 3 is printed with $m$ up to $M$, $M + 1$
terms, which would give an empty ray $(M + 1)/M > 1$:

$$ I_l(x) = \sum_{m=0}^{M-1} \frac{1}{M} \prod_{i=0}^{m-1} (1 - \alpha_i),
\qquad \mathrm{AO}(x) = \sum_l \hat w_l\, I_l(x), \quad
\hat w_l = \frac{w_l}{\sum_k w_k}. $$

With all weights equal, $\hat w_l = 1/L$ and this is eq. 4 of Ancel et al.; the
normalised weights are Titov et al.'s eq. 3 with weights that keep AO in
$[0, 1]$. AO is 1 where nothing occludes and falls towards 0 with occlusion.

**Sample positions.** The shell $[a, R]$ ($a$ the initial *offset*) is split into
$M$ segments of length $\Delta s = (R - a)/M$; $\alpha_i$ is the opacity of
segment $i$, sampled at its midpoint $s_i = a + (i + \tfrac12)\Delta s$, i.e. at
$x + s_i\, l$ in voxel index units. Term $m$ of $I_l$ is the transmittance to
the start of segment $m$, so eq. 3 is the left Riemann sum of the continuous
eq. 2 of Ancel et al. The last segment's opacity $\alpha_{M-1}$ does not enter
eq. 3, so only $M - 1$ samples are taken (and $M = 1$ gives AO = 1).

**Opacity correction.** The seeds' form (eq. 3) uses the opacity $\alpha$
unchanged, whatever $\Delta s$. With ``opacity_correction=True`` each sample
is corrected to the step, $\alpha' = 1 - (1 - \alpha)^{\Delta s / \Delta s_0}$
with $\Delta s_0 = 1$ voxel, so ``alpha`` is read as the opacity of a one-voxel
step and changing ``radius``, ``offset`` or ``samples`` changes the physics
consistently (then AO $\to 1$ as $R \to a$, wherever the samples read opacities
below 1: an opacity of exactly 1 stays opaque at any step).

**How it is computed.** For a fixed direction and sample, the offset $s_i l$ is
the same for every voxel, so the sample volume is the opacity volume shifted by
$\lfloor s_i l \rfloor$ (on a grid plane, the cell the ray enters) and blended
with eight fixed trilinear weights: eight ``lax.dynamic_slice`` reads of a
zero-padded copy of ``alpha`` that XLA fuses into one dense pass, with no
gather. The integer shift is traced, so ``radius`` and ``offset`` are dynamic:
changing them never recompiles. Directions and chunks of samples are
``lax.scan`` loops (each chunk of about $\sqrt{M}$ samples unrolled so XLA fuses
it); the forward pass holds about five volume-sized buffers whatever $L$ and
$M$.

**Forward** evaluates eq. 3 back to front in Horner form,
$H_i = H_{i+1} + 1 - \alpha_i H_{i+1}$ with $M I_l = H_0$, so the march carries
one volume and each chunk of samples is one fused pass reading every sample once.

**Forward mode** (``jax.jvp``, ``jax.jacfwd``) marches the tangent beside the values:
back to front, $\dot H_i = \dot H_{i+1} (1 - \alpha_i) - \dot\alpha_i H_{i+1}$, with
$\dot\alpha_i$ the same eight shifted reads of the opacity's tangent plus the
opacity's slope along the ray times the sample's move $\dot s_i$ (from the radius and
offset). It carries two volumes and costs about 2.7 forward passes (64^3, 16 rays of 16
samples, a tangent in the radius or the opacity, on a 2-core CPU).

**Reverse mode** is that map's transpose, written by hand, recomputing instead of
storing (the checkpointing idea, done by hand; ``volshade._linear`` couples the two,
so each mode runs its own pass). Per direction one front-to-back pass keeps the
transmittance $T$ at each chunk start; the chunks are then visited in reverse,
each recomputing its $T_i$ and sweeping back with the suffix sums
$S_i = 1 + (1 - \alpha_{i+1}) S_{i+1}$, so $\partial (M I_l)/\partial \alpha_i =
-T_i S_i$ needs no division by $1 - \alpha_i$ (exact at $\alpha = 1$). The adjoint
of a shifted read is the opposite shift, so the backward pass is gather- and
scatter-free as well; its memory is about $2\sqrt{M} + 8$ volumes for any $L$. On a
CPU each chunk's opacities are read once and kept for its sweep: there XLA fuses each
sample's eight reads into every pass that uses the opacity, and forward plus the
gradient w.r.t. opacity and radius took 15x the forward where it now takes 11.5x
(64^3, 16 rays of 16 samples, 2 cores; with the opacity correction 12.7x and 6.8x).
That costs memory, about $3\sqrt{M} + 8$ volumes, and $6\sqrt{M} + 8$ with the
opacity correction, whose derivative's terms are kept too (64^3, 16 rays: 20.6 and
32.6 against 17.3 and 20.3 at $M = 16$; 29.9 and 50.9 against 23.3 and 26.3 at
$M = 50$), and compilation time (both sweeps are traced, and the kept one is unrolled:
a gradient at 32^3 traced and compiled in 2.0-3.0 s against 1.1-1.4 s, and second
derivatives twice as long). So windows of fewer than 32^3 voxels recompute (a gradient
at 24^3 took as long either way, at 32^3 22 ms against 28 ms; radius 16). The count is
one march's: a brick's, or one element's of a ``vmap``, however many are marched at
once, so bricked and batched gradients recompute below it (a review measured keeping
14-22% faster there, 64^3 in bricks of 16, and 8 volumes of 24^3). Each
direction's and each chunk's recomputation is checkpointed (``jax.checkpoint``), so
that JAX's own derivatives of the backward pass (second derivatives) recompute them
too, instead of storing the recomputed opacities of every direction and sample (as the
backward pass's transpose did when ``vs.fit`` built forward mode from it: a fit of the
half-resolution head, 42 rays of 16 samples, 15.1 GB peak, against 1.06 GB checkpointed;
a transposed VJP now runs the forward-mode march). Second derivatives in the opacity are
not available with bricks (:func:`_skipped_gradient`).
(An earlier variant that kept each chunk's reads and slopes was faster on a CPU but
slower and twice as memory-hungry on an H200, so other platforms recompute.)
``directions`` are not differentiated.

**On a GPU** ``implementation="pallas"`` runs the same march, values and
gradients, as Pallas (Triton) kernels in which one program marches all rays of a
tile of voxels in registers (``volshade._lao_pallas``). On an H200 (JAX 0.11.2,
$512^3$, $L = 54$, $M = 50$, $R = 50$; ``python -m benchmarks.run lao_pallas``) it
marched 0.63 T samples/s against the XLA march's 0.23 T (0.58 s against 1.59 s, in
one run), and forward plus the gradient w.r.t. opacity and radius took 4.7 s, 8.2x its
forward (the XLA march's took 14.5 s, 9.1x, in another run on an H200), with the
same values (2.4e-7) and gradients (1.3e-5 relative). Forward mode has no kernel: it
runs the XLA march's tangent pass beside the kernels' values (and so at its speed);
second derivatives, which would differentiate the kernels, are refused. It stays opt-in:
it holds four padded copies of the volume (the XLA forward, about three volumes in
all), 29 volumes in reverse mode against 22.5, and Pallas' Triton backend is
deprecated from JAX 0.11 in favour of Mosaic GPU.

**Bricks** (``brick_size``): bricks with no opacity within reach get AO = 1 and
are not marched; the active ones are compacted and marched in groups, ``vmap``-ped
over their padded windows. When more than half are active the plain march is
used instead (``lax.cond``; under ``vmap`` the batch runs as a loop, so that each
element takes its own branch and skips its own bricks). The skipped
bricks' gradient w.r.t. the opacity is not zero (opacity added near an empty
brick would darken it); at zero opacity it is a fixed kernel, applied in the
backward pass as one FFT convolution, so bricked gradients equal unbricked ones.
"""

import functools
import math
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.signal import fftconvolve

from . import _checks
from . import directions as _directions
from ._linear import jvp_of_nonzero, linear_primitive
from ._numerics import correct_opacity, scaled_down
from ._types import Array, ArrayLike, Float, Volume

_WHERE = "volshade.lao"
_CORNERS = tuple(np.ndindex(2, 2, 2))
# the platforms on which reverse mode keeps each chunk's opacities, and the fewest voxels
# of a window it keeps them for (module docstring)
_KEEP_CHUNK_READS_ON = ("cpu",)
_KEEP_CHUNK_READS_FROM = 32**3


# --------------------------------------------------------------------------- kernel


def _corner_weights(frac: Array) -> list[tuple[tuple[int, int, int], Array]]:
    """The eight trilinear weights ``w_c(f) = prod_ax (f_ax if c_ax else 1 - f_ax)``."""
    # (each axis read once: a read of a traced vector is an op to trace and compile)
    above = [frac[ax] for ax in range(3)]
    below = [1 - f for f in above]
    out = []
    for corner in _CORNERS:
        weight = None
        for ax in range(3):
            factor = above[ax] if corner[ax] else below[ax]
            weight = factor if weight is None else weight * factor
        out.append((corner, weight))
    return out


def _cell(offset: Array, direction: Array) -> tuple[Array, Array]:
    """Fraction and integer corner ``(f, n)`` of the trilinear cell of the sample at
    ``offset`` ``= s l``: ``offset`` is about ``n + f``, with ``f`` in [0, 1].

    On a grid plane this is the cell the ray enters as $s$ grows (``n`` is the plane for
    ``l_ax > 0``, the plane minus 1 for ``l_ax < 0``): the value is the same either side,
    but the slope along the ray is not, and this way it is the derivative from above in
    $s$ (and so in the radius and the offset) for every direction, not one side for rays
    going up and the other for rays going down. An offset within 4 ulps of a plane counts
    as on it, so that how XLA rounds ``s l`` (it may fuse the product into an FMA in one
    place and not in another) does not change the side; ``f`` is clipped to [0, 1], which
    moves the sample by those few ulps at most.
    """
    nearest = jnp.floor(offset + 0.5)
    on_plane = jnp.abs(offset - nearest) <= 4 * jnp.finfo(offset.dtype).eps * jnp.abs(offset)
    n = jnp.where(on_plane, jnp.where(direction < 0, nearest - 1, nearest), jnp.floor(offset))
    return jnp.clip(offset - n, 0, 1), n.astype(jnp.int32)


def _corner_slices(source: Array, pad: tuple[int, int, int], shape: tuple[int, int, int],
                   offset: Array, direction: Array):
    """Fraction of ``offset`` and the eight shifted windows ``source[pad + x + n + c]``.

    ``source`` is the opacity zero-padded by ``pad`` voxels on each side (so the
    window's voxel ``x`` is ``source[x + pad]``); the cell ``n`` (:func:`_cell`) is
    traced and each corner is one ``dynamic_slice`` (no gather). Where ``pad`` is at
    least the volume extent, clamped starts land in the zero padding, which is exactly
    the zero outside the volume.
    """
    frac, n = _cell(offset, direction)
    # clamp here: lax.dynamic_slice would wrap a negative start around, like NumPy (and
    # then it need not bind the wrapping)
    starts = []
    for ax in range(3):
        cell, top = pad[ax] + n[ax], source.shape[ax] - shape[ax]
        starts.append((jnp.clip(cell, 0, top), jnp.clip(cell + 1, 0, top)))
    slices = {c: lax.dynamic_slice(source, [starts[ax][c[ax]] for ax in range(3)], shape,
                                   allow_negative_indices=False) for c in _CORNERS}
    return frac, n, slices


def _weighted_sum(weights: list, values: list) -> Array:
    """``sum_c weights[c] * values[c]``."""
    total = None
    for w, v in zip(weights, values, strict=True):
        total = w * v if total is None else total + w * v
    return total


def _blend_corners(frac, values: list, *, exact: bool) -> Array:
    r"""The trilinear blend of the eight corner ``values`` (in ``_CORNERS`` order).

    ``exact=False``: the weighted sum of the corners. ``exact=True``: seven nested lerps
    ``a + f (b - a)``, exact wherever the corners are equal, so an opaque block blends
    to exactly 1 (the weighted sum can round a few ulps below). Only the opacity
    correction needs that: its slope $r (1 - \alpha)^{r - 1}$ is singular at 1 for
    $r < 1$ (about 1e8 in float64 a few ulps below it, 0 by convention at 1), while
    uncorrected opacities enter the march linearly, and the weighted sum costs fewer
    instructions (27.1 against 31.8 per voxel and sample in the sm_90a SASS of an earlier
    version of the Pallas forward kernel, the GPU goal's case; the current kernel's
    weighted sum takes 30.1, ``docs/results/pallas_sass_sm90a.json``, which holds no
    nested-lerp row).
    """
    if not exact:
        return _weighted_sum([w for _, w in _corner_weights(frac)], values)
    for ax in (2, 1, 0):  # _CORNERS is row-major: neighbours differ in the last axis first
        values = [a + frac[ax] * (b - a) for a, b in zip(values[0::2], values[1::2],
                                                           strict=True)]
    return values[0]


def _trilinear_shifted(source, pad, shape, offset, direction, *, exact: bool) -> Array:
    """``alpha(x + offset)`` for every voxel ``x`` of the window: 8 fused shifted reads
    (``exact``: see :func:`_blend_corners`)."""
    frac, _, slices = _corner_slices(source, pad, shape, offset, direction)
    return _blend_corners(frac, [slices[c] for c in _CORNERS], exact=exact)


def _corner_slopes(frac, direction) -> list:
    """``d w_c(f + s l) / ds`` at ``s = 0`` for the eight corners (in ``_CORNERS``
    order): the derivative of each trilinear weight along the ray ``direction``."""
    above = [frac[ax] for ax in range(3)]
    below = [1 - f for f in above]
    up = [direction[ax] for ax in range(3)]
    down = [-d for d in up]
    out = []
    for corner in _CORNERS:
        slope = None
        for ax in range(3):
            term = up[ax] if corner[ax] else down[ax]
            for bx in range(3):
                if bx != ax:
                    term = term * (above[bx] if corner[bx] else below[bx])
            slope = term if slope is None else slope + term
        out.append(slope)
    return out


def _trilinear_shifted_with_slope(source, pad, shape, offset, direction, *, exact: bool):
    """Value (as :func:`_trilinear_shifted`) and its derivative along ``direction``
    (``d/ds alpha(x + offset + s l)``).

    Both blend the same eight shifted windows, so XLA fuses them into one pass.
    """
    frac, _, slices = _corner_slices(source, pad, shape, offset, direction)
    values = [slices[c] for c in _CORNERS]
    return (_blend_corners(frac, values, exact=exact),
            _weighted_sum(_corner_slopes(frac, direction), values))


def _add_trilinear_shifted_adjoint(accumulator, cotangent, pad, offset, direction) -> Array:
    """Add the transpose of :func:`_trilinear_shifted` (in ``source``) to ``accumulator``.

    Corner ``c`` read ``source[pad + n + c + x]``, so its adjoint adds ``w_c g[x]``
    there. The eight corners are first blended on a window one voxel larger,
    ``h[z] = sum_c w_c g[z - c]`` (static slices), which is then added in place at
    ``pad + n`` (one ``dynamic_update_slice``): no scatter and window-sized work.
    Shifts that put the whole window in the zero padding (``|n| >= pad``, possible
    only when ``pad`` is the volume extent) read zeros and contribute nothing.
    """
    frac, n = _cell(offset, direction)
    shape = cotangent.shape
    inside = jnp.all((n >= -jnp.asarray(pad)) & (n <= jnp.asarray(pad) - 1))
    padded = jnp.pad(jnp.where(inside, cotangent, 0), 1)
    blended = None
    for corner, weight in _corner_weights(frac):
        lo = tuple(1 - c for c in corner)
        term = weight * padded[lo[0]:lo[0] + shape[0] + 1, lo[1]:lo[1] + shape[1] + 1,
                               lo[2]:lo[2] + shape[2] + 1]
        blended = term if blended is None else blended + term
    start = tuple(jnp.clip(pad[ax] + n[ax], 0, 2 * pad[ax] - 1) for ax in range(3))
    current = lax.dynamic_slice(accumulator, start, blended.shape,
                                allow_negative_indices=False)
    return lax.dynamic_update_slice(accumulator, current + blended, start,
                                    allow_negative_indices=False)


def _chunking(n_samples: int, longest: int | None = None) -> tuple[int, int]:
    """``(n_chunks, chunk)`` with ``n_chunks * chunk >= n_samples``, the chunks as even
    as they can be and no longer than ``longest`` samples (default: about the square
    root of ``n_samples``, which balances the chunk starts kept against a chunk's
    samples)."""
    if n_samples <= 0:
        return 0, 0
    chunk = math.ceil(math.sqrt(n_samples)) if longest is None else min(longest, n_samples)
    n_chunks = math.ceil(n_samples / chunk)
    return n_chunks, math.ceil(n_samples / n_chunks)


def _sample_opacity(source, pad, shape, distance, direction, ratio, correction: bool) -> Array:
    alpha = _trilinear_shifted(source, pad, shape, distance * direction, direction,
                               exact=correction)
    return correct_opacity(alpha, ratio) if correction else alpha


def _sample_table(samples: int, radius, offset):
    """Sample indices ``(n_chunks, chunk)``, distances, validity mask and the step.

    Distances are $s_i = a + (i + 1/2)(R - a)/M$ for the $M - 1$ samples that
    eq. 3 uses; the last chunk is padded with masked samples ($v_i = 0$).
    """
    n_chunks, chunk = _chunking(samples - 1)
    index = jnp.arange(n_chunks * chunk).reshape(n_chunks, chunk)
    step = (radius - offset) / samples
    distances = offset + (index.astype(step.dtype) + 0.5) * step
    valid = (index < samples - 1).astype(step.dtype)
    return index, distances, valid, step


def _horner_chunks(source, pad, shape, direction, distances, valid, ratio, correction):
    r"""March one direction back to front: $H_0$ and $H$ at the end of every chunk.

    $H_{M-1} = 1$ and $H_i = H_{i+1} + v_i (1 - \alpha'_i H_{i+1})$, so that
    $H_i = \sum_{m \ge i} \prod_{i \le j < m} (1 - \alpha'_j)$ over the valid samples
    and $H_0 = \sum_m T_m = M I_l$ (eq. 3 in Horner form). One volume is carried,
    so XLA fuses each chunk into a single pass that reads every sample once.
    """

    def step(horner, sample):
        distance, is_valid = sample
        alpha = _sample_opacity(source, pad, shape, distance, direction, ratio, correction)
        return horner + is_valid * (1 - alpha * horner), None

    def chunk(horner, samples):
        end = horner
        horner, _ = lax.scan(step, horner, samples, reverse=True, unroll=True)
        return horner, end

    return lax.scan(chunk, jnp.ones(shape, source.dtype), (distances, valid), reverse=True)


def _forward_chunks(source, pad, shape, direction, distances, valid, ratio, correction,
                    occlusion: bool = True):
    """March one direction: ``occ = sum_i v_i (1 - T_{i+1})`` (``= M (1 - I_l)``; a
    scalar 0 unless ``occlusion``) and the transmittance at each chunk start."""

    def step(carry, sample):
        transmittance, occ = carry
        distance, is_valid = sample
        alpha = _sample_opacity(source, pad, shape, distance, direction, ratio, correction)
        transmittance = transmittance * (1 - is_valid * alpha)
        if occlusion:
            occ = occ + is_valid * (1 - transmittance)
        return (transmittance, occ), None

    def chunk(carry, samples):
        start = carry[0]
        carry, _ = lax.scan(step, carry, samples, unroll=True)
        return carry, start

    dtype = source.dtype
    init = (jnp.ones(shape, dtype), jnp.zeros(shape if occlusion else (), dtype))
    (_, occ), starts = lax.scan(chunk, init, (distances, valid))
    return occ, starts


def _reverse_step(cotangent, transmittance, suffix_next, alpha, slope, valid, step, coef,
                  acc_slope, acc_radius, *, samples, correction):
    r"""One sample of the reverse sweep (see :func:`_occlusion_sum_transpose`), shared with
    the Pallas kernels: the cotangent $g$ of the opacity $\alpha_i$ (through the
    opacity correction), the suffix sum carried to the previous sample, and the
    accumulated slope and radius terms ($\partial s_i / \partial R$ = ``coef``).

    Returns:
        ``(g_alpha, suffix_next, acc_slope, acc_radius)``.
    """
    suffix = valid + suffix_next
    g_corrected = cotangent * valid * transmittance * suffix
    if correction:
        corrected, vjp = jax.vjp(correct_opacity, alpha, jnp.broadcast_to(step, alpha.shape))
        g_alpha, g_ratio = vjp(g_corrected)
        acc_radius = acc_radius + g_ratio / samples
    else:
        corrected, g_alpha = alpha, g_corrected
    g_slope = g_alpha * slope
    return (g_alpha, (1 - valid * corrected) * suffix, acc_slope + g_slope,
            acc_radius + coef * g_slope)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _occlusion_sum(pad, shape, correction, samples, source, directions, weights, radius,
                   offset):
    """``sum_l w_l occ_l`` over the directions for one window of ``shape``, where
    ``occ_l = M - H_0 = M (1 - I_l)``. Forward mode is :func:`_occlusion_sum_tangent`,
    reverse mode its transpose :func:`_occlusion_sum_transpose` (``directions`` are held
    constant)."""
    _, distances, valid, step = _sample_table(samples, radius, offset)

    def body(total, direction_weight):
        direction, weight = direction_weight
        horner, _ = _horner_chunks(source, pad, shape, direction, distances, valid, step,
                                   correction)
        return total + weight * (samples - horner), None

    total, _ = lax.scan(body, jnp.zeros(shape, source.dtype), (directions, weights))
    return total


def _occlusion_sum_tangent(source, directions, weights, radius, offset, d_source, d_weights,
                           d_radius, d_offset, *, pad, shape, correction, samples, live):
    r"""The JVP of :func:`_occlusion_sum`, by one back-to-front march per direction that
    carries the tangent of the Horner sum (:func:`_horner_chunks`) beside it:

    $$ \dot H_i = \dot H_{i+1} (1 - v_i \alpha'_i) - v_i \dot\alpha'_i H_{i+1},
    \qquad \dot{occ}_l = -\dot H_0, $$

    with $\dot\alpha_i$ the shifted read of $\dot{\mathrm{source}}$ (the same eight
    windows and weights) plus the opacity's slope along the ray times
    $\dot s_i = \frac{i + 1/2}{M} \dot R + (1 - \frac{i + 1/2}{M}) \dot a$, and through
    the opacity correction the step ratio's tangent $(\dot R - \dot a)/M$. Two volumes
    are carried and each chunk of samples is one fused pass, as in the forward march.
    ``live`` flags the tangents ``(d_source, d_weights, d_radius, d_offset)`` that are
    not zero; the others are zero, passed as scalar zeros and not read.
    """
    dtype = source.dtype
    index, distances, valid, step = _sample_table(samples, radius, offset)
    coef = (index.astype(dtype) + 0.5) / samples
    d_distances = coef * d_radius + (1 - coef) * d_offset
    d_step = (d_radius - d_offset) / samples
    moves = live[2] or live[3]

    def body(total, inputs):
        direction, weight, d_weight = inputs

        def sample(carry, inputs):
            horner, d_horner = carry
            distance, d_distance, is_valid = inputs
            at = distance * direction
            frac, _, slices = _corner_slices(source, pad, shape, at, direction)
            values = [slices[c] for c in _CORNERS]
            alpha = _blend_corners(frac, values, exact=correction)
            d_alpha = jnp.zeros_like(alpha)
            if moves:
                d_alpha = d_distance * _weighted_sum(_corner_slopes(frac, direction), values)
            if live[0]:
                _, _, d_slices = _corner_slices(d_source, pad, shape, at, direction)
                d_alpha = d_alpha + _weighted_sum([w for _, w in _corner_weights(frac)],
                                                  [d_slices[c] for c in _CORNERS])
            if correction:
                alpha, d_alpha = jax.jvp(correct_opacity,
                                         (alpha, jnp.broadcast_to(step, alpha.shape)),
                                         (d_alpha, jnp.broadcast_to(d_step, alpha.shape)))
            return (horner + is_valid * (1 - alpha * horner),
                    d_horner * (1 - is_valid * alpha) - is_valid * d_alpha * horner), None

        def chunk(carry, inputs):
            carry, _ = lax.scan(sample, carry, inputs, reverse=True, unroll=True)
            return carry, None

        init = (jnp.ones(shape, dtype), jnp.zeros(shape, dtype))
        (horner, d_horner), _ = lax.scan(chunk, init, (distances, d_distances, valid),
                                         reverse=True)
        total = total - weight * d_horner
        return (total + d_weight * (samples - horner) if live[1] else total), None

    d_weights = jnp.broadcast_to(d_weights, weights.shape)
    total, _ = lax.scan(body, jnp.zeros(shape, dtype), (directions, weights, d_weights))
    return (total,)


def _occlusion_sum_transpose(source, directions, weights, radius, offset, cotangent, *, pad,
                             shape, correction, samples, live):
    r"""The transpose of :func:`_occlusion_sum_tangent` (reverse mode), by recomputation:
    memory about $2\sqrt{M} + 8$ volumes, for any $L$ (on a CPU, which keeps each chunk's
    opacities for windows of 32^3 voxels or more, $3\sqrt{M} + 8$, or $6\sqrt{M} + 8$
    with the opacity correction). Returns the cotangents of
    ``(source, weights, radius, offset)``; those that ``live`` marks as not wanted are
    scalar zeros, and the opacity's (the adjoint reads) is then not accumulated.

    With $T_{i+1} = T_i (1 - v_i \alpha'_i)$ and $occ = \sum_j v_j (1 - T_{j+1})$,
    $\partial occ / \partial \alpha'_i = v_i T_i S_i$ with the suffix sum
    $S_i = v_i + (1 - v_{i+1}\alpha'_{i+1}) S_{i+1}$, which runs back to front. Per
    direction one forward pass keeps $T$ at each chunk start; chunks are then
    visited in reverse, each recomputing its $T_i$ and sweeping back with $S$.
    The cotangent of ``source`` is the opposite shift (a stencil, no scatter). The
    radius and offset cotangents are accumulated as volumes and reduced once:
    $\partial s_i / \partial R = (i + \frac12)/M$, $\partial s_i / \partial a = 1 -
    (i + \frac12)/M$, and the step ratio $(R - a)/M$ of the opacity correction.
    """
    dtype = source.dtype
    index, distances, valid, step = _sample_table(samples, radius, offset)
    coef_radius = (index.astype(dtype) + 0.5) / samples

    def direction_bwd(carry, direction_weight):
        direction, weight = direction_weight
        # (the weights' cotangent alone needs the occlusion)
        occlusion, starts = _forward_chunks(source, pad, shape, direction, distances, valid,
                                            step, correction, occlusion=live[1])
        d_weight = jnp.sum(cotangent * occlusion)
        ct = weight * cotangent

        def transmitted(transmittance, alpha, is_valid):
            corrected = correct_opacity(alpha, step) if correction else alpha
            return transmittance * (1 - is_valid * corrected)

        def reverse(state, transmittance, alpha, slope, is_valid, distance, coef):
            """One sample of the sweep back (:func:`_reverse_step`), its opacity's
            cotangent added to ``d_source`` (the opposite shift). A sum that no wanted
            cotangent reads stays the scalar it started as."""
            suffix, d_source, acc_slope, acc_radius = state
            g_alpha, suffix, slope_sum, radius_sum = _reverse_step(
                ct, transmittance, suffix, alpha, slope, is_valid, step, coef, acc_slope,
                acc_radius, samples=samples, correction=correction)
            if live[0]:
                d_source = _add_trilinear_shifted_adjoint(d_source, g_alpha, pad,
                                                          distance * direction, direction)
            return (suffix, d_source, slope_sum if live[3] else acc_slope,
                    radius_sum if live[2] or live[3] else acc_radius)

        def read(distance):
            return _trilinear_shifted_with_slope(source, pad, shape, distance * direction,
                                                 direction, exact=correction)

        def chunk_recomputed(state, chunk):
            start, dists, valids, coefs = chunk

            def t_step(transmittance, sample):
                distance, is_valid = sample
                # (the value alone: its slope is read on the way back)
                alpha = _trilinear_shifted(source, pad, shape, distance * direction,
                                           direction, exact=correction)
                return transmitted(transmittance, alpha, is_valid), transmittance

            _, transmittances = lax.scan(t_step, start, (dists, valids))

            def sample_bwd(state, sample):
                transmittance, distance, is_valid, coef = sample
                return reverse(state, transmittance, *read(distance), is_valid, distance,
                               coef), None

            state, _ = lax.scan(sample_bwd, state, (transmittances, dists, valids, coefs),
                                reverse=True)
            return state

        def chunk_kept(state, chunk):
            start, dists, valids, coefs = chunk
            n = dists.shape[0]
            reads = [read(dists[k]) for k in range(n)]
            # kept: the sums below run from sample to sample, and XLA would otherwise
            # fuse the eight windows' reads into each of their uses again
            alphas = lax.optimization_barrier(jnp.stack([value for value, _ in reads]))
            transmittances = [start]
            for k in range(n - 1):
                transmittances.append(transmitted(transmittances[-1], alphas[k], valids[k]))
            for k in reversed(range(n)):
                state = reverse(state, transmittances[k], alphas[k], reads[k][1], valids[k],
                                dists[k], coefs[k])
            return state

        def chunk_bwd(state, chunk):
            if math.prod(shape) < _KEEP_CHUNK_READS_FROM:
                return chunk_recomputed(state, chunk), None
            return lax.platform_dependent(
                state, chunk, default=chunk_recomputed,
                **dict.fromkeys(_KEEP_CHUNK_READS_ON, chunk_kept)), None

        # (checkpointed, as the directions below: JAX's derivatives of this pass, second
        # derivatives, would otherwise store every iteration's recomputed opacities)
        (_, *carry), _ = lax.scan(jax.checkpoint(chunk_bwd),
                                  (jnp.zeros(shape, dtype), *carry),
                                  (starts, distances, valid, coef_radius), reverse=True)
        return tuple(carry), d_weight

    # the cotangents that ``live`` does not ask for are not accumulated: a primitive's
    # body is not pruned by JAX as the inline code was (the offset's sum, one volume)
    init = tuple(jnp.zeros(size if wanted else (), dtype) for size, wanted in (
        (source.shape, live[0]), (shape, live[3]), (shape, live[2] or live[3])))
    (d_source, acc_slope, acc_radius), d_weights = lax.scan(
        jax.checkpoint(direction_bwd), init, (directions, weights))
    d_radius = jnp.sum(acc_radius)
    d_offset = jnp.sum(acc_slope) - d_radius
    zero = jnp.zeros((), dtype)
    return (d_source, d_weights if live[1] else zero, d_radius if live[2] else zero,
            d_offset if live[3] else zero)


# the tangent map as a primitive transposed by the hand-written reverse mode
# (``directions`` are among its residuals: they are not differentiated)
_occlusion_tangent = linear_primitive("volshade_lao_tangent", _occlusion_sum_tangent,
                                      _occlusion_sum_transpose, n_residuals=5)


def _occlusion_sum_jvp(pad, shape, correction, samples, primals, tangents):
    out = _occlusion_sum(pad, shape, correction, samples, *primals)
    (tangent,) = _occlusion_tangent(
        primals, (tangents[0], *tangents[2:]),  # no derivative in the directions
        pad=pad, shape=shape, correction=correction, samples=samples)
    return out, tangent


_occlusion_sum.defjvp(_occlusion_sum_jvp, symbolic_zeros=True)


def _march(source, pad, shape, directions, weights, radius, offset, samples,
           correction: bool) -> Array:
    """AO of a window of ``shape`` whose opacity, padded by ``pad``, is ``source``
    (``samples >= 2``)."""
    total = _occlusion_sum(pad, shape, correction, samples, source, directions, weights,
                           radius, offset)
    return 1 - total / samples


def _marchers(pad, directions, weights, radius, offset, samples, correction):
    """``march(source, shape)``, the AO of a padded window, and ``dense(alpha)``, the AO
    of a whole volume, for these parameters."""
    def march(source, shape):
        return _march(source, pad, shape, directions, weights, radius, offset, samples,
                      correction)

    def dense(alpha):
        return march(jnp.pad(alpha, tuple((p, p) for p in pad)), alpha.shape)

    return march, dense


# --------------------------------------------------------------------------- bricks


def _brick_group(brick: int, window: tuple[int, int, int], n_bricks: int) -> int:
    """How many bricks are marched together, vectorised: about $2^{16}$ voxels on a CPU
    (a group's working set then stays in cache; measured best of $2^{16}$, $2^{18}$,
    $2^{20}$) and $2^{21}$ elsewhere, where one kernel needs that many threads; never
    more than $2^{24}$ voxels of padded windows (a halo wide against the brick would
    otherwise make a group's windows many volumes large); and at most an eighth of
    the bricks, since the empty slots of the last group are marched too (a group of
    all the bricks marched a whole 32^3 volume for one affected brick)."""
    target = 2**16 if jax.default_backend() == "cpu" else 2**21
    return max(1, min(-(-n_bricks // 8), target // brick**3, 2**24 // math.prod(window)))


_MAX_ACTIVE_FRACTION = 0.5
_IMPLEMENTATIONS = {"xla": "fused shifted reads (XLA)",
                    "pallas": "Pallas kernels (Triton on an NVIDIA GPU)"}


def _bricks_holding(mask, brick) -> Array:
    """The bricks (a boolean grid) holding a True voxel of ``mask``."""
    n_bricks = tuple(-(-s // brick) for s in mask.shape)
    extra = tuple(nb * brick - s for nb, s in zip(n_bricks, mask.shape, strict=True))
    blocks = jnp.pad(mask, tuple((0, e) for e in extra)).reshape(
        n_bricks[0], brick, n_bricks[1], brick, n_bricks[2], brick)
    return jnp.any(blocks, axis=(1, 3, 5))


def _active_bricks(alpha, pad, brick) -> Array:
    """Bricks (a boolean grid) with opacity within ``pad`` voxels of them."""
    occupied = _bricks_holding(alpha > 0, brick)
    reach = tuple(-(-p // brick) for p in pad)
    return lax.reduce_window(
        occupied, False, lax.bitwise_or, tuple(2 * r + 1 for r in reach), (1, 1, 1),
        tuple((r, r) for r in reach))


def _bricked(alpha, active, pad, brick, march) -> tuple[Array, Array]:
    """Run ``march`` only on the ``active`` bricks; return AO (1 in the other bricks) and
    the mask of the voxels that were skipped.

    Active bricks are compacted and marched in groups: each group's padded windows
    are copied out and the march is ``vmap``-ped over them, so one pass covers the
    whole group (a brick at a time is too little work per kernel to pay off). The
    group body is checkpointed, so reverse mode keeps brick indices, not windows.
    """
    shape = alpha.shape
    n_bricks = active.shape
    aligned = tuple(nb * brick for nb in n_bricks)
    extra = tuple(a - s for a, s in zip(aligned, shape, strict=True))
    source = jnp.pad(alpha, tuple((p, p + e) for p, e in zip(pad, extra, strict=True)))
    total = math.prod(n_bricks)
    window = tuple(brick + 2 * p for p in pad)
    group = _brick_group(brick, window, total)
    n_groups = -(-total // group)
    (index,) = jnp.nonzero(active.reshape(-1), size=n_groups * group, fill_value=total)
    out_shape = (brick,) * 3

    @jax.checkpoint
    def one(indices):
        def compute(indices):
            coords = jnp.unravel_index(jnp.minimum(indices, total - 1), n_bricks)
            starts = brick * jnp.stack(coords, -1)
            windows = jax.vmap(lambda st: lax.dynamic_slice(source, tuple(st), window))(starts)
            return jax.vmap(lambda w: march(w, out_shape))(windows)

        # compacted indices: a group that starts with the fill value is all fill
        return lax.cond(indices[0] < total, compute,
                        lambda i: jnp.ones((group, *out_shape), alpha.dtype), indices)

    computed = lax.map(one, index.reshape(n_groups, group)).reshape(-1, *out_shape)
    result = jnp.ones((total, *out_shape), alpha.dtype).at[index].set(computed, mode="drop")
    result = result.reshape(*n_bricks, *out_shape).transpose(0, 3, 1, 4, 2, 5)
    result = result.reshape(aligned)
    skipped = jnp.repeat(jnp.repeat(jnp.repeat(~active, brick, 0), brick, 1), brick, 2)
    crop = (slice(0, shape[0]), slice(0, shape[1]), slice(0, shape[2]))
    return result[crop], skipped[crop]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _skipped_gradient(pad, samples, correction, skipped, alpha, directions, weights, radius,
                      offset) -> Array:
    r"""Zero, carrying the derivative w.r.t. ``alpha`` of the AO of ``skipped`` voxels.

    A skipped voxel $x$ has no opacity within reach, so its AO is 1 whatever the
    radius, offset and weights, but not whatever the opacity: raising $\alpha$ at a
    zero-opacity voxel $y$ near it lowers $\mathrm{AO}(x)$. At zero opacity every
    $T_i = 1$ and $S_i = M - 1 - i$, so that derivative is the fixed kernel
    $\partial \mathrm{AO}(x) / \partial \alpha(x + d) = -\frac{\kappa}{M} K(d)$,
    $K(d) = \sum_l \hat w_l \sum_i (M - 1 - i)\, w_c(s_i l)$ over the trilinear
    corners $\lfloor s_i l \rfloor + c = d$ ($\kappa$ the step ratio with opacity
    correction, else 1). Forward mode applies it to the opacity's tangent as one FFT
    correlation, and reverse mode (its transpose) to the skipped voxels' cotangent as
    one FFT convolution, whatever $L$ and $M$, so bricked derivatives equal unbricked
    ones and skipping stays cheap in both modes.
    """
    del pad, samples, correction, skipped, directions, weights, radius, offset
    return jnp.zeros_like(alpha)


def _skipped_kernel(pad, samples, correction, directions, weights, radius, offset, dtype):
    r"""$-\frac{\kappa}{M} K$ of :func:`_skipped_gradient`, ``(2 pad + 1)`` per axis,
    centred: the derivative of a skipped voxel's AO in the opacity at offset ``d``."""
    index, distances, valid, step = _sample_table(samples, radius, offset)
    suffix = valid * (samples - 1 - index).astype(valid.dtype)
    positions = distances.reshape(-1)[:, None, None] * directions[None]  # (samples, L, 3)
    floor = jnp.floor(positions)
    frac = positions - floor
    base = floor.astype(jnp.int32) + jnp.asarray(pad)[None, None, :]
    scale = suffix.reshape(-1)[:, None] * weights[None]
    kernel = jnp.zeros(tuple(2 * p + 1 for p in pad), dtype)
    for corner, weight in _corner_weights(tuple(frac[..., ax] for ax in range(3))):
        # offsets beyond the padding reach no voxel; send them past the end to be
        # dropped (a negative index would wrap around, like NumPy's)
        where = [(base[..., ax] + corner[ax]).reshape(-1) for ax in range(3)]
        outside = functools.reduce(jnp.logical_or, [(w < 0) | (w > 2 * p)
                                                    for w, p in zip(where, pad, strict=True)])
        where = tuple(jnp.where(outside, 2 * p + 1, w) for w, p in zip(where, pad, strict=True))
        kernel = kernel.at[where].add((scale * weight).reshape(-1), mode="drop")
    kappa = step if correction else 1
    return -(kappa / samples) * kernel


def _skipped_tangent(skipped, alpha, directions, weights, radius, offset, d_alpha, *, pad,
                     samples, correction, live):
    r"""The skipped voxels' AO tangent: $\sum_d K(d)\, \dot\alpha(x + d)$, a
    convolution with the kernel flipped (centred and of odd size, so mode "same" keeps it
    aligned)."""
    del live  # (its one tangent is live: linear_primitive binds no map of zero tangents)
    kernel = _skipped_kernel(pad, samples, correction, directions, weights, radius, offset,
                             alpha.dtype)
    correlated = fftconvolve(d_alpha, kernel[::-1, ::-1, ::-1], mode="same")
    return (jnp.where(skipped, correlated, 0),)


def _skipped_transpose(skipped, alpha, directions, weights, radius, offset, cotangent, *, pad,
                       samples, correction, live):
    """The transpose of :func:`_skipped_tangent`: the skipped voxels' cotangent convolved
    with the kernel. (The kernel is built again rather than kept from the forward pass:
    the FFT of a padded kernel, 2.6 volumes at 48^3, would be stored between them.)"""
    del live
    kernel = _skipped_kernel(pad, samples, correction, directions, weights, radius, offset,
                             alpha.dtype)
    return (fftconvolve(jnp.where(skipped, cotangent, 0), kernel, mode="same"),)


# the opacity is a residual held constant: the kernel is the derivative at zero opacity,
# and the second derivative there is not zero
_skipped_linear = linear_primitive(
    "volshade_lao_skipped", _skipped_tangent, _skipped_transpose, n_residuals=6,
    constant={1: "volshade.lao: second derivatives in the opacity are not available with "
                 "`brick_size` (a skipped brick's derivative is taken at zero opacity); "
                 "use brick_size=None for them."})


def _skipped_gradient_jvp(pad, samples, correction, primals, tangents):
    (tangent,) = _skipped_linear(primals, (tangents[1],), pad=pad, samples=samples,
                                 correction=correction)
    return jnp.zeros_like(primals[1]), tangent


_skipped_gradient.defjvp(_skipped_gradient_jvp, symbolic_zeros=True)


# --------------------------------------------------------------------------- public API


def _concrete(x) -> float | None:
    """``float(x)`` for a Python/NumPy/concrete JAX scalar, ``None`` for a tracer."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        arr = np.asarray(x)
    except Exception:  # noqa: BLE001 - anything not convertible is treated as traced
        return None
    if arr.shape != () or not (np.issubdtype(arr.dtype, np.integer)
                               or np.issubdtype(arr.dtype, np.floating)):
        return None  # a complex number is refused by name later, by _checks.scalar
    return float(arr)


def _divided(x, divisor, xp):
    """``x / divisor`` for a scale ``divisor > 0`` that the caller's result does not
    depend on (held constant): on the host for NumPy arrays, else
    :func:`~volshade._numerics.scaled_down` (no subnormal reciprocal)."""
    return x / divisor if xp is np else scaled_down(x, divisor)


def _as_given(given, checked: Array, dtype) -> tuple:
    """``(xp, values)`` to check and normalise a direction set or weights with: NumPy and
    ``given`` in float64 where its values are known, else ``jnp`` and ``checked`` (its
    array, type- and shape-checked) in ``dtype``."""
    known = _checks.concrete(given)
    return (jnp, checked.astype(dtype)) if known is None else (np, known.astype(np.float64))


def _directions_array(directions, dtype, where: str = _WHERE) -> Array:
    if isinstance(directions, int | np.integer) and not isinstance(directions, bool):
        if directions < 1:
            raise ValueError(f"{where}: `directions` must be >= 1 rays (or an (L, 3) array), "
                             f"got {directions}.")
        directions = _directions.fibonacci(int(directions))
    try:
        # (this array is for the type and shape checks; with x64 off a float64 beyond
        # float32 overflows here, which is not an error: the values are read below)
        with np.errstate(over="ignore"):
            dirs = jnp.asarray(directions)
    except (TypeError, ValueError) as err:  # ValueError: None, a ragged nested list
        raise TypeError(f"{where}: `directions` must be an (L, 3) array of unit vectors "
                        f"(e.g. `volshade.directions.icosphere(1)`) or an int L, "
                        f"got {type(directions).__name__}.") from err
    if _checks.holds_bool(directions):  # a bool would pass as 0 or 1
        raise TypeError(f"{where}: `directions` must hold numbers, got a bool in "
                        f"{directions!r:.80}.")
    dirs = _checks.as_float_array(dirs, "directions", where)  # refuses complex numbers
    if dirs.ndim != 2 or dirs.shape[-1] != 3:
        raise ValueError(f"{where}: `directions` must have shape (L, 3) in (d, h, w) order, "
                         f"got {tuple(dirs.shape)}; use `volshade.directions.fibonacci(L)`.")
    if dirs.shape[0] == 0:
        raise ValueError(f"{where}: `directions` is empty (L = 0); pass at least one "
                         f"direction, e.g. `volshade.directions.icosphere(0)` (12 rays).")
    message = ("`directions` holds a zero or non-finite vector; every direction must be a "
               "non-zero finite 3-vector.")
    # known directions are checked and scaled on the host, as given in float64 (with x64
    # off, jnp.asarray rounds them to float32 first, where 1e-50 is 0 and 1e40 inf)
    xp, dirs = _as_given(directions, dirs, dtype)
    peak = xp.max(xp.abs(dirs), axis=-1, keepdims=True)
    dirs = _checks.refuse(dirs, [(~xp.all(xp.isfinite(dirs)) | xp.any(peak == 0), message)],
                          where)
    # the squares of (0, 0, 1e20) overflow float32 (which made it a zero direction) and
    # those of (0, 0, 1e-30) underflow: such vectors are divided by their largest
    # component first (others are not, so that a unit vector stays exactly as given)
    extreme = ((peak < 1e-15) & (peak > 0)) | (peak > 1e15)
    dirs = _divided(dirs, xp.where(extreme, peak, 1), xp)
    # 0 only for a refused zero row, kept finite
    norm = xp.sqrt(xp.sum(dirs * dirs, axis=-1, keepdims=True))
    return jnp.asarray(dirs / xp.where(norm == 0, 1, norm), dtype)


def _weights_array(weights, n_dirs: int, where: str, *, batch: bool = False) -> Array:
    """``weights`` as a float array, one per direction (trace-time shape check);
    ``batch``: leading batch axes allowed (a module to be vmapped)."""
    weights = _checks.numbers(weights, "weights", where)
    if weights.shape != (n_dirs,) and not (batch and weights.shape[-1:] == (n_dirs,)):
        raise ValueError(f"{where}: `weights` must have shape (L,) = ({n_dirs},), one "
                         f"per direction, got {tuple(weights.shape)}.")
    return weights


class _Prepared(NamedTuple):
    """Validated inputs of a march (see :func:`_prepare`)."""

    alpha: Array
    dtype: jnp.dtype
    directions: Array
    weights: Array
    radius: Array
    offset: Array
    pad: tuple[int, int, int]
    samples: int
    correction: bool
    brick_size: int | None


def _prepare(alpha, *, directions, radius, offset, samples, weights, opacity_correction,
             brick_size, max_radius, where: str) -> _Prepared:
    """Check and normalise :func:`lao`'s arguments (errors name ``where``): the opacity,
    unit directions, weights summing to 1, radius and offset as scalars of the working
    dtype, and the zero padding the march needs. The march works in the opacity's dtype,
    half precision widened to float32 (as the Pallas kernels and the FFT of the skipped
    bricks' gradient need; the radius and offset are then not rounded to half
    precision), and ``dtype`` is the opacity's own, for the result."""
    alpha = _checks.volume(alpha, "alpha", where, unit_range=True)
    result_dtype = alpha.dtype
    alpha = _checks.at_least_float32(alpha)
    dtype = alpha.dtype
    samples = _checks.positive_int(samples, "samples", where)
    opacity_correction = _checks.flag(opacity_correction, "opacity_correction", where)
    if brick_size is not None:
        brick_size = _checks.positive_int(brick_size, "brick_size", where)
    if max_radius is not None:
        max_radius = _checks.positive_float(max_radius, "max_radius", where)
    dirs = lax.stop_gradient(_directions_array(directions, dtype, where))
    n_dirs = dirs.shape[0]

    # known values are checked as the march will use them, in its dtype: a float32 march
    # would take a radius of 1.00000001 as an offset of 1 (3.5e38, which it would take as
    # inf, is refused by _checks.scalar)
    r_given, a_given = _concrete(radius), _concrete(offset)
    radius = _checks.scalar(radius, "radius", where, unit="voxels", dtype=dtype)
    offset = _checks.scalar(offset, "offset", where, unit="voxels", dtype=dtype)
    # in `dtype`, rounded on the host: under jit the converted arrays are tracers even
    # for a Python number, which left the padding (`bound`) the whole volume
    r_value, a_value = (None if v is None else np.asarray(v).astype(dtype)
                        for v in (r_given, a_given))
    working = f"in {jnp.dtype(dtype).name}, the dtype of the march"
    if a_value is not None and not (np.isfinite(a_value) and a_value >= 0):
        raise ValueError(f"{where}: `offset` must be a finite number >= 0 (voxels) {working}, "
                         f"got {a_given!r}.")
    if r_value is not None:
        if not np.isfinite(r_value):
            raise ValueError(f"{where}: `radius` must be finite (voxels) {working}, got "
                             f"{r_given!r}.")
        if a_value is not None and r_value <= a_value:
            raise ValueError(f"{where}: `radius` ({r_given!r}) must be > `offset` "
                             f"({a_given!r}) {working}; increase the radius or lower the "
                             f"offset.")
        if max_radius is not None and r_value > max_radius:
            raise ValueError(f"{where}: `radius` ({r_given!r}) exceeds `max_radius` "
                             f"({max_radius}); raise `max_radius`.")
    if r_value is None or a_value is None:  # known values were checked above, in NumPy
        alpha = _checks.refuse(alpha, [
            (~(offset >= 0) | ~jnp.isfinite(radius),
             "`offset` must be >= 0 and `radius` finite (voxels)."),
            (~(radius > offset), "`radius` must be > `offset`; increase the radius or lower "
                                 "the offset."),
            *([] if max_radius is None else [
                (radius > max_radius, f"`radius` exceeds `max_radius` ({max_radius}); raise "
                                      f"`max_radius`.")])], where)

    if weights is None:
        weights = jnp.asarray(np.full((n_dirs,), 1 / n_dirs), dtype)
    else:
        with np.errstate(over="ignore"):  # (as for the directions)
            checked = _weights_array(weights, n_dirs, where)
        # known weights are checked and normalised on the host, as given in float64 (as
        # the directions are)
        xp, w = _as_given(weights, checked, dtype)
        peak = xp.max(w)
        w = _checks.refuse(w, [(~xp.all(xp.isfinite(w)) | xp.any(w < 0) | ~(peak > 0),
                                "`weights` must be finite, >= 0 and not all zero.")], where)
        # w / sum(w) through w / max(w): a float32 sum of weights of 1e38 overflows
        scaled = _divided(w, xp.where(peak > 0, peak, 1), xp)
        weights = jnp.asarray(scaled / xp.sum(scaled), dtype)

    bound = max_radius if max_radius is not None else r_value
    # a padding as wide as the (brick-aligned) volume makes clamped reads land in zeros
    extent = (alpha.shape if brick_size is None
              else tuple(-(-s // brick_size) * brick_size for s in alpha.shape))
    pad = tuple(e if bound is None else min(e, math.ceil(bound) + 1) for e in extent)

    return _Prepared(alpha, result_dtype, dirs, weights, radius, offset, pad, samples,
                     opacity_correction, brick_size)


def lao(
    alpha: Volume,
    *,
    directions: Float[ArrayLike, "L 3"] | int,
    radius: Float[ArrayLike, ""],
    offset: Float[ArrayLike, ""] = 1.0,
    samples: int = 16,
    weights: Float[ArrayLike, " L"] | None = None,
    opacity_correction: bool = False,
    brick_size: int | None = None,
    max_radius: float | None = None,
    implementation: str = "xla",
) -> Volume:
    r"""Local ambient occlusion of an opacity volume, by gather-free ray marching.

    $I_l(x) = \sum_{m=0}^{M-1} \frac1M \prod_{i<m} (1 - \alpha_i)$ with
    $\alpha_i$ the trilinear opacity at $x + s_i l$, $s_i = a + (i + \frac12)
    \frac{R - a}{M}$ (Ancel et al. 2010, section 3, eq. 3, with $M$ terms as in Titov
    et al.'s eq. 2), and
    $\mathrm{AO}(x) = \sum_l w_l I_l(x) / \sum_l w_l$ (eq. 4; Titov et al. eq. 3).
    See the module docstring for the exact positions and the opacity correction.

    Args:
        alpha: ``(D, H, W)`` opacities in ``[0, 1]`` (zero outside the volume).
        directions: ``(L, 3)`` ray directions in ``(d, h, w)`` order, voxel units
            (normalised here; e.g. ``volshade.directions.icosphere(1)``), or an int
            ``L`` meaning ``volshade.directions.fibonacci(L)``. Static configuration:
            not differentiated (``lao`` stops their gradient).
        radius: sphere radius $R$ in voxels; dynamic and differentiable, in forward
            and reverse mode (``implementation="pallas"``: not twice). Where a
            sample lies on a voxel plane (trilinear interpolation has a kink there) the
            derivative is the one from above.
        offset: initial offset $a$ in voxels, ``0 <= offset < radius``; dynamic and
            differentiable (from above where a sample lies on a voxel plane).
        samples: $M$, the number of segments of the shell (static, ``>= 1``);
            ``M - 1`` opacity samples are taken per ray, so ``samples=1`` takes none
            and gives AO = 1 everywhere.
        weights: ``(L,)`` non-negative directional weights $w_l$ (not all zero),
            normalised to sum to 1; ``None`` means equal weights (the plain mean).
            Differentiable.
        opacity_correction: if True, correct each sample to the step,
            $\alpha' = 1 - (1-\alpha)^{\Delta s}$ ($\Delta s$ in voxels). False (the
            default) is the seeds' form, in which the same $M$ samples spread over a
            longer ray as $R$ grows, so AO can rise with the radius; to compare radii
            physically, use True. With True and a step under one voxel, a sample of
            opacity exactly 1 passes a derivative of 0 (its one-sided slope is
            infinite) to the opacity, ``radius`` and ``offset``.
        brick_size: if set, split the volume into bricks of this edge (voxels) and
            march only bricks with opacity within reach; the others get AO = 1
            without any work. Results and derivatives equal the unbricked path (the
            skipped bricks' derivative w.r.t. ``alpha`` is one FFT convolution), but
            for second derivatives in ``alpha``, which are refused with bricks. It
            pays on sparse volumes; when more than half of the bricks are active
            the whole volume is marched instead (decided at run time), since
            bricks then cost more than they save (``python -m benchmarks.run lao``
            measures both).
        max_radius: static upper bound on ``radius`` (voxels), which sets the zero
            padding (``ceil(max_radius) + 1`` voxels per side, at most the extent,
            brick-aligned when bricked) and the brick halo. By default it is
            ``radius`` when that is a concrete number, and the volume extent when
            ``radius`` is traced (exact for any radius, but the padded copy is then
            27 volumes or more; pass ``max_radius`` when fitting the radius).
            Eager calls with a new concrete ``radius`` and no ``max_radius``
            recompile, since the padding follows the radius.
        implementation: ``"xla"`` (the default) marches with fused shifted reads
            (see the module docstring); ``"pallas"`` uses Pallas kernels that march
            every ray of a tile of voxels in registers, values and reverse mode
            (``volshade._lao_pallas``; forward mode is the XLA march's tangent pass, and
            second derivatives are refused), compiled by Triton on an NVIDIA GPU and run
            in Pallas' interpreter elsewhere (exact but slow: for tests). Both
            compute the same values and gradients (to rounding). With ``brick_size``
            the Pallas march skips every tile of voxels whose bricks have no opacity
            within reach (always, where the XLA march first weighs the active
            fraction); its gradient is computed everywhere. ``"pallas"`` is about
            2.7x faster on an H200 and needs more memory (module docstring).

    Returns:
        ``(D, H, W)`` AO in ``[0, 1]``, in the dtype of ``alpha`` (computed in float32
        at least: half precision is widened for the march and the result rounded).

    Raises:
        ValueError: ``alpha`` not 3-D, bad ``directions``/``weights`` shape, empty
            direction set, ``samples < 1``, ``brick_size < 1``, ``max_radius`` not a
            finite number > 0, a non-finite ``radius`` or ``offset``,
            ``radius <= offset`` or ``offset < 0`` (at trace time when they are
            numbers), an unknown ``implementation``; when traced, second derivatives
            with ``implementation="pallas"``, or in ``alpha`` with ``brick_size``.
        TypeError: non-numeric inputs.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            ``alpha`` outside ``[0, 1]`` or non-finite, ``radius <= offset``,
            ``offset < 0``, ``radius > max_radius``, negative or all-zero ``weights``.

    References:
        Hernell, Ljung, Ynnerman, "Efficient ambient and emissive tissue
        illumination using local occlusion in multiresolution volume rendering",
        Volume Graphics 2007. Ancel, Dischler, Mongenet, "Feature-driven ambient
        occlusion for direct volume rendering", IEEE/EG Volume Graphics 2010 (eq. 2-4,
        section 4.3).
        Titov et al., "Contextual ambient occlusion" (eq. 2-3).

    Example:
        >>> alpha = jnp.zeros((16, 16, 16)).at[8, 8, 8].set(1.0)
        >>> ao = lao(alpha, directions=volshade.directions.icosphere(0), radius=4.0)
        >>> ao.shape, float(ao[0, 0, 0])
        ((16, 16, 16), 1.0)
    """
    _checks.option(implementation, _IMPLEMENTATIONS, "implementation", _WHERE)
    p = _prepare(alpha, directions=directions, radius=radius, offset=offset, samples=samples,
                 weights=weights, opacity_correction=opacity_correction,
                 brick_size=brick_size, max_radius=max_radius, where=_WHERE)
    return _lao(p.alpha, p.directions, p.weights, p.radius, p.offset, pad=p.pad,
                samples=p.samples, correction=p.correction, brick_size=p.brick_size,
                max_active=_MAX_ACTIVE_FRACTION, implementation=implementation).astype(p.dtype)


def _unoccluded(alpha: Array, *checked: Any) -> Array:
    """AO = 1 everywhere, for ``samples = 1`` (eq. 3 with M = 1 is a single term with an
    empty product: no sample is taken), reading ``alpha`` and the arrays of ``checked``
    so that their run-time checks survive jit (:func:`volshade._checks.reading`)."""
    return _checks.reading(jnp.ones_like(alpha), alpha, *checked)


@eqx.filter_jit
def _lao(alpha, dirs, weights, radius, offset, *, pad, samples, correction, brick_size,
         max_active, implementation):
    """The validated computation, compiled once per shape and static options."""
    if samples == 1:
        return _unoccluded(alpha, dirs, weights, radius, offset)
    if implementation == "pallas":
        # imported here: Pallas is loaded only by those who ask for it
        from . import _lao_pallas

        total = _lao_pallas.occlusion_sum(alpha, dirs, weights, radius, offset, pad=pad,
                                          samples=samples, correction=correction,
                                          brick=brick_size)
        return 1 - total / samples

    if brick_size is None:
        _, dense = _marchers(pad, dirs, weights, radius, offset, samples, correction)
        return dense(alpha)

    def bricked(alpha, dirs, weights, radius, offset):
        march, dense = _marchers(pad, dirs, weights, radius, offset, samples, correction)

        def sparse(alpha):
            ao, skipped = _bricked(alpha, active, pad, brick_size, march)
            return ao + _skipped_gradient(pad, samples, correction, skipped, alpha, dirs,
                                          weights, radius, offset)

        # grouped bricks cost about 1.7x the plain march per brick (measured on CPU), so
        # they pay only when well under 60% of them are active: the cut is at half
        active = _active_bricks(alpha, pad, brick_size)
        return lax.cond(jnp.mean(active) <= max_active, sparse, dense, alpha)

    return _one_at_a_time(bricked)(alpha, dirs, weights, radius, offset)


def _one_at_a_time(fn):
    """``fn``, batched under ``jax.vmap`` by a loop over the batch, so that each
    element (a volume, a radius, a pose of a clip) keeps its own ``lax.cond``s and
    marches only its own active bricks: ``vmap`` of a ``lax.cond`` with a batched
    predicate runs both branches, the plain march of the whole volume as well as the
    bricks. Measured on 2 CPU cores, float32, 16 rays of 16 samples, R = 8, bricks of
    16: three sparse 96^3 volumes vmapped took 0.06 s where a batched cond took 0.49 s
    (0.20 s unbricked), when this was written; at 7ad754c 0.059 s against 0.180 s
    unbricked, 3.1x (``python -m benchmarks.run lao --quick``,
    ``docs/results/bench_cpu_lao.json``).

    The loop (``jax.custom_batching.sequential_vmap``) has no derivative of its own, so
    ``fn``'s is given as a custom JVP: ``fn``'s own, batched as usual (both branches
    under ``vmap``), whose transpose is reverse mode (a loop would have no transpose).
    The arrays without a tangent (of the arguments, pytrees such as a clip included)
    are held constant, so that, e.g., a derivative in the radius alone does not march a
    zero opacity tangent. The forward pass and gradient of a bricked sparse 96^3 volume
    (16 rays of 16 samples, R = 8, bricks of 16) took 0.279 s, against 0.270 s when the
    gradient was a custom VJP that ran ``fn`` again (interleaved, in one process)."""
    forward = jax.custom_batching.sequential_vmap(fn)

    @jax.custom_jvp
    def wrapped(*args):
        return forward(*args)

    def wrapped_jvp(primals, tangents):
        # the values through ``wrapped``, so that a derivative of this rule (a second
        # derivative) comes here again: JAX 0.10's sequential_vmap fails under a vmap of
        # its JVP ("scan got no values to scan over"), which jax.hessian is
        return wrapped(*primals), jvp_of_nonzero(fn, primals, tangents)[1]

    wrapped.defjvp(wrapped_jvp, symbolic_zeros=True)
    return wrapped


class LocalAmbientOcclusion(eqx.Module):
    """Parameters of :func:`lao`, as a Module: ``radius``, ``offset`` (and ``weights``)
    are array leaves a fit can change; counts and switches are static. Under
    ``eqx.filter_jit`` the radius is traced, so the padding is bounded by the static
    ``max_radius`` (see :func:`lao`), by default twice the radius given here: a fit
    can grow the radius up to that without recompiling, and beyond it gets a clear
    error asking for a larger ``max_radius``. ``directions`` is an array leaf but is
    not differentiated.

    Args:
        radius: $R$ in voxels (default 16), an array leaf; a leading batch axis makes
            a Module of several settings. Map it with ``eqx.filter_vmap(f,
            in_axes=(axes,))``, ``axes`` marking the batched leaves (``directions``
            and ``offset`` are array leaves too): ``axes = eqx.tree_at(lambda p:
            p.radius, jax.tree_util.tree_map(lambda _: None, params), 0, is_leaf=lambda
            x: x is None)``.
        offset: $a$ in voxels (default 1), an array leaf.
        directions: ``(L, 3)`` directions, or an int ``L`` for
            ``volshade.directions.fibonacci(L)`` (default 42).
        samples, weights, opacity_correction, brick_size, implementation: as for
            :func:`lao` (defaults 16, equal weights, False, no bricks, ``"xla"``).
        max_radius: static bound on the radius (voxels); default twice ``radius``
            (a radius traced when the Module is built, inside ``jit``, has no known
            double: then none, and :func:`lao` pads by the volume's extent, same
            values, more memory and time: give ``max_radius`` there).

    Raises:
        ValueError / TypeError: the errors :func:`lao` raises for these arguments,
            when the Module is built rather than at its first call.

    Example:
        >>> params = LocalAmbientOcclusion(4.0, directions=12, samples=8, max_radius=6.0)
        >>> alpha = jnp.zeros((16, 16, 16)).at[6:10, 6:10, 6:10].set(0.5)
        >>> ao = params(alpha)
        >>> grads = eqx.filter_grad(lambda p: jnp.sum(p(alpha)))(params)
        >>> bool(grads.radius < 0)  # a longer reach sees more of the block: darker
        True
    """

    radius: Array
    offset: Array
    directions: Array
    weights: Array | None
    samples: int = eqx.field(static=True)
    opacity_correction: bool = eqx.field(static=True)
    brick_size: int | None = eqx.field(static=True)
    max_radius: float | None = eqx.field(static=True)
    implementation: str = eqx.field(static=True)

    def __init__(self, radius: ArrayLike = 16.0, *, offset: ArrayLike = 1.0,
                 directions: ArrayLike | int = 42, samples: int = 16,
                 weights: ArrayLike | None = None, opacity_correction: bool = False,
                 brick_size: int | None = None, max_radius: float | None = None,
                 implementation: str = "xla"):
        where = "volshade.LocalAmbientOcclusion"
        self.radius = _checks.float_leaf(radius, "radius", where).astype(float)
        self.offset = _checks.float_leaf(offset, "offset", where).astype(float)
        # checked here when known, since the default max_radius is derived from it
        # (lao checks traced values again at run time)
        xp, r, a = _checks.for_check(self.radius, self.offset)
        _checks.refuse(self.radius, [(_checks.not_positive(r),
                                      f"`radius` must be a finite number > 0 (voxels), got "
                                      f"{radius!r}.")], where, traced=False)
        _checks.refuse(self.offset, [
            (~xp.all(xp.isfinite(a) & (a >= 0)),
             f"`offset` must be a finite number >= 0 (voxels), got {offset!r}."),
            (~xp.all(r > a),
             f"`radius` ({radius!r}) must be > `offset` ({offset!r}); increase the radius "
             f"or lower the offset (default 1 voxel).")], where, traced=False)
        # the options lao() checks, checked here too: stored unchecked, they would fail
        # only at the first call, perhaps deep inside a jit (a module with a batch axis,
        # for vmap, like a batched radius: its first member)
        one = directions
        if eqx.is_array(directions) and directions.ndim > 2:
            one = directions.reshape(-1, *directions.shape[-2:])[0]
        n_dirs = _directions_array(one, jnp.result_type(float), where).shape[0]
        if isinstance(directions, int | np.integer) and not isinstance(directions, bool):
            directions = _directions.fibonacci(int(directions))
        self.directions = jnp.asarray(directions)
        self.weights = (None if weights is None
                        else _weights_array(weights, n_dirs, where, batch=True))
        if self.weights is not None:  # known values now, as lao() would at the first call
            xp, w = _checks.for_check(self.weights)
            _checks.refuse(self.weights, [
                (~xp.all(xp.isfinite(w)) | xp.any(w < 0) | ~xp.all(xp.max(w, axis=-1) > 0),
                 "`weights` must be finite, >= 0 and not all zero.")], where, traced=False)
        self.samples = _checks.positive_int(samples, "samples", where)
        self.opacity_correction = _checks.flag(opacity_correction, "opacity_correction", where)
        self.brick_size = (None if brick_size is None
                           else _checks.positive_int(brick_size, "brick_size", where))
        if max_radius is not None:
            max_radius = _checks.positive_float(max_radius, "max_radius", where)
            _checks.refuse(self.radius, [(xp.any(r > max_radius),
                                          f"`radius` ({radius!r}) exceeds `max_radius` "
                                          f"({max_radius}); raise `max_radius`.")],
                           where, traced=False)
        elif not isinstance(radius, jax.core.Tracer):
            max_radius = 2 * float(np.max(np.asarray(radius)))
        self.max_radius = max_radius
        _checks.option(implementation, _IMPLEMENTATIONS, "implementation", where)
        self.implementation = _checks.python_scalar(implementation)

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        return {"directions": "the ray directions are configuration; `lao` stops their "
                              "gradient"}

    def _arguments(self) -> dict:
        """These parameters as :func:`lao`'s keyword arguments, but ``implementation``
        (so :func:`_prepare` takes them too)."""
        return dict(directions=self.directions, radius=self.radius, offset=self.offset,
                    samples=self.samples, weights=self.weights,
                    opacity_correction=self.opacity_correction, brick_size=self.brick_size,
                    max_radius=self.max_radius)

    def __call__(self, alpha: Volume) -> Volume:
        """AO of ``alpha``: :func:`lao` with these parameters."""
        return lao(alpha, **self._arguments(), implementation=self.implementation)
