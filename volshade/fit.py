r"""Fitting a scene's continuous parameters to target images with optimistix.

:func:`fit` names the parameters to fit by their path in the :class:`~volshade.scene.Scene`
(``"lao.radius"``, ``"importance.intensity"``, ``"transfer.opacities"``, or one element
of an array, ``"transfer.opacities.3"``), renders the scene from one or more cameras,
and minimises the mean squared difference to the target images,

$$ \mathcal{L}(\theta) = \frac{\sum_{v,p,c} w_{v,p,c}
    \big(I_v(\theta)_{p,c} - T_{v,p,c}\big)^2}{\sum_{v,p,c} w_{v,p,c}} ,$$

the weighted mean over the compared values (pixels $p$ and channels $c$ of views
$v$; $w = 1$ unless ``weights`` are given, so that a mask gives the mean over the
pixels it keeps), by Gauss--Newton with a line search on the residuals
by default (:class:`GaussNewtonLineSearch`; any optimistix least-squares solver, or
any minimiser on $\mathcal{L} / \mathcal{L}(\theta_0)$). Every parameter is an
array leaf, so the solver's loop is compiled once per fit, whatever values it tries.

Bounds: a parameter with bounds is fitted through a smooth bijection from the real
line onto its interval (a logistic for ``(low, high)``, a softplus for a half line),
so no step of the solver leaves the interval. Give bounds to every parameter with a
domain (an LAO radius above its offset, opacities and colours in [0, 1], Phong
coefficients and importance exponents >= 0 or > 0): the renderer refuses values
outside it, so a step there would stop the fit with that runtime error. The initial
value must lie strictly inside.

Scaling and local minima: the default solver's least-squares solve scales the
Jacobian's columns to norm 1 (:class:`GaussNewtonLineSearch`), so that a parameter the
image is far less sensitive to than another (an LAO radius beside Phong's diffuse)
still gets its step. The loss is not convex in most parameters: from a start far off,
a fit can end in a local minimum, or on a bound, where the bijection's slope vanishes
(an LAO radius fitted from 11.5 in (1.5, 12) towards 5, beside the diffuse, ended at
12), and it reports success there. Compare ``Fit.values`` with the bounds, and start
nearer. Importance weights should not start at exactly 0, their default, where every
importance ties and the gradient is not a one-sided derivative (see
:class:`volshade.Importance`); opacities of importance-aware compositing not at 0
(see :func:`volshade.composite`).

Derivatives: a least-squares solver builds the Jacobian with one forward-mode
derivative (JVP) of the render per scalar parameter and step, and transposes it for
$J^T r$; a minimiser gets the gradient from one reverse-mode pass per step. LAO and
importance-aware compositing have forward modes of their own (a tangent march beside
the values) and their hand-written reverse modes as the transposes, so each costs what
it needs: a JVP of LAO in its radius about 2.7 times its forward pass, its gradient
about 13 times (64^3, 16 rays of 16 samples, on a 2-core CPU). For a few parameters the
default solver is the better choice; for hundreds (a whole transfer function), a
minimiser costs less per step. The fit is a
tool, not a differentiable layer: differentiating through :func:`fit` is not
supported.
"""

import dataclasses
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import lineax.internal
import numpy as np
import optimistix as optx

from . import _checks
from ._types import Array, ArrayLike, Float
from .camera import Camera
from .lao import LocalAmbientOcclusion
from .scene import _PARAMETERS, Scene, _check_cameras, render

_WHERE = "volshade.fit"

Bounds = tuple[float | None, float | None]


class Fit(eqx.Module):
    r"""What :func:`fit` found.

    Attributes:
        scene: the scene with the fitted values in place of the initial ones.
        values: the fitted value of each parameter, by path.
        loss: $\mathcal{L}$ (mean squared difference to the targets) at the fitted
            values.
        initial_loss: $\mathcal{L}$ at the initial values.
        steps: the number of solver steps taken.
        result: the solver's ``optimistix.RESULTS`` (``successful`` or why it stopped;
            ``result == optimistix.RESULTS.successful`` tests it, and a successful
            result prints as ``RESULTS<>``, its message being empty).
    """

    scene: Scene
    values: dict[str, Array]
    loss: Float[Array, ""]
    initial_loss: Float[Array, ""]
    steps: Array
    result: optx.RESULTS


def _path_parts(path: Any) -> list[str]:
    if not isinstance(path, str) or not path or any(not p for p in path.split(".")):
        raise ValueError(f"{_WHERE}: a parameter must be a dotted path into the scene such "
                         f"as 'lao.radius' or 'transfer.opacities', got {path!r}.")
    return path.split(".")


def _is_index(part: str) -> bool:
    """Whether a path part is a number (ASCII digits: ``str.isdigit`` takes '²')."""
    return part.isascii() and part.isdigit()


def _static_hint(node: Any, part: str, path: str) -> str:
    """What to fit in place of a static field: for a scene's stage option (``ambient``,
    ...), the same path under the parameters of the effect it names, where they have
    that field."""
    effects = ([name for name, (_, stage, _, _) in _PARAMETERS.items() if stage == part]
               if isinstance(node, Scene) else [])
    if not effects:
        return "fit an array parameter"
    chosen = getattr(node, part)
    effect = chosen if chosen in effects else effects[0]
    rest = path.split(".")[1:]  # (a scene is the root of every path)
    fields = {f.name for f in dataclasses.fields(_PARAMETERS[effect][0])}
    example = ".".join([effect, *rest]) if rest and rest[0] in fields else f"{effect}.<field>"
    return (f"the parameters of the `{part}` effects are the scene's fields "
            f"{', '.join(effects)}: e.g. {example!r}")


def _child(node: Any, part: str, path: str) -> Any:
    """One step of a path: a Module field or a sequence index, refused with the valid
    names when it does not exist and when it is static (it cannot be fitted)."""
    if isinstance(node, eqx.Module):
        fields = {f.name: f for f in dataclasses.fields(node)}
        if part not in fields:
            valid = ", ".join(repr(name) for name in fields)
            raise ValueError(f"{_WHERE}: {path!r}: {type(node).__name__} has no field "
                             f"{part!r}; its fields are {valid}.")
        if fields[part].metadata.get("static", False):
            raise ValueError(f"{_WHERE}: {path!r}: `{part}` is static (it sets shapes or the "
                             f"traced program) and cannot be fitted; "
                             f"{_static_hint(node, part, path)}.")
        # array leaves the image depends on with a zero derivative: a fit would stop at
        # once and report success with the value unchanged
        why = getattr(node, "_without_gradient", dict)().get(part)
        if why is not None:
            raise ValueError(f"{_WHERE}: {path!r} gets no gradient ({why}), so a fit cannot "
                             f"move it; fit a differentiable parameter.")
        value = getattr(node, part)
        if value is None and isinstance(node, Scene) and part in _PARAMETERS:
            _, stage, users, _ = _PARAMETERS[part]
            wanted = " or ".join(f"{stage}={u!r}" for u in users)
            raise ValueError(f"{_WHERE}: {path!r}: the scene does not use `{part}` "
                             f"({stage}={getattr(node, stage)!r}); make it with {wanted} "
                             f"to fit it.")
        return value
    if isinstance(node, list | tuple) and _is_index(part) and int(part) < len(node):
        return node[int(part)]
    if node is None:
        raise ValueError(f"{_WHERE}: {path!r}: cannot take {part!r} of None: the scene "
                         f"has no value there; give it one (e.g. `focus=vs.Focus()`) first.")
    raise ValueError(f"{_WHERE}: {path!r}: cannot take {part!r} of a "
                     f"{type(node).__name__} (the scene holds {node!r} there).")


def _at(tree: Any, path: str) -> Any:
    """The node at a field path already checked by :func:`_parameter` (for
    ``eqx.tree_at``)."""
    for part in path.split("."):
        tree = tree[int(part)] if _is_index(part) else getattr(tree, part)
    return tree


class _Parameter(NamedTuple):
    """Where a parameter lies: the path of its scene leaf and, for one element or slice
    of an array leaf, the index into it (``()``: the whole leaf)."""

    field: str
    index: tuple[int, ...]


def _parameter(scene: Scene, path: str) -> tuple[_Parameter, Array | float]:
    """The parameter at ``path`` and its value: a floating-point array leaf (or a number
    set with ``eqx.tree_at``), or the part of one that the numbers after it index."""
    parts, node, k = _path_parts(path), scene, 0
    while k < len(parts) and not eqx.is_array(node):
        node = _child(node, parts[k], path)
        k += 1
    if not (eqx.is_inexact_array(node)
            or isinstance(node, float | int) and not isinstance(node, bool)):
        what = (f"an array of dtype {node.dtype}" if eqx.is_array(node)
                else f"a {type(node).__name__}; name one of its array fields instead")
        raise ValueError(f"{_WHERE}: {path!r} must name a floating-point array leaf of the "
                         f"scene, got {what}.")
    # one spelling per leaf ('features.00' is 'features.0'), so overlaps are found
    field = ".".join(str(int(p)) if _is_index(p) else p for p in parts[:k])
    unread = scene._unread_leaves().get(field)
    if unread is not None:
        raise ValueError(f"{_WHERE}: {path!r} is not read by this scene ({unread.reason}), "
                         f"so a fit cannot move it; fit a parameter the render uses.")
    index = parts[k:]
    if index and jnp.ndim(node) == 0:
        raise ValueError(f"{_WHERE}: {path!r}: {field!r} is a scalar; name it without "
                         f"an index.")
    if len(index) > jnp.ndim(node) or not all(
            _is_index(p) and int(p) < n for p, n in zip(index, jnp.shape(node), strict=False)):
        raise ValueError(f"{_WHERE}: {path!r}: {'.'.join(index)!r} is not an index into "
                         f"{field!r}, an array of shape {jnp.shape(node)}; give one number "
                         f"from 0 to the length minus 1 per axis (e.g. {field + '.0'!r}).")
    index = tuple(int(p) for p in index)
    return _Parameter(field, index), node[index] if index else node


def _placed(scene: Scene, where: Sequence[_Parameter], values: Sequence[Array]) -> Scene:
    """``scene`` with each parameter's value in place: a whole leaf replaced, an element
    set in its array (several elements of one array are set in turn)."""
    leaves: dict[str, Any] = {}
    for (field, index), value in zip(where, values, strict=True):
        leaves[field] = (jnp.asarray(leaves.get(field, _at(scene, field))).at[index].set(value)
                         if index else value)
    return eqx.tree_at(lambda s: [_at(s, f) for f in leaves], scene, list(leaves.values()))


def _bounds(path: str, value: Any) -> Bounds:
    if value is None:
        return None, None
    if not isinstance(value, tuple | list) or len(value) != 2:
        raise ValueError(f"{_WHERE}: the bounds of {path!r} must be None or a pair "
                         f"(low, high), each a number or None, got {value!r}.")
    try:
        if _checks.holds_bool(value):
            raise TypeError("a bool would pass as 0 or 1")
        if any(isinstance(b, str | bytes) for b in value):
            raise TypeError("float() would parse a string")
        low, high = (None if b is None else float(b) for b in value)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{_WHERE}: the bounds of {path!r} must be numbers or None, got "
                        f"{value!r}.") from err
    if any(b is not None and not math.isfinite(b) for b in (low, high)):
        raise ValueError(f"{_WHERE}: the bounds of {path!r} must be finite numbers or None "
                         f"(None for an open end), got {value!r}.")
    if low is not None and high is not None and not low < high:
        raise ValueError(f"{_WHERE}: the bounds of {path!r} need low < high, got {value!r}.")
    return low, high


def _softplus_inverse(y: Array) -> Array:
    # log(exp(y) - 1), written so that it neither overflows for large y nor loses
    # digits for small y
    return y + jnp.log(-jnp.expm1(-y))


def _to_bounded(u: Array, bounds: Bounds) -> Array:
    """The bijection from the real line onto the open interval ``bounds``. Rounding
    would put a long step exactly on a bound (in float32, ``1 + 11 * sigmoid(-20)`` is
    1), where a kernel may refuse the value (an LAO radius equal to its offset), so
    the result is kept to the floats strictly inside."""
    low, high = bounds
    if low is not None and high is not None:
        x = low + (high - low) * jax.nn.sigmoid(u)
    elif low is not None:
        x = low + jax.nn.softplus(u)
    elif high is not None:
        x = high - jax.nn.softplus(u)
    else:
        return u
    inside_low = None if low is None else jnp.nextafter(jnp.asarray(low, u.dtype), jnp.inf)
    inside_high = None if high is None else jnp.nextafter(jnp.asarray(high, u.dtype), -jnp.inf)
    return jnp.clip(x, inside_low, inside_high)


def _from_bounded(x: Array, bounds: Bounds, path: str) -> Array:
    """The inverse of :func:`_to_bounded` at an initial value strictly inside."""
    low, high = bounds
    known = _checks.concrete(x)
    if known is not None and not np.all(np.isfinite(known)):
        # -inf is a legal value of some leaves (an importance that hides the background),
        # but a solver cannot step from it: it reported non-finite values, naming nothing
        raise ValueError(f"{_WHERE}: the initial value of {path!r} ({known}) must be finite "
                         f"to be fitted: a solver steps by finite amounts. Start from a "
                         f"finite value (set it with `eqx.tree_at`).")
    if known is not None and (low is not None and np.any(known <= low)
                              or high is not None and np.any(known >= high)):
        raise ValueError(f"{_WHERE}: the initial value of {path!r} ({known}) must lie "
                         f"strictly inside its bounds ({low}, {high}): a logistic or "
                         f"softplus reaches a bound only at infinity. Start from values "
                         f"inside (e.g. move opacities of exactly 0 or 1 to 1e-3 or "
                         f"1 - 1e-3 with `eqx.tree_at`); widen the bounds only where the "
                         f"scene accepts the values beyond them.")
    if known is None:  # traced (fit under jax.vmap or jit): refused at run time
        bad = ~jnp.all(jnp.isfinite(x))
        bad = bad if low is None else bad | jnp.any(x <= low)
        bad = bad if high is None else bad | jnp.any(x >= high)
        x = _checks.refuse(x, [(bad, f"the initial value of {path!r} must be finite and lie "
                                     f"strictly inside its bounds ({low}, {high}). Start "
                                     f"from values inside.")], _WHERE)
    if low is not None and high is not None:
        u = jnp.log(x - low) - jnp.log(high - x)  # accurate near either bound
    elif low is not None:
        u = _softplus_inverse(x - low)
    elif high is not None:
        u = _softplus_inverse(high - x)
    else:
        return x
    return _checks.refuse(u, [(~jnp.all(jnp.isfinite(u)), f"the initial value of {path!r} is "
                               f"too close to its bounds ({low}, {high}) for {x.dtype}; "
                               f"start further inside.")], _WHERE)


def _parameters(scene: Scene, params: Any
                ) -> tuple[dict[str, Bounds], list[_Parameter], list[Any]]:
    """The parameters' bounds by path, where they lie and their values, checked."""
    if isinstance(params, str):
        raise TypeError(f"{_WHERE}: `params` must be a sequence of paths or a mapping from "
                        f"paths to bounds, got the single string {params!r}; write "
                        f"params=({params!r},).")
    if isinstance(params, Mapping):
        named = {p: _bounds(p, b) for p, b in params.items()}
    elif isinstance(params, Sequence):
        if not all(isinstance(p, str) for p in params):
            raise TypeError(f"{_WHERE}: `params` must hold paths as strings, e.g. "
                            f"('lao.radius',), got {list(params)!r}.")
        if len(set(params)) != len(params):
            raise ValueError(f"{_WHERE}: `params` names a parameter twice: {list(params)}.")
        named = {p: (None, None) for p in params}
    else:
        raise TypeError(f"{_WHERE}: `params` must be a sequence of paths or a mapping from "
                        f"paths to bounds, got {type(params).__name__}.")
    if not named:
        raise ValueError(f"{_WHERE}: `params` is empty; name at least one parameter, e.g. "
                         f"params=('lao.radius',).")
    where, values = zip(*(_parameter(scene, path) for path in named), strict=True)
    for (path, (_, high)), p in zip(named.items(), where, strict=True):
        owner, _, leaf = p.field.rpartition(".")
        module = _at(scene, owner) if owner else scene
        # a static bound: the fit would stop with the kernel's error once a step passed it
        if (leaf == "radius" and isinstance(module, LocalAmbientOcclusion) and high is not None
                and module.max_radius is not None and high > module.max_radius):
            raise ValueError(f"{_WHERE}: the bounds of {path!r} reach {high:g}, beyond "
                             f"`{owner}.max_radius` ({module.max_radius:g}, static): lower the "
                             f"upper bound, or build the scene's LocalAmbientOcclusion with "
                             f"max_radius={high:g}.")
    for (a, pa), (b, pb) in itertools.combinations(zip(named, where, strict=True), 2):
        short = min(len(pa.index), len(pb.index))
        if pa.field == pb.field and pa.index[:short] == pb.index[:short]:
            raise ValueError(f"{_WHERE}: `params` names {a!r} and {b!r}, which overlap; "
                             f"name each element once.")
    return named, list(where), list(values)


def _one_per_camera(value: Any, name: str, count: int, single: bool, *, what: str,
                    stack: str, stacked_ndim: int, counted: str) -> list[Any]:
    """``value`` as a list with one entry per camera: itself for a single camera, else a
    sequence or a stack along a leading axis (at least ``stacked_ndim`` dimensions), so
    that an array meant for every camera is not silently split into its rows."""
    if single:
        return [value]
    if not isinstance(value, list | tuple) and np.ndim(value) < stacked_ndim:
        raise ValueError(f"{_WHERE}: for {count} cameras, `{name}` must be a sequence of "
                         f"{count} {what} or {stack}, got shape {np.shape(value)}.")
    values = list(value)
    if len(values) != count:
        raise ValueError(f"{_WHERE}: {count} cameras but {len(values)} {counted}; give "
                         f"one per camera.")
    return values


def _views(camera: Any, target: Any, weights: Any) -> list[tuple[Camera, Array, Array | None]]:
    """Cameras, targets and weights as one list of views, their shapes checked."""
    _check_cameras(camera, _WHERE)
    cameras = [camera] if isinstance(camera, Camera) else list(camera)
    single = isinstance(camera, Camera)
    targets = _one_per_camera(target, "target", len(cameras), single, what="images",
                              stack="a (V, H, W, C) stack", stacked_ndim=4,
                              counted="targets")
    weight_list = [None] * len(cameras) if weights is None else _one_per_camera(
        weights, "weights", len(cameras), single, what=f"weight arrays (e.g. [w] * "
        f"{len(cameras)})", stack="a stack with one per camera", stacked_ndim=3,
        counted="weights")
    views = []
    for cam, tgt, w in zip(cameras, targets, weight_list, strict=True):
        if jnp.issubdtype(jnp.result_type(tgt), jnp.integer):
            # an image read from a file: 0-255 against renders in [0, 1] would fit nonsense
            raise TypeError(f"{_WHERE}: `target` has the integer dtype "
                            f"{jnp.result_type(tgt)} (an image read from a file?); renders "
                            f"are floats in [0, 1]: convert it, e.g. with "
                            f"`skimage.util.img_as_float(target)`.")
        tgt = _checks.as_float_array(tgt, "target", _WHERE)
        shape = (*cam.image_shape, 4)
        if tgt.shape not in (shape, shape[:2] + (3,)):
            raise ValueError(f"{_WHERE}: a target for a camera of image_shape "
                             f"{cam.image_shape} must have shape {shape} (RGBA, as "
                             f"volshade.render returns) or {shape[:2] + (3,)} (RGB), got "
                             f"{tuple(tgt.shape)}.")
        # a float image of 0-255 would fit nonsense, and end with the solver's "maximum
        # number of steps" error, which does not name the target; noise a little outside
        # [0, 1] (a noisy photograph, a render plus noise) is a target like any other
        xp, values = _checks.for_check(tgt)
        tgt = _checks.refuse(tgt, [*_checks.finite_problems(tgt, "target"),
                                   (xp.any((values < -1) | (values > 2)),
                                    "`target` holds values far outside [0, 1], where renders "
                                    "lie (beyond [-1, 2]); divide an image of 0-255 by 255 "
                                    "(e.g. `skimage.util.img_as_float`).")], _WHERE)
        if w is not None:
            w = _checks.as_float_array(w, "weights", _WHERE)
            # a 2-D array is a weight per pixel: of another shape it could as well be
            # meant to broadcast over the channels, so it is refused, not guessed at
            if w.ndim == 2 and w.shape != tuple(cam.image_shape):
                raise ValueError(f"{_WHERE}: 2-D `weights` weigh pixels and must have the "
                                 f"image shape {tuple(cam.image_shape)}, got "
                                 f"{tuple(w.shape)}; to weigh channels give shape "
                                 f"({tgt.shape[-1]},), or (1, 1, {tgt.shape[-1]}).")
            try:
                w = jnp.broadcast_to(w if w.ndim != 2 else w[..., None], tgt.shape)
            except ValueError as err:
                raise ValueError(f"{_WHERE}: `weights` must have the target's shape "
                                 f"{tuple(tgt.shape)} or its image shape "
                                 f"{cam.image_shape}, got {tuple(w.shape)}.") from err
            w = _checks.refuse(w, [(~jnp.all(jnp.isfinite(w) & (w >= 0)),
                                    "`weights` must be finite and >= 0."),
                                   (jnp.sum(w) <= 0, "`weights` are all 0: nothing to "
                                    "compare in that view; leave the camera out.")], _WHERE)
        views.append((cam, tgt, w))
    return views


class _Problem(eqx.Module):
    """A fit's residuals as a function of the unconstrained parameters ``u``. A Module
    passed as optimistix's ``args``: its arrays are traced and its paths and bounds
    static, so every fit of the same structure (other values, targets or starting
    points) reuses one compiled solver."""

    scene: Scene
    cameras: tuple[Camera, ...]
    targets: tuple[Array, ...]
    weights: tuple[Array | None, ...]
    where: tuple[_Parameter, ...] = eqx.field(static=True)
    bounds: tuple[Bounds, ...] = eqx.field(static=True)

    def place(self, u: list[Array]) -> tuple[Scene, list[Array]]:
        """The scene with the parameters' values for ``u``, and those values."""
        values = [_to_bounded(ui, b) for ui, b in zip(u, self.bounds, strict=True)]
        return _placed(self.scene, self.where, values), values

    def residuals(self, u: list[Array]) -> list[Array]:
        fitted, _ = self.place(u)
        total = sum(t.size if w is None else jnp.sum(w)
                    for t, w in zip(self.targets, self.weights, strict=True))
        scale = 1 / jnp.sqrt(total)
        out = []
        # one render call for all views: the ambient volume and the rest of what does not
        # depend on the view is computed once, not once per camera
        images = render(fitted, list(self.cameras))
        for image, tgt, w in zip(images, self.targets, self.weights, strict=True):
            diff = image[..., : tgt.shape[-1]] - tgt
            out.append(scale * (diff if w is None else jnp.sqrt(w) * diff))
        return out

    def loss(self, u: list[Array]) -> Array:
        return sum(jnp.sum(r**2) for r in self.residuals(u))


def _residuals(u: list[Array], problem: _Problem) -> list[Array]:
    return problem.residuals(u)


def _relative_loss(u: list[Array], args: tuple[_Problem, Array]) -> Array:
    return args[0].loss(u) / args[1]


def _quiet(**kwargs) -> None:
    return None


class _ColumnScaledSVD(lx.SVD):
    r"""The least-squares solve of :class:`lineax.SVD` on the operator with its
    columns scaled to norm 1 (Jacobi scaling): $x = D\, (A D)^+ b$, $D =
    \mathrm{diag}(1 / \lVert A_k \rVert)$ (1 for a zero column, which gets no step).
    Where $A$ has full rank this is $A^+ b$; the scaling changes only which directions
    the SVD's cut-off ($2 \epsilon \max(M, N)$ of the largest singular value) drops.
    Unscaled, a parameter the image is far less sensitive to than another lost its
    direction: beside Phong's diffuse, an LAO radius (a Jacobian of condition 589, two
    32 x 32 RGBA views: the cut-off 1.95e-3) got no step, and the fit stopped 30% off
    it reporting success. The state is an SVD's with $V^T D$ in place of $V^T$, which
    the inherited solve, transpose and conjugate read as they should. A column whose
    norm is not finite (an inf entry) is left unscaled, as lineax would take it."""

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        a = operator.as_matrix()
        # the norm through the column's largest entry: squares of entries beyond 1e19
        # (float32) would overflow, and of entries below 1e-19 flush to 0
        peak = jnp.max(jnp.abs(a), axis=0)
        usable = (peak > 0) & jnp.isfinite(peak)
        safe = jnp.where(usable, peak, 1)
        norms = safe * jnp.sqrt(jnp.sum(jnp.square(a / safe[None, :]), axis=0))
        inverse = jnp.where(usable, 1 / jnp.where(usable, norms, 1), 1)
        u, s, vt = jax.scipy.linalg.svd(a * inverse[None, :], full_matrices=False)
        return (u, s, vt * inverse[None, :]), lx.internal.pack_structures(operator)


class GaussNewtonLineSearch(optx.AbstractGaussNewton):
    r"""Gauss--Newton with a backtracking Armijo line search: :func:`fit`'s default.

    The Gauss--Newton step $-(J^T J)^{-1} J^T r$ (a least-squares solve, so a
    parameter without effect on the image gets no step rather than an error) does not
    depend on the scale of the residuals, and the line search halves it until the loss
    falls enough. Optimistix's Levenberg--Marquardt damps $J^T J$ with $\lambda I$
    from $\lambda = 1$: image residuals give a $J^T J$ far below 1, so its first
    steps are gradient steps of about $10^{-5}$, which its termination test takes
    for convergence (measured: a fit of ``importance.intensity`` from 0.5 to 2.0
    stopped after 2 steps at 0.500006; this solver reaches 1.999998 in 5).

    Attributes:
        rtol, atol: optimistix's Cauchy termination: the parameters (as the solver
            sees them: through the bounds' bijections) and the residuals both change
            by less than ``atol + rtol * |value|`` in one step.
        norm: the norm of that test (default ``optimistix.max_norm``).
        descent: the step (default ``optimistix.NewtonDescent`` with a least-squares
            linear solve: ``lineax.SVD`` of the Jacobian with its columns scaled to
            norm 1, so that a parameter the image is far less sensitive to than
            another is not cut off with the small singular values).
        search: the line search (default ``optimistix.BacktrackingArmijo()``).
        verbose: optimistix's progress printer (default: prints nothing).
    """

    rtol: float
    atol: float
    norm: Callable[[Any], Array] = optx.max_norm
    descent: optx.AbstractDescent = optx.NewtonDescent(linear_solver=_ColumnScaledSVD())
    search: optx.AbstractSearch = optx.BacktrackingArmijo()
    verbose: Callable[..., None] = _quiet


def _default_solver(dtype) -> GaussNewtonLineSearch:
    # atol applies to the residuals as well as to the parameters, and the residuals of
    # a fit that matches are near 0: sqrt(eps) would stop while the loss can still fall
    tol = float(np.sqrt(np.finfo(dtype).eps))
    return GaussNewtonLineSearch(rtol=tol, atol=tol**2)


def fit(
    scene: Scene,
    camera: Camera | Sequence[Camera],
    target: Float[ArrayLike, "H W C"] | Sequence[Float[ArrayLike, "H W C"]],
    *,
    params: Sequence[str] | Mapping[str, Bounds | None],
    solver: optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser | None = None,
    weights: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."]] | None = None,
    max_steps: int = 64,
    throw: bool = True,
) -> Fit:
    r"""Fit continuous parameters of ``scene`` so that its renders match ``target``.

    Minimises the mean squared difference $\mathcal{L}$ between
    :func:`~volshade.scene.render` of the scene and the targets (module docstring)
    over the named parameters, the others held fixed.

    Args:
        scene: the scene, holding the initial values.
        camera: one :class:`~volshade.camera.Camera`, or a sequence of them (one
            target each) to fit to several views at once.
        target: ``(H, W, 4)`` RGBA, as :func:`~volshade.scene.render` returns, or
            ``(H, W, 3)`` RGB (then the accumulated opacity is not compared), for
            each camera.
        params: paths of the parameters to fit (``"lao.radius"``,
            ``"importance.intensity"``, ``"transfer.opacities"``, ``"phong.ambient"``,
            ``"feature_ao.lao.radius"``; a number indexes a sequence, and numbers after
            an array leaf pick part of it, one per axis: ``"transfer.opacities.3"``
            fits one control point and holds the others, ``"transfer.colors.2"`` one
            RGB colour, ``"transfer.colors.2.0"`` its red), as a sequence,
            or as a mapping from path to bounds ``(low, high)`` (either end ``None``
            for an open one; ``None`` for no bounds). Array parameters are
            fitted element by element, each element within the bounds. A parameter
            with a valid range needs bounds inside it (an LAO radius between its
            offset and ``max_radius``, an opacity in ``(0, 1)``): a step outside
            would stop the fit with the kernel's runtime error. A parameter whose
            derivative is zero wherever it is defined (it selects voxels or pixels, or
            is static configuration held in an array) is refused, and so is one the
            image does not depend on at its initial value (switched off by a weight
            of 0: one VJP before the solve tests it) when the fit leaves it there
            (fitted with the weight that switches it on, starting at 0, it moves once
            the weight has); an element of an array the
            image does not depend on (a control point outside the volume's range)
            gets no step. Two fields that hold one array object are fitted apart.
        solver: an ``optimistix`` least-squares solver or minimiser (e.g.
            ``optx.BFGS``); by default ``vs.GaussNewtonLineSearch`` with
            ``rtol = sqrt(eps)`` and ``atol = eps`` of the render's dtype.
        weights: optional weights $w \ge 0$ for each camera: of its image shape
            ``(H, W)`` (e.g. a mask of the pixels that matter; the only 2-D shape
            taken), or broadcastable to the target's shape (``(4,)`` weighs the
            channels). For several cameras, a sequence with one entry per camera
            (or a stack along a leading axis): a list of numbers weighs whole
            views, so with four cameras ``[1, 1, 1, 0.5]`` halves the last view; to
            weigh the channels of every view, give ``[w] * len(cameras)``.
        max_steps: the solver's step limit.
        throw: raise when the solver fails (as optimistix does); with ``False``,
            check ``Fit.result``.

    Returns:
        A :class:`Fit`: the fitted scene, the fitted values by path, the loss before
        and after, the steps taken and the solver's result.

    Raises:
        TypeError: ``scene`` not a :class:`~volshade.Scene`; bounds that are not
            numbers (strings and bools included).
        ValueError / TypeError: a path that does not name a floating-point array
            leaf of the scene or part of one (the message lists the valid fields),
            a static parameter, one named twice or overlapping another, one that gets
            no gradient (``lao.directions``, an interval feature's ends, a clip's pose
            and sizes, the saliency threshold, a circular or screen-door focus's centre
            and radius), bad bounds or an initial value outside them or not finite
            (a background importance of ``-inf``), an LAO radius's upper bound above
            its ``max_radius``, targets or weights that do not match the cameras,
            targets far outside [0, 1] (beyond [-1, 2]: an image of 0-255; an integer
            image is a ``TypeError``), a solver of another kind.
        equinox.EquinoxRuntimeError: a parameter the render does not depend on at its
            initial value (every derivative of the image in it exactly 0: a weight of
            0 switches it off) and that the fit left there, named with the settings
            to look at (raised whatever ``throw`` is: it is a mistake in the call).

    Example:
        >>> vol = vs.data.phantom("shells", shape=12)
        >>> cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))
        >>> truth = vs.Scene(volume=vol, transfer=vs.transfer.preset("shells"),
        ...                  composition="importance",
        ...                  importance=vs.Importance(intensity=2.0))
        >>> target = vs.render(truth, cam)
        >>> start = eqx.tree_at(lambda s: s.importance.intensity, truth, 0.5)
        >>> result = vs.fit(start, cam, target, params={"importance.intensity": (0.0, None)})
        >>> round(float(result.values["importance.intensity"]), 3)
        2.0
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"{_WHERE}: `scene` must be a volshade.Scene (the start of the fit), "
                        f"got {type(scene).__name__}.")
    named, where, leaves = _parameters(scene, params)
    views = _views(camera, target, weights)
    max_steps = _checks.positive_int(max_steps, "max_steps", _WHERE)
    _checks.flag(throw, "throw", _WHERE)
    if solver is not None and not isinstance(solver, optx.AbstractLeastSquaresSolver
                                             | optx.AbstractMinimiser):
        raise TypeError(f"{_WHERE}: `solver` must be an optimistix least-squares solver "
                        f"(e.g. optx.LevenbergMarquardt) or minimiser (e.g. optx.BFGS), "
                        f"got {type(solver).__name__}.")
    paths = tuple(named)
    # strongly typed: jit caches a weakly typed start (a Python number, which several
    # constructors keep weakly typed) apart, and would compile the solver again
    initial = []
    for leaf, path in zip(leaves, named, strict=True):
        x = _checks.float_leaf(leaf, path, _WHERE)
        initial.append(jnp.array(x, dtype=x.dtype))
    # numbers set with eqx.tree_at (an int as the float a constructor would make of it)
    # as arrays: jit would hold a Python number as static, and compile the solver again
    # for every other value
    scene = jax.tree.map(lambda x: jnp.asarray(float(x)) if isinstance(x, float | int)
                         and not isinstance(x, bool) else x, scene)
    problem = _Problem(scene=_placed(scene, where, initial),
                       cameras=tuple(c for c, _, _ in views),
                       targets=tuple(t for _, t, _ in views),
                       weights=tuple(w for _, _, w in views),
                       where=tuple(where), bounds=tuple(named.values()))
    u0 = [_from_bounded(x, named[p], p) for x, p in zip(initial, paths, strict=True)]
    u, loss, initial_loss, steps, result = _solve(problem, u0, solver, max_steps, throw)
    # only a parameter the fit left where it started can be one the render does not depend
    # on; the test (a reverse pass) is compiled apart, for such fits alone: in the solve's
    # program it made every fit compile longer (the first call of the example below on a
    # 2-core CPU: 10.2 s with it, 9.0 s without)
    # (under jax.vmap or jit the values are not known: the test runs, at the price of
    # compiling its reverse pass too, which made a vmapped fit of an 8^3 scene compile
    # in 17-27 s instead of 13-14; np.array_equal of a tracer is False, and skipped it)
    if _checks.traced(u) or any(np.array_equal(ui, u0_i)
                                for ui, u0_i in zip(u, u0, strict=True)):
        u = _refuse_without_effect(problem, u, u0, paths)
    fitted, values = problem.place(u)
    return Fit(scene=fitted, values=dict(zip(paths, values, strict=True)), loss=loss,
               initial_loss=initial_loss, steps=steps, result=result)


def _without_effect(problem: _Problem, u0: list[Array]) -> list[Array]:
    r"""Whether the residuals do not depend on each parameter at ``u0`` (one flag per
    parameter). The test is one VJP with a random cotangent $c$: $(J^T c)_k$ is exactly
    0 for every element $k$ of a parameter whose columns of $J$ are all 0, and almost
    never otherwise."""
    residuals, vjp = jax.vjp(problem.residuals, u0)
    keys = jax.random.split(jax.random.key(0), len(residuals))
    (slopes,) = vjp([jax.random.normal(k, r.shape, r.dtype)
                     for k, r in zip(keys, residuals, strict=True)])
    return [jnp.all(slope == 0) for slope in slopes]


def _refuse_unmoved(u: list[Array], u0: list[Array], flat: list[Array],
                    paths: tuple[str, ...]) -> list[Array]:
    """``u``, refused (at run time) for a parameter the residuals did not depend on at
    the start and that the fit left there. A weight of 0 switches measures off (with
    the default :class:`~volshade.importance.Importance`, the silhouette's and the
    lighting's exponents, the darkening and the unocclusion offset change nothing),
    and a solver stopped at once and reported success with the value unchanged. A
    parameter switched on by another one fitted with it (its weight, starting at 0)
    moves once that one has, and is not refused."""
    return _checks.refuse(u, [
        (flat_i & jnp.all(ui == u0_i),
         f"the render does not depend on {path!r} at its initial value (its derivative "
         f"is exactly 0 at every compared pixel), and the fit left it there. Something "
         f"switches it off: an importance exponent, offset or darkening whose weight "
         f"(importance.silhouette, .lighting or .unocclusion) is 0, any importance under "
         f"a global weight of 0, an effect the scene's opacity never reaches, an initial "
         f"value on its bound, or pixels and channels it changes all weighted 0. Turn "
         f"that on or leave {path!r} out.")
        for ui, u0_i, flat_i, path in zip(u, u0, flat, paths, strict=True)], _WHERE)


@eqx.filter_jit
def _refuse_without_effect(problem: _Problem, u: list[Array], u0: list[Array],
                           paths: tuple[str, ...]) -> list[Array]:
    """``u`` after a fit, refused (:func:`_refuse_unmoved`, at run time) where it stayed
    at ``u0`` on a parameter the residuals do not depend on there."""
    return _refuse_unmoved(u, u0, _without_effect(problem, u0), paths)


@eqx.filter_jit
def _solve(problem: _Problem, u0: list[Array], solver, max_steps: int, throw: bool):
    """The solve, with the loss before and after it, as one compiled program (the
    losses compiled apart cost a second compile of the render: 2-3 s on a CPU)."""
    initial_loss = problem.loss(u0)
    solver = _default_solver(initial_loss.dtype) if solver is None else solver
    if isinstance(solver, optx.AbstractLeastSquaresSolver):
        solution = optx.least_squares(_residuals, solver, u0, args=problem,
                                      max_steps=max_steps, throw=throw)
        scale = None
    else:
        # relative to the initial loss: a mean squared error of images is small, and
        # minimisers are not invariant to the scale of their objective (quasi-Newton
        # curvature estimates drown in float32 rounding, first steps are gradient steps)
        scale = jnp.where(initial_loss > 0, initial_loss, 1)
        solution = optx.minimise(_relative_loss, solver, u0, args=(problem, scale),
                                 max_steps=max_steps, throw=throw)
    steps = solution.stats["num_steps"]
    return (solution.value, _final_loss(solver, solution, problem, scale, initial_loss),
            initial_loss, steps, solution.result)


def _final_loss(solver, solution: optx.Solution, problem: _Problem,
                scale: Array | None, initial_loss: Array) -> Array:
    """The loss at ``solution.value``. Optimistix's Gauss--Newton and quasi-Newton
    solvers return the point whose residuals (or objective) their state holds, so the
    render need not be compiled a third time for it (the fit's compile for a 12^3
    importance scene on a CPU: 5.6 s -> 4.1 s); other solvers' losses are recomputed.
    Before a first step that state holds zeros, and the value is the start.
    """
    if isinstance(solver, optx.AbstractGaussNewton):
        held = sum(jnp.sum(r**2) for r in solution.state.f_info.residual)
    elif isinstance(solver, optx.AbstractQuasiNewton):
        held = solution.state.f_info.f * scale
    else:
        return problem.loss(solution.value)
    return jnp.where(solution.stats["num_steps"] > 0, held, initial_loss)
