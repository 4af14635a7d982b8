r"""Front-to-back compositing of samples along rays: standard and importance-aware.

A compositor is three pure functions, so that the renderer and
:func:`composite` share one step and any batch of rays can be carried at once
(every array below has the batch shape ``(...)`` of the rays in front):

* ``init(batch_shape, dtype) -> state``
* ``step(state, sample) -> state`` for one sample per ray (the body of a
  ``lax.scan`` over the samples),
* ``finish(state, background_rgb, background_importance) -> rgba``.

They are registered by name in :data:`COMPOSITORS` (``"standard"``,
``"importance"``).

Colours are *opacity-weighted* (premultiplied): a sample of colour $c_s$ and
opacity $\alpha_s$ arrives as $C_s = \alpha_s c_s$. Standard emission--absorption
compositing front to back (Pinto & Freitas 2010, eq. 1) is

$$ C_{i+1} = C_i + T_i\, C_s, \qquad T_{i+1} = T_i (1 - \alpha_s), $$

with accumulated opacity $\alpha_i = 1 - T_i$; the background is blended under
what remains, $C = C_n + T_n\, c_{bg}$.

Importance-aware compositing (eq. 8) lets a sample's importance $I_s$ scale the
accumulated colour and opacity down just enough for the sample to be seen; see
:func:`importance_step` for the exact, numerically safe form used here.

References:
    F. de Moura Pinto and C. M. D. S. Freitas, "Importance-aware composition for
    illustrative volume rendering", SIBGRAPI 2010.
"""

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _checks
from ._numerics import tiny
from ._types import Array, ArrayLike, Float


class Sample(NamedTuple):
    """One sample per ray: premultiplied colour ``(..., 3)``, opacity ``(...)`` in
    [0, 1] and importance ``(...)`` (ignored by standard compositing)."""

    color: Array
    alpha: Array
    importance: Array | None = None


def _expand(x: Array) -> Array:
    """``(...)`` -> ``(..., 1)`` so it multiplies ``(..., 3)`` colours without rank promotion."""
    return x[..., None]


def _background(background: ArrayLike, batch_shape: tuple[int, ...], dtype) -> Array:
    """Background colour ``(3,)`` or ``(..., 3)`` broadcast explicitly to ``(..., 3)``."""
    bg = jnp.asarray(background, dtype)
    return jnp.broadcast_to(bg[..., :3], (*batch_shape, 3))


# --------------------------------------------------------------------------- standard


class StandardState(NamedTuple):
    """Accumulated premultiplied colour ``(..., 3)`` and transmittance ``(...)``."""

    color: Array
    transmittance: Array


def standard_init(batch_shape: tuple[int, ...], dtype) -> StandardState:
    """Empty rays: no colour, transmittance 1."""
    return StandardState(jnp.zeros((*batch_shape, 3), dtype), jnp.ones(batch_shape, dtype))


def standard_step(state: StandardState, sample: Sample) -> StandardState:
    """One front-to-back step (eq. 1); exact at alpha = 0 and 1, no division anywhere."""
    color = state.color + _expand(state.transmittance) * sample.color
    return StandardState(color, state.transmittance * (1 - sample.alpha))


def standard_finish(
    state: StandardState, background: ArrayLike, background_importance: ArrayLike | None = None
) -> Float[Array, "*batch 4"]:
    """Blend the background colour under the remaining transmittance.

    Returns RGBA with alpha $= 1 - T_n$; ``background_importance`` is accepted for a
    uniform compositor interface and ignored.
    """
    del background_importance
    t = state.transmittance
    rgb = state.color + _expand(t) * _background(background, t.shape, t.dtype)
    return jnp.concatenate([rgb, _expand(1 - t)], axis=-1)


# --------------------------------------------------------------------------- importance


class ImportanceState(NamedTuple):
    r"""State of importance-aware compositing, per ray.

    The paper's accumulated importance $I_i$ (eq. 8e) enters every formula
    through the opacity-normalised importance $K_i = I_i - \ln\alpha_i$; it is
    carried as $K_i = P_i + \delta_i$, with $P_i$ the largest importance of a
    sample so far (an input value, exact) and the offset $\delta_i \le 0$, so
    that importance gaps are differences of input values and small offsets:
    float32 stays accurate even for importances around $10^4$.

    Attributes:
        color: ``(..., 3)`` accumulated colour *divided by the accumulated opacity*,
            $\bar c_i = C_i / \alpha_i$ (0 on an empty ray). It stays within the
            range of the sample colours, so no rescaling can overflow.
        transmittance: ``(...)`` $T_i = 1 - \alpha_i$, updated exactly as in
            standard compositing (eq. 8c).
        peak_importance: ``(...)`` $P_i$, the largest importance of a sample with
            $\alpha_s > 0$ so far (0 on an empty ray, unused there).
        importance_offset: ``(...)`` $\delta_i = K_i - P_i \le 0$.
    """

    color: Array
    transmittance: Array
    peak_importance: Array
    importance_offset: Array

    @property
    def opacity(self) -> Array:
        r"""Accumulated opacity $\alpha_i = 1 - T_i$ (eq. 8c), ``(...)``."""
        return 1 - self.transmittance

    @property
    def premultiplied_color(self) -> Array:
        r"""Accumulated opacity-weighted colour $C_i = \alpha_i \bar c_i$, ``(..., 3)``."""
        return _expand(self.opacity) * self.color

    @property
    def accumulated_importance(self) -> Array:
        r"""The paper's accumulated importance $I_i = K_i + \ln\alpha_i$ ($-\infty$ if empty)."""
        alpha = self.opacity
        nonempty = alpha > 0
        k = self.peak_importance + self.importance_offset
        return jnp.where(nonempty, k + jnp.log(jnp.where(nonempty, alpha, 1)), -jnp.inf)


def importance_init(batch_shape: tuple[int, ...], dtype) -> ImportanceState:
    """Empty rays: colour 0, transmittance 1, importance state 0 (unused until a sample lands)."""
    zeros = jnp.zeros(batch_shape, dtype)
    return ImportanceState(jnp.zeros((*batch_shape, 3), dtype), jnp.ones(batch_shape, dtype),
                           zeros, zeros)


def _gap(state: ImportanceState, importance: Array, active: Array) -> Array:
    r"""$K_i - I_s = \delta_i + (P_i - I_s)$ where ``active``, else 0 (finite everywhere)."""
    diff = state.peak_importance - jnp.where(active, importance, state.peak_importance)
    return jnp.where(active, state.importance_offset + diff, 0)


def modulation(state: ImportanceState, importance: ArrayLike) -> Array:
    r"""The modulation factor $m_i$ (eq. 2 with eq. 3) for an incoming sample.

    With $vis(I_s, I_i) = 1 - e^{I_i - I_s}$ (eq. 3), the three cases of eq. 2
    collapse to $m_i = \min(1, e^{I_i - I_s} / \alpha_i)$, i.e. in log space

    $$ m_i = \exp\big(\min(0,\; I_i - I_s - \ln\alpha_i)\big)
           = \exp\big(\min(0,\; K_i - I_s)\big), $$

    which never overflows. On an empty ray ($\alpha_i = 0$) $m_i = 1$.

    Args:
        state: the :class:`ImportanceState` before the sample.
        importance: ``(...)`` sample importance $I_s$.

    Returns:
        ``(...)`` modulation factor in [0, 1].
    """
    importance = jnp.asarray(importance, state.transmittance.dtype)
    return jnp.exp(jnp.minimum(_gap(state, importance, state.transmittance < 1), 0))


def importance_step(state: ImportanceState, sample: Sample) -> ImportanceState:
    r"""One step of importance-aware compositing (eq. 8a--8e), numerically safe.

    With $a = m_i\alpha_i$ (eq. 2, see :func:`modulation`) the paper's step is

    $$ C' = m C_i + (1 - a) C_s \;(8a), \quad \alpha' = a(1-\alpha_s) + \alpha_s \;(8b), \quad
       \alpha_{i+1} = \alpha_i(1-\alpha_s) + \alpha_s \;(8c), $$
    $$ C_{i+1} = \alpha_{i+1} C' / \alpha' \;(8d, \text{0 where } \alpha' = 0), \quad
       I_{i+1} = \max\big(I_i,\; \ln(\alpha_s + (1-\alpha_s)e^{I_i - I_s}) + I_s\big) \;(8e). $$

    Dividing 8d by $\alpha_{i+1}$ shows that the *average* colour
    $\bar c = C/\alpha$ is a convex combination,

    $$ \bar c_{i+1} = w\, \bar c_i + (1 - w)\, c_s, \qquad w = a / \alpha',\;
       1 - w = \alpha_s (1 - a) / \alpha', $$

    so the state carries $\bar c$, the exact transmittance $T = 1 - \alpha$
    (eq. 8c is the standard update, bit for bit) and $K = I - \ln\alpha$
    (see :class:`ImportanceState`). In terms of $K$ the modulation is
    $m = e^{\min(0, K_i - I_s)}$ and eq. 8e reads, with $M = \max(K_i, I_s)$,
    $\beta = \alpha_i / \alpha_{i+1}$, $\rho = (1-\alpha_s)\beta$,

    $$ K_{i+1} = M + \ln\max\big(\beta\, e^{K_i - M},\;
                                 (1-\rho)\, e^{I_s - M} + \rho\, e^{K_i - M}\big), $$

    a log-sum-exp whose exponents are $\le 0$ and whose argument lies in
    $[e^{-|K_i - I_s|}, 1]$: no exp overflows for any importance gap and no
    division by zero happens ($\alpha' \ge \alpha_s$, $\alpha_{i+1} \ge \alpha_s$;
    the only zero denominators are on an empty ray meeting a sample with
    $\alpha_s = 0$, where the state is kept). Every guarded operation uses the
    double-``where`` idiom, so gradients are finite at $\alpha_s = 0$ and 1 and
    for importance gaps of $10^4$. A sample with $\alpha_s = 0$ (or below
    $\sqrt{\text{tiny}}$ of the dtype, $10^{-19}$ in float32) changes nothing
    (its colour is not used, as 8a--8d give when $C_s = \alpha_s c_s$), and with
    equal importances everywhere $m = 1$ and the step is standard compositing.
    Only two transcendental functions (one ``exp``, one ``log``) are evaluated.

    Args:
        state: :class:`ImportanceState` of the rays, batch shape ``(...)``.
        sample: :class:`Sample` with premultiplied ``color`` ``(..., 3)``,
            ``alpha`` ``(...)`` in [0, 1] and ``importance`` ``(...)`` (any real).

    Returns:
        The updated :class:`ImportanceState`.

    Raises:
        ValueError: ``sample.importance`` is None.

    References:
        Pinto & Freitas, "Importance-aware composition for illustrative volume
        rendering", SIBGRAPI 2010, sec. III, eq. 2, 3 and 8.

    Example:
        >>> s = importance_init((), jnp.float32)
        >>> s = importance_step(s, Sample(jnp.array([1.0, 0, 0]), jnp.array(1.0), jnp.array(0.0)))
        >>> s = importance_step(s, Sample(jnp.array([0, 0.5, 0]), jnp.array(0.5), jnp.array(5.0)))
    """
    alpha_s, c_s, imp_s = sample.alpha, sample.color, sample.importance
    if imp_s is None:
        raise ValueError("volshade.composition.importance_step: the sample has no `importance`; "
                         "pass Sample(color, alpha, importance).")
    c_acc, t_acc = state.color, state.transmittance
    one = jnp.ones_like(t_acc)
    zero = jnp.zeros_like(t_acc)
    alpha_acc = 1 - t_acc
    nonempty = alpha_acc > 0
    # An empty ray adopts the sample's importance (K is never used there): P = I_s, delta = 0.
    peak = jnp.where(nonempty, state.peak_importance, imp_s)
    offset = jnp.where(nonempty, state.importance_offset, zero)
    to_peak = jnp.where(nonempty, imp_s - peak, zero)   # I_s - P_i (exact input difference)
    gap = offset - to_peak                             # K_i - I_s
    g = jnp.exp(-jnp.abs(gap))                         # e^{-|K_i - I_s|}, in [0, 1]
    ahead = gap >= 0                                   # accumulated importance dominates
    m = jnp.where(ahead, one, g)                       # eq. 2-3: exp(min(0, K_i - I_s))
    # a = m alpha_i and 1 - a = T_i + (1 - m) alpha_i (exact where m = 1).
    a = m * alpha_acc
    one_minus_a = t_acc + (1 - m) * alpha_acc
    alpha_p = a + alpha_s * one_minus_a                # eq. 8b
    t_new = t_acc * (1 - alpha_s)                      # eq. 8c
    alpha_new = 1 - t_new
    # alpha_s = 0 keeps the state exactly. Opacities below sqrt(tiny) (1e-19 in float32),
    # which cannot change T either, count as 0: then 1 / alpha'^2 in the gradient stays finite.
    visible = alpha_s > jnp.sqrt(tiny(alpha_s))
    # eq. 8a/8d as a convex combination of the average colours.
    p_ok = visible & (alpha_p > 0)
    inv_p = 1 / jnp.where(p_ok, alpha_p, one)
    w = jnp.where(p_ok, a * inv_p, one)
    u = jnp.where(p_ok, one_minus_a * inv_p, zero)
    color = _expand(w) * c_acc + _expand(u) * c_s
    # eq. 8e in terms of K = P + delta.
    n_ok = visible & (alpha_new > 0)
    inv_n = 1 / jnp.where(n_ok, alpha_new, one)
    beta = alpha_acc * inv_n
    rho = (1 - alpha_s) * beta
    y = jnp.where(ahead, g, one)                       # e^{I_s - M}; e^{K_i - M} = m
    arg = jnp.maximum(beta * m, alpha_s * inv_n * y + rho * m)
    ok = n_ok & (arg > 0)
    # M - P_{i+1} = delta_i where K_i >= I_s, else min(I_s - P_i, 0)
    base = jnp.where(ahead, offset, jnp.minimum(to_peak, zero))
    new_offset = jnp.where(ok, base + jnp.log(jnp.where(ok, arg, one)), offset)
    new_peak = jnp.where(visible, jnp.maximum(peak, imp_s), peak)
    return ImportanceState(color, t_new, new_peak, jnp.minimum(new_offset, zero))


def importance_finish(
    state: ImportanceState, background: ArrayLike, background_importance: ArrayLike = -jnp.inf
) -> Float[Array, "*batch 4"]:
    r"""Composite the background as a final, fully opaque layer (sec. IV-C).

    The background is one more step of eq. 8 with $\alpha_s = 1$, colour
    $c_{bg}$ and importance $I_{bg}$: with $a = m\,\alpha_n$ (eq. 2),

    $$ \mathrm{rgb} = a\, \bar c_n + (1 - a)\, c_{bg}, \qquad \mathrm{alpha} = a, $$

    i.e. RGBA of the (possibly faded) volume premultiplied over the background.
    A low-importance volume fades to the background as $I_{bg}$ grows;
    $I_{bg} = -\infty$ (the default) never fades it and gives the standard
    $C_n + T_n c_{bg}$ with alpha $= 1 - T_n$ (eq. 8c).

    Args:
        state: :class:`ImportanceState` after the last sample.
        background: ``(3,)`` or ``(..., 3)`` background colour.
        background_importance: scalar or ``(...)`` importance $I_{bg}$ (finite, or
            $-\infty$ for none).

    Returns:
        ``(..., 4)`` RGBA: premultiplied RGB over the background and the volume's
        effective opacity.
    """
    c_acc, t_acc = state.color, state.transmittance
    dtype = t_acc.dtype
    alpha_acc = 1 - t_acc
    i_bg = jnp.broadcast_to(jnp.asarray(background_importance, dtype), t_acc.shape)
    active = (alpha_acc > 0) & (i_bg > -jnp.inf)
    m = jnp.exp(jnp.minimum(_gap(state, i_bg, active), 0))
    a = m * alpha_acc
    one_minus_a = t_acc + (1 - m) * alpha_acc
    rgb = _expand(a) * c_acc + _expand(one_minus_a) * _background(background, t_acc.shape, dtype)
    return jnp.concatenate([rgb, _expand(a)], axis=-1)


# --------------------------------------------------------------------------- registry


class Compositor(NamedTuple):
    """The three functions of a compositor (see the module docstring)."""

    init: Callable[[tuple[int, ...], Any], Any]
    step: Callable[[Any, Sample], Any]
    finish: Callable[..., Array]


COMPOSITORS: dict[str, Compositor] = {
    "standard": Compositor(standard_init, standard_step, standard_finish),
    "importance": Compositor(importance_init, importance_step, importance_finish),
}


def composite(
    colors: Float[ArrayLike, "*batch S 3"],
    alphas: Float[ArrayLike, "*batch S"],
    *,
    importance: Float[ArrayLike, "*batch S"] | None = None,
    background: Float[ArrayLike, "*#batch 3"] | None = None,
    background_importance: Float[ArrayLike, "*#batch"] | None = None,
    unroll: int = 1,
) -> Float[Array, "*batch 4"]:
    r"""Composite sample arrays front to back into one RGBA value per ray.

    Standard compositing (eq. 1) when ``importance`` is None, importance-aware
    compositing (eq. 8, :func:`importance_step`) otherwise, as a ``lax.scan``
    over the samples with all rays carried at once.

    Args:
        colors: ``(..., S, 3)`` opacity-weighted colours $C_s = \alpha_s c_s$ of
            S samples per ray, front first.
        alphas: ``(..., S)`` opacities in [0, 1].
        importance: optional ``(..., S)`` sample importances $I_s$ (any real;
            only differences matter).
        background: optional ``(3,)`` or ``(..., 3)`` colour blended under the
            volume; without it the result is premultiplied RGBA over black.
        background_importance: optional scalar or ``(...)`` importance of the
            background layer (sec. IV-C; needs ``importance``). Default: none
            ($-\infty$), the background never fades the volume.
        unroll: samples per iteration of the ``lax.scan`` (static; larger values
            trade compile time for less loop overhead on GPUs).

    Returns:
        ``(..., 4)`` premultiplied RGB (over the background) and opacity, in the
        dtype of the inputs. Standard: opacity $1 - \prod(1-\alpha)$. Importance:
        the volume's opacity after the background's modulation (equal to the
        standard one without background importance).

    Raises:
        ValueError: mismatched shapes, ``background_importance`` without
            ``importance``; at run time (``eqx.error_if``) NaN/inf in the inputs
            or alphas outside [0, 1].
        TypeError: non-numeric inputs.

    Example:
        >>> composite(jnp.array([[0.5, 0.0, 0.0]]), jnp.array([0.5]))
        Array([0.5, 0. , 0. , 0.5], dtype=float32)
        >>> composite(jnp.array([[1.0, 0, 0], [0, 0.5, 0]]), jnp.array([1.0, 0.5]),
        ...           importance=jnp.array([0.0, 3.0]))  # the green sample shows through
    """
    where = "volshade.composite"
    unroll = _checks.positive_int(unroll, "unroll", where)
    colors = _checks.as_float_array(colors, "colors", where)
    alphas = _checks.as_float_array(alphas, "alphas", where)
    if colors.ndim < 2 or colors.shape[-1] != 3 or colors.shape[:-1] != alphas.shape:
        raise ValueError(f"{where}: `colors` must be (..., S, 3) and `alphas` (..., S) with the "
                         f"same leading shape, got {colors.shape} and {alphas.shape}.")
    arrays = [colors, alphas]
    if importance is not None:
        importance = _checks.as_float_array(importance, "importance", where)
        if importance.shape != alphas.shape:
            raise ValueError(f"{where}: `importance` must have the shape of `alphas` (..., S) = "
                             f"{alphas.shape}, got {importance.shape}.")
        arrays.append(importance)
    elif background_importance is not None:
        raise ValueError(f"{where}: `background_importance` only acts in importance-aware "
                         f"compositing; pass `importance=` (e.g. zeros like `alphas`) too.")
    dtype = jnp.result_type(*arrays)
    batch = alphas.shape[:-1]
    colors = _checks.finite(colors.astype(dtype), "colors", where)
    alphas = _checks.finite(alphas.astype(dtype), "alphas", where, unit_range=True)
    if background is None:
        bg = jnp.zeros((*batch, 3), dtype)
    else:
        bg = _checks.finite(_checks.as_float_array(background, "background", where).astype(dtype),
                            "background", where)
        if bg.shape[-1:] != (3,) or (bg.ndim > 1 and bg.shape[:-1] != batch):
            raise ValueError(f"{where}: `background` must be (3,) or (..., 3) = {(*batch, 3)}, "
                             f"got {bg.shape}.")

    if importance is None:
        comp = COMPOSITORS["standard"]
        xs = Sample(jnp.moveaxis(colors, -2, 0), jnp.moveaxis(alphas, -1, 0))
        bg_imp = None
    else:
        comp = COMPOSITORS["importance"]
        importance = _checks.finite(importance.astype(dtype), "importance", where)
        xs = Sample(jnp.moveaxis(colors, -2, 0), jnp.moveaxis(alphas, -1, 0),
                    jnp.moveaxis(importance, -1, 0))
        if background_importance is None:
            bg_imp = jnp.full(batch, -jnp.inf, dtype)
        else:
            bg_imp = _checks.as_float_array(background_importance, "background_importance", where)
            if bg_imp.ndim > 0 and bg_imp.shape != batch:
                raise ValueError(f"{where}: `background_importance` must be a scalar or "
                                 f"(...) = {batch}, got {bg_imp.shape}.")
            bg_imp = eqx.error_if(
                bg_imp.astype(dtype), jnp.any(jnp.isnan(bg_imp) | (bg_imp == jnp.inf)),
                f"{where}: `background_importance` must be finite or -inf (no background "
                f"importance), got NaN or +inf.")
    state = comp.init(batch, dtype)
    state, _ = jax.lax.scan(lambda s, x: (comp.step(s, x), None), state, xs, unroll=unroll)
    return comp.finish(state, bg, bg_imp)
