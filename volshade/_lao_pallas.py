r"""The LAO march as Pallas kernels (Triton on a GPU), forward and reverse mode.

This computes exactly what :func:`volshade.lao._occlusion_sum` computes, the
occlusion sum $\sum_l \hat w_l\, occ_l$ with $occ_l = M (1 - I_l)$ (Ancel et al.
2010, section 3, eq. 3-4), for ``lao(..., implementation="pallas")``. The XLA
version reads eight shifted copies of the padded volume per sample and relies on
XLA to fuse each chunk of samples into one pass. Here one program owns a tile of
voxels and marches all $L$ rays and $M$ samples over it in registers: the
volume is read only through the eight corner loads of each sample, which hit the
cache (neighbouring tiles and samples read overlapping windows), and the output
is written once. The sample offset $s_i l$ is the same for every voxel of the
tile, so its floor and the eight trilinear weights are scalars. The march reads
from four copies of the padded volume shifted by 0-3 voxels along ``w``, so that
every read starts 16-byte aligned and loads four voxels per instruction (see
:class:`Launch` for the instruction counts this was chosen by). With bricks (the
``brick_size`` of :func:`volshade.lao.lao`), a tile whose bricks have no opacity
within reach is not marched, by the XLA path's criterion, so no value changes.

Reverse mode keeps the recompute-instead-of-store scheme of the XLA VJP, one
direction at a time, in three kernels:

1. ``_chunk_starts_kernel``: march forward, store the transmittance $T$ at the start of
   every chunk of about $\sqrt{M}$ samples ($\sqrt M$ volumes; ``Launch.chunk``
   sets shorter chunks), and $occ_l$ (for the weight's cotangent).
2. ``_chunk_cotangents_kernel`` (chunks in reverse): reload the chunk's samples and
   their slopes along the ray, rebuild $T_i$ from the stored start, sweep back
   with the suffix sums $S_i$ and write $g_i = \bar o\, \hat w_l\, v_i T_i S_i$
   (through the opacity correction) for each sample of the chunk; sum the radius
   and offset terms $g_i\, \partial\alpha_i/\partial s\, \partial s_i/
   \partial(R, a)$ over the tile (one partial sum per program).
3. ``_chunk_adjoint_kernel``: the adjoint of a shifted read is the opposite shift, so
   $\bar\alpha(z) \mathrel{+}= \sum_i \sum_c w_c(i)\, g_i(z - n_i - c)$ is a
   gather-free stencil too. The $g_i$ live in a buffer with a zero halo as wide
   as the padding, so no read leaves it (the Triton lowering would allow masked
   reads, but Pallas' interpreter, which the CPU tests use, does not emulate
   partly out-of-bounds windows).

Memory, in volumes of the (tile-rounded) input: the forward holds the four
shifted copies of the padded volume, $4 (n + 2p)^3 / n^3$ (5.8 at $256^3$ with
$R = 16$), and the output. Reverse mode holds the copies, the chunk starts
($\sqrt M$), the $g$ buffer of one chunk (its $\sqrt M$ samples' volumes, each
grown by the padding, $(n + 2p)^3 / n^3$ of one: about 1.7 at $512^3$ with
$R = 50$, but 27 when the padding is the whole extent, i.e. a traced radius
without ``max_radius``) and about four carried volumes, for any $L$.

When lowered for CUDA the kernels are compiled by Triton; on any other platform
they run in Pallas' interpreter (exact, slow), which is how the test suite checks
them against the XLA march on a CPU (``lax.platform_dependent`` chooses, so a
computation placed on the CPU of a GPU machine is interpreted too). Tile shapes are
powers of two (a Triton requirement); the volume is padded up to whole tiles and
cropped. The kernels compute in float32 at least (Triton has no half-precision
division); half-precision inputs are promoted and the result cast back. JAX 0.11
deprecates Pallas' Triton backend in favour of Mosaic GPU (Hopper and newer); these
kernels use only tiles, dynamic slices and scalar loops, which a Mosaic GPU port
would keep.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.experimental import pallas as pl

from ._linear import linear_primitive
from ._numerics import correct_opacity
from .lao import (
    _CORNERS,
    _active_bricks,
    _blend_corners,
    _cell,
    _chunking,
    _corner_slopes,
    _corner_weights,
    _occlusion_sum_tangent,
    _reverse_step,
    _weighted_sum,
)


class Launch(NamedTuple):
    r"""How the kernels are launched.

    ``tile`` is the ``(d, h, w)`` block of voxels one program of the forward,
    chunk-start and adjoint kernels owns (powers of two), ``cotangent_tile`` the same
    for the reverse-mode cotangent kernel (it holds a chunk of samples in registers)
    and ``corrected_cotangent_tile`` for that kernel with opacity correction (whose
    derivative needs about twice the registers), ``num_warps`` Triton's warps per
    program, and ``vector`` the number of copies of the padded opacity, shifted by
    ``0 .. vector - 1`` voxels along ``w``, that the march reads (1: the padded
    opacity itself). With ``vector = 4`` each window read starts at a multiple of 4
    voxels of one copy, so Triton loads four voxels (16 bytes) per instruction, at
    the price of four padded volumes in memory. ``chunk`` is the most samples of a
    reverse-mode chunk (``None``: about $\sqrt{M}$, :func:`volshade.lao._chunking`).
    The cotangent kernel holds a chunk's transmittances, opacities and slopes in
    registers, so a shorter chunk needs fewer of them (more programs can run at once)
    and keeps a shorter $g$ buffer, at the price of more chunk starts: $\lceil (M -
    1) / c \rceil$ volumes instead of about $\sqrt{M}$.

    The Triton IR of jaxlib 0.10.2 compiled by Triton 3.6 for sm_90a (H100/H200;
    ``python -m benchmarks.run pallas_sass``; another jaxlib and Triton may differ
    somewhat), in instructions per voxel and sample with the default launch: the
    forward march 30 (55 with tile ``(2, 8, 32)`` and ``vector = 1``), the reverse-mode
    kernels 33 (chunk starts), 59 (cotangents: 255 registers, 4 bytes spilled) and 38
    (adjoint); with opacity correction the forward takes 100 and the cotangents 222
    (255 registers, no spill; ``(2, 8, 32)`` and ``(1, 8, 64)`` spill 1228 and 1276
    bytes there, in an earlier run whose record was not kept; the recorded run,
    ``docs/results/pallas_sass_sm90a.json``, holds the rest). Timings need a GPU:
    ``python -m benchmarks.run lao_pallas``.

    Timed on an H200 (JAX 0.11.2, 2026-12-04; $512^3$, $L = 54$, $M = 50$, $R = 50$,
    no opacity correction unless said). Only one run is on record,
    ``docs/results/lao_pallas_h200.json`` (the forward tiles and the default's 4.74 s
    below); the figures of the other runs were read from their output at the time, and
    their records were not kept. Forward, in one run: tile ``(4, 4, 64)``
    0.579 s (0.63 T samples/s), ``(4, 8, 32)`` 0.615 s, ``(2, 8, 64)`` 0.644 s,
    ``(4, 4, 64)`` with 8 warps 0.730 s, with ``vector = 1`` 0.830 s; in others,
    ``(8, 4, 32)`` as ``(4, 8, 32)``, ``(2, 16, 32)`` 0.68 s, ``(2, 8, 32)`` 0.72 s,
    ``(4, 8, 64)`` 0.77 s, ``(1, 8, 128)`` 0.78 s, 2 warps 0.82 s, ``(8, 8, 32)``
    0.95 s, and bf16 copies of the opacity (16 bytes hold 8 voxels) 0.95 s. Keeping
    the eight corner windows of the previous sample in registers and reading again
    only those whose cell moved (a step crossing $k$ grid planes reads
    $8 (1 - 2^{-k})$ windows: about 40% fewer loads) took 0.68 s with ``(4, 8, 32)``
    (0.61 s without) and 0.60 s with ``(4, 8, 64)`` (0.77 s without, in another run):
    it helps a tile of 16 voxels per thread and hurts one of 8, did not beat
    ``(4, 4, 64)`` without it (0.58 s in that run), and was dropped (it was not tried
    with ``(4, 4, 64)``). Forward and gradient, in one run: the default 4.74 s, tiles
    ``(4, 8, 32)`` and ``(2, 8, 32)`` (the previous default) 5.50 s. Of those 5.50 s
    (timed by replacing kernels with copies), the forward and the chunk starts took
    1.66 s, the cotangents 2.68 s and the adjoint 1.14 s. With opacity correction the
    default's forward takes 1.29 s and with the gradient 8.35 s (the cotangent tile
    ``(1, 8, 32)``: ``(1, 8, 64)`` took 8.98 s against 8.51 s in another run).
    Computing each sample's cell, fractions and window starts, and the cotangent
    kernel's weight slopes, once in XLA as tables the kernels read, rather than in
    every program, cut the instructions per voxel and sample (forward 30 -> 26,
    cotangents 59 -> 52, adjoint 38 -> 34) and changed no timing (forward 0.582 s
    against 0.576 s, with the gradient 4.81 s against 4.71 s, in one run), so it was
    dropped too: the instruction count does not bound these kernels.

    Shorter reverse-mode chunks (``chunk``), in that sm_90a build (static, not timed;
    ``docs/results/pallas_sass_sm90a.json``), for the cotangent kernel; warps that
    fit on a multiprocessor by registers in brackets: without opacity correction,
    tile ``(2, 8, 64)`` takes 255 registers at the default chunk of 7 samples (8
    warps), 151 at chunk 3 (12) and 87 at chunk 2 (20), for 59, 68 and 74
    instructions per voxel and sample, and ``(4, 4, 64)`` at chunk 5 168 registers
    (12) and 63 instructions; with correction, ``(1, 8, 64)`` at chunk 4 253
    registers without a spill (8) and 179 instructions against the default's 222,
    and ``(2, 8, 32)`` at chunk 2 149 registers (12) and 189 instructions. Each chunk
    costs the adjoint and the suffix carry a volume read and written, and the adjoint
    kernel's per-chunk work shows too (38 instructions per voxel and sample at chunks
    of 7 and 5, 50-53 at 4, 3 and 2), so shorter chunks trade those for occupancy:
    ``GRADIENT_LAUNCHES`` and
    ``CORRECTED_GRADIENT_LAUNCHES`` are the launches the GPU benchmark times to
    decide.
    """

    tile: tuple[int, int, int] = (4, 4, 64)
    cotangent_tile: tuple[int, int, int] = (2, 8, 64)
    corrected_cotangent_tile: tuple[int, int, int] = (1, 8, 32)
    num_warps: int = 4
    vector: int = 4
    chunk: int | None = None


#: The launches ``python -m benchmarks.run lao_pallas`` times (forward).
DEFAULT_LAUNCH = Launch()
LAUNCHES = (DEFAULT_LAUNCH, Launch(tile=(4, 8, 32), cotangent_tile=(2, 8, 32)),
            Launch(tile=(2, 8, 64)), Launch(num_warps=8),
            Launch(tile=(2, 8, 32), vector=1), Launch(tile=(4, 4, 64), vector=1))
#: The reverse-mode launches it times forward plus gradient, without and with opacity
#: correction: shorter chunks with the cotangent tiles that fit them in fewer registers
#: (see :class:`Launch`; the forward kernel is the default's).
GRADIENT_LAUNCHES = (DEFAULT_LAUNCH, Launch(cotangent_tile=(4, 4, 64), chunk=5),
                     Launch(chunk=3), Launch(chunk=2))
CORRECTED_GRADIENT_LAUNCHES = (DEFAULT_LAUNCH,
                               Launch(corrected_cotangent_tile=(1, 8, 64), chunk=4),
                               Launch(corrected_cotangent_tile=(2, 8, 32), chunk=2))


def _check_launch(launch: Launch) -> None:
    """Tiles of powers of two (Triton's tensors must be, and the shared tile-rounded
    shape of the reverse-mode kernels is a multiple of every tile only then), powers
    of two for ``num_warps`` and ``vector``, and a positive ``chunk``."""
    def power_of_two(n):
        return isinstance(n, int) and n >= 1 and n & (n - 1) == 0

    tiles = (launch.tile, launch.cotangent_tile, launch.corrected_cotangent_tile)
    if not (all(power_of_two(t) for tile in tiles for t in tile)
            and all(len(tile) == 3 for tile in tiles)
            and power_of_two(launch.num_warps) and power_of_two(launch.vector)):
        raise ValueError(f"volshade._lao_pallas: {launch} needs tiles of three powers of "
                         f"two and a power-of-two `num_warps` and `vector`.")
    if launch.chunk is not None and not (isinstance(launch.chunk, int) and launch.chunk >= 1):
        raise ValueError(f"volshade._lao_pallas: {launch} needs a `chunk` of at least one "
                         f"sample, or None for about sqrt(samples).")


def _tiling(shape, tile):
    """The tile actually used (no larger than the volume's power-of-two cover), the
    grid, and the tile-aligned output shape."""
    tile = tuple(min(t, pl.next_power_of_2(s)) for t, s in zip(tile, shape, strict=True))
    grid = tuple(-(-s // t) for s, t in zip(shape, tile, strict=True))
    return tile, grid, tuple(g * t for g, t in zip(grid, tile, strict=True))


def _compiler_params(launch: Launch, interpret: bool) -> dict:
    if interpret:
        return {"interpret": True}
    from jax.experimental.pallas import triton as pltriton

    return {"compiler_params": pltriton.CompilerParams(num_warps=launch.num_warps,
                                                       num_stages=1)}


def _pack(*values, dtype):
    """Scalars and small arrays as one flat vector, padded to a power of two (Triton
    loads must be)."""
    flat = jnp.concatenate([jnp.ravel(jnp.asarray(v, dtype)) for v in values])
    return jnp.pad(flat, (0, pl.next_power_of_2(flat.shape[0]) - flat.shape[0]))


def _position(radius, offset, samples, index, direction):
    """Segment-midpoint distance $s_i = a + (i + 1/2)(R - a)/M$, and the fraction and
    integer corner of the trilinear cell of $s_i l$ (voxels; as
    :func:`volshade.lao._cell` chooses it)."""
    step = (radius - offset) / samples
    distance = offset + (index.astype(step.dtype) + 0.5) * step
    cells = [_cell(distance * direction[ax], direction[ax]) for ax in range(3)]
    return step, [f for f, _ in cells], [n for _, n in cells]


def window_start(origin, pad, shift, corner):
    """Start, along one axis, of the source window that corner ``corner`` of a sample
    shifted by ``shift`` reads for the tile at ``origin``:
    ``origin + clip(pad + shift + corner, 0, 2 pad)``, in ``[origin, origin + 2 pad]``.

    The clip mirrors :func:`volshade.lao._corner_slices`: it binds only when the
    padding is the whole extent, and then the window lies in the zero padding.
    """
    return origin + jnp.clip(pad + shift + corner, 0, 2 * pad)


def adjoint_start(origin, pad, shift, corner):
    """Start, along one axis, of the window of the halo'd cotangent buffer (voxel
    ``x`` at ``x + pad``) that the adjoint reads for the tile at ``origin``: the
    forward read moved voxel ``x`` by ``window_start - origin - pad``, so the adjoint
    reads ``origin - that + pad``, in ``[origin, origin + 2 pad]`` as well."""
    return origin + 2 * pad - jnp.clip(pad + shift + corner, 0, 2 * pad)


def _windows(ref, origin, pad, tile, shift):
    """The eight tile-sized windows of the padded opacity that the corners of a sample
    shifted by ``shift`` touch, read from ``ref``, its ``vector`` shifted copies
    (:func:`_copies`): a window starting at ``w`` is read from copy ``w % vector``
    at ``w - w % vector``, an aligned start."""
    vector = ref.shape[0]
    out = []
    for corner in _CORNERS:
        at = [window_start(origin[ax], pad[ax], shift[ax], corner[ax]) for ax in range(3)]
        copy = at[2] % vector
        out.append(ref[copy, pl.ds(at[0], tile[0]), pl.ds(at[1], tile[1]),
                       pl.ds(pl.multiple_of(at[2] - copy, vector), tile[2])])
    return out


def _origin(tile):
    return [pl.program_id(ax) * tile[ax] for ax in range(3)]


def _opacity(value, step, correction):
    return correct_opacity(value, step) if correction else value


# --------------------------------------------------------------------------- forward


def _forward_kernel(params_ref, active_ref, source_ref, out_ref, *, pad, tile, samples,
                    n_dirs, correction):
    origin = _origin(tile)
    radius, offset = params_ref[0], params_ref[1]
    dtype = out_ref.dtype

    def direction_body(index, total):
        direction = [params_ref[2 + 4 * index + ax] for ax in range(3)]
        weight = params_ref[2 + 4 * index + 3]

        def sample_body(i, horner):
            # back to front, the Horner form of eq. 3, rounded as the XLA march rounds it
            # (an opaque sample gives exactly 1): H_i = H_{i+1} + (1 - alpha'_i H_{i+1}),
            # H_{M-1} = 1, occ_l = M - H_0; summing the T_i instead would lose float32
            # precision where they are all near 1
            step, frac, shift = _position(radius, offset, samples, samples - 2 - i, direction)
            alpha = _blend_corners(frac, _windows(source_ref, origin, pad, tile, shift),
                                   exact=correction)
            return horner + (1 - _opacity(alpha, step, correction) * horner)

        horner = lax.fori_loop(0, samples - 1, sample_body, jnp.ones(tile, dtype))
        return total + weight * (samples - horner)

    def march():
        return lax.fori_loop(0, n_dirs, direction_body, jnp.zeros(tile, dtype))

    # a tile with no opacity within reach is not marched: its occlusion is exactly 0
    active = active_ref[pl.program_id(0), pl.program_id(1), pl.program_id(2)]
    out_ref[...] = lax.cond(active != 0, march, lambda: jnp.zeros(tile, dtype))


def _copies(alpha, pad, out_shape, vector):
    """``(vector, ...)``: ``alpha`` zero-padded by ``pad`` in front and up to
    ``out_shape + pad`` behind, and shifted by ``r`` voxels along ``w`` in copy
    ``r`` (copy ``r`` at ``w`` holds the padded opacity at ``w + r``); the ``w``
    extent is rounded up to a multiple of ``vector``."""
    padded = jnp.pad(alpha, tuple((p, p + o - s) for p, o, s
                                  in zip(pad, out_shape, alpha.shape, strict=True)))
    width = -(-padded.shape[2] // vector) * vector
    padded = jnp.pad(padded, ((0, 0), (0, 0), (0, width + vector - 1 - padded.shape[2])))
    return jnp.stack([padded[:, :, r:r + width] for r in range(vector)])


def _active_tiles(alpha, pad, brick, tile, grid):
    """``(grid)`` int32: 1 for the tiles to march. Without ``brick`` every tile; with
    it, the tiles that touch a brick with opacity within ``pad`` voxels
    (:func:`volshade.lao._active_bricks`, the XLA path's criterion), so skipping
    never changes a value."""
    if brick is None:
        return jnp.ones(grid, jnp.int32)
    bricks = _active_bricks(alpha, pad, brick).astype(jnp.int32)
    touches = []
    for ax in range(3):
        # tile t covers voxels [t tile, (t + 1) tile - 1], bricks of those // brick
        t = np.arange(grid[ax])[:, None]
        b = np.arange(bricks.shape[ax])[None, :]
        touches.append(jnp.asarray((b >= t * tile[ax] // brick)
                                   & (b <= ((t + 1) * tile[ax] - 1) // brick), jnp.int32))
    return (jnp.einsum("ia,jb,kc,abc->ijk", *touches, bricks) > 0).astype(jnp.int32)


def _forward(alpha, directions, weights, radius, offset, *, pad, samples, correction, launch,
             brick, interpret):
    tile, grid, out_shape = _tiling(alpha.shape, launch.tile)
    params = _pack(radius, offset, jnp.concatenate([directions, weights[:, None]], 1),
                   dtype=alpha.dtype)
    kernel = functools.partial(_forward_kernel, pad=pad, tile=tile, samples=samples,
                               n_dirs=directions.shape[0], correction=correction)
    total = pl.pallas_call(
        kernel, out_shape=jax.ShapeDtypeStruct(out_shape, alpha.dtype), grid=grid,
        in_specs=[pl.no_block_spec, pl.no_block_spec, pl.no_block_spec],
        out_specs=pl.BlockSpec(tile, lambda i, j, k: (i, j, k)),
        **_compiler_params(launch, interpret))(
            params, _active_tiles(alpha, pad, brick, tile, grid),
            _copies(alpha, pad, out_shape, launch.vector))
    return total[:alpha.shape[0], :alpha.shape[1], :alpha.shape[2]]


# --------------------------------------------------------------------------- reverse


def _chunk_starts_kernel(params_ref, source_ref, starts_ref, occ_ref, *, pad, tile, samples,
                         n_chunks, chunk, correction):
    origin = _origin(tile)
    radius, offset = params_ref[0], params_ref[1]
    direction = [params_ref[2 + ax] for ax in range(3)]
    dtype = occ_ref.dtype

    def chunk_body(k, carry):
        starts_ref[k, pl.ds(origin[0], tile[0]), pl.ds(origin[1], tile[1]),
                   pl.ds(origin[2], tile[2])] = carry[0]

        def sample_body(j, carry):
            transmittance, occlusion = carry
            index = k * chunk + j
            valid = (index < samples - 1).astype(dtype)
            step, frac, shift = _position(radius, offset, samples, index, direction)
            alpha = _blend_corners(frac, _windows(source_ref, origin, pad, tile, shift),
                                   exact=correction)
            transmittance = transmittance * (1 - valid * _opacity(alpha, step, correction))
            return transmittance, occlusion + valid * (1 - transmittance)

        return lax.fori_loop(0, chunk, sample_body, carry)

    zeros = jnp.zeros(tile, dtype)
    _, occlusion = lax.fori_loop(0, n_chunks, chunk_body, (zeros + 1, zeros))
    occ_ref[...] = occlusion


def _chunk_cotangents_kernel(params_ref, index_ref, source_ref, starts_ref, suffix_ref, ct_ref,
                             g_in_ref, suffix_out_ref, g_ref, slope_ref, radius_ref, *, pad,
                             tile, samples, chunk, correction):
    del g_in_ref  # aliased to g_ref: its zero halo is kept, the interior rewritten
    origin = _origin(tile)
    radius, offset = params_ref[0], params_ref[1]
    direction = [params_ref[2 + ax] for ax in range(3)]
    cotangent = params_ref[5] * ct_ref[...]
    dtype = ct_ref.dtype
    first = index_ref[0] * chunk

    transmittance = starts_ref[index_ref[0], pl.ds(origin[0], tile[0]),
                               pl.ds(origin[1], tile[1]), pl.ds(origin[2], tile[2])]
    kept = []
    for j in range(chunk):
        index = first + j
        valid = (index < samples - 1).astype(dtype)
        step, frac, shift = _position(radius, offset, samples, index, direction)
        windows = _windows(source_ref, origin, pad, tile, shift)
        alpha = _blend_corners(frac, windows, exact=correction)
        slope = _weighted_sum(_corner_slopes(frac, direction), windows)
        kept.append((transmittance, alpha, slope, valid, step, index))
        transmittance = transmittance * (1 - valid * _opacity(alpha, step, correction))

    suffix_next = suffix_ref[...]
    acc_slope = acc_radius = jnp.zeros(tile, dtype)
    for j in reversed(range(chunk)):
        transmittance, alpha, slope, valid, step, index = kept[j]
        g_alpha, suffix_next, acc_slope, acc_radius = _reverse_step(
            cotangent, transmittance, suffix_next, alpha, slope, valid, step,
            (index.astype(dtype) + 0.5) / samples, acc_slope, acc_radius, samples=samples,
            correction=correction)
        g_ref[j, pl.ds(origin[0] + pad[0], tile[0]), pl.ds(origin[1] + pad[1], tile[1]),
              pl.ds(origin[2] + pad[2], tile[2])] = g_alpha
    suffix_out_ref[...] = suffix_next
    # the radius and offset need only the totals: one partial sum per program
    # (not two volumes read and written per chunk)
    slope_ref[...] = jnp.sum(acc_slope, keepdims=True)
    radius_ref[...] = jnp.sum(acc_radius, keepdims=True)


def _chunk_adjoint_kernel(params_ref, index_ref, g_ref, acc_in_ref, acc_ref, *, pad, tile,
                          samples, chunk):
    r"""$\bar\alpha(z) \mathrel{+}= \sum_j \sum_c w_c\, g_j(z - \mathrm{shift}_c)$ with the
    forward read's shift ``clip(pad + n + c, 0, 2 pad) - pad``; the halo'd buffer
    holds $g_j(x)$ at ``x + pad``."""
    origin = _origin(tile)
    radius, offset = params_ref[0], params_ref[1]
    direction = [params_ref[2 + ax] for ax in range(3)]
    first = index_ref[0] * chunk
    total = acc_in_ref[...]
    for j in range(chunk):
        _, frac, shift = _position(radius, offset, samples, first + j, direction)
        for corner, weight in _corner_weights(frac):
            at = [adjoint_start(origin[ax], pad[ax], shift[ax], corner[ax]) for ax in range(3)]
            total = total + weight * g_ref[j, pl.ds(at[0], tile[0]), pl.ds(at[1], tile[1]),
                                           pl.ds(at[2], tile[2])]
    acc_ref[...] = total


def _backward(alpha, directions, weights, radius, offset, cotangent, *, pad, samples,
              correction, launch, interpret):
    """Cotangents of ``alpha``, ``weights``, ``radius`` and ``offset``."""
    dtype = alpha.dtype
    shape = alpha.shape
    cotangent_tile = launch.corrected_cotangent_tile if correction else launch.cotangent_tile
    _, _, out_shape = _tiling(shape, tuple(
        max(a, b) for a, b in zip(launch.tile, cotangent_tile, strict=True)))
    n_chunks, chunk = _chunking(samples - 1, launch.chunk)
    source = _copies(alpha, pad, out_shape, launch.vector)
    ct = jnp.pad(cotangent, tuple((0, o - s) for o, s in zip(out_shape, shape, strict=True)))
    halo = tuple(o + 2 * p for o, p in zip(out_shape, pad, strict=True))
    volume = jax.ShapeDtypeStruct(out_shape, dtype)

    def call(kernel, tile, layout):
        """``pallas_call`` of ``kernel`` over ``out_shape`` in tiles of ``tile``;
        ``layout(block, grid)`` gives its shapes and specs, ``block`` being one tile."""
        tile, grid, _ = _tiling(out_shape, tile)
        kernel = functools.partial(kernel, pad=pad, tile=tile, samples=samples)
        return pl.pallas_call(kernel, grid=grid,
                              **layout(pl.BlockSpec(tile, lambda i, j, k: (i, j, k)), grid),
                              **_compiler_params(launch, interpret))

    whole = pl.no_block_spec
    starts_call = call(
        functools.partial(_chunk_starts_kernel, n_chunks=n_chunks, chunk=chunk,
                          correction=correction), launch.tile,
        lambda block, grid: dict(
            out_shape=(jax.ShapeDtypeStruct((n_chunks, *out_shape), dtype), volume),
            in_specs=(whole, whole), out_specs=(whole, block)))
    # the radius and offset sums: one partial sum per program
    one = pl.BlockSpec((1, 1, 1), lambda i, j, k: (i, j, k))
    cotangents_call = call(
        functools.partial(_chunk_cotangents_kernel, chunk=chunk, correction=correction),
        cotangent_tile,
        lambda block, grid: dict(
            out_shape=(volume, jax.ShapeDtypeStruct((chunk, *halo), dtype),
                       jax.ShapeDtypeStruct(grid, dtype), jax.ShapeDtypeStruct(grid, dtype)),
            in_specs=(whole, whole, whole, whole, block, block, whole),
            out_specs=(block, whole, one, one), input_output_aliases={6: 1}))
    adjoint_call = call(
        functools.partial(_chunk_adjoint_kernel, chunk=chunk), launch.tile,
        lambda block, grid: dict(out_shape=volume, in_specs=(whole, whole, whole, block),
                                 out_specs=block, input_output_aliases={3: 0}))

    def direction_bwd(carry, direction_weight):
        d_alpha, acc_slope, acc_radius, g = carry
        direction, weight = direction_weight
        params = _pack(radius, offset, direction, weight, dtype=dtype)
        starts, occlusion = starts_call(params, source)

        def chunk_bwd(state, k):
            suffix, g, d_alpha, acc_slope, acc_radius = state
            index = jnp.reshape(k, (1,)).astype(jnp.int32)
            suffix, g, slope, radius_part = cotangents_call(
                params, index, source, starts, suffix, ct, g)
            d_alpha = adjoint_call(params, index, g, d_alpha)
            return (suffix, g, d_alpha, acc_slope + jnp.sum(slope),
                    acc_radius + jnp.sum(radius_part)), None

        state = (jnp.zeros(out_shape, dtype), g, d_alpha, acc_slope, acc_radius)
        (_, g, d_alpha, acc_slope, acc_radius), _ = lax.scan(
            chunk_bwd, state, jnp.arange(n_chunks), reverse=True)
        return (d_alpha, acc_slope, acc_radius, g), jnp.sum(ct * occlusion)

    zero = jnp.zeros((), dtype)
    init = (jnp.zeros(out_shape, dtype), zero, zero, jnp.zeros((chunk, *halo), dtype))
    (d_alpha, d_slope, d_radius, _), d_weights = lax.scan(
        direction_bwd, init, (directions, weights))
    d_offset = d_slope - d_radius
    return (d_alpha[:shape[0], :shape[1], :shape[2]], d_weights, d_radius, d_offset)


# --------------------------------------------------------------------------- entry point


def _on_platform(fn, *args):
    """``fn(*args)`` compiled by Triton when lowered for CUDA, interpreted elsewhere."""
    return lax.platform_dependent(*args, cuda=functools.partial(fn, interpret=False),
                                  default=functools.partial(fn, interpret=True))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3, 4))
def _occlusion_sum(pad, samples, correction, launch, brick, alpha, directions, weights, radius,
                   offset):
    """The occlusion sum by the kernels. Forward mode is :func:`_tangent`, reverse mode
    its transpose :func:`_transpose`, the reverse-mode kernels."""
    forward = functools.partial(_forward, pad=pad, samples=samples, correction=correction,
                                launch=launch, brick=brick)
    return _on_platform(forward, alpha, directions, weights, radius, offset)


def _tangent(alpha, directions, weights, radius, offset, d_alpha, d_weights, d_radius,
             d_offset, *, pad, samples, correction, launch, live):
    """Forward mode: the XLA march's tangent (:func:`volshade.lao._occlusion_sum_tangent`)
    on the padded opacity; there is no tangent kernel, so forward mode runs at the XLA
    march's speed."""
    del launch
    widths = [(p, p) for p in pad]
    d_source = jnp.pad(d_alpha, widths) if live[0] else d_alpha
    return _occlusion_sum_tangent(jnp.pad(alpha, widths), directions, weights, radius,
                                  offset, d_source, d_weights, d_radius, d_offset, pad=pad,
                                  shape=alpha.shape, correction=correction, samples=samples,
                                  live=live)


def _transpose(alpha, directions, weights, radius, offset, cotangent, *, pad, samples,
               correction, launch, live):
    """Reverse mode: the kernels' cotangents of ``(alpha, weights, radius, offset)``
    (all four are computed; ``live`` does not enter). Every voxel's is computed: a
    skipped tile's AO still depends on the opacity around it."""
    del live
    backward = functools.partial(_backward, pad=pad, samples=samples, correction=correction,
                                 launch=launch)
    d_alpha, d_weights, d_radius, d_offset = _on_platform(
        backward, alpha, directions, weights, radius, offset, cotangent)
    return (d_alpha, d_weights.astype(weights.dtype), d_radius.astype(radius.dtype),
            d_offset.astype(offset.dtype))


# second derivatives would differentiate the kernels, which JAX cannot do: refused
_SECOND = ("volshade.lao: second derivatives are not available with "
           "implementation='pallas' (JAX cannot differentiate its kernels); use "
           "implementation='xla' for them.")
_tangent_map = linear_primitive("volshade_lao_pallas_tangent", _tangent, _transpose,
                                n_residuals=5, constant=dict.fromkeys(range(5), _SECOND))


def _occlusion_sum_jvp(pad, samples, correction, launch, brick, primals, tangents):
    out = _occlusion_sum(pad, samples, correction, launch, brick, *primals)
    (tangent,) = _tangent_map(
        primals, (tangents[0], *tangents[2:]),  # no derivative in the directions
        pad=pad, samples=samples, correction=correction, launch=launch)
    return out, tangent


_occlusion_sum.defjvp(_occlusion_sum_jvp, symbolic_zeros=True)


def occlusion_sum(alpha, directions, weights, radius, offset, *, pad, samples: int,
                  correction: bool, launch: Launch = DEFAULT_LAUNCH,
                  brick: int | None = None):
    r"""$\sum_l \hat w_l\, occ_l$ for the opacity volume ``alpha`` (unpadded), as
    :func:`volshade.lao._occlusion_sum` computes it for the source padded by ``pad``;
    ``samples`` must be at least 2. Differentiable in ``alpha``, ``weights``,
    ``radius`` and ``offset`` (``directions`` get a zero cotangent), in reverse mode by
    the kernels and in forward mode by the XLA march's tangent; not twice. Computed in
    float32 at least and returned in the dtype of ``alpha``. With ``brick`` the
    forward skips the tiles whose bricks of that edge have no opacity within ``pad``
    voxels (their sum is 0); the gradient is computed everywhere."""
    _check_launch(launch)
    if samples < 2:  # M = 1 takes no sample: lao answers it without a kernel
        raise ValueError(f"volshade._lao_pallas.occlusion_sum: `samples` must be >= 2, got "
                         f"{samples}.")
    work = jnp.promote_types(alpha.dtype, jnp.float32)
    total = _occlusion_sum(pad, samples, correction, launch, brick,
                           *(jnp.asarray(x).astype(work)
                             for x in (alpha, directions, weights, radius, offset)))
    return total.astype(alpha.dtype)
