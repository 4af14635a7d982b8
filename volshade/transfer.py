r"""Transfer functions: classification of intensities into colour and opacity.

A :class:`TransferFunction` is piecewise linear in the intensity: between
control points ``points[k]`` the RGB colour and the opacity are interpolated
linearly. Values outside ``[points[0], points[-1]]`` are refused rather than classified
like the end points (that clamp would render a volume in other units as one solid
blob): a window over part of the range still needs control points at the volume's
minimum and maximum, e.g. of opacity 0. Every control
value (positions, colours, opacities) is an array leaf, so the image is
differentiable with respect to all of them.

Opacities are given for a *reference step* ``step0`` (mm, default 1 mm = one
voxel at unit spacing). A sample that stands for a segment of length
$\Delta s$ gets the corrected opacity

$$ \alpha = 1 - (1 - \alpha_0)^{\Delta s / \Delta s_0} = 1 - e^{-\tau \Delta s},
\qquad \tau = -\ln(1 - \alpha_0) / \Delta s_0, $$

(opacity correction), so the rendered physics does not depend on the sampling
rate.

A *feature* (used by feature-driven ambient occlusion) is either a transfer
function of its own or an :class:`IntervalFeature`, an intensity interval that
selects the part of a base transfer function's opacity lying inside it.
"""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import _checks, _numerics
from ._types import Array, Float

__all__ = [
    "TransferFunction", "IntervalFeature", "Feature", "feature_opacities", "PRESETS", "preset",
]

_WHERE = "volshade.TransferFunction"


def _step(step: Any, where: str, shape: tuple[int, ...]) -> Array | None:
    """A segment length for opacity correction: finite and >= 0 mm (0: opacity 0), one
    or one per value (broadcasting to the volume's ``shape``)."""
    if step is None:
        return None
    step = _checks.numbers(step, "step", where)
    if not _checks.broadcasts(step.shape, shape):
        raise ValueError(f"{where}: `step` must be one length or broadcast to the volume's "
                         f"shape {shape}, got shape {step.shape}.")
    return _checks.refuse(step, [(~(jnp.isfinite(step) & (step >= 0)),
                                  "`step` must be a finite segment length >= 0 mm (a "
                                  "length of 0 has opacity 0).")], where)


_LEAVES = ("points", "colors", "opacities")


class TransferFunction(eqx.Module):
    """Piecewise-linear 1D transfer function (intensity -> RGB colour, opacity).

    Attributes:
        points: ``(K,)`` increasing intensity positions of the control points.
        colors: ``(K, 3)`` RGB colours in [0, 1] at the control points.
        opacities: ``(K,)`` opacities in [0, 1] for a segment of length ``step0``.
        step0: reference segment length in mm for ``opacities`` (static).

    Raises:
        ValueError: ``points`` not a non-empty 1-D array; ``colors`` not ``(K, 3)`` or
            ``opacities`` not ``(K,)``; ``step0`` not a finite number > 0.
        TypeError: non-numeric (or bool) ``points``, ``colors`` or ``opacities``;
            ``step0`` not a number.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): ``points`` not
            finite and strictly increasing, ``colors`` or ``opacities`` outside [0, 1]
            (or NaN); traced values are checked where the function is used
            (:meth:`opacity`, :meth:`color`, a render).

    Example:
        >>> tf = TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (1.0, 1, 1, 1, 0.5)])
        >>> float(tf.opacity(jnp.array(0.5)))
        0.25
    """

    points: Float[Array, " K"] = eqx.field(converter=_checks.leaf(_WHERE, "points"))
    colors: Float[Array, "K 3"] = eqx.field(converter=_checks.leaf(_WHERE, "colors"))
    opacities: Float[Array, " K"] = eqx.field(converter=_checks.leaf(_WHERE, "opacities"))
    # a Python float (equinox warns of a JAX array in a static field)
    step0: float = eqx.field(static=True, default=1.0,
                             converter=lambda s: _checks.positive_float(s, "step0", _WHERE))

    def __check_init__(self):
        self._check_shapes()
        _checks.refuse(self, self._problems(), _WHERE, traced=False)  # traced: when used

    def _check_shapes(self) -> None:
        k = jnp.shape(self.points)
        # (a batch of transfer functions, stacked for jax.vmap, fails here when used
        # without it: say so)
        batch = "; a batch of transfer functions is for jax.vmap" if len(k) > 1 else ""
        if len(k) != 1 or k[0] < 1:
            raise ValueError(f"{_WHERE}: `points` must be a non-empty 1-D array, got shape "
                             f"{k}{batch}.")
        if jnp.shape(self.colors) != (k[0], 3):
            raise ValueError(f"{_WHERE}: `colors` must have shape ({k[0]}, 3) to match `points`, "
                             f"got {jnp.shape(self.colors)}.")
        if jnp.shape(self.opacities) != k:
            raise ValueError(f"{_WHERE}: `opacities` must have shape {k} to match `points`, "
                             f"got {jnp.shape(self.opacities)}.")

    def _problems(self) -> list[tuple[Array, str]]:
        """``(is_bad, message)`` for the control values: points finite and strictly
        increasing, colours and opacities in [0, 1]."""
        xp, points, colors, opacities = _checks.for_check(self.points, self.colors,
                                                          self.opacities)

        def outside(x):
            return ~((x >= 0) & (x <= 1))

        return [
            (xp.any(xp.diff(points) <= 0) | ~xp.all(xp.isfinite(points)),
             "`points` must be finite and strictly increasing (sort the control points; "
             "a fit should keep their order, e.g. through cumulative positive gaps)."),
            (xp.any(outside(colors)) | xp.any(outside(opacities)),
             "`colors` and `opacities` must lie in [0, 1] (a fit should keep them there, "
             "e.g. through a sigmoid)."),
        ]

    def _checked(self, volume, where: str) -> tuple["TransferFunction", Array]:
        """This function and ``volume``, checked for use: the control values (which a fit
        or ``eqx.tree_at`` may have set), and ``volume`` finite and within the points
        (integers and bools as floats: the interpolation runs in the volume's dtype, which
        would truncate every opacity and colour to 0; half precision as float32:
        ``jnp.interp`` refuses it)."""
        # leaves set with eqx.tree_at skipped the converters and the shape checks
        tf = _checks.float_leaves(self, _LEAVES, _WHERE)
        tf._check_shapes()
        tf = _checks.refuse(tf, tf._problems(), _WHERE)
        volume = _checks.finite(_checks.as_working_float(volume, "volume", where), "volume",
                                where)
        # in the volume's dtype, as _interp classifies: float32(0.3) > 0.3 in float64
        points = tf.points.astype(volume.dtype)
        # (an elementwise test: an empty volume has no value outside, and is classified)
        outside = jnp.any((volume < points[0]) | (volume > points[-1]))
        # jnp.interp takes points closer than this for a step (a volume in units of
        # 1e-15 classified 0.25 of the way between two points as the first point's)
        resolution = float(np.spacing(np.finfo(volume.dtype).eps))
        return tf, _checks.refuse(volume, [(
            jnp.any(jnp.diff(points) <= resolution),
            f"the transfer function's `points` must lie more than {resolution:.1e} apart "
            f"in {volume.dtype.name}, the volume's dtype (jnp.interp, which classifies, "
            f"takes closer points for a step); rescale the volume and the points, e.g. "
            f"to [0, 1]."), (
            # interpolation would classify all those values like the end points (a 0-255
            # volume through a [0, 1] transfer function renders as one solid blob)
            outside,
            "`volume` has values outside the transfer function's control points "
            "[points[0], points[-1]], which would all be classified like the end points; "
            "add control points at the volume's minimum and maximum (e.g. of opacity 0 "
            "around a window), or rescale the volume to the points' range (e.g. "
            "`volshade.data.load(..., normalize=True)` for [0, 1]).")], where)

    @classmethod
    def from_points(
        cls, points: Sequence[Sequence[float]], *, step0: float = 1.0, dtype=None
    ) -> "TransferFunction":
        """Build from rows ``(intensity, r, g, b, opacity)`` with increasing intensities.

        Raises:
            ValueError: rows not of length 5, intensities not strictly increasing,
                colours or opacities outside [0, 1], or non-finite values.
            TypeError: values that are not real numbers, or traced ones (the
                constructor takes those).
        """
        where = "volshade.TransferFunction.from_points"
        if _checks.traced(points):
            raise TypeError(f"{where}: `points` is traced (inside jit, grad or vmap), and "
                            f"from_points checks its rows when it is called; build "
                            f"`TransferFunction(points[:, 0], points[:, 1:4], points[:, 4])`,"
                            f" whose arrays may be traced, instead.")
        try:
            table = np.asarray(points)
        except ValueError as err:  # rows of different lengths
            raise ValueError(f"{where}: `points` must be rows (intensity, r, g, b, opacity) "
                             f"of 5 numbers each, got {points!r:.80}.") from err
        # converted, a complex number would lose its imaginary part, a bool pass as 0/1
        # (also beside numbers, which NumPy promotes)
        has_bool = _checks.holds_bool(points)
        if has_bool or table.dtype.kind not in "iuf":
            got = "a bool" if has_bool else f"{table.dtype} values"
            raise TypeError(f"{where}: `points` must be rows of 5 real numbers (intensity, "
                            f"r, g, b, opacity), got {got}.")
        table = table.astype(float)
        if table.ndim != 2 or table.shape[1] != 5 or table.shape[0] < 1:
            raise ValueError(f"{where}: `points` must be rows (intensity, r, g, b, opacity), "
                             f"got shape {table.shape}.")
        if not np.all(np.isfinite(table)):
            raise ValueError(f"{where}: `points` contains NaN or inf.")
        dtype = (jnp.result_type(float) if dtype is None
                 else _checks.floating_dtype(dtype, where))
        return cls(jnp.asarray(table[:, 0], dtype), jnp.asarray(table[:, 1:4], dtype),
                   jnp.asarray(table[:, 4], dtype), step0=step0)

    def _interp(self, values: Array, table: Array) -> Array:
        # Classification follows the volume's dtype, whatever the control values' dtype.
        return jnp.interp(values, self.points.astype(values.dtype), table.astype(values.dtype))

    def _opacity(self, volume: Array, step) -> Array:
        alpha0 = self._interp(volume, self.opacities)
        if step is None:
            return alpha0
        return _numerics.correct_opacity(alpha0, jnp.asarray(step, volume.dtype) / self.step0)

    def _color(self, volume: Array) -> Array:
        return jnp.stack([self._interp(volume, self.colors[:, c]) for c in range(3)], axis=-1)

    def _rgba(self, volume: Array, step=None) -> tuple[Array, Array]:
        """``(color, opacity)`` without the finiteness check, for the renderer's samples
        (interpolated from a volume checked once; a run-time check at every step of the
        march would cost a host round trip on a GPU)."""
        return self._color(volume), self._opacity(volume, step)

    def opacity(self, volume: Float[Array, "*shape"], *, step: float | Array | None = None
                ) -> Float[Array, "*shape"]:
        r"""Opacity of each value; with ``step`` (mm), corrected to that segment length.

        Integer and bool volumes are classified as their values (as floats, of the
        default float dtype); half precision is classified and returned in float32 (so
        are :meth:`color`, :meth:`extinction` and the call): its few digits would round
        the control points. The correction $1 - (1 - \alpha_0)^{r}$,
        $r = $ ``step / step0``, has an infinite slope at $\alpha_0 = 1$ for $r < 1$;
        its gradient there is returned as 0 (so that it stays finite): an opacity of
        exactly 1 sampled at a step shorter than ``step0`` (as :func:`volshade.render`
        does for ``step < step0``) gets no gradient. Keep fitted opacities below 1 to
        fit them.

        Raises:
            ValueError: NaN or inf in ``volume`` (interpolation would clamp an
                infinite value to the last control point's opacity, silently), or
                values outside ``[points[0], points[-1]]`` (the same clamp); control
                points closer than ``jnp.interp`` resolves in the volume's dtype
                (1.4e-14 in float32); a negative or non-finite ``step``, or one that
                does not broadcast to the volume.
            TypeError: ``volume`` not real numbers (complex, strings).
        """
        tf, volume = self._checked(volume, f"{_WHERE}.opacity")
        return tf._opacity(volume, _step(step, f"{_WHERE}.opacity", volume.shape))

    def extinction(self, volume: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        r"""Extinction $\tau = -\ln(1-\alpha_0)/\Delta s_0$ per mm (inf where opaque)."""
        tf, volume = self._checked(volume, f"{_WHERE}.extinction")
        return -_numerics.log1m(tf._opacity(volume, None)) / self.step0

    def color(self, volume: Float[Array, "*shape"]) -> Float[Array, "*shape 3"]:
        """RGB colour of each value, shape ``(*shape, 3)``; NaN or inf, and values
        outside ``[points[0], points[-1]]``, are refused (as by :meth:`opacity`)."""
        tf, volume = self._checked(volume, f"{_WHERE}.color")
        return tf._color(volume)

    def __call__(self, volume: Float[Array, "*shape"], *, step=None):
        """``(color, opacity)`` of each value; NaN or inf, and values outside
        ``[points[0], points[-1]]``, are refused (as by :meth:`opacity`)."""
        tf, volume = self._checked(volume, f"{_WHERE}.__call__")
        return tf._rgba(volume, _step(step, f"{_WHERE}.__call__", volume.shape))


def _ordered(xp, low, high):
    """Whether every interval ``[low, high]`` has finite ends, ``low < high`` (``xp``:
    NumPy for the known ends, ``jax.numpy`` for traced ones)."""
    return xp.all(xp.isfinite(low) & xp.isfinite(high) & (low < high))


class IntervalFeature(eqx.Module):
    """A feature given by an intensity interval ``[low, high]`` of a base transfer function.

    Its opacity is the base opacity where ``low <= value <= high`` and 0 elsewhere.

    Args:
        low, high: the interval's ends, in the intensity units of the base transfer
            function's ``points``, ``low < high`` (array leaves; the selection is a
            step in them, so they get no gradient). Finite, as every scene parameter
            (for an open side, use the transfer function's end point).

    Raises:
        TypeError: a non-numeric (or bool) ``low`` or ``high``.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): ``low >= high``
            or an end that is not finite; traced values are checked where the feature
            is used (:meth:`opacity`, :func:`feature_opacities`), and so are the ends'
            shapes (scalars there; a batch of features is for ``jax.vmap``).
    """

    low: Float[Array, ""]
    high: Float[Array, ""]

    def __init__(self, low: float, high: float):
        where = "volshade.IntervalFeature"
        self.low = _checks.float_leaf(low, "low", where).astype(float)
        self.high = _checks.float_leaf(high, "high", where).astype(float)
        # on the inputs: under jit, even an array made from a Python number is traced
        # (traced bounds are checked where they are used, in _select)
        known_low, known_high = _checks.concrete(low), _checks.concrete(high)
        if known_low is not None and known_high is not None and \
                not _ordered(np, known_low, known_high):
            raise ValueError(f"{where}: need finite `low` < `high`, got {low}, {high}.")

    def _without_gradient(self) -> dict[str, str]:
        """The leaves whose derivative is zero wherever defined (:func:`volshade.fit`)."""
        why = "the interval's ends only select voxels"
        return {"low": why, "high": why}

    def opacity(self, volume: Array, base: TransferFunction, *,
                step: float | Array | None = None) -> Array:
        """``base.opacity(volume, step=step)`` inside ``[low, high]``, 0 outside; an interval
        known to lie outside ``base``'s control points (it would select nothing) is
        refused."""
        where = "volshade.IntervalFeature.opacity"
        if not isinstance(base, TransferFunction):
            raise TypeError(f"{where}: `base` must be a volshade.TransferFunction, got "
                            f"{type(base).__name__}.")
        _check_interval_meets(self, base, "the interval", where)
        volume = _checks.as_working_float(volume, "volume", where)
        return self._select(volume, base.opacity(volume, step=step))

    def _select(self, volume: Array, base_opacity: Array) -> Array:
        # compared in the volume's dtype, as it is classified: a float32 volume of 0.4
        # lies inside [0.2, 0.4] whatever the dtype the bounds were made in
        # (as arrays: an end set to a Python float with eqx.tree_at has no astype)
        low, high = (jnp.asarray(end, volume.dtype) for end in (self.low, self.high))
        selected = jnp.where((volume >= low) & (volume <= high), base_opacity, 0)
        return _checks.refuse(selected, [(~_ordered(jnp, self.low, self.high),
                                          "need finite `low` < `high`.")],
                              "volshade.IntervalFeature")


Feature = TransferFunction | IntervalFeature


def _feature_tuple(features: Any, where: str) -> tuple[Feature, ...]:
    """``features`` as a non-empty tuple of features, or a clear error naming ``where``."""
    if isinstance(features, Feature):
        raise TypeError(f"{where}: `features` must be a list of features; for one, pass "
                        f"[{type(features).__name__}(...)].")
    try:
        features = tuple(features)
    except TypeError as err:
        raise TypeError(f"{where}: `features` must be a list of TransferFunction or "
                        f"IntervalFeature, got {type(features).__name__}.") from err
    if not features:
        raise ValueError(f"{where}: `features` is empty; pass at least one feature.")
    for i, feature in enumerate(features):
        if not isinstance(feature, Feature):
            raise TypeError(f"{where}: features[{i}] must be a TransferFunction or "
                            f"IntervalFeature, got {type(feature).__name__}.")
    return features


def feature_opacities(
    volume: Float[Array, "D H W"],
    features: Sequence[Feature],
    *,
    base: TransferFunction | None = None,
    step: float | None = None,
) -> Float[Array, "F D H W"]:
    """Stack the opacity volume of each feature (transfer functions or intervals of ``base``).

    ``step`` (mm, > 0), if given, corrects every opacity to that segment length, as
    :meth:`TransferFunction.opacity` does.

    Raises:
        ValueError: no features, an interval feature without a ``base``, a ``step``
            that is not a finite number > 0.
        TypeError: ``features`` not a list of features, ``base`` not a
            :class:`TransferFunction`.
    """
    return _feature_opacities(volume, features, base, step,
                              "volshade.transfer.feature_opacities")


def _feature_opacities(volume, features, base, step, where: str) -> Array:
    """:func:`feature_opacities`, its errors naming ``where`` (the function called)."""
    features = _feature_tuple(features, where)
    # half precision as float32, as every feature's classification (and _select) reads it
    volume = _checks.at_least_float32(_checks.volume(volume, "volume", where))
    if base is not None and not isinstance(base, TransferFunction):
        raise TypeError(f"{where}: `base` must be a volshade.TransferFunction (the one the "
                        f"interval features select from), got {type(base).__name__}.")
    if step is not None:
        step = _checks.positive_float(step, "step", where)
    out = []
    base_opacity = None  # classified once for all the intervals
    # the volume's range, fetched from the device once for all the features (when known)
    extent = (_checks.concrete(jnp.stack([jnp.min(volume), jnp.max(volume)]))
              if any(isinstance(f, TransferFunction) for f in features) else None)
    for i, feature in enumerate(features):
        if isinstance(feature, TransferFunction):
            _check_feature_range(feature, volume.dtype, extent, i, where)
            out.append(feature.opacity(volume, step=step))
            continue
        if base is None:
            raise ValueError(f"{where}: features[{i}] is an interval; pass `base=` "
                             f"the transfer function it selects from.")
        _check_interval_meets(feature, base, f"features[{i}], the interval", where)
        if base_opacity is None:
            base_opacity = base.opacity(volume, step=step)
        out.append(feature._select(volume, base_opacity))
    return jnp.stack(out)


def _check_interval_meets(feature: "IntervalFeature", base: TransferFunction, what: str,
                          where: str) -> None:
    """Refuse, when known, an interval that lies outside ``base``'s control points: the
    volume's values lie within them (``base.opacity`` refuses others), so it would select
    no voxel, and its feature's AO would be 1 everywhere without a word (an interval
    written in raw intensities, e.g. (40, 100), for a normalised volume). Its ends must
    be scalars here: an array of them would broadcast over the volume's last axis, each
    column of voxels selected by another interval (a batch of features is for
    ``jax.vmap``, as a batch of clips)."""
    for name in ("low", "high"):
        if jnp.shape(getattr(feature, name)) != ():
            raise ValueError(f"{where}: {what}'s `{name}` must have shape () where it is "
                             f"used, got {jnp.shape(getattr(feature, name))}; for several "
                             f"intervals make several features, or jax.vmap over them.")
    known = _checks.concrete((feature.low, feature.high, base.points[0], base.points[-1]))
    if known is None:
        return
    low, high, first, last = (float(v) for v in known)
    if high < first or low > last:
        raise ValueError(f"{where}: {what} [{low:g}, {high:g}] lies "
                         f"outside `base`'s control points [{first:g}, {last:g}], which "
                         f"every value of the volume lies within: it selects no voxel. "
                         f"Give it in the volume's values (e.g. normalised to [0, 1]).")


def _check_feature_range(feature: TransferFunction, dtype, extent: np.ndarray | None, i: int,
                         where: str) -> None:
    """Refuse, when known, a feature whose control points do not span the volume's
    ``extent`` (min, max): the natural way to write a band stops at its edges.
    ``opacity`` checks traced values."""
    # (fields set with eqx.tree_at skipped the converters and the shape checks)
    feature = _checks.float_leaves(feature, _LEAVES, _WHERE)
    feature._check_shapes()
    # in the dtype opacity() compares in (half precision as float32)
    points = _checks.concrete(feature.points.astype(jnp.promote_types(dtype, jnp.float32)))
    if points is None or extent is None:
        return
    low, high = (float(x) for x in extent)
    if low < points[0] or high > points[-1]:
        raise ValueError(
            f"{where}: features[{i}]'s control points span [{points[0]:g}, {points[-1]:g}], "
            f"but `volume` holds values in [{low:g}, {high:g}], which it would classify like "
            f"its end points; add control points at the volume's ends (opacity 0 outside the "
            f"band), or select the band with volshade.IntervalFeature(low, high) and `base=`.")


def _preset_grey() -> TransferFunction:
    return TransferFunction.from_points([(0.0, 0, 0, 0, 0.0), (0.1, 0.3, 0.3, 0.3, 0.0),
                                         (1.0, 1, 1, 1, 0.3)])


def _preset_shells() -> TransferFunction:
    return TransferFunction.from_points([
        (0.0, 0.0, 0.0, 0.0, 0.0), (0.15, 0.9, 0.6, 0.3, 0.0), (0.3, 0.9, 0.6, 0.3, 0.04),
        (0.45, 0.9, 0.6, 0.3, 0.0), (0.5, 0.3, 0.6, 0.9, 0.0), (0.6, 0.3, 0.6, 0.9, 0.15),
        (0.75, 0.3, 0.6, 0.9, 0.0), (0.85, 0.95, 0.95, 0.9, 0.3), (1.0, 0.95, 0.95, 0.9, 0.9),
    ])


def _preset_head() -> TransferFunction:
    # Colin27 T1 normalised to [0, 1]: air < 0.05, skull (dark) 0.05-0.12, brain
    # 0.2-0.35, scalp and its fat 0.2-0.6; a firm skin surface from about 0.15 up.
    return TransferFunction.from_points([
        (0.0, 0, 0, 0, 0.0), (0.1, 0.8, 0.55, 0.45, 0.0), (0.2, 0.93, 0.72, 0.6, 0.35),
        (0.45, 0.97, 0.82, 0.72, 0.6), (1.0, 1.0, 0.95, 0.9, 0.85),
    ])


def _preset_head_skull() -> TransferFunction:
    # The head preset plus the dark T1 band of the skull (0.05-0.12) as a faint bluish
    # bone layer: hidden under the skin by standard compositing, revealed by importance.
    return TransferFunction.from_points([
        (0.0, 0, 0, 0, 0.0), (0.04, 0.9, 0.9, 0.95, 0.0), (0.07, 0.9, 0.9, 0.95, 0.1),
        (0.1, 0.9, 0.9, 0.95, 0.1), (0.14, 0.93, 0.72, 0.6, 0.02), (0.2, 0.93, 0.72, 0.6, 0.5),
        (0.45, 0.97, 0.82, 0.72, 0.6), (1.0, 1.0, 0.95, 0.9, 0.85),
    ])


def _preset_corner() -> TransferFunction:
    # Intensities of the corner phantom's walls: 0.5 green, 0.75 blue, 1.0 white. The walls
    # are labels: classified after interpolation, the values between air and a wall pass
    # through the lower walls' bands, so render them with classification="pre".
    return TransferFunction.from_points([
        (0.0, 0, 0, 0, 0.0), (0.25, 0.1, 0.8, 0.1, 0.0), (0.5, 0.1, 0.8, 0.1, 1.0),
        (0.625, 0.1, 0.8, 0.1, 1.0), (0.626, 0.1, 0.2, 0.9, 1.0), (0.75, 0.1, 0.2, 0.9, 1.0),
        (0.875, 0.1, 0.2, 0.9, 1.0), (0.876, 1, 1, 1, 1.0), (1.0, 1, 1, 1, 1.0),
    ])


PRESETS: dict[str, Callable[[], TransferFunction]] = {
    "grey": _preset_grey,
    "shells": _preset_shells,
    "head": _preset_head,
    "head_skull": _preset_head_skull,
    "corner": _preset_corner,
}


def preset(name: str) -> TransferFunction:
    """A named transfer function from :data:`PRESETS`.

    ``"grey"``, ``"shells"`` (the shells phantom), ``"head"`` and ``"head_skull"``
    (Colin27 T1; the latter with the skull band), ``"corner"`` (the corner phantom's
    labels: 0.5 green, 0.75 blue, 1.0 white). The corner phantom's walls are labels:
    classified after interpolation (the renderer's default), the values between air
    and the white wall pass through the green and blue bands, and the floor shows
    rings of those colours. Render labels with ``Scene(classification="pre")``, which
    interpolates the classified voxels instead.

    Raises:
        ValueError: unknown name (the message lists the valid ones).
        TypeError: ``name`` not a string.
    """
    return _checks.option(name, PRESETS, "transfer-function preset", "volshade.transfer.preset")()
