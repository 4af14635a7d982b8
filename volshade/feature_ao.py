r"""Feature-driven ambient occlusion: AO per feature, the other features transparent, merged.

Classic local ambient occlusion over-darkens multi-layer volumes: an inner layer
(the skull under the scalp) is occluded by the outer one and disappears. Ancel et
al. (2010, section 4) split the volume into *features* $k = 1..n_f$ (transfer
functions or intensity intervals), compute one occlusion volume per feature with
every other feature transparent,

$$ T_k(x) = \mathrm{AO}\big(\alpha_k\big)(x), \qquad \alpha_k = \text{opacity of feature } k,
\quad \alpha_j = 0 \text{ for } j \ne k \quad \text{(section 4.1)}, $$

so each feature keeps its self-occlusion (the shape cues) without the
occlusion of the others, and then merge the $T_k$ into one ambient volume
(section 4.2, :data:`MERGES`):

* ``"max"`` (the paper's choice, used for all its results): the *maximum
  occlusion*, $\mathrm{AO}(x) = \min_k T_k(x)$. The paper writes it as a
  maximum of its occlusion values, which grow towards a feature; here AO is a
  visibility (1 = unoccluded, as :func:`~volshade.lao.lao` returns it), so the
  same operator is the minimum. The maximum *visibility* would be 1 wherever any
  one feature is out of reach, i.e. almost everywhere. (Section 4.1 of the paper
  describes the $T_k$ as occlusion factors that *decrease* towards occluders,
  which would make its maximum this same visibility maximum; its section 4.2 and
  its results read them as occlusions, and so does this merge.) Each voxel keeps the
  occlusion of the single feature that occludes it most, its own or a
  neighbour's: it "extends the influence of opaque features to neighbouring less
  opaque ones" (section 4.2), and only the sum of several features' occlusions,
  which over-darkens classic AO, is gone.
* ``"feature"``: each voxel takes the value of its own feature,
  $T_{f(x)}(x)$ (Figure 3a), with $f(x)$ the feature of largest opacity at
  $x$ (the first on ties); voxels of no feature (all $\alpha_k = 0$) take the
  ``"max"`` value. Only this merge drops all inter-occlusion; it shows the
  abrupt borders that motivate the other two.
* ``"neighbourhood"``: where the voxel and all its 26 neighbours inside the
  volume belong to one feature $k$, $T_k(x)$ (the ``"feature"`` value);
  otherwise the opacity-weighted mean over the $3^3$ neighbourhood, the voxel
  itself included (section 4.2, Figure 3b),

  $$ \mathrm{AO}(x) = \frac{\sum_i \alpha_i\, T_{f(x^i)}(x^i)}{\sum_i \alpha_i}, $$

  with $\alpha_i$ the opacity of neighbour $x^i$'s feature there (empty voxels
  weigh 0, voxels outside the volume are left out); a neighbourhood with no
  feature, or whose opacities sum to less than the dtype's epsilon, takes the
  ``"max"`` value (the mean's derivative grows as the inverse of that sum). The
  paper does not say whether the voxel itself counts; here it does in both
  cases.

Every $T_k$ is :func:`~volshade.lao.lao` of $\alpha_k$, so it is exact, gather-free
and differentiable in the radius, the offset, the directional weights and (through
the opacities) the transfer functions' control values and the volume. The features
are marched one after the other (``lax.map``): one compiled march whatever $n_f$;
the forward pass holds one :func:`~volshade.lao.lao` call's memory plus $2 n_f$
volumes, and reverse mode keeps each feature's march inputs as well.

**Bricking** (section 4.3): with ``brick_size`` each feature's march skips the
bricks with none of *that* feature's opacity within reach of the radius
(:func:`~volshade.lao.lao`'s bricking, on $\alpha_k$). The paper's per-feature
structure marks instead the bricks that hold none of the feature's voxels, "with
some overlapping" (1 to 3 voxels in its Table 3), and skips them as unused by the
merge; but the ``"max"`` and ``"neighbourhood"`` merges read $T_k$ at voxels of
other features and of empty space, so here a brick is skipped only where $T_k = 1$
exactly, and skipping never changes a value. The paper's single global structure
(bricks empty of every feature) exists to save building $n_f$ structures on the
GPU; here a structure is one max-pool of the opacity, negligible beside a march,
so only the per-feature structure, which skips at least as much, is offered.

References:
    Ancel, Dischler, Mongenet, "Feature-driven ambient occlusion for direct volume
    rendering", IEEE/EG Volume Graphics 2010, sections 4.1-4.3, eq. 3-6.
"""

import functools
import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from . import _checks
from ._types import Array, ArrayLike, Float, Int, Volume
from .lao import _IMPLEMENTATIONS, LocalAmbientOcclusion, _concrete, _prepare
from .transfer import Feature, TransferFunction, _feature_opacities, _feature_tuple

_WHERE = "volshade.feature_ao"
_NO_FEATURE = -1


def _fold(op, stack: Array) -> Array:
    """``op`` folded over the (small, static) feature axis: on XLA's CPU backend this is
    ~30x faster than the equivalent reduction over a leading axis (measured)."""
    return functools.reduce(op, [stack[k] for k in range(stack.shape[0])])


def feature_labels(opacities: Float[Array, "F D H W"]) -> Int[Array, "D H W"]:
    """The feature $f(x)$ of every voxel (section 4.2).

    Args:
        opacities: ``(F, D, H, W)`` opacity of each feature, in [0, 1].

    Returns:
        ``(D, H, W)`` index of the feature of largest opacity (the first on ties), or
        -1 where every feature is transparent.

    Raises:
        ValueError: ``opacities`` not 4-D, or empty.
        TypeError: non-numeric ``opacities``.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): NaN, inf or
            values outside ``[0, 1]``.

    Example:
        >>> a = jnp.stack([jnp.full((2, 2, 2), 0.3), jnp.full((2, 2, 2), 0.6)])
        >>> int(feature_labels(a.at[:, 0].set(0.0))[0, 0, 0]), int(feature_labels(a)[1, 1, 1])
        (-1, 1)
    """
    where = "volshade.feature_ao.feature_labels"
    opacities = _checks.as_float_array(opacities, "opacities", where)
    _checks.check_ndim(opacities, 4, "opacities", where, "(F, D, H, W)")
    return _labels(_checks.finite(opacities, "opacities", where, unit_range=True))


def _labels(opacities: Array) -> Array:
    """:func:`feature_labels` of checked opacities."""
    return jnp.where(_fold(jnp.maximum, opacities) > 0, jnp.argmax(opacities, axis=0),
                     _NO_FEATURE)


def _own(ao: Array, labels: Array, fallback: Array) -> Array:
    """$T_{f(x)}(x)$, and ``fallback`` where $x$ has no feature."""
    own = fallback
    for k in range(ao.shape[0]):
        own = jnp.where(labels == k, ao[k], own)
    return own


def _max_occlusion(ao: Array, opacities: Array) -> Array:
    return _fold(jnp.minimum, ao)


def _own_feature(ao: Array, opacities: Array) -> Array:
    return _own(ao, _labels(opacities), _max_occlusion(ao, opacities))


def _box(x: Array, op, mode: str) -> Array:
    """``op`` (associative) over the 3x3x3 neighbourhood of every voxel, separably;
    outside the volume the neighbours are 0 (``mode="constant"``) or the nearest
    voxel (``"edge"``), as ``jnp.pad`` pads."""
    x = jnp.pad(x, 1, mode=mode)
    for axis in range(3):
        n = x.shape[axis] - 2
        x = op(op(lax.slice_in_dim(x, 0, n, axis=axis), lax.slice_in_dim(x, 1, n + 1, axis=axis)),
               lax.slice_in_dim(x, 2, n + 2, axis=axis))
    return x


def _neighbourhood(ao: Array, opacities: Array) -> Array:
    labels = _labels(opacities)
    fallback = _max_occlusion(ao, opacities)
    own = _own(ao, labels, fallback)
    weight = _fold(jnp.maximum, opacities)  # the opacity of each voxel's own feature
    numerator = _box(weight * own, jnp.add, "constant")
    denominator = _box(weight, jnp.add, "constant")
    # an edge-padded neighbour is the nearest voxel inside, itself a neighbour: so this
    # asks whether every neighbour inside the volume has the voxel's feature (a
    # neighbourhood of no feature gets `own`, which is then the fallback too)
    uniform = _box(labels, jnp.minimum, "edge") == _box(labels, jnp.maximum, "edge")
    # below eps the mean's derivative (of order 1 / denominator) would overflow
    enough = denominator > jnp.finfo(denominator.dtype).eps
    mixed = jnp.where(enough, numerator / jnp.where(enough, denominator, 1), fallback)
    return jnp.where(uniform, own, mixed)


MERGES: dict[str, Callable[[Array, Array], Array]] = {
    "max": _max_occlusion,
    "feature": _own_feature,
    "neighbourhood": _neighbourhood,
}
"""Merge operators of section 4.2: name -> ``(ao (F, D, H, W), opacities (F, D, H, W))
-> (D, H, W)``."""


def merge_feature_ao(
    ao: Float[Array, "F D H W"],
    opacities: Float[Array, "F D H W"],
    *,
    merge: str = "max",
) -> Volume:
    r"""Merge per-feature occlusion volumes $T_k$ into one AO volume (section 4.2).

    Args:
        ao: ``(F, D, H, W)`` per-feature AO $T_k$ in ``[0, 1]`` (1 = unoccluded).
        opacities: ``(F, D, H, W)`` opacity $\alpha_k$ of each feature, in ``[0, 1]``;
            they assign voxels to features (largest opacity) and weigh the
            ``"neighbourhood"`` mean.
        merge: ``"max"`` (maximum occlusion, i.e. $\min_k T_k$; the paper's choice),
            ``"feature"`` (each voxel's own feature) or ``"neighbourhood"``
            (opacity-weighted $3^3$ mean at feature borders); see the module
            docstring.

    Returns:
        ``(D, H, W)`` AO in ``[0, 1]``, in the dtype of ``ao`` (computed in float32 at
        least).

    Raises:
        ValueError: ``ao`` or ``opacities`` not 4-D or empty (no feature), shapes that
            differ, an unknown ``merge``.
        TypeError: ``ao`` or ``opacities`` not arrays of real numbers.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time):
            NaN, inf or values outside ``[0, 1]``.

    Example:
        >>> ao = jnp.stack([jnp.full((4, 4, 4), 0.75), jnp.full((4, 4, 4), 0.5)])
        >>> float(merge_feature_ao(ao, jnp.ones_like(ao))[0, 0, 0])  # maximum occlusion
        0.5
    """
    where = "volshade.merge_feature_ao"
    _checks.option(merge, MERGES, "merge", where)
    ao = _checks.as_float_array(ao, "ao", where)
    opacities = _checks.as_float_array(opacities, "opacities", where)
    _checks.check_ndim(ao, 4, "ao", where, "(F, D, H, W)")
    if opacities.shape != ao.shape:
        raise ValueError(f"{where}: `opacities` must have the shape of `ao` {ao.shape}, one "
                         f"opacity volume per feature, got {opacities.shape}.")
    ao = _checks.finite(ao, "ao", where, unit_range=True,
                        hint="(AO volumes, 1 = unoccluded)")
    opacities = _checks.finite(opacities, "opacities", where, unit_range=True)
    # half precision is merged in float32: the neighbourhood mean's derivative, of order
    # 1 / (summed opacity)^2, overflows float16 below a sum of 4e-3
    work = _checks.at_least_float32(ao)
    # "max" ignores the opacities: read them, or their run-time check is pruned under jit
    merged = _checks.reading(_merge(work, opacities.astype(work.dtype), merge), opacities)
    return merged.astype(ao.dtype)


@functools.partial(jax.jit, static_argnames="merge")
def _merge(ao: Array, opacities: Array, merge: str) -> Array:
    """``MERGES[merge]``, compiled once per shape: eagerly, each of its operations
    would be compiled on its own."""
    return MERGES[merge](ao, opacities)


def feature_ao(
    volume: Volume,
    *,
    features: Sequence[Feature],
    directions: Float[ArrayLike, "L 3"] | int,
    radius: Float[ArrayLike, ""],
    offset: Float[ArrayLike, ""] = 1.0,
    samples: int = 16,
    merge: str = "max",
    base: TransferFunction | None = None,
    step: float | None = None,
    weights: Float[ArrayLike, " L"] | None = None,
    opacity_correction: bool = False,
    brick_size: int | None = None,
    max_radius: float | None = None,
    implementation: str = "xla",
) -> Volume:
    r"""Feature-driven ambient occlusion of a volume (Ancel et al. 2010, section 4).

    $T_k = \mathrm{AO}(\alpha_k)$ for each feature with the others transparent
    (section 4.1; $\mathrm{AO}$ is eq. 3-4, :func:`~volshade.lao.lao`), merged by
    ``merge`` (section 4.2). See the module docstring.

    Args:
        volume: ``(D, H, W)`` intensities (classified by each feature; NaN or inf is
            refused).
        features: the features, each a :class:`~volshade.TransferFunction` (its
            opacity) or an :class:`~volshade.IntervalFeature` of ``base``.
        directions, radius, offset, samples, weights, opacity_correction, brick_size,
            max_radius, implementation: as for :func:`~volshade.lao.lao`, shared by
            every feature; ``brick_size`` skips, per feature, the bricks with none of
            that feature's opacity within reach (section 4.3).
        merge: ``"max"`` (maximum occlusion, the paper's choice), ``"feature"`` or
            ``"neighbourhood"`` (:data:`MERGES`, :func:`merge_feature_ao`).
        base: the transfer function that interval features select from.
        step: segment length (mm, > 0) the features' opacities are corrected to
            (:meth:`~volshade.TransferFunction.opacity`); with
            ``opacity_correction``, pass the voxel size so that each opacity is that
            of a one-voxel step, as :func:`~volshade.lao.lao` reads it. ``None``
            (the default) takes the opacities as classified.

    Returns:
        ``(D, H, W)`` AO in ``[0, 1]`` (1 = unoccluded), in the volume's dtype (at
        least float32).

    Raises:
        ValueError: no features, an interval feature without ``base``, a bad ``step``,
            an unknown ``merge``, a volume outside a transfer function's control points
            (``base``'s or a feature's), and every error of :func:`~volshade.lao.lao`.
        TypeError: ``features`` not a list of features, a ``base`` that is not a
            transfer function.

    References:
        Ancel, Dischler, Mongenet, "Feature-driven ambient occlusion for direct
        volume rendering", IEEE/EG Volume Graphics 2010, section 4.

    Example:
        >>> vol = vs.data.phantom("shells", shape=16)
        >>> inner = vs.IntervalFeature(0.8, 1.0)
        >>> outer = vs.IntervalFeature(0.2, 0.4)
        >>> ao = feature_ao(vol, features=[inner, outer], base=vs.transfer.preset("shells"),
        ...                 directions=12, radius=4.0, samples=8)
        >>> ao.shape
        (16, 16, 16)
    """
    _checks.option(merge, MERGES, "merge", _WHERE)
    _checks.option(implementation, _IMPLEMENTATIONS, "implementation", _WHERE)
    opacities = _checked(_feature_opacities(volume, features, base, step, _WHERE),
                         dict(directions=directions, radius=radius, offset=offset,
                              samples=samples, weights=weights,
                              opacity_correction=opacity_correction,
                              brick_size=brick_size, max_radius=max_radius), _WHERE)
    known = _concrete(radius)
    if max_radius is None and known is not None:
        # the padding lao sizes from a known radius, as a static bound: other radii up to
        # the same whole number reuse the compiled loop
        max_radius = float(math.ceil(known))
    params = LocalAmbientOcclusion(radius, offset=offset, directions=directions,
                                   samples=samples, weights=weights,
                                   opacity_correction=opacity_correction,
                                   brick_size=brick_size, max_radius=max_radius,
                                   implementation=implementation)
    return _merged(opacities, params, merge)


def _checked(opacities: Array, arguments: dict, where: str) -> Array:
    """``opacities`` after :func:`~volshade.lao.lao`'s checks of ``arguments``, naming
    ``where``: values known now raise at once, and the checks of traced ones are tied to
    the first feature's opacity, so that they fail at run time naming ``where`` before
    the compiled loop's own checks, which would name ``volshade.lao``."""
    prepared = _prepare(opacities[0], **arguments, where=where)
    # the checked directions and weights tied in by adding 0: unread, their checks were
    # dropped under jit, and the march's named volshade.lao
    tie = 0 * (jnp.sum(prepared.directions) + jnp.sum(prepared.weights))
    return opacities.at[0].set((prepared.alpha + tie).astype(opacities.dtype))


@eqx.filter_jit
def _merged(opacities: Array, ao_of: Callable[[Array], Array], merge: str) -> Array:
    """``ao_of`` of each feature's opacity, merged: one feature at a time (``lax.map``),
    so one compiled march and one march's memory whatever the number of features.
    Compiled (``ao_of`` is a :class:`~volshade.LocalAmbientOcclusion`: its arrays are
    traced and its options static), so an eager call does not trace and compile the
    loop again each time."""
    return MERGES[merge](lax.map(ao_of, opacities), opacities)


class FeatureAmbientOcclusion(eqx.Module):
    """Parameters of :func:`feature_ao` as a Module: the features, the shared
    :class:`~volshade.LocalAmbientOcclusion` parameters (radius, offset and weights are
    leaves a fit can change) and the merge operator (static). Transfer-function
    features get gradients through their control values; interval ends select voxels,
    so theirs is zero.

    Args:
        features: a non-empty list of :class:`~volshade.TransferFunction` or
            :class:`~volshade.IntervalFeature` features.
        lao: the shared LAO parameters; default ``LocalAmbientOcclusion()`` (radius
            16 voxels, offset 1, 42 directions, 16 samples).
        merge: ``"max"`` (default), ``"feature"`` or ``"neighbourhood"``
            (:data:`MERGES`).

    Raises:
        ValueError / TypeError: no features, ``features`` not a list of features,
            ``lao`` not a :class:`~volshade.LocalAmbientOcclusion`, an unknown
            ``merge``.

    Example:
        >>> tf = vs.transfer.preset("shells")
        >>> params = FeatureAmbientOcclusion(
        ...     [vs.IntervalFeature(0.8, 1.0), vs.IntervalFeature(0.2, 0.4)],
        ...     lao=vs.LocalAmbientOcclusion(4.0, directions=12, samples=8))
        >>> params(vs.data.phantom("shells", shape=16), base=tf).shape
        (16, 16, 16)
    """

    features: tuple[Feature, ...]
    lao: LocalAmbientOcclusion
    merge: str = eqx.field(static=True)

    def __init__(self, features: Sequence[Feature], *,
                 lao: LocalAmbientOcclusion | None = None, merge: str = "max"):
        where = "volshade.FeatureAmbientOcclusion"
        self.features = _feature_tuple(features, where)
        self.lao = LocalAmbientOcclusion() if lao is None else lao
        if not isinstance(self.lao, LocalAmbientOcclusion):
            raise TypeError(f"{where}: `lao` must be a volshade.LocalAmbientOcclusion, got "
                            f"{type(self.lao).__name__}.")
        _checks.option(merge, MERGES, "merge", where)
        self.merge = _checks.python_scalar(merge)

    def __call__(self, volume: Volume, *, base: TransferFunction | None = None,
                 step: float | None = None) -> Volume:
        """Feature-driven AO of ``volume``: :func:`feature_ao` with these parameters
        (``base`` and ``step`` as there)."""
        where = "volshade.FeatureAmbientOcclusion"
        opacities = _checked(_feature_opacities(volume, self.features, base, step, where),
                             self.lao._arguments(), where)
        return _merged(opacities, self.lao, self.merge)
