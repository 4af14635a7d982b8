r"""Volumes to shade: analytic phantoms, NIfTI loading and the real-data lookup.

Conventions fixed here for the whole library:

* A volume is a ``(D, H, W)`` array; axis ``d`` is the slowest. Voxel
  ``(i, j, k)`` has its centre at index coordinates ``(i, j, k)``.
* Phantoms are ``float32`` arrays with values in ``[0, 1]``, **always float32**
  (also when ``jax_enable_x64`` is on): they are data, and transfer functions
  map ``[0, 1]`` intensities to colour and opacity. Cast them yourself
  (``vol.astype(jnp.float64)``) for float64 work.
* Phantom geometry is given in *normalised* coordinates: each axis spans
  ``[-1, 1]`` across the volume (voxel centres at ``(2 i + 1) / n - 1``), so a
  phantom scales with ``shape``; a non-cubic shape stretches it (spheres become
  ellipsoids).
* NIfTI volumes (RAS+, arrays indexed ``(x, y, z)`` by nibabel) are returned
  transposed to ``(z, y, x)``: ``d`` is inferior -> superior, ``h`` posterior ->
  anterior, ``w`` left -> right, and the voxel spacing (mm) is given in the same
  ``(d, h, w)`` order.

These are data-preparation functions, not kernels: they run eagerly in NumPy
(their arguments set shapes) and return concrete ``jax.Array`` s. Call them
outside ``jax.jit``.

Example:
    >>> vol = phantom("shells", shape=32)
    >>> vol.shape, vol.dtype
    ((32, 32, 32), dtype('float32'))
"""

import math
import os
import pathlib
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from . import _checks
from ._types import Array, Float

__all__ = [
    "BUCKY_VALUES",
    "CORNER_VALUES",
    "DATASETS",
    "ORANGE_VALUES",
    "PHANTOMS",
    "SHELL_VALUES",
    "data_path",
    "load",
    "load_nifti",
    "phantom",
]

Spacing = tuple[float, float, float]

# ----------------------------------------------------------------------------------------------
# Documented intensity levels of the phantoms (build transfer functions from these).
# ----------------------------------------------------------------------------------------------

CORNER_VALUES: dict[str, float] = {"white": 1.0, "blue": 0.75, "green": 0.5}
"""Intensities of the three walls of the ``"corner"`` phantom, by the colour they are
meant to be given (Ruiz et al. 2008, section 3.2, Figure 4: "left wall: green, right
wall: blue, floor: white"): the floor (low ``d``) is ``"white"`` = 1.0, the wall at
low ``h`` is ``"green"`` = 0.5, the wall at low ``w`` is ``"blue"`` = 0.75, so that a
camera above the open corner (``volshade.Camera.orbit`` with an azimuth between 0 and
90 degrees) sees green at its left and blue at its right, as in the figure. Where two
walls meet the larger value wins; everything else is 0 (empty)."""

SHELL_VALUES: tuple[float, float, float] = (0.3, 0.6, 1.0)
"""Densities of the ``"shells"`` phantom's shells, from the outer to the inner one."""

ORANGE_VALUES: dict[str, float] = {"peel": 1.0, "pith": 0.7, "flesh": 0.4}
"""Intensities of the ``"orange"`` phantom: the peel, the pith (the white layer under
the peel, the segment membranes and the central column) and the flesh of the
segments; outside is 0."""

BUCKY_VALUES: dict[str, float] = {"ball": 1.0, "bond": 0.5}
"""Peak intensities of the ``"bucky"`` phantom: the 60 balls (carbon atoms) and the 90
thinner bonds between neighbouring balls; both fall off smoothly to 0."""

# ----------------------------------------------------------------------------------------------
# Phantoms
# ----------------------------------------------------------------------------------------------


def _axis_coords(n: int) -> np.ndarray:
    """Normalised coordinates of the ``n`` voxel centres along one axis, in ``(-1, 1)``."""
    return (np.arange(n, dtype=np.float64) + 0.5) * (2.0 / n) - 1.0


def _grid(shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Open (broadcastable) normalised grid ``d, h, w`` of shapes (D,1,1), (1,H,1), (1,1,W)."""
    d, h, w = (_axis_coords(n) for n in shape)
    return d[:, None, None], h[None, :, None], w[None, None, :]


def _half_voxel(shape: tuple[int, int, int]) -> float:
    """Half the largest voxel size in normalised units (one voxel is ``2 / n``)."""
    return 1.0 / min(shape)


def _shells(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    d, h, w = _grid(shape)
    r = np.sqrt(d * d + h * h + w * w)
    # Shells (outer radius, thickness) from outside in; thickness is at least one voxel.
    thickness = max(0.16, 2.0 * _half_voxel(shape))
    out = np.zeros(shape, dtype=np.float64)
    for outer, value in zip((0.92, 0.62, 0.32), SHELL_VALUES, strict=True):
        out = np.where((r <= outer) & (r > outer - thickness), value, out)
    return out


def _corner(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    out = np.zeros(shape, dtype=np.float64)
    td, th, tw = (max(2, n // 16) for n in shape)
    out[:, :th, :] = CORNER_VALUES["green"]
    out[:, :, :tw] = np.maximum(out[:, :, :tw], CORNER_VALUES["blue"])
    out[:td, :, :] = np.maximum(out[:td, :, :], CORNER_VALUES["white"])
    return out


def _orange(shape: tuple[int, int, int], seed: int, n_segments: int = 10) -> np.ndarray:
    d, h, w = _grid(shape)
    r = np.sqrt(d * d + h * h + w * w)
    rho = np.sqrt(h * h + w * w)  # distance from the stem axis (the d axis)
    phi = np.arctan2(h, w)
    wedge = 2.0 * np.pi / n_segments
    # Segment k is centred on the azimuth phi = k * wedge (segment 0 on the +w axis), with
    # membranes at (k + 1/2) * wedge; delta is the angle to the nearest membrane half-plane.
    delta = np.abs(np.mod(phi, wedge) - 0.5 * wedge)
    membrane_dist = rho * np.sin(np.minimum(delta, 0.5 * np.pi))
    # Half-width >= 0.75 voxel, so each membrane separates its neighbouring segments.
    half_width = max(0.025, 1.5 / min(shape[1:]))
    core = rho <= max(0.08, 2.0 * _half_voxel(shape))
    pith = (membrane_dist <= half_width) | core
    flesh_r, pith_r, peel_r = 0.78, 0.85, 0.95
    out = np.where(r <= flesh_r, np.where(pith, ORANGE_VALUES["pith"], ORANGE_VALUES["flesh"]),
                   0.0)
    out = np.where((r > flesh_r) & (r <= pith_r), ORANGE_VALUES["pith"], out)
    out = np.where((r > pith_r) & (r <= peel_r), ORANGE_VALUES["peel"], out)
    return np.broadcast_to(out, shape)


def _fullerene() -> tuple[np.ndarray, np.ndarray]:
    """Vertices (60, 3) and edges (90, 2) of a truncated icosahedron with edge length 2.

    Vertices are the even permutations of (0, +-1, +-3 phi), (+-1, +-(2 + phi), +-2 phi)
    and (+-phi, +-2, +-(2 phi + 1)), phi the golden ratio."""
    phi = (1.0 + math.sqrt(5.0)) / 2.0
    bases = ((0.0, 1.0, 3 * phi), (1.0, 2 + phi, 2 * phi), (phi, 2.0, 2 * phi + 1))
    even_perms = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
    signs = np.array([[sa, sb, sc] for sa in (1, -1) for sb in (1, -1) for sc in (1, -1)])
    pts = np.concatenate([(np.array(b) * signs)[:, list(p)] for b in bases for p in even_perms])
    verts = np.unique(np.round(pts, 12), axis=0)
    dist = np.linalg.norm(verts[:, None, :] - verts[None, :, :], axis=-1)
    i, j = np.nonzero(np.triu(np.isclose(dist, 2.0), k=1))
    return verts, np.stack([i, j], axis=-1)


def _splat(out: np.ndarray, coords: list[np.ndarray], lo: np.ndarray, hi: np.ndarray,
           profile: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> None:
    """``out = max(out, profile)`` over the voxels whose normalised centres lie in [lo, hi]."""
    idx = []
    for c, a, b in zip(coords, lo, hi, strict=True):
        i0, i1 = np.searchsorted(c, a, side="left"), np.searchsorted(c, b, side="right")
        if i1 <= i0:
            return
        idx.append(slice(i0, i1))
    sub = np.ix_(*(c[s] for c, s in zip(coords, idx, strict=True)))
    block = out[tuple(idx)]
    np.maximum(block, profile(*sub), out=block)


def _bucky(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    verts, edges = _fullerene()
    centres = verts * (0.72 / np.linalg.norm(verts[0]))  # circumsphere radius 0.72
    ball_r = max(0.1, 3.0 * _half_voxel(shape))
    bond_r = max(0.045, 2.0 * _half_voxel(shape))
    coords = [_axis_coords(n) for n in shape]
    out = np.zeros(shape, dtype=np.float64)

    def bump(dist2: np.ndarray, radius: float, peak: float) -> np.ndarray:
        # C^1 compact bump: peak * (1 - s^2)^2 for s = dist / radius < 1, else 0.
        s2 = np.minimum(dist2 / (radius * radius), 1.0)
        return peak * (1.0 - s2) ** 2

    for a, b in edges:
        pa, pb = centres[a], centres[b]
        seg = pb - pa

        def bond(d, h, w, pa=pa, seg=seg):
            rel = (d - pa[0], h - pa[1], w - pa[2])
            t = np.clip(sum(r * s for r, s in zip(rel, seg, strict=True)) / (seg @ seg), 0, 1)
            dist2 = sum((r - t * s) ** 2 for r, s in zip(rel, seg, strict=True))
            return bump(dist2, bond_r, BUCKY_VALUES["bond"])

        _splat(out, coords, np.minimum(pa, pb) - bond_r, np.maximum(pa, pb) + bond_r, bond)
    for c in centres:
        def ball(d, h, w, c=c):
            return bump((d - c[0]) ** 2 + (h - c[1]) ** 2 + (w - c[2]) ** 2, ball_r,
                        BUCKY_VALUES["ball"])

        _splat(out, coords, c - ball_r, c + ball_r, ball)
    return out


def _noise(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    from skimage.filters import gaussian

    field = np.random.default_rng(seed).standard_normal(shape)
    sigma = tuple(max(1.0, n / 16.0) for n in shape)
    smooth = gaussian(field, sigma=sigma, mode="reflect", preserve_range=True)
    lo, hi = smooth.min(), smooth.max()
    if hi <= lo:
        return np.zeros(shape, dtype=np.float64)
    return (smooth - lo) / (hi - lo)


_PHANTOMS: dict[str, Callable[[tuple[int, int, int], int], np.ndarray]] = {
    "shells": _shells,
    "corner": _corner,
    "orange": _orange,
    "bucky": _bucky,
    "noise": _noise,
}

PHANTOMS: tuple[str, ...] = tuple(_PHANTOMS)
"""Names accepted by :func:`phantom`."""


def _shape(shape: Any, where: str) -> tuple[int, int, int]:
    def ok(v: Any) -> bool:
        return isinstance(v, int | np.integer) and not isinstance(v, bool) and v > 0

    if ok(shape):
        return (int(shape),) * 3
    if isinstance(shape, tuple | list) and len(shape) == 3 and all(ok(v) for v in shape):
        return tuple(int(v) for v in shape)  # type: ignore[return-value]
    raise ValueError(f"{where}: `shape` must be a positive int (a cube) or 3 positive ints "
                     f"(D, H, W), got {shape!r}; e.g. `shape=64` or `shape=(64, 64, 32)`.")


def phantom(name: str, *, shape: int | tuple[int, int, int] = (64, 64, 64),
            seed: int = 0) -> Float[Array, "D H W"]:
    r"""An analytic test volume, ``float32`` with values in ``[0, 1]``.

    The phantoms (geometry in normalised coordinates, each axis spanning ``[-1, 1]``,
    so they scale with ``shape``; ``r`` is the normalised distance from the centre):

    * ``"shells"``: three concentric spherical shells of rising density, empty space
      between them: outer $0.76 < r \le 0.92$ at 0.3, middle $0.46 < r \le 0.62$ at
      0.6, inner $0.16 < r \le 0.32$ at 1.0 (:data:`SHELL_VALUES`; each shell is at
      least one voxel thick, so at very small shapes the shells grow inwards). The
      layered case in which classic ambient occlusion over-darkens inner layers
      (Ancel et al. 2010, section 4).
    * ``"corner"``: the colour-bleeding case of Ruiz et al. (2008, section 3.2,
      Figure 4, which uses $128^3$; pass ``shape=128`` for it): the three walls at
      the low-index faces, each ``max(2, n // 16)`` voxels thick, are opaque: the
      floor (low ``d``) 1.0 ("white"), the wall at low ``h`` 0.5 ("green", at the
      left as the camera of ``Camera.orbit`` sees the open corner, as in the figure),
      the wall at low ``w`` 0.75 ("blue"), the maximum where walls meet, 0 elsewhere
      (:data:`CORNER_VALUES`).
    * ``"orange"``: a layered sphere after the orange of Ancel et al. (2010, Table 1):
      peel ($0.85 < r \le 0.95$, 1.0), pith under it ($0.78 < r \le 0.85$, 0.7) and
      flesh ($r \le 0.78$, 0.4) cut into 10 wedge-shaped segments around the ``d``
      axis (segment 0 centred on the ``+w`` axis) by membranes of pith (0.7), at least
      1.5 voxels thick so that they always separate the segments, around a central
      column of pith of radius ``max(0.08, 1 voxel)`` (:data:`ORANGE_VALUES`).
    * ``"bucky"``: a buckyball: 60 balls on the vertices of a truncated icosahedron
      (the C60 fullerene layout; circumsphere radius 0.72, ball radius
      ``max(0.1, 1.5 voxels)``) with the 90 bonds between neighbours as thinner rods
      (radius ``max(0.045, 1 voxel)``); resolved from about $32^3$. Each has the smooth
      profile
      $v_\text{peak} (1 - (\delta / R)^2)^2$ for distance $\delta < R$, peak 1.0 for
      balls and 0.5 for bonds, combined by maximum (:data:`BUCKY_VALUES`).
    * ``"noise"``: white Gaussian noise from ``numpy.random.default_rng(seed)``,
      smoothed by a Gaussian of standard deviation ``max(1, n / 16)`` voxels per axis
      (``skimage.filters.gaussian``, reflecting borders) and rescaled to span exactly
      ``[0, 1]``.

    Only ``"noise"`` depends on ``seed``; the others are deterministic geometry.

    Args:
        name: one of :data:`PHANTOMS`.
        shape: ``(D, H, W)`` in voxels, or one int for a cube. Default ``(64, 64, 64)``.
        seed: random seed (``"noise"`` only).

    Returns:
        ``(D, H, W)`` ``float32`` ``jax.Array`` in ``[0, 1]`` (float32 even under x64).

    Raises:
        ValueError: unknown ``name`` (the message lists the valid names), or ``shape``
            not a positive int or 3 positive ints, or a negative ``seed``.
        TypeError: ``seed`` is not an int.

    References:
        Ancel, Dischler, Mongenet: Feature-Driven Ambient Occlusion for Direct Volume
        Rendering, IEEE/EG Volume Graphics 2010.
        Ruiz, Boada, Viola, Bruckner, Feixas, Sbert: Obscurance-based Volume Rendering
        Framework, IEEE/EG Volume and Point-Based Graphics 2008.

    Example:
        >>> vol = phantom("corner", shape=32)
        >>> float(vol[0, 16, 16]), float(vol[16, 0, 16]), float(vol[16, 16, 0])
        (1.0, 0.5, 0.75)
    """
    where = "volshade.data.phantom"
    builder = _checks.option(name, _PHANTOMS, "phantom name", where)
    shape = _shape(shape, where)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise TypeError(f"{where}: `seed` must be an int, got {seed!r}.")
    if seed < 0:
        raise ValueError(f"{where}: `seed` must be >= 0 (NumPy's random seeds), got {seed}.")
    vol = np.clip(builder(shape, int(seed)), 0.0, 1.0).astype(np.float32)
    return jnp.asarray(vol, dtype=jnp.float32)


# ----------------------------------------------------------------------------------------------
# NIfTI loading
# ----------------------------------------------------------------------------------------------


def _downsample(vol: np.ndarray, factor: int) -> np.ndarray:
    """Means of ``factor^3`` blocks. A partial block at a far face is the mean of the
    voxels it holds: ``downscale_local_mean`` pads it with zeros, which would darken
    that layer wherever tissue or a non-zero background reaches the face."""
    if factor == 1:
        return vol
    from skimage.transform import downscale_local_mean

    means = downscale_local_mean(vol, (factor,) * 3)
    held = [np.minimum(factor, n - factor * np.arange(m)) / factor
            for n, m in zip(vol.shape, means.shape, strict=True)]
    return means / (held[0][:, None, None] * held[1][None, :, None] * held[2][None, None, :])


def load_nifti(path: str | os.PathLike, *, normalize: bool = True,
               downsample: int = 1) -> tuple[Float[Array, "D H W"], Spacing]:
    r"""Read a NIfTI-1/2 volume as a ``(D, H, W)`` ``float32`` array and its voxel spacing.

    The image is first reoriented to the closest canonical RAS+ orientation
    (``nibabel.as_closest_canonical``); its ``(x, y, z)`` array is then transposed to
    ``(z, y, x)`` so that ``d`` runs inferior -> superior, ``h`` posterior ->
    anterior and ``w`` left -> right, and the spacing (the voxel sizes of the
    reoriented affine, ``nibabel.affines.voxel_sizes``; the header's pixdim can
    disagree with the affine) is reversed into the same ``(d, h, w)`` order.
    Intensities include the header's ``scl_slope``/``scl_inter`` scaling. With
    ``normalize=True`` (the default, since transfer functions work on ``[0, 1]``)
    they are mapped linearly,
    $v' = (v - v_\min) / (v_\max - v_\min)$, to ``[0, 1]`` (a constant image gives
    zeros); with ``normalize=False`` the raw intensities are returned, as ``float32``
    (integers above $2^{24}$ are rounded).

    Args:
        path: the ``.nii`` or ``.nii.gz`` file.
        normalize: map ``min..max`` of the full-resolution image to ``[0, 1]``
            (default ``True``).
        downsample: integer factor ``f >= 1``: average ``f^3`` blocks of voxels
            (``skimage.transform.downscale_local_mean``, applied after normalising,
            so a tissue keeps its value at every factor and a transfer function
            fits them all, while the block means' range can end below 1;
            a partial block at the far faces averages the voxels it holds), giving
            shape ``ceil(n / f)`` per axis and spacing multiplied by ``f``.

    Returns:
        ``(volume, spacing)``: a ``(D, H, W)`` ``float32`` ``jax.Array``, and
        ``(sd, sh, sw)`` voxel sizes in mm as Python floats.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        IsADirectoryError: ``path`` is a folder.
        ImportError: nibabel is not installed (``pip install "volshade[data]"``).
        ValueError: the file is not an image nibabel can read (or is cut short), its
            voxels are not real numbers, the image is not 3-D
            (a 4-D image is accepted when its 4th dimension is 1), contains NaN or
            inf, or (with ``normalize=False``) intensities beyond float32's range, or
            ``downsample`` < 1.
        TypeError: ``normalize`` not ``True`` or ``False``.

    Example:
        >>> vol, spacing = load_nifti("colin27_ch2_t1_head.nii.gz")  # doctest: +SKIP
        >>> vol.shape, spacing  # doctest: +SKIP
        ((181, 217, 181), (1.0, 1.0, 1.0))
    """
    where = "volshade.data.load_nifti"
    factor = _checks.positive_int(downsample, "downsample", where)
    normalize = _checks.flag(normalize, "normalize", where)
    try:
        path = pathlib.Path(os.fspath(path)).expanduser()
    except TypeError as err:
        raise TypeError(f"{where}: `path` must be a file path (str or os.PathLike), got "
                        f"{path!r:.80}.") from err
    if path.is_dir():
        raise IsADirectoryError(f"{where}: `path` is a folder, not a NIfTI file: "
                                f"{str(path)!r}.")
    if not path.is_file():
        raise FileNotFoundError(f"{where}: no such file: {str(path)!r}.")
    try:
        import nibabel
    except ImportError as err:
        raise ImportError(f'{where} needs nibabel; install it with `pip install "volshade[data]"` '
                          f"(or `pip install nibabel`).") from err
    try:
        img = nibabel.as_closest_canonical(nibabel.load(str(path)))
    except nibabel.filebasedimages.ImageFileError as err:
        raise ValueError(f"{where}: {str(path)!r} is not an image nibabel can read (NIfTI "
                         f"'.nii' or '.nii.gz'): {err}") from err
    shape = img.shape
    if len(shape) < 3 or any(n != 1 for n in shape[3:]):
        raise ValueError(f"{where}: {str(path)!r} has shape {shape}; only 3-D volumes (or 4-D "
                         f"with a single volume) are supported; split the series first "
                         f"(e.g. `nibabel.four_to_three`).")
    if 0 in shape[:3]:
        raise ValueError(f"{where}: {str(path)!r} has shape {shape}: no voxels to render.")
    if not np.issubdtype(img.get_data_dtype(), np.number) or \
            np.issubdtype(img.get_data_dtype(), np.complexfloating):
        # get_fdata would keep only the real part of complex voxels, with a mere warning
        raise ValueError(f"{where}: {str(path)!r} holds {img.get_data_dtype()} voxels; only "
                         f"real intensities can be rendered (take e.g. the magnitude first).")
    try:
        data = np.asarray(img.get_fdata(dtype=np.float64))
    except (OSError, EOFError) as err:  # the header read, the voxels are cut short
        raise ValueError(f"{where}: {str(path)!r} could not be read whole (a truncated or "
                         f"damaged file?): {err}") from err
    data = data.reshape(shape[:3])
    n_bad = int(np.size(data) - np.count_nonzero(np.isfinite(data)))
    if n_bad:
        raise ValueError(f"{where}: {str(path)!r} has {n_bad} NaN or inf voxels; clean them "
                         f"(e.g. `np.nan_to_num`) and save the image again.")
    vol = np.ascontiguousarray(np.transpose(data, (2, 1, 0)))
    # from the affine actually used: pixdim may disagree with it, and nibabel rewrites
    # it only when it reorients, so it would depend on the file's storage order
    zooms = tuple(float(z) for z in nibabel.affines.voxel_sizes(img.affine))
    spacing = (zooms[2], zooms[1], zooms[0])
    if normalize:
        # in halves: hi - lo of +-1.7e308 would overflow (halving is exact)
        lo, hi = vol.min() / 2, vol.max() / 2
        vol = (vol / 2 - lo) / (hi - lo) if hi > lo else np.zeros_like(vol)
    vol = _downsample(vol, factor)
    if normalize:
        vol = np.clip(vol, 0.0, 1.0)  # only float rounding of block means can leave [0, 1]
    spacing = tuple(s * factor for s in spacing)
    # finite in float64, but the cast would make it inf
    if vol.size and np.max(np.abs(vol)) > np.finfo(np.float32).max:
        raise ValueError(f"{where}: {str(path)!r} has intensities beyond float32's range "
                         f"(+-3.4e38); load it with normalize=True, or rescale it.")
    return jnp.asarray(vol.astype(np.float32), dtype=jnp.float32), spacing  # type: ignore


# ----------------------------------------------------------------------------------------------
# Real data lookup
# ----------------------------------------------------------------------------------------------

_FILES: dict[str, str] = {
    "colin27": "colin27_ch2_t1_head.nii.gz",
    "mni152": "mni152_2009a_t1_brain.nii.gz",
    "mni152_gm": "mni152_2009a_gm.nii.gz",
    "mni152_wm": "mni152_2009a_wm.nii.gz",
}

DATASETS: tuple[str, ...] = tuple(_FILES)
"""Names accepted by :func:`load` and :func:`data_path`."""

_DEBIAN_CH2 = pathlib.Path("/usr/share/mricron/templates/ch2.nii.gz")
_FALLBACKS: dict[str, Callable[[], pathlib.Path]] = {"colin27": lambda: _DEBIAN_CH2}

_HOW_TO_GET = """\
To get the files, put them in one folder and set VOLSHADE_DATA to it
(`export VOLSHADE_DATA=/path/to/data`; several folders may be joined with '{sep}'):
  * colin27_ch2_t1_head.nii.gz: Colin27 T1 head, Debian package `mricron-data`
    (`sudo apt-get install mricron-data` installs it as {ch2}, which is found
    without VOLSHADE_DATA; or `apt-get download mricron-data` and extract
    ./usr/share/mricron/templates/ch2.nii.gz with `dpkg-deb --fsys-tarfile`).
  * mni152_2009a_{{t1_brain,gm,wm}}.nii.gz: MNI152 ICBM 2009a templates in the PyPI
    wheel nilearn==0.14.1 (`pip download --no-deps nilearn==0.14.1`, then
    `unzip -p nilearn-0.14.1-py3-none-any.whl
    nilearn/datasets/data/mni_icbm152_{{t1_tal_nlin_sym_09a_converted,gm_tal_nlin_sym_09a_converted,wm_tal_nlin_sym_09a_converted}}.nii.gz`
    into the matching file name)."""


def _search_dirs() -> list[pathlib.Path]:
    env = os.environ.get("VOLSHADE_DATA", "")
    return [pathlib.Path(p).expanduser() for p in env.split(os.pathsep) if p]


def data_path(name: str) -> pathlib.Path:
    """Where the real volume ``name`` is on this machine.

    Searches, in order: ``$VOLSHADE_DATA/<file>`` (``VOLSHADE_DATA`` may list several
    folders separated by ``os.pathsep``), then, for ``"colin27"`` only, Debian's
    ``/usr/share/mricron/templates/ch2.nii.gz`` (package ``mricron-data``). File
    names: ``colin27_ch2_t1_head.nii.gz``, ``mni152_2009a_t1_brain.nii.gz``,
    ``mni152_2009a_gm.nii.gz``, ``mni152_2009a_wm.nii.gz``.

    Args:
        name: one of :data:`DATASETS`: ``"colin27"`` (Colin27 whole-head T1 MRI,
            181x217x181 at 1 mm), ``"mni152"`` (MNI152 2009a T1, brain only,
            197x233x189 at 1 mm), ``"mni152_gm"`` / ``"mni152_wm"`` (its grey/white
            matter probability maps).

    Returns:
        The path of an existing file.

    Raises:
        ValueError: unknown ``name`` (the message lists the valid names).
        FileNotFoundError: the file is in none of the places searched; the message
            lists them and says how to get the data.

    Example:
        >>> data_path("colin27").name  # doctest: +SKIP
        'colin27_ch2_t1_head.nii.gz'
    """
    where = "volshade.data.data_path"
    filename = _checks.option(name, _FILES, "dataset name", where)
    candidates = [folder / filename for folder in _search_dirs()]
    if name in _FALLBACKS:
        candidates.append(_FALLBACKS[name]())
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    searched = "\n".join(f"  {c}" for c in candidates) or "  (nothing: VOLSHADE_DATA is not set)"
    env = os.environ.get("VOLSHADE_DATA")
    env_note = f"VOLSHADE_DATA={env!r}" if env is not None else "VOLSHADE_DATA is not set"
    raise FileNotFoundError(
        f"{where}: dataset {name!r} ({filename}) not found ({env_note}). Searched:\n{searched}\n"
        + _HOW_TO_GET.format(sep=os.pathsep, ch2=_DEBIAN_CH2))


def load(name: str, *, downsample: int = 1,
         normalize: bool = True) -> tuple[Float[Array, "D H W"], Spacing]:
    """Load a real volume by name: find it with :func:`data_path`, read it with :func:`load_nifti`.

    Args:
        name: one of :data:`DATASETS` (``"colin27"``, ``"mni152"``, ``"mni152_gm"``,
            ``"mni152_wm"``).
        downsample: integer factor: block-mean over ``f^3`` voxels (for smaller heads
            in demos and tests); the spacing grows by ``f``.
        normalize: map the intensities ``min..max`` to ``[0, 1]`` (default ``True``),
            before the block mean (:func:`load_nifti`): downsampled, the range can end
            below 1 (Colin27 at ``downsample=3``: 0.94).

    Returns:
        ``(volume, spacing)``: ``(D, H, W)`` ``float32`` ``jax.Array`` in axis order
        ``(z, y, x)`` of the RAS+ image (``d`` inferior -> superior), and the voxel
        size ``(sd, sh, sw)`` in mm. Colin27 is ``(181, 217, 181)`` at 1 mm; the
        MNI152 volumes are ``(189, 233, 197)`` at 1 mm.

    Raises:
        ValueError: unknown ``name`` (a file path is for :func:`load_nifti`), or
            ``downsample`` < 1.
        TypeError: ``normalize`` not ``True`` or ``False``.
        FileNotFoundError: the data is not on this machine; the message says how to
            get it (set ``VOLSHADE_DATA``, ``apt-get install mricron-data``, or the
            nilearn 0.14.1 wheel).
        ImportError: nibabel is missing (``pip install "volshade[data]"``).

    Example:
        >>> head, spacing = load("colin27", downsample=2)  # doctest: +SKIP
        >>> head.shape, spacing  # doctest: +SKIP
        ((91, 109, 91), (2.0, 2.0, 2.0))
    """
    where = "volshade.data.load"
    if isinstance(name, str | os.PathLike) and name not in _FILES and (
            os.fspath(name).endswith((".nii", ".nii.gz")) or os.path.exists(name)):
        raise ValueError(f"{where}: {os.fspath(name)!r} names a file, not a dataset; "
                         f"read a NIfTI file with volshade.data.load_nifti(path), or name "
                         f"one of {', '.join(map(repr, _FILES))}.")
    _checks.option(name, _FILES, "dataset name", where)
    _checks.positive_int(downsample, "downsample", where)
    _checks.flag(normalize, "normalize", where)
    return load_nifti(data_path(name), normalize=normalize, downsample=downsample)
