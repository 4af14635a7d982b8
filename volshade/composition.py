r"""Front-to-back compositing of samples along rays.

A compositor is three pure functions, so that the renderer and
:func:`composite` share one step and any batch of rays can be carried at once:

* ``init(batch_shape, dtype) -> state``
* ``step(state, sample) -> state`` for one sample per ray (the body of a
  ``lax.scan`` over the samples),
* ``finish(state, background) -> rgba``.

Colours are *opacity-weighted* (premultiplied): a sample of colour $c$ and
opacity $\alpha$ contributes $\alpha c$. Standard emission--absorption
compositing (front to back) is

$$ C_{i+1} = C_i + T_i\, \alpha_s c_s, \qquad T_{i+1} = T_i (1 - \alpha_s), $$

with accumulated opacity $\alpha_i = 1 - T_i$. The background is blended under
what remains: $C = C_n + T_n\, c_{bg}$.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import _checks
from ._types import Array, Float


class Sample(NamedTuple):
    """One sample per ray: premultiplied colour ``(..., 3)``, opacity ``(...)`` and
    importance ``(...)`` (ignored by standard compositing)."""

    color: Array
    alpha: Array
    importance: Array | None = None


class StandardState(NamedTuple):
    """Accumulated premultiplied colour ``(..., 3)`` and transmittance ``(...)``."""

    color: Array
    transmittance: Array


def standard_init(batch_shape: tuple[int, ...], dtype) -> StandardState:
    return StandardState(jnp.zeros((*batch_shape, 3), dtype), jnp.ones(batch_shape, dtype))


def standard_step(state: StandardState, sample: Sample) -> StandardState:
    """One front-to-back step; exact at alpha = 0 and 1, no division anywhere."""
    color = state.color + state.transmittance[..., None] * sample.color
    return StandardState(color, state.transmittance * (1 - sample.alpha))


def standard_finish(state: StandardState, background: Array) -> Float[Array, "*batch 4"]:
    """Blend the background colour under the remaining transmittance; RGBA, alpha = 1 - T."""
    rgb = state.color + state.transmittance[..., None] * background[..., :3]
    return jnp.concatenate([rgb, (1 - state.transmittance)[..., None]], axis=-1)


class Compositor(NamedTuple):
    init: object
    step: object
    finish: object


COMPOSITORS: dict[str, Compositor] = {
    "standard": Compositor(standard_init, standard_step, standard_finish),
}


def composite(
    colors: Float[Array, "*batch S 3"],
    alphas: Float[Array, "*batch S"],
    *,
    background: Float[Array, "3"] | None = None,
) -> Float[Array, "*batch 4"]:
    r"""Composite sample arrays front to back into one RGBA value per ray.

    Args:
        colors: ``(..., S, 3)`` opacity-weighted colours of S samples, front first.
        alphas: ``(..., S)`` opacities in [0, 1].
        background: optional ``(3,)`` colour blended under the remaining
            transmittance; without it the result is premultiplied RGBA over black.

    Returns:
        ``(..., 4)`` premultiplied RGB and accumulated opacity $1 - \prod(1-\alpha)$.

    Raises:
        ValueError: mismatched shapes.

    Example:
        >>> composite(jnp.array([[0.5, 0.0, 0.0]]), jnp.array([0.5]))
        Array([0.5, 0. , 0. , 0.5], dtype=float32)
    """
    where = "volshade.composite"
    colors = _checks.as_float_array(colors, "colors", where)
    alphas = _checks.as_float_array(alphas, "alphas", where)
    if colors.ndim < 2 or colors.shape[-1] != 3 or colors.shape[:-1] != alphas.shape:
        raise ValueError(f"{where}: `colors` must be (..., S, 3) and `alphas` (..., S) with the "
                         f"same leading shape, got {colors.shape} and {alphas.shape}.")
    dtype = jnp.result_type(colors, alphas)
    bg = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)
    comp = COMPOSITORS["standard"]
    samples = Sample(jnp.moveaxis(colors, -2, 0).astype(dtype), jnp.moveaxis(alphas, -1, 0).astype(dtype))
    state = comp.init(alphas.shape[:-1], dtype)
    state, _ = jax.lax.scan(lambda s, x: (comp.step(s, Sample(*x)), None), state, samples[:2])
    return comp.finish(state, bg)
