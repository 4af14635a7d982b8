r"""Gradient estimation by 4D linear regression (Neumann, Csébfalvi, König, Gröller 2000).

Around each voxel the values of a cubic neighbourhood ($3^3$ or $5^3$) are fitted
with a linear function $f(\mathbf{x}) \approx \mathbf{g}\cdot\mathbf{x} + b$ in the
weighted least-squares sense. Because the neighbourhood and the weights are
symmetric, the normal equations decouple and each gradient component is one fixed
convolution:

$$ g_i = \frac{\sum_k w(k)\, f(k)\, x_i(k)}{\sum_k w(k)\, x_i(k)^2} $$

with $x_i(k)$ the $i$-th component (in mm) of the vector from the centre voxel to
neighbour $k$. The obscurance paper (Ruiz et al. 2008, eq. 4) uses the same sums
with the unnormalised weights $w(k) = |\mathbf{x}(k)|$ on a $5^3$ cube; the
normalisation above only rescales each component and makes the estimate exact
for linear fields, whatever the weights. Volumes are extended by edge
replication at the border, so within ``size // 2`` voxels of it a linear field's
gradient comes out smaller (the outermost layer of a $5^3$ fit gets half of it).
The sums are taken over central differences $f(\mathbf{x} + k) - f(\mathbf{x} - k)$,
so a constant neighbourhood gives an exactly zero gradient.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, _numerics
from ._types import Array, ArrayLike, Float

__all__ = ["regression_kernel", "regression_gradient", "gradient_magnitude"]

_WEIGHTS = {
    "distance": lambda r: r,
    "inverse_distance": lambda r: np.divide(1.0, r, out=np.zeros_like(r), where=r > 0),
    "uniform": lambda r: np.ones_like(r),
}


def _check_size(size, where: str) -> None:
    """The regression neighbourhood edge: the int 3 or 5 (static: it sets the kernel)."""
    if isinstance(size, jax.core.Tracer):
        raise TypeError(f"{where}: `size` sets the kernel and must be a static int (3 or 5), "
                        f"not a traced value; close over it instead.")
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size not in (3, 5):
        got = (f"a {size.dtype} array; pass the Python int {int(size)}"
               if isinstance(size, np.ndarray | jax.Array) and size.ndim == 0
               and float(size) in (3.0, 5.0) else repr(size))
        raise ValueError(f"{where}: `size` must be the int 3 or 5 (neighbourhood edge), "
                         f"got {got}.")


def regression_kernel(
    size: int = 5, *, spacing=(1.0, 1.0, 1.0), weighting: str = "distance"
) -> np.ndarray:
    """The ``(3, size, size, size)`` convolution kernels of the regression gradient.

    Args:
        size: neighbourhood edge, 3 or 5 voxels.
        spacing: voxel size ``(sd, sh, sw)`` in mm.
        weighting: ``"distance"`` (w = |x|, the seeds' choice), ``"inverse_distance"``
            (w = 1/|x|, Neumann et al.'s) or ``"uniform"``.
    """
    return _kernel(size, spacing, weighting, "volshade.gradient.regression_kernel")


def _kernel(size, spacing, weighting: str, where: str) -> np.ndarray:
    """:func:`regression_kernel`, its errors naming ``where``."""
    _check_size(size, where)
    weight_fn = _checks.option(weighting, _WEIGHTS, "weighting", where)
    sp = np.asarray(_checks.spacing(spacing, where))
    # in units of the largest spacing, then divided by it: every weighting is
    # homogeneous, so the kernel scales as 1 / spacing, while sum(w x^2), which grows as
    # spacing^3, would underflow or overflow for extreme spacings (0 / 0 or inf / inf)
    unit = sp.max()
    half = size // 2
    grid = np.stack(np.meshgrid(*[np.arange(-half, half + 1)] * 3, indexing="ij"), axis=-1)
    offsets = grid * (sp / unit)
    weights = weight_fn(np.linalg.norm(offsets, axis=-1))
    kernels = []
    for i in range(3):
        numer = weights * offsets[..., i]
        kernels.append(numer / np.sum(numer * offsets[..., i]) / unit)
    return np.stack(kernels)


def regression_gradient(
    volume: Float[Array, "D H W"],
    *,
    spacing=(1.0, 1.0, 1.0),
    size: int = 5,
    weighting: str = "distance",
) -> Float[Array, "D H W 3"]:
    r"""Gradient of a scalar volume by 4D linear regression.

    Args:
        volume: ``(D, H, W)`` scalar field.
        spacing: voxel size ``(sd, sh, sw)`` in mm (scalar for isotropic).
        size: neighbourhood edge, 3 or 5 voxels (5 is the obscurance paper's choice).
        weighting: see :func:`regression_kernel`.

    Returns:
        ``(D, H, W, 3)`` gradient $(\partial_d, \partial_h, \partial_w)$ in value
        units per mm, in the dtype of ``volume``.

    Raises:
        ValueError: ``volume`` not 3-D or not finite, ``size`` not 3 or 5, a bad
            ``spacing`` or an unknown ``weighting``.
        TypeError: ``volume`` not numbers (a string, a complex dtype).

    References:
        Neumann, Csébfalvi, König, Gröller: Gradient estimation in volume data using
        4D linear regression. Computer Graphics Forum 19(3), 2000.

    Example:
        >>> d = jnp.arange(8.0)[:, None, None] * jnp.ones((8, 8, 8))
        >>> g = regression_gradient(d)
        >>> [round(float(c), 4) + 0.0 for c in g[4, 4, 4]]  # + 0.0: no -0.0 from rounding
        [1.0, 0.0, 0.0]
    """
    where = "volshade.regression_gradient"
    volume = _checks.volume(volume, "volume", where)
    _kernel(size, spacing, weighting, where)  # its checks, at once
    return _regression_gradient(volume, size, _checks.spacing(spacing, where), weighting)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _regression_gradient(volume: Array, size: int, spacing: tuple[float, float, float],
                         weighting: str) -> Array:
    """:func:`regression_gradient` after its checks: one compiled program per shape and
    setting (eagerly, each of its hundreds of shifted differences would be dispatched
    on its own)."""
    kernel = regression_kernel(size, spacing=spacing, weighting=weighting)
    half = size // 2
    shape = volume.shape

    def gradient(volume):
        padded = _numerics.edge_pad(volume, [(half, half)] * 3)

        def shifted(k):
            return padded[tuple(slice(half + k[ax], half + k[ax] + shape[ax])
                                for ax in range(3))]

        # The kernels are odd (K_i(-k) = -K_i(k)), so each pair {k, -k} contributes
        # K_i(k) (f(x + k) - f(x - k)): exactly 0 wherever the neighbourhood is constant.
        # A convolution's rounding leaves noise there instead, which normalising turns
        # into random unit normals with huge derivatives. Each difference is taken once.
        components = [None, None, None]
        for index in np.ndindex(*kernel.shape[1:]):
            k = tuple(int(c) - half for c in index)
            if k <= (0, 0, 0):  # one offset of each pair (lexicographically positive)
                continue
            diff = shifted(k) - shifted(tuple(-c for c in k))
            for i in range(3):
                weight = float(kernel[(i, *index)])
                if weight != 0:
                    term = weight * diff
                    components[i] = term if components[i] is None else components[i] + term
        return jnp.stack(components, axis=-1)

    # A volume in tiny or huge units (a peak beyond 2^(+-b), b = maxexp / 2; float32:
    # above 1.8e19 or below 5.4e-20) is scaled by 2^(-+b/2), and the gradient back:
    # exact wherever the scaled values stay normal numbers, while the weighted
    # differences no longer fall to subnormals (flushed to 0 on a CPU; float32: a
    # volume below about 1e-33) or overflow (float32: above 1.7e38). A volume inside
    # that range is not scaled, and one outside it is scaled by that fixed factor, not
    # to unit size, so that values far below the peak keep their bits.
    # The operator is linear, so its derivative is the unscaled one (a cotangent scaled
    # by the factor and back could overflow); a rule, not value_and_tangent, so that a
    # forward pass traces the operator once.
    @jax.custom_jvp
    def scaled_gradient(volume):
        peak = jnp.max(jnp.abs(volume))
        bound = jnp.finfo(volume.dtype).maxexp // 2
        edge, factor = 2.0**bound, 2.0 ** (bound // 2)
        huge, tiny = peak > edge, (peak > 0) & (peak < 1 / edge)
        down = jnp.where(huge, 1 / factor, jnp.where(tiny, factor, 1)).astype(volume.dtype)
        up = jnp.where(huge, factor, jnp.where(tiny, 1 / factor, 1)).astype(volume.dtype)
        return gradient(volume * down) * up

    scaled_gradient.defjvp(lambda primals, tangents: (scaled_gradient(*primals),
                                                      gradient(*tangents)))
    # half precision is summed in float32: 62 weighted differences of bfloat16 values
    # were off by up to 1.9 % (float32 rounded back to bfloat16: 0.4 %)
    return scaled_gradient(_checks.at_least_float32(volume)).astype(volume.dtype)


def gradient_magnitude(gradient: Float[ArrayLike, "*batch k"], *, scaled: bool = False
                       ) -> Float[Array, "*batch"]:
    """Euclidean norm over the last axis, with a zero (not NaN) derivative at 0.

    With ``scaled=True`` the magnitudes are divided by their maximum, so they lie in
    [0, 1] (all zeros where the maximum is 0): the $m_G$ of importance-aware
    composition and the voxel saliency of Ruiz et al. (eq. 4) both use this. The
    last axis may hold several stacked gradients (e.g. one per colour channel).
    Components of any finite size are handled (their squares are not formed); subnormal
    ones count as 0 (a CPU flushes them).

    Raises:
        ValueError: ``gradient`` has no axis, no components (a last axis of size 0), or
            no element with ``scaled=True`` (no maximum); NaN or inf in it (at run time
            when traced).
        TypeError: ``scaled`` is not a bool, ``gradient`` not numeric.
    """
    where = "volshade.gradient.gradient_magnitude"
    scaled = _checks.flag(scaled, "scaled", where)
    gradient = _checks.as_float_array(gradient, "gradient", where)
    if gradient.ndim == 0:
        raise ValueError(f"{where}: `gradient` must have at least one axis (the vector "
                         f"components are the last one), got a scalar.")
    if gradient.shape[-1] == 0:
        raise ValueError(f"{where}: `gradient` has shape {gradient.shape}: its last axis "
                         f"holds the vector components, and there are none.")
    if scaled and gradient.size == 0:
        raise ValueError(f"{where}: `gradient` is empty, shape {gradient.shape}: "
                         f"`scaled=True` divides by the largest magnitude, and there is none.")
    return _magnitude(_checks.finite(gradient, "gradient", where), scaled=scaled)


def _magnitude(gradient: Array, *, scaled: bool) -> Array:
    """:func:`gradient_magnitude` without its checks, for callers that checked the field."""
    if scaled:
        # the field divided by its largest component first, so that neither the
        # magnitudes nor the quotient's derivative (m / M^2) leave the float range; the
        # scaled magnitude does not depend on that factor, which is held constant
        gradient = _numerics.scaled_down(gradient, _divisor(jnp.max(jnp.abs(gradient))))
    result = _norm(gradient)
    return _numerics.safe_div(result, jnp.max(result)) if scaled else result


def _over_peak(g: Array) -> tuple[Array, Array]:
    """``(g / p, p)``, ``p`` the largest |component| over the last axis (1 for a zero
    vector): the squares of ``g``'s large components would overflow (float32: above
    1e19) and those of its small ones underflow."""
    peak = _divisor(jnp.max(jnp.abs(g), axis=-1, keepdims=True))
    return _numerics.scaled_down(g, peak), peak


@jax.custom_jvp
def _norm(g: Array) -> Array:
    """``|g|`` over the last axis, as ``p |g / p|`` (:func:`_over_peak`); its tangent is
    ``u . dg`` with ``u = g / |g|`` (0 at the zero vector), as the rule of
    ``p |g / p|`` would scale a cotangent by ``p`` first, which overflows where the
    result does not."""
    scaled, peak = _over_peak(g)
    return peak[..., 0] * _numerics.safe_norm(scaled, axis=-1)


@_norm.defjvp
def _norm_jvp(primals, tangents):
    (g,), (dg,) = primals, tangents
    scaled, _ = _over_peak(g)
    return _norm(g), jnp.sum(_numerics.safe_normalize(scaled) * dg, axis=-1)


def _divisor(x: Array) -> Array:
    """``x`` where it is a finite number > 0, else 1 (a zero field stays 0, an infinite
    component keeps an infinite norm instead of giving inf / inf)."""
    return jnp.where((x > 0) & jnp.isfinite(x), x, jnp.ones_like(x))
