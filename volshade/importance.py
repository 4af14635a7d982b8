r"""Sample importance measures and focus-plus-context weights (Pinto & Freitas 2010, sec. IV).

The importance of a sample is a weighted sum of measures computed on the fly,
scaled by a global (or per-ray) weight (sec. IV-B):

$$ I_s = W_{global} \sum_n W_n I_n . $$

Measures (sec. IV-A): intensity, extinction $\ln(1+\tau)$, normalised gradient
magnitude $m_G$, silhouetteness (eq. 9), unocclusion $20 - \sum \tau d$ and
lighting (eq. 10). The importances feed the importance-aware compositor
(:mod:`volshade.composition`, ``"importance"``).

Conventions: vectors are in ``(d, h, w)`` order. The view vector $V$ points
from the sample towards the eye, the light vector $L$ towards the light; both
are normalised here, and so is the normal $N$ (typically the gradient).
Normals are turned to face the viewer before lighting (two-sided lighting), so
the sign convention of the gradient does not matter. Intensities are expected
in [0, 1]; $m_G$ is the gradient magnitude divided by its maximum over the
volume (:func:`normalized_gradient_magnitude`), as in the paper's eq. 9 and 10.
The gradient measure (sec. IV-A3) uses $m_G$ too, where the paper writes the raw
$|\nabla f|$: so $W_{gradient}$ does not depend on the volume's intensity scale.

References:
    F. de Moura Pinto and C. M. D. S. Freitas, "Importance-aware composition for
    illustrative volume rendering", SIBGRAPI 2010.
"""

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import quotient, safe_norm, safe_normalize, safe_pow, smoothstep
from ._types import Array, ArrayLike, Float
from .gradient import _magnitude

_VECTORS = ("normal", "view", "light")
_WEIGHTS = ("intensity", "extinction", "gradient", "silhouette", "unocclusion", "lighting")


class Importance(eqx.Module):
    r"""Weights and shape parameters of the importance measures (sec. IV).

    Every field is a differentiable scalar array leaf, so a fit never recompiles.
    The defaults (all measure weights 0) give $I_s = 0$ everywhere, for which
    importance-aware compositing equals standard compositing up to rounding (about
    1e-15 in float64, 1e-6 in float32: eq. 8's terms are not formed as standard
    compositing forms them, so the rounding differs), for opacity-weighted colours
    (the renderer's; see :func:`volshade.composite` for a colour given at opacity 0).
    Compositing depends on importance differences only, and gaps of any size are
    handled stably; but the products $W_{global} W_{measure} \cdot measure$ are formed
    in the render's dtype, so in float32 weights whose product passes about $10^{38}$
    (e.g. both $10^{30}$) overflow to infinity and the image degrades without an
    error: use float64 there.

    Where every sample of a ray has the same importance (all measure weights exactly 0,
    the defaults, or a focus weight of 0), every step is a tie $K_i = I_s$, which has
    no derivative; each is taken as behind (:func:`volshade.composition.importance_step`),
    so the gradient w.r.t. a weight there is the sum of the derivatives from above and
    below, not either one (e.g. -1.19 where they are +0.015 and -1.20: a minimum that
    the gradient says to leave upwards). Start a fit of these weights off 0 (e.g. at
    $10^{-3}$), where the derivative is exact.

    Attributes:
        global_weight: $W_{global}$ (sec. IV-B); per-ray weights for focus plus
            context (sec. IV-D) can override it in :func:`sample_importance`.
        intensity: $W_{intensity}$ (sec. IV-A1).
        extinction: $W_\tau$ for $\ln(1 + \tau)$ (sec. IV-A2).
        gradient: $W_{gradient}$ for $m_G$ (sec. IV-A3).
        silhouette: $W_{sil}$ for silhouetteness (eq. 9, sec. IV-A4).
        unocclusion: $W_{unocclusion}$ (sec. IV-A5).
        lighting: $W_{lighting}$ (eq. 10, sec. IV-A6).
        background: importance of the background layer before the global
            weight, $I_{bg} = W_{global} W_{bg}$. Sec. IV-C gives the background
            only "an adjustable importance" (sec. V: a slider of its own); scaling
            it by $W_{global}$, as the samples' importance is, is this library's
            choice: a ray's global (or focus) weight then rescales samples and
            background alike and keeps their order. The default 0 is the
            paper's slider at zero: samples of negative importance (negative
            weights) then rank below the background, which fades them; ``-inf``
            (:func:`volshade.composite`'s default) means no background layer.
        silhouette_exponent, silhouette_start, silhouette_end: $p$, $s_1$, $s_2$
            of eq. 9 (1.7, 0.4, 1.0).
        darkening: silhouette colour darkening $k$ in $e^{-k\,sil}$ (paper: 4); read
            only where the ``silhouette`` weight is not 0.
        unocclusion_offset: the constant of unocclusion (paper: 20).
        specular_exponent, diffuse_exponent, gradient_exponent: $p_1$, $p_2$, $p_3$
            of eq. 10 (50, 5, 30).

    Raises:
        ValueError: a non-scalar field.
        TypeError: a non-numeric (or bool) field.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN or inf in
            a field (``background`` may be -inf), an exponent <= 0, ``darkening < 0``,
            ``silhouette_start >= silhouette_end``; traced values are checked where
            the weights are used (:func:`sample_importance`, a render).

    Example:
        >>> imp = Importance(intensity=4.0, silhouette=2.0)
    """

    global_weight: Float[Array, ""] = eqx.field(
        default=1.0, converter=_checks.leaf("volshade.Importance", "global_weight"))
    intensity: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "intensity"))
    extinction: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "extinction"))
    gradient: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "gradient"))
    silhouette: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "silhouette"))
    unocclusion: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "unocclusion"))
    lighting: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "lighting"))
    background: Float[Array, ""] = eqx.field(
        default=0.0, converter=_checks.leaf("volshade.Importance", "background"))
    silhouette_exponent: Float[Array, ""] = eqx.field(
        default=1.7, converter=_checks.leaf("volshade.Importance", "silhouette_exponent"))
    silhouette_start: Float[Array, ""] = eqx.field(
        default=0.4, converter=_checks.leaf("volshade.Importance", "silhouette_start"))
    silhouette_end: Float[Array, ""] = eqx.field(
        default=1.0, converter=_checks.leaf("volshade.Importance", "silhouette_end"))
    darkening: Float[Array, ""] = eqx.field(
        default=4.0, converter=_checks.leaf("volshade.Importance", "darkening"))
    unocclusion_offset: Float[Array, ""] = eqx.field(
        default=20.0, converter=_checks.leaf("volshade.Importance", "unocclusion_offset"))
    specular_exponent: Float[Array, ""] = eqx.field(
        default=50.0, converter=_checks.leaf("volshade.Importance", "specular_exponent"))
    diffuse_exponent: Float[Array, ""] = eqx.field(
        default=5.0, converter=_checks.leaf("volshade.Importance", "diffuse_exponent"))
    gradient_exponent: Float[Array, ""] = eqx.field(
        default=30.0, converter=_checks.leaf("volshade.Importance", "gradient_exponent"))

    # leaves for which -inf is a value, not an error: a background importance of -inf
    # means "no background" (volshade.composite); the renderer's finiteness check asks
    may_be_minus_inf: ClassVar[tuple[str, ...]] = ("background",)

    def __check_init__(self):
        self._check_scalars()
        # traced values (a fit, jit) are checked by the renderer (with checked() and its
        # named finiteness check) and by sample_importance
        _checks.refuse(self, [*self._non_finite(), *self._problems()], "volshade.Importance",
                       traced=False)

    def _check_scalars(self) -> None:
        _checks.scalar_fields(self, _leaves(self), "volshade.Importance",
                              fix="for per-ray global weights pass `global_weight=` to "
                                  "`sample_importance`")

    def _non_finite(self) -> list[tuple[Array, str]]:
        """NaN or inf weights (-inf allowed where :attr:`may_be_minus_inf` says)."""
        return [(_checks.non_finite(v, minus_inf=name in self.may_be_minus_inf),
                 f"`{name}` must be finite"
                 f"{', or -inf for none' if name in self.may_be_minus_inf else ''}.")
                for name, v in _leaves(self).items()]

    def _problems(self) -> list[tuple[Array, str]]:
        """Shape parameters outside their domain: exponents must be positive (0^p is 0
        only for p > 0), a negative darkening brightens the silhouettes without bound,
        and smoothstep needs its start below its end."""
        # as arrays: a leaf set to a Python float (eqx.tree_at) would make `~` bitwise
        value = {name: jnp.asarray(v) for name, v in _leaves(self).items()}
        exponents = [(~(value[name] > 0), f"`{name}` must be > 0.") for name in
                     ("silhouette_exponent", "specular_exponent", "diffuse_exponent",
                      "gradient_exponent")]
        return [*exponents,
                (~(value["darkening"] >= 0), "`darkening` must be >= 0 (0: no darkening)."),
                (~(value["silhouette_start"] < value["silhouette_end"]),
                 "`silhouette_start` must be < `silhouette_end` (the smoothstep's edges).")]

    def checked(self) -> "Importance":
        """These weights, refused at run time where traced values are out of range, and
        at once where they are not scalars (a field set with ``eqx.tree_at`` skipped the
        constructor's checks)."""
        self._check_scalars()
        return _checks.refuse(self, self._problems(), "volshade.Importance")

    def background_importance(self, global_weight: ArrayLike | None = None) -> Array:
        r"""Importance of the background layer, $I_{bg} = W_{global} W_{bg}$ (sec. IV-C).

        The factor $W_{global}$ is this library's choice (see ``background``); the
        paper gives the background an adjustable importance of its own.

        A zero global weight gives 0 (importance off). $W_{bg} = -\infty$ ("no
        background") gives $-\infty$ for any other weight, of either sign, with
        finite gradients.

        Args:
            global_weight: optional per-ray weights ``(...)`` replacing
                ``self.global_weight`` (focus plus context).
        """
        g = self.global_weight if global_weight is None else jnp.asarray(global_weight)
        # a zero weight switches importance off (0, not 0 * -inf = NaN); W_bg = -inf means
        # "no background" whatever the weight's sign, and is kept out of the product so
        # that its gradients stay finite (double where). A finite W_bg enters the product
        # at g = 0 too, whose slope there is W_bg.
        off, none = g == 0, self.background == -jnp.inf
        product = g * jnp.where(none, 0, self.background)
        return jnp.where(none, jnp.where(off, 0, -jnp.inf), product)


def _leaves(params: Importance) -> dict[str, Array]:
    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _feature(value: ArrayLike, name: str, where: str, *, check: bool = True) -> Array:
    """A measure's input as a floating array, vectors checked to be ``(..., 3)``; with
    ``check``, refused at run time where it is not finite or outside its domain (the
    measures assume it: they would clip it, or give a wrong value without an error)."""
    # a bool direction is no direction (data such as a mask may be bool)
    v = (_checks.numbers if name in _VECTORS else _checks.as_float_array)(value, name, where)
    if name in _VECTORS and (v.ndim < 1 or v.shape[-1] != 3):
        raise ValueError(f"{where}: `{name}` must be (..., 3) in (d, h, w) order, "
                         f"got {v.shape}.")
    if not check:
        return v
    v = _checks.finite(v, name, where)
    if name in ("extinction", "optical_depth"):
        xp, host = _checks.for_check(v)
        return _checks.refuse(v, [(xp.any(host < 0), f"`{name}` must be >= 0.")], where)
    if name == "gradient_magnitude":
        return _checks.in_unit_range(v, name, where, hint="(normalise it by the volume's "
                                     "maximum: normalized_gradient_magnitude)")
    return v


def silhouetteness(
    normal: Float[ArrayLike, "*batch 3"],
    view: Float[ArrayLike, "*batch 3"],
    gradient_magnitude: Float[ArrayLike, "*batch"],
    *,
    exponent: ArrayLike = 1.7,
    start: ArrayLike = 0.4,
    end: ArrayLike = 1.0,
) -> Float[Array, "*batch"]:
    r"""Silhouetteness, eq. 9: $sil = m_G^p\, \mathrm{smoothstep}(s_1, s_2, 1 - |V\cdot N|)$.

    Args:
        normal: ``(..., 3)`` normal $N$ (normalised here; the zero vector gives
            $|V \cdot N| = 0$).
        view: ``(..., 3)`` view vector $V$ (normalised here).
        gradient_magnitude: ``(...)`` normalised gradient magnitude $m_G$ in [0, 1].
        exponent, start, end: $p > 0$, $s_1 < s_2$.

    Returns:
        ``(...)`` silhouetteness in [0, 1].

    Raises:
        ValueError: vectors not ``(..., 3)``; at run time, inputs that are not
            finite, $m_G$ outside [0, 1], $p \le 0$ or $s_1 \ge s_2$.
    """
    where = "volshade.importance.silhouetteness"
    n, v = (_feature(x, k, where) for x, k in ((normal, "normal"), (view, "view")))
    m_g = _feature(gradient_magnitude, "gradient_magnitude", where)
    exponent, start, end = (_checks.numbers(x, k, where) for x, k in
                            ((exponent, "exponent"), (start, "start"), (end, "end")))
    xp, a, b = _checks.for_check(start, end)
    m_g = _checks.refuse(m_g, [
        (_checks.not_positive(exponent), "`exponent` must be a finite number > 0."),
        (~xp.all(xp.isfinite(a) & xp.isfinite(b) & (a < b)),
         "`start` and `end` must be finite, with `start` < `end` (the smoothstep's edges).")],
        where)
    return _compiled_silhouetteness(n, v, m_g, exponent, start, end)


def _silhouetteness(n: Array, v: Array, m_g: Array, exponent, start, end) -> Array:
    facing = jnp.abs(_dot(safe_normalize(n), safe_normalize(v)))
    return safe_pow(m_g, exponent) * smoothstep(start, end, 1 - facing)


def lighting_importance(
    normal: Float[ArrayLike, "*batch 3"],
    view: Float[ArrayLike, "*batch 3"],
    light: Float[ArrayLike, "*batch 3"],
    gradient_magnitude: Float[ArrayLike, "*batch"],
    *,
    specular_exponent: ArrayLike = 50.0,
    diffuse_exponent: ArrayLike = 5.0,
    gradient_exponent: ArrayLike = 30.0,
) -> Float[Array, "*batch"]:
    r"""Lighting importance, eq. 10: $3 - (N\cdot H)^{p_1} - (N\cdot L)^{p_2} - (1 - m_G)^{p_3}$.

    $H = (L + V)/|L + V|$ is the half vector. The normal is first turned towards
    the viewer ($N \leftarrow -N$ where $N \cdot V < 0$) and the dot products are
    clamped at 0, as in Phong shading, so the powers are of numbers in [0, 1].

    Args:
        normal, view, light: ``(..., 3)`` vectors $N$, $V$, $L$ (normalised here).
        gradient_magnitude: ``(...)`` $m_G$ in [0, 1].
        specular_exponent, diffuse_exponent, gradient_exponent: $p_1$, $p_2$,
            $p_3$, all $> 0$.

    Returns:
        ``(...)`` importance in [0, 3]: high where the Phong illumination is weak.

    Raises:
        ValueError: vectors not ``(..., 3)``; at run time, inputs that are not
            finite, $m_G$ outside [0, 1] or an exponent $\le 0$.
    """
    where = "volshade.importance.lighting_importance"
    n, v, l = (_feature(x, k, where) for x, k in  # noqa: E741
               ((normal, "normal"), (view, "view"), (light, "light")))
    m_g = _feature(gradient_magnitude, "gradient_magnitude", where)
    exponents = {k: _checks.numbers(x, k, where)
                 for x, k in ((specular_exponent, "specular_exponent"),
                              (diffuse_exponent, "diffuse_exponent"),
                              (gradient_exponent, "gradient_exponent"))}
    m_g = _checks.refuse(m_g, [(_checks.not_positive(x), f"`{k}` must be a finite number > 0.")
                               for k, x in exponents.items()], where)
    return _compiled_lighting_importance(n, v, l, m_g, *exponents.values())


def _lighting_importance(n: Array, v: Array, l: Array, m_g: Array,  # noqa: E741
                         specular_exponent, diffuse_exponent, gradient_exponent) -> Array:
    n, v, l = safe_normalize(n), safe_normalize(v), safe_normalize(l)  # noqa: E741
    n = jnp.where((_dot(n, v) < 0)[..., None], -n, n)
    h = safe_normalize(l + v)
    n_h = jnp.clip(_dot(n, h), 0, 1)
    n_l = jnp.clip(_dot(n, l), 0, 1)
    # m_G is in [0, 1] (checked, or a trilinear blend of such values, which rounding
    # can lift by an ulp: safe_pow gives 0 for the negative 1 - m_G then, as for 0)
    return (3 - safe_pow(n_h, specular_exponent) - safe_pow(n_l, diffuse_exponent)
            - safe_pow(1 - m_g, gradient_exponent))


def sample_importance(
    params: Importance,
    *,
    intensity: Float[ArrayLike, "*batch"] | None = None,
    extinction: Float[ArrayLike, "*batch"] | None = None,
    gradient_magnitude: Float[ArrayLike, "*batch"] | None = None,
    normal: Float[ArrayLike, "*batch 3"] | None = None,
    view: Float[ArrayLike, "*#batch 3"] | None = None,
    light: Float[ArrayLike, "*#batch 3"] | None = None,
    optical_depth: Float[ArrayLike, "*batch"] | None = None,
    global_weight: Float[ArrayLike, "*#batch"] | None = None,
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    r"""Importance of one batch of samples and their silhouette colour scale (sec. IV).

    $$ I_s = W_{global} \big(W_{int}\, x + W_\tau \ln(1+\tau) + W_{grad}\, m_G
        + W_{sil}\, sil + W_{unocc} (c_u - \textstyle\sum\tau d) + W_{light} I_{light}\big) $$

    with $sil$ from eq. 9 (:func:`silhouetteness`), $I_{light}$ from eq. 10
    (:func:`lighting_importance`) and $c_u = 20$ (sec. IV-A5). The colour scale
    is $e^{-k\, sil\, w}$ with $w = \mathrm{clip}(W_{global}, 0, 1)$ (sec. IV-A4,
    $k = 4$), applied only where $W_{sil} \ne 0$: full darkening at weight 1 or
    more, none at 0, so the default :class:`Importance` and context rays with
    zero global weight render as standard DVR (up to rounding), and smooth in between, so
    that the darkening fades with the focus weights as the importance does
    (sec. IV-D: "a smooth transition ... by varying the per-ray-global weight").

    A measure whose inputs are not given is left out (it contributes 0), if its
    weight is 0 or traced; a known non-zero weight without its inputs is refused, as are
    vectors that no measure would read. Silhouetteness needs ``normal``, ``view`` and
    ``gradient_magnitude``; lighting needs ``normal``, ``view`` and
    ``gradient_magnitude`` (``light`` defaults to ``view``, a headlight).

    Args:
        params: the :class:`Importance` weights.
        intensity: ``(...)`` sample value $x$, normally in [0, 1].
        extinction: ``(...)`` extinction coefficient $\tau \ge 0$ (per mm) from the
            transfer function.
        gradient_magnitude: ``(...)`` $m_G$ in [0, 1] (gradient magnitude divided
            by its volume maximum, :func:`normalized_gradient_magnitude`).
        normal: ``(..., 3)`` normal $N$ (e.g. the gradient; normalised here).
        view: ``(3,)`` or ``(..., 3)`` vector $V$ towards the eye.
        light: ``(3,)`` or ``(..., 3)`` vector $L$ towards the light.
        optical_depth: ``(...)`` $\sum \tau d$ accumulated along the ray in front
            of the sample (dimensionless; the renderer accumulates it).
        global_weight: optional scalar or ``(...)`` per-ray weights replacing
            ``params.global_weight`` (focus plus context, sec. IV-D; see
            :func:`focus_weights`).

    Returns:
        ``(importance, color_scale)``, both ``(...)`` in the features' dtype, float32
        at least: $I_s$ (any real) and the factor in (0, 1] to multiply the sample
        colour by.

    Raises:
        ValueError: no features given, shapes that do not broadcast, vectors whose last
            axis is not 3; vectors without the other inputs of silhouetteness and
            lighting; a known non-zero weight whose measure's inputs are not given.
        TypeError: non-numeric features.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN or inf in a
            feature or a weight, a negative ``extinction`` or ``optical_depth``, a
            ``gradient_magnitude`` outside ``[0, 1]``, ``params`` out of their domain
            (see :class:`Importance`).

    Example:
        >>> imp, scale = sample_importance(Importance(intensity=5.0), intensity=jnp.ones(8))
    """
    where = "volshade.sample_importance"
    scalars = {"intensity": intensity, "extinction": extinction,
               "gradient_magnitude": gradient_magnitude, "optical_depth": optical_depth}
    vectors = {"normal": normal, "view": view, "light": light}
    if not isinstance(params, Importance):
        raise TypeError(f"{where}: `params` must be a volshade.Importance, got "
                        f"{type(params).__name__}.")
    params = _checks.refuse(params.checked(), params._non_finite(), where)
    scalars, vectors = ({k: _feature(v, k, where) for k, v in features.items() if v is not None}
                        for features in (scalars, vectors))
    _refuse_unread(params, {*scalars, *vectors}, per_ray=global_weight is not None, where=where)
    if global_weight is not None:
        global_weight = _checks.finite(
            _checks.as_float_array(global_weight, "global_weight", where), "global_weight",
            where)
    if scalars or vectors:
        # a Python number (weakly typed) compiles as an array of the dtype it computes in
        params, scalars, vectors, global_weight = _checks.strongly_typed(
            (params, scalars, vectors, global_weight), _measure_dtype(scalars, vectors))
    return _compiled_sample_importance(params, scalars, vectors, global_weight)


# the features each measure reads (silhouetteness and lighting read the same three, and
# are the only readers of the vectors)
_NEEDS = {"intensity": ("intensity",), "extinction": ("extinction",),
          "gradient": ("gradient_magnitude",), "unocclusion": ("optical_depth",),
          "silhouette": ("normal", "view", "gradient_magnitude"),
          "lighting": ("normal", "view", "gradient_magnitude")}


def _refuse_unread(params: Importance, given: set[str], *, per_ray: bool, where: str) -> None:
    """Refuse what would be dropped without a word: vectors that no measure reads
    (silhouetteness and lighting need ``normal``, ``view`` and ``gradient_magnitude``
    together), and a known non-zero weight whose measure lacks a feature (unless a
    global weight of 0, not replaced by ``per_ray`` weights, turns them all off)."""
    unread = [k for k in _VECTORS if k in given] if not set(_NEEDS["silhouette"]) <= given \
        else []
    if unread:
        missing = [f"`{k}`" for k in _NEEDS["silhouette"] if k not in given]
        raise ValueError(f"{where}: {', '.join(f'`{k}`' for k in unread)} would be unread: "
                         f"only silhouetteness and lighting read the vectors, and they also "
                         f"need {', '.join(missing)}. Give {'it' if len(missing) == 1 else 'them'}"
                         f", or leave the vectors out.")
    if not per_ray and _checks.concrete(params.global_weight) == 0:
        return  # importance off: no weight is read
    for weight, needs in _NEEDS.items():
        value = _checks.concrete(getattr(params, weight))
        missing = [k for k in needs if k not in given]
        if missing and value is not None and value != 0:
            raise ValueError(f"{where}: `params.{weight}` is {float(value):g}, but its "
                             f"measure needs {', '.join(f'`{k}`' for k in missing)}, not "
                             f"given; give {'it' if len(missing) == 1 else 'them'}, or set "
                             f"the weight to 0.")


def _measure_dtype(scalars: dict, vectors: dict):
    """The dtype the measures are weighted and summed in: the features', float32 at
    least (a float16 weighted sum overflows: intensity 7e4 is inf)."""
    return jnp.promote_types(jnp.result_type(*scalars.values(), *vectors.values()),
                             jnp.float32)


def _sample_importance(params, scalars, vectors, global_weight):
    """:func:`sample_importance` on feature dicts, without its value checks: the
    renderer's features come from a checked volume, and a run-time check at every
    step of the march would cost a host round trip on a GPU."""
    where = "volshade.sample_importance"
    scalars = {k: _feature(v, k, where, check=False)
               for k, v in scalars.items() if v is not None}
    vectors = {k: _feature(v, k, where, check=False)
               for k, v in vectors.items() if v is not None}
    if not scalars and not vectors:
        raise ValueError(f"{where}: give at least one feature (intensity=, extinction=, "
                         f"gradient_magnitude=, normal=/view=, optical_depth=).")
    shapes = [v.shape for v in scalars.values()] + [v.shape[:-1] for v in vectors.values()]
    if global_weight is not None:
        global_weight = _checks.as_float_array(global_weight, "global_weight", where)
        shapes.append(global_weight.shape)
    try:
        batch = jnp.broadcast_shapes(*shapes)
    except ValueError as err:
        raise ValueError(f"{where}: feature shapes {shapes} do not broadcast to one batch shape.") \
            from err
    dtype = _measure_dtype(scalars, vectors)
    scalars = {k: jnp.broadcast_to(v.astype(dtype), batch) for k, v in scalars.items()}
    vectors = {k: jnp.broadcast_to(v.astype(dtype), (*batch, 3)) for k, v in vectors.items()}
    p = {k: jnp.asarray(v).astype(dtype) for k, v in _leaves(params).items()}

    total = jnp.zeros(batch, dtype)
    if "intensity" in scalars:
        total = total + p["intensity"] * scalars["intensity"]
    if "extinction" in scalars:
        total = total + p["extinction"] * jnp.log1p(jnp.maximum(scalars["extinction"], 0))
    m_g = scalars.get("gradient_magnitude")
    if m_g is not None:
        total = total + p["gradient"] * m_g
    if "optical_depth" in scalars:
        total = total + p["unocclusion"] * (p["unocclusion_offset"] - scalars["optical_depth"])
    g = p["global_weight"] if global_weight is None else global_weight.astype(dtype)
    g = jnp.broadcast_to(g, batch)
    scale = jnp.ones(batch, dtype)
    n, v = vectors.get("normal"), vectors.get("view")
    if set(_NEEDS["silhouette"]) <= {*scalars, *vectors}:
        sil = _silhouetteness(n, v, m_g, p["silhouette_exponent"], p["silhouette_start"],
                              p["silhouette_end"])
        total = total + p["silhouette"] * sil
        strength = jnp.clip(g, 0, 1)
        scale = jnp.where(p["silhouette"] != 0, jnp.exp(-p["darkening"] * sil * strength),
                          scale)
        light_vec = vectors.get("light", v)
        total = total + p["lighting"] * _lighting_importance(
            n, v, light_vec, m_g, p["specular_exponent"], p["diffuse_exponent"],
            p["gradient_exponent"])
    return g * total, scale


# the measures after their eager checks: one compiled program per structure and shape,
# not an XLA program per operation (sample_importance's first eager call on a 32^3
# volume: 0.52 s -> 0.30 s, the rest being the checks of the volume-sized features)
_compiled_sample_importance = eqx.filter_jit(_sample_importance)
_compiled_silhouetteness = jax.jit(_silhouetteness)
_compiled_lighting_importance = jax.jit(_lighting_importance)


def normalized_gradient_magnitude(gradient: Float[ArrayLike, "D H W 3"]) -> Float[Array, "D H W"]:
    r"""$m_G = |\nabla f| / \max |\nabla f|$ over the volume, in [0, 1] (sec. IV-A4).

    Args:
        gradient: ``(D, H, W, 3)`` gradient, e.g. from
            :func:`volshade.regression_gradient` (the paper's choice).

    Returns:
        ``(D, H, W)`` normalised magnitude; all zeros for a constant volume.
    """
    where = "volshade.importance.normalized_gradient_magnitude"
    gradient = _checks.as_float_array(gradient, "gradient", where)
    if gradient.ndim != 4 or gradient.shape[-1] != 3:
        raise ValueError(f"{where}: `gradient` must be (D, H, W, 3), got {gradient.shape}.")
    return _magnitude(_checks.finite(gradient, "gradient", where), scaled=True)


# --------------------------------------------------------------------------- focus + context

# 4x4 ordered-dither (Bayer) thresholds in (0, 1).
_BAYER = (np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]]) + 0.5) / 16


def _circular(dist, radius, rows, cols):
    return (dist <= radius).astype(dist.dtype)


def _gaussian(dist, radius, rows, cols):
    # past 40 radii exp(-800) is 0 even in float64; cutting there (with a zero gradient)
    # keeps dist / radius, and its slope in radius, finite for the tiniest radius
    far = dist > 40 * radius
    ratio = quotient(jnp.where(far, jnp.zeros_like(dist), dist), radius)
    return jnp.where(far, jnp.zeros_like(dist), jnp.exp(-0.5 * jnp.square(ratio)))


def _screen_door(dist, radius, rows, cols):
    threshold = jnp.asarray(_BAYER, dist.dtype)[rows % 4][:, cols % 4]  # (H, W)
    return (_gaussian(dist, radius, rows, cols) > threshold).astype(dist.dtype)


FOCUS_KINDS: dict[str, Callable[..., Array]] = {
    "circular": _circular,
    "gaussian": _gaussian,
    "screen_door": _screen_door,
}


def _image_size(image_shape: Any, where: str) -> tuple[int, int]:
    """``(H, W)`` of ``image_shape``, a tuple or list of two positive ints."""
    if not isinstance(image_shape, tuple | list) or len(image_shape) != 2:
        raise ValueError(f"{where}: `image_shape` must be (H, W), a tuple of two ints, got "
                         f"{image_shape!r:.80}.")
    return tuple(_checks.positive_int(s, "image_shape", where) for s in image_shape)


def focus_weights(
    image_shape: tuple[int, int],
    *,
    center: Float[ArrayLike, "2"],
    radius: Float[ArrayLike, ""],
    kind: str = "gaussian",
    inside: Float[ArrayLike, ""] = 1.0,
    outside: Float[ArrayLike, ""] = 0.0,
    dtype=None,
) -> Float[Array, "H W"]:
    r"""Per-ray global importance weights for focus plus context (sec. IV-D).

    With $r$ the distance (pixels) of pixel $(i, j)$ to the focus centre and
    $R$ the radius, the weight is $w = o + (n - o) f(r)$ ($n$ = ``inside``,
    $o$ = ``outside``) with

    * ``"circular"``: $f = [r \le R]$ (a step);
    * ``"gaussian"``: $f = e^{-r^2 / (2R^2)}$ (smooth; differentiable in centre and radius);
    * ``"screen_door"``: $f = [e^{-r^2/(2R^2)} > b_{ij}]$ with $b$ a 4x4 ordered-dither
      (Bayer) pattern, so the density of focus pixels follows the Gaussian.

    Pass the result as ``global_weight=`` to :func:`sample_importance` (the
    context renders as standard DVR where the weight is 0).

    Args:
        image_shape: ``(H, W)`` pixels (static).
        center: ``(2,)`` focus centre ``(row, column)`` in pixels (pixel centres at
            integer coordinates).
        radius: focus radius (pixels, > 0).
        kind: ``"circular"``, ``"gaussian"`` or ``"screen_door"``.
        inside: weight at the focus centre.
        outside: weight far from the focus.
        dtype: output dtype (default: float of the inputs).

    Returns:
        ``(H, W)`` weights between ``outside`` and ``inside``.

    Raises:
        ValueError: unknown ``kind``, bad ``image_shape`` or ``center`` shape, a
            non-scalar ``radius``, ``inside`` or ``outside``.
        TypeError: ``image_shape`` not ints, non-numeric inputs.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN or inf in
            ``center``, ``inside`` or ``outside``; ``radius`` not a finite number > 0.

    Example:
        >>> w = focus_weights((64, 64), center=(32.0, 20.0), radius=10.0, kind="circular")
    """
    where = "volshade.focus_weights"
    fn = _checks.option(kind, FOCUS_KINDS, "kind", where)
    h, w = _image_size(image_shape, where)
    center = _checks.numbers(center, "center", where)
    if center.shape != (2,):
        raise ValueError(f"{where}: `center` must be (row, column), got shape {center.shape}.")
    center = _checks.finite(center, "center", where)
    radius = _checks.numbers(radius, "radius", where)
    if radius.ndim != 0:
        raise ValueError(f"{where}: `radius` must be a scalar (pixels), got shape {radius.shape}.")
    inside, outside = (_checks.numbers(x, name, where)
                       for x, name in ((inside, "inside"), (outside, "outside")))
    for x, name in ((inside, "inside"), (outside, "outside")):
        if x.ndim != 0:
            raise ValueError(f"{where}: `{name}` must be a scalar weight, got shape {x.shape}; "
                             f"for one weight per pixel, pass an (H, W) array as "
                             f"`global_weight=` instead.")
    inside = _checks.finite(inside, "inside", where)
    outside = _checks.finite(outside, "outside", where)
    if dtype is None:
        dtype = jnp.result_type(center, radius, inside, outside)
    _checks.floating_dtype(dtype, where)
    # in the geometry's dtype (_focus_weights): rounded to a half-precision output dtype,
    # a radius of 1e-8 would become 0
    work = jnp.promote_types(dtype, jnp.float32)  # as _focus_weights computes
    radius = _checks.refuse(radius.astype(work), [(_checks.not_positive(radius),
                                                   "`radius` must be a finite number > 0 "
                                                   "pixels.")], where)
    # a Python number (weakly typed) compiles as an array of the dtype it computes in
    center, inside, outside = _checks.strongly_typed((center, inside, outside), work)
    return _focus_weights(fn, (h, w), jnp.dtype(dtype), center, radius, inside, outside)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _focus_weights(fn, shape, dtype, center, radius, inside, outside) -> Array:
    """:func:`focus_weights` after its checks: one compiled program per kind, shape and
    dtype (an eager call ran an XLA program per operation: 1.4 s for the first, now 0.09 s)."""
    # pixel geometry in float32 at least (bfloat16 pixel indices are not exact past
    # 256), the weights cast to ``dtype`` at the end
    work = jnp.promote_types(dtype, jnp.float32)
    rows, cols = jnp.arange(shape[0]), jnp.arange(shape[1])
    dr = rows.astype(work)[:, None] - center[0].astype(work)
    dc = cols.astype(work)[None, :] - center[1].astype(work)
    dist = safe_norm(jnp.stack(jnp.broadcast_arrays(dr, dc), axis=-1))
    f = fn(dist, radius.astype(work), rows, cols)
    inside, outside = inside.astype(work), outside.astype(work)
    return (outside + (inside - outside) * f).astype(dtype)


class Focus(eqx.Module):
    """Focus plus context for a :class:`volshade.Scene`, independent of the image size.

    Attributes:
        center: ``(2,)`` focus centre ``(row, column)`` as fractions of the image
            height and width, in [0, 1] (``(0.5, 0.5)`` is the centre; a centre in
            pixels is refused: that is :func:`focus_weights`'s convention).
        radius: radius as a fraction of the image height.
        kind: ``"circular"``, ``"gaussian"`` or ``"screen_door"`` (static).
        inside, outside: global weights at the focus centre and far from it; they
            scale the :class:`Importance` measure weights, so with all of those 0 (the
            default) a focus changes nothing.

    Raises:
        ValueError: an unknown ``kind``; ``center`` not of shape ``(2,)``; when known,
            ``radius`` not a finite number > 0, NaN or inf in ``center``, ``inside`` or
            ``outside``, or ``center`` outside [0, 1]; from
            :meth:`weights`, a non-scalar ``radius``, ``inside`` or ``outside``.
        TypeError: a non-numeric (or bool) field.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): from
            :meth:`weights` (and so a render), ``radius`` not a finite number > 0,
            ``center`` outside [0, 1], NaN or inf in ``center``, ``inside`` or
            ``outside``.
    """

    center: Float[Array, "2"] = eqx.field(
        converter=_checks.leaf("volshade.Focus", "center"), default=(0.5, 0.5))
    radius: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Focus", "radius"), default=0.25)
    kind: str = eqx.field(static=True, default="gaussian", converter=_checks.python_scalar)
    inside: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Focus", "inside"), default=1.0)
    outside: Float[Array, ""] = eqx.field(
        converter=_checks.leaf("volshade.Focus", "outside"), default=0.0)

    def __check_init__(self):
        _checks.option(self.kind, FOCUS_KINDS, "kind", "volshade.Focus")
        if jnp.shape(self.center) != (2,):
            raise ValueError(f"volshade.Focus: `center` must be (row, column) fractions, "
                             f"got shape {jnp.shape(self.center)}.")
        _checks.refuse(self, [*((_checks.non_finite(getattr(self, name)),
                                 f"`{name}` must be finite.")
                                for name in ("center", "inside", "outside")),
                              (_checks.not_positive(self.radius), "`radius` must be a "
                               "finite number > 0 (a fraction of the image height)."),
                              self._center_problem()],
                       "volshade.Focus", traced=False)  # traced: by weights()

    def _center_problem(self) -> tuple[Array, str]:
        """``center`` outside ``[0, 1]``, for :func:`volshade._checks.refuse`: pixel
        coordinates would put the focus far off the image."""
        return (jnp.any((self.center < 0) | (self.center > 1)),
                "`center` must be (row, column) fractions of the image in [0, 1]; for a "
                "centre in pixels use volshade.focus_weights.")

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        if self.kind == "gaussian":
            return {}
        why = f"a {self.kind} focus is a step in it; kind='gaussian' is smooth"
        return {"center": why, "radius": why}

    def weights(self, image_shape: tuple[int, int]) -> Float[Array, "H W"]:
        """Per-ray weights for an image of ``image_shape`` (:func:`focus_weights`)."""
        # (fields set with eqx.tree_at, e.g. a tuple centre, skipped the converters)
        focus = _checks.float_leaves(self, ("center", "radius", "inside", "outside"),
                                     "volshade.Focus")
        for name, shape in (("center", (2,)), ("radius", ()), ("inside", ()), ("outside", ())):
            if jnp.shape(getattr(focus, name)) != shape:
                raise ValueError(f"volshade.Focus: `{name}` must have shape {shape}, got "
                                 f"{jnp.shape(getattr(focus, name))}; for several foci, build "
                                 f"each Focus inside jax.vmap, e.g. jax.vmap(lambda r: "
                                 f"Focus(radius=r).weights(shape))(radii).")
        h, w = _image_size(image_shape, "volshade.Focus.weights")
        dtype = jnp.result_type(focus.center, focus.radius, focus.inside, focus.outside)
        center = _checks.refuse(focus.center, [focus._center_problem()], "volshade.Focus")
        # in pixels in float32 at least: bfloat16 keeps 8 significant bits, so a
        # centre past 128 px would be rounded to half a pixel or more
        center, radius = (_checks.as_working_float(x, name, "volshade.Focus")
                          for x, name in ((center, "center"), (focus.radius, "radius")))
        center = center * jnp.asarray([h, w], center.dtype) - 0.5
        return focus_weights(image_shape, center=center, radius=radius * h, kind=focus.kind,
                             inside=focus.inside, outside=focus.outside, dtype=dtype)
