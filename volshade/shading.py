r"""Local shading of samples: Blinn--Phong with an ambient term from a shading volume.

For a sample of colour $c$, unit normal $N$, light direction $L$, view
direction $V$ and half vector $H = (L + V)/|L + V|$,

$$ I = c\,(k_a A + k_d |N\cdot L|) + k_s |N\cdot H|^n, $$

where $A$ is the ambient factor taken from a precomputed view-independent
shading volume (ambient occlusion, obscurance; grey or RGB) and 1 without one.
The diffuse and specular terms are two-sided (``|N.L|``), as usual in volume
rendering where gradients point either way across a boundary. Where the
gradient vanishes the normal is the zero vector and only the ambient term
remains; the normal is computed with :func:`~volshade._numerics.safe_normalize`
so its gradient stays finite there. :func:`obscurance_lit` (eq. 5 of Ruiz et
al.) has no ambient term: there a sample without a gradient is black.

References:
    Blinn: Models of light reflection for computer synthesized pictures. SIGGRAPH 1977.
"""

from collections.abc import Callable
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp

from . import _checks
from ._numerics import safe_normalize, safe_pow
from ._types import Array, Float
from .obscurance import _obscurance_shading


class Phong(eqx.Module):
    """Blinn--Phong coefficients; all are differentiable leaves, finite and ``>= 0``
    (``shininess > 0``), checked when the Module is built from known values.

    Attributes:
        ambient: $k_a$, weight of the ambient term.
        diffuse: $k_d$.
        specular: $k_s$ (white highlights).
        shininess: Phong exponent $n$.

    Raises:
        TypeError: a non-numeric (or bool) coefficient.
        ValueError: a coefficient that is not a scalar, when a render shades with it
            (leaves may carry a batch axis, for ``jax.vmap``).
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): a coefficient
            that is not a finite number >= 0, or ``shininess <= 0``; traced values are
            checked when a render uses them.
    """

    ambient: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Phong", "ambient"), default=0.35)
    diffuse: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Phong", "diffuse"), default=0.65)
    specular: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Phong", "specular"), default=0.25)
    shininess: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Phong", "shininess"), default=24.0)
    _COEFFICIENTS: ClassVar[tuple[str, ...]] = ("ambient", "diffuse", "specular", "shininess")

    def __check_init__(self):
        # checked here when known (built eagerly; leaves may carry a batch axis for
        # vmap); traced values (a fit, jit) by the renderer, with checked()
        _checks.refuse(self, self._problems(), "volshade.Phong", traced=False)

    def _problems(self) -> list[tuple[Array, str]]:
        # as arrays: a leaf set to a Python float (eqx.tree_at) would make `~` bitwise
        values = {name: jnp.asarray(getattr(self, name)) for name in self._COEFFICIENTS}
        problems = [(~(jnp.isfinite(v) & (v >= 0)), f"`{name}` must be a finite number >= 0.")
                    for name, v in values.items()]
        return [*problems, (~(values["shininess"] > 0), "`shininess` must be > 0.")]

    def checked(self) -> "Phong":
        """These coefficients, refused at run time where traced values are out of range,
        and at once where they are not scalars (a batch of settings is for vmap)."""
        _checks.scalar_fields(self, self._COEFFICIENTS, "volshade.Phong", use=" to shade",
                              fix="for a batch of settings, jax.vmap the render over the "
                                  "Phong module")
        return _checks.refuse(self, self._problems(), "volshade.Phong")


def blinn_phong(
    color: Float[Array, "*batch 3"],
    gradient: Float[Array, "*batch 3"],
    light: Float[Array, "*batch 3"],
    view: Float[Array, "*batch 3"],
    ambient: Float[Array, "*batch #3"],
    params: Phong,
) -> Float[Array, "*batch 3"]:
    """Blinn--Phong shading of samples (see the module docstring for the formula).

    Args:
        color: ``(..., 3)`` unshaded RGB.
        gradient: ``(..., 3)`` field gradient; the normal is ``-gradient / |gradient|``.
        light, view: ``(..., 3)`` unit vectors from the sample to the light and the eye.
        ambient: ``(..., 1)`` or ``(..., 3)`` ambient factor in [0, 1].
        params: :class:`Phong` coefficients.

    Returns:
        ``(..., 3)`` shaded RGB (may exceed 1 where highlights add up).
    """
    normal = safe_normalize(-gradient)
    half = safe_normalize(light + view)
    n_dot_l = jnp.abs(jnp.sum(normal * light, axis=-1, keepdims=True))
    n_dot_h = jnp.abs(jnp.sum(normal * half, axis=-1, keepdims=True))
    ka, kd, ks, n = (jnp.asarray(p, color.dtype) for p in
                     (params.ambient, params.diffuse, params.specular, params.shininess))
    return color * (ka * ambient + kd * n_dot_l) + ks * safe_pow(n_dot_h, n)


def unlit(color, gradient, light, view, ambient, params):
    """Emission only: the colour scaled by the ambient factor (1 without an ambient volume)."""
    del gradient, light, view, params
    return color * ambient


def obscurance_lit(color, gradient, light, view, ambient, params):
    r"""Eq. 5 of Ruiz et al. 2008, two-sided like :func:`blinn_phong`:
    $c\,(k_d |N\cdot L| + k_s |N\cdot H|^n)\, O(x)$, the whole local lighting scaled by
    the (grey or RGB) obscurance passed as ``ambient``. The equation has no ambient
    term, so a sample whose gradient vanishes (the inside of a homogeneous region,
    seen through a clip) is black: use ``"phong"`` shading with the obscurance as its
    ambient term for those."""
    obs = jnp.broadcast_to(ambient, color.shape)
    return color * _obscurance_shading(-gradient, jnp.asarray(light, color.dtype),
                                       jnp.asarray(view, color.dtype), obs, params.diffuse,
                                       params.specular, params.shininess, two_sided=True)


class Shader(NamedTuple):
    fn: Callable
    needs_gradient: bool


SHADERS: dict[str, Shader] = {
    "none": Shader(unlit, needs_gradient=False),
    "phong": Shader(blinn_phong, needs_gradient=True),
    "obscurance": Shader(obscurance_lit, needs_gradient=True),
}
