"""The scene: what the user wants rendered, and a plan that computes only that.

A :class:`Scene` names the volume, its transfer function and the effects to
apply: an ambient term, a local shading model and a compositing rule. Each
effect is looked up in a small table (effect name -> function); an effect
that is off is never called, so it is neither traced nor computed.
Differentiable values (the volume, transfer-function control values, Phong
coefficients, effect parameters, background) are array leaves; effect names,
the spacing and the sampling step are static, so a fit over the leaves never
recompiles.
"""

import dataclasses
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _checks
from ._types import Array, Float
from .camera import Camera
from .clip import Clip, clip_mask, clip_opacity
from .composition import COMPOSITORS
from .feature_ao import FeatureAmbientOcclusion
from .importance import Focus, Importance
from .lao import LocalAmbientOcclusion
from .obscurance import ObscuranceParams
from .render import (
    _CLASSIFICATIONS,
    BACKGROUND_HINT,
    Medium,
    _structure,
    march_view,
    march_views,
    medium,
)
from .saliency import SaliencyModulation
from .shading import SHADERS, Phong
from .transfer import TransferFunction

_WHERE = "volshade.Scene"


def _nothing(scene: "Scene") -> None:
    return None


def _volume_ambient(scene: "Scene") -> Array:
    # (its finiteness is checked with every other scene leaf)
    return _checks.in_unit_range(scene.ambient_volume, "scene.ambient_volume", "volshade.render",
                                 hint="(an ambient factor); rescale it, e.g. divide by its "
                                      "maximum")


def _voxel_step(scene: "Scene", params) -> float | None:
    # the corrected form reads alpha as the opacity of a one-voxel step (the geometric
    # mean edge for anisotropic voxels); the seeds' form takes the classified opacity
    return math.prod(scene.spacing) ** (1 / 3) if params.opacity_correction else None


def _kept(scene: "Scene") -> Array | None:
    """1 where the scene's clip keeps the voxel, 0 where it removes it (None: no clip)."""
    if scene.clip is None:
        return None
    return jnp.where(clip_mask(scene.volume.shape, scene.clip), 0.0, 1.0).astype(
        jnp.promote_types(scene.volume.dtype, jnp.float32))


def _lao_ambient(scene: "Scene") -> Array:
    alpha = scene.transfer.opacity(scene.volume, step=_voxel_step(scene, scene.lao))
    return scene.lao(alpha if scene.clip is None else clip_opacity(alpha, scene.clip))


def _feature_ao_ambient(scene: "Scene") -> Array:
    return scene.feature_ao(scene.volume, base=scene.transfer,
                            step=_voxel_step(scene, scene.feature_ao.lao))


def _obscurance_ambient(scene: "Scene") -> Array:
    return scene.obscurance(scene.volume, scene.transfer)


def _saliency_factor(scene: "Scene") -> Array:
    return scene.saliency(scene.volume, scene.transfer, scene.spacing)


def _as_array(volume):
    """Nested lists become an array (kept as a list, every voxel would be a static
    Python float under ``eqx.filter_jit``); arrays are kept with their dtype."""
    if eqx.is_array(volume):
        return volume
    try:
        return jnp.asarray(volume)
    except (TypeError, ValueError):  # ValueError: a ragged nested list
        return volume  # refused by __check_init__, with the argument's name


# Effect tables: stage -> effect name -> what to compute for it. An effect that is off
# maps to `_nothing`, so it is never traced.
AMBIENT: dict[str, Callable[["Scene"], Array | None]] = {
    "none": _nothing,
    "volume": _volume_ambient,
    "lao": _lao_ambient,
    "feature_ao": _feature_ao_ambient,
    "obscurance": _obscurance_ambient,
}
MODULATION: dict[str, Callable[["Scene"], Array | None]] = {
    "none": _nothing,
    "saliency": _saliency_factor,
}


# Effect parameters: field -> (its type, the stage that reads it, the stage's options that
# use it, whether the type has defaults). A scene that uses an effect whose parameters are
# left out gets the defaults; parameters given to a scene that never reads them are
# refused, or a render would look as if they had no effect.
_PARAMETERS: dict[str, tuple[type, str, tuple[str, ...], bool]] = {
    "lao": (LocalAmbientOcclusion, "ambient", ("lao",), True),
    "feature_ao": (FeatureAmbientOcclusion, "ambient", ("feature_ao",), False),
    "obscurance": (ObscuranceParams, "ambient", ("obscurance",), True),
    "saliency": (SaliencyModulation, "modulation", ("saliency",), True),
    "phong": (Phong, "shading", ("phong", "obscurance"), True),
    "importance": (Importance, "composition", ("importance",), True),
}


def _option(name: str, table: dict, hint: str = "") -> Callable[[Any], str]:
    """The converter of an option field: the name itself, checked against ``table``."""
    def check(value: Any) -> str:
        _checks.option(value, table, name, _WHERE, hint=hint)
        return _checks.python_scalar(value)
    return check


def _changed(value: eqx.Module, kind: type) -> Any:
    """Whether effect parameters differ from their type's defaults: a bool, or a traced
    one where their values are traced (a copy under ``jit``)."""
    same = eqx.tree_equal(value, kind())
    known = _checks.concrete(same)
    return jnp.logical_not(same) if known is None else not bool(known)


def _unused_message(name: str, stage: str, option: str, users: tuple[str, ...]) -> str:
    wanted = " or ".join(f"{stage}={u!r}" for u in users)
    return (f"`{name}` is used only with {wanted}, got {stage}={option!r}; set {wanted} or "
            f"leave `{name}` out (a copy with dataclasses.replace keeps it: pass "
            f"`{name}=None` too).")


class _Unread(NamedTuple):
    """A leaf of a scene's effect parameters that its other settings leave unread."""

    leaf: Any
    default: float
    reason: str
    message: str  # refusing another value than the default

    def set(self) -> Any:
        """Whether the leaf holds another value than its default (a ``bad`` for
        :func:`volshade._checks.refuse`)."""
        xp, value = _checks.for_check(self.leaf)
        return xp.any(value != self.default)


class Scene(eqx.Module):
    """A volume, its classification and the effects to render it with.

    The parameters of an effect (``lao``, ``obscurance``, ``saliency``, ``phong``,
    ``importance``) are used only by the effect: left out, they are the defaults of
    their type when the scene names the effect and ``None`` when it does not; given to a
    scene that does not name the effect (e.g. ``lao=`` with ``ambient="none"``), they are
    refused rather than ignored. A copy that turns an effect off
    (``dataclasses.replace(scene, ambient="none")``) drops the defaults the scene filled
    in, and refuses parameters that were given or changed unless they are dropped too
    (``lao=None``); under ``jit``, where a change is not known while tracing, the copy is
    refused when its render runs (the check rides on ``background``). Which parameters
    were filled in is static, part of the scene's pytree structure: a scene given
    ``phong=vs.Phong()`` and one that left it out are different pytrees (not
    ``eqx.tree_equal``, compiled apart, not stacked for ``jax.vmap`` nor joined by
    ``lax.cond``); build the scenes of a sweep alike. :func:`render` checks again which
    effects use what, since a module set with ``eqx.tree_at`` skips the constructor.

    The constructor checks types, shapes, options and which effects use what (see
    Raises); values (NaN or inf in ``volume`` or a parameter, out-of-range values)
    are checked by :func:`render`, at run time when they are traced.

    Attributes:
        volume: ``(D, H, W)`` intensities.
        transfer: the transfer function.
        spacing: voxel size ``(sd, sh, sw)`` in mm (static).
        step: sampling distance along rays in mm (static).
        ambient: ambient term: ``"none"``, ``"volume"`` (use ``ambient_volume``),
            ``"lao"`` (ray-marched local ambient occlusion of the transfer-function
            opacity, with ``lao``), ``"feature_ao"`` (feature-driven AO, with
            ``feature_ao``) or ``"obscurance"`` (grey or colour-bleeding
            obscurance, with ``obscurance``).
        ambient_volume: ``(D, H, W)`` or ``(D, H, W, 3)`` precomputed ambient
            factor in [0, 1] for ``ambient="volume"``.
        lao: :class:`~volshade.lao.LocalAmbientOcclusion` parameters (radius and
            offset in voxels are leaves). It gets the transfer function's opacity
            as classified (per ``step0`` mm, the seeds' form) or, with
            ``opacity_correction``, corrected to a one-voxel step (the geometric
            mean of ``spacing``), as :func:`~volshade.lao.lao` reads it then. For
            ``ambient="lao"`` only.
        feature_ao: :class:`~volshade.feature_ao.FeatureAmbientOcclusion` parameters
            for ``ambient="feature_ao"`` (no default: the features are the scene's
            own); interval features select from ``transfer``, and the opacities are
            corrected as for ``lao``.
        obscurance: :class:`~volshade.obscurance.ObscuranceParams`, for
            ``ambient="obscurance"``.
        modulation: opacity modulation: ``"none"`` or ``"saliency"`` (obscurance
            saliency, with ``saliency``).
        saliency: :class:`~volshade.saliency.SaliencyModulation` parameters, for
            ``modulation="saliency"``.
        shading: ``"none"`` (emission-absorption), ``"phong"`` (Blinn--Phong with
            the ambient term) or ``"obscurance"`` (eq. 5 of Ruiz et al.: all local
            lighting scaled by the ambient volume; two-sided, like ``"phong"``; with
            no ambient term, samples without a gradient are black).
        phong: Blinn--Phong coefficients, for ``shading="phong"`` or
            ``"obscurance"`` (which reads its diffuse and specular terms).
        composition: ``"standard"`` or ``"importance"`` (importance-aware, with
            ``importance`` and optional per-ray ``focus`` weights).
        importance: :class:`~volshade.importance.Importance` weights, for
            ``composition="importance"``.
        focus: optional :class:`~volshade.importance.Focus` (focus plus context). It
            scales the importance measures' weights per ray, so with all of them 0
            (the default :class:`~volshade.importance.Importance`) it changes nothing
            until a fit or the user gives one a value.
        background: ``(3,)`` RGB background colour, in [0, 1] (checked when the scene
            is built from known values; a value set by a fit or ``eqx.tree_at`` is
            checked for NaN or inf only, so a fit can converge to 0 or 1 with a
            rounding error either side and its scene still renders).
        clip: optional clip shape (:mod:`volshade.clip`): the voxels inside it are
            removed from the render (their opacity scaled by 0, sampled
            trilinearly) and from the opacity ``ambient="lao"`` sees. With a moving
            clip, compute the ambient volume with
            :func:`~volshade.cao.contextual_ao` and pass it as
            ``ambient="volume"``. ``ambient="feature_ao"`` and ``"obscurance"``
            and ``modulation="saliency"`` do not take the clip into account and are
            refused with it. Gradients (Phong normals, importance) are those of the
            unclipped volume, so a cut face is shaded with the normals of the tissue
            it cuts through.
        classification: ``"post"`` (default: classify interpolated intensities) or
            ``"pre"`` (interpolate the classified voxels' opacity-weighted colours:
            for label volumes, such as the ``"corner"`` phantom; see
            :func:`~volshade.render.march`) (static).

    Raises:
        ValueError: ``volume`` not 3-D or empty; ``step`` not a finite number > 0;
            ``spacing`` not 1 or 3 finite numbers > 0; an unknown ``ambient``,
            ``modulation``, ``shading``, ``composition`` or ``classification``;
            ``ambient="volume"`` without ``ambient_volume``, or ``ambient_volume`` with
            another ``ambient`` or a shape other than ``(D, H, W)`` or ``(D, H, W, 3)``;
            ``ambient="feature_ao"`` without ``feature_ao``; effect parameters given to a
            scene that does not use them; ``focus`` without ``composition="importance"``;
            ``importance.global_weight`` (with ``focus``) or ``phong.ambient`` (with
            ``shading="obscurance"``) set to other than its default (set with
            ``eqx.tree_at`` or traced: refused by :func:`render`); ``clip`` with
            ``ambient="feature_ao"`` or ``"obscurance"`` or ``modulation="saliency"``;
            ``background`` not of shape ``(3,)`` or outside [0, 1].
        TypeError: non-numeric ``volume``, ``ambient_volume`` (complex included) or
            ``background`` (a bool ``background``);
            ``step`` or ``spacing`` not numbers, or traced (they are static);
            ``transfer``, ``lao``, ``feature_ao``, ``obscurance``, ``saliency``,
            ``phong``, ``importance``, ``focus`` or ``clip`` not of its volshade type.

    Example:
        >>> vol = jnp.zeros((8, 8, 8))
        >>> scene = Scene(volume=vol, transfer=vs.transfer.preset("grey"))
        >>> render(scene, Camera.orbit(image_shape=(4, 4))).shape
        (4, 4, 4)
    """

    volume: Float[Array, "D H W"] = eqx.field(converter=_as_array)
    transfer: TransferFunction
    spacing: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0),
                                                    converter=lambda s: _checks.spacing(s, _WHERE))
    step: float = eqx.field(static=True, default=0.5,  # a Python float, as spacing's
                            converter=lambda s: _checks.positive_float(s, "step", _WHERE))
    # (options are checked by their converters, before equinox warns of an array or a
    # module given in their place)
    ambient: str = eqx.field(static=True, default="none", converter=_option(
        "ambient", AMBIENT, "an ambient volume of your own goes in `ambient_volume=`, with "
                            "ambient='volume'; LAO parameters in `lao=`"))
    ambient_volume: Array | None = eqx.field(
        default=None, converter=lambda v: None if v is None else _as_array(v))
    lao: LocalAmbientOcclusion | None = None
    feature_ao: FeatureAmbientOcclusion | None = None
    obscurance: ObscuranceParams | None = None
    modulation: str = eqx.field(static=True, default="none", converter=_option(
        "modulation", MODULATION, "saliency parameters go in `saliency=`"))
    saliency: SaliencyModulation | None = None
    shading: str = eqx.field(static=True, default="none", converter=_option(
        "shading", SHADERS, "Phong coefficients go in `phong=`, with shading='phong'"))
    phong: Phong | None = None
    composition: str = eqx.field(static=True, default="standard", converter=_option(
        "composition", COMPOSITORS, "importance weights go in `importance=`, with "
                                    "composition='importance'"))
    importance: Importance | None = None
    focus: Focus | None = None
    background: Float[Array, "3"] = eqx.field(
        converter=_checks.leaf("volshade.Scene", "background"), default=(0.0, 0.0, 0.0))
    clip: Clip | None = None
    # last: the fields before it keep their positions
    classification: str = eqx.field(static=True, default="post", converter=_option(
        "classification", _CLASSIFICATIONS))
    # the effect parameters __post_init__ filled in (not given): a copy that turns their
    # effect off (dataclasses.replace) drops them, where given ones are refused
    _defaulted: tuple[str, ...] = eqx.field(static=True, default=(), repr=False)

    def __post_init__(self):
        defaulted = set(self._defaulted)
        for name, (kind, stage, users, has_defaults) in _PARAMETERS.items():
            if not has_defaults:
                continue
            value, option = getattr(self, name), getattr(self, stage)
            used = isinstance(option, str) and option in users  # (others: the converter's)
            if value is None and used:
                setattr(self, name, kind())
                defaulted.add(name)
                continue
            if name not in defaulted:
                continue
            changed = True if value is None else _changed(value, kind)
            if changed is True:
                defaulted.discard(name)  # (a value put in its place is the user's)
            elif not used:
                if changed is not False:
                    # traced (a copy under jit): a value changed with eqx.tree_at cannot be
                    # told from the defaults here, so the copy is refused at run time
                    self.background = _checks.refuse(
                        _checks.float_leaf(self.background, "background", _WHERE),
                        [(changed, _unused_message(name, stage, option, users))], _WHERE)
                setattr(self, name, None)
                defaulted.discard(name)
        self._defaulted = tuple(sorted(defaulted))

    def __check_init__(self):
        _checks.as_float_array(self.volume, "volume", _WHERE)
        _checks.check_ndim(jnp.asarray(self.volume), 3, "volume", _WHERE, "(D, H, W)")
        self._check_effects(_WHERE)
        _checks.refuse(None, [(unread.set(), unread.message)
                              for unread in self._unread_leaves().values()], _WHERE,
                       traced=False)
        if jnp.shape(self.background) != (3,):
            raise ValueError(f"{_WHERE}: `background` must be an RGB triple, "
                             f"got shape {jnp.shape(self.background)}.")
        _checks.in_unit_range(self.background, "background", _WHERE, hint=BACKGROUND_HINT,
                              traced=False)

    def _check_effects(self, where: str) -> None:
        """The transfer function; each effect's parameters present where its stage uses
        them, of their type, and absent elsewhere; the focus and the clip where they are
        read. Checked by the constructor and again by :func:`render`: a module set with
        ``eqx.tree_at`` skipped the constructor (a clip in an obscurance scene rendered
        unclipped without a word)."""
        if not isinstance(self.transfer, TransferFunction):
            raise TypeError(f"{where}: `transfer` must be a volshade.TransferFunction, "
                            f"got {type(self.transfer).__name__}.")
        if self.ambient == "volume" and self.ambient_volume is None:
            raise ValueError(f"{where}: ambient='volume' needs `ambient_volume`.")
        if self.ambient != "volume" and self.ambient_volume is not None:
            raise ValueError(f"{where}: `ambient_volume` is used only with "
                             f"ambient='volume', got ambient={self.ambient!r}; set "
                             f"ambient='volume' or leave `ambient_volume` out.")
        if self.ambient_volume is not None:
            _checks.as_float_array(self.ambient_volume, "ambient_volume", where)
            shape, ambient_shape = jnp.shape(self.volume), jnp.shape(self.ambient_volume)
            if ambient_shape not in (shape, (*shape, 3)):
                raise ValueError(f"{where}: `ambient_volume` must have the shape of `volume`, "
                                 f"{shape} (grey) or {(*shape, 3)} (RGB), got {ambient_shape}.")
        for name, (kind, stage, users, _) in _PARAMETERS.items():
            value, option = getattr(self, name), getattr(self, stage)
            if value is None:
                if option in users:  # (only feature_ao has no defaults)
                    raise ValueError(f"{where}: {stage}={option!r} needs `{name}=` a "
                                     f"volshade.{kind.__name__}.")
                continue
            # a number or a dict in its place would fail only inside the render, unnamed
            if not isinstance(value, kind):
                raise TypeError(f"{where}: `{name}` must be a volshade.{kind.__name__}, "
                                f"got {type(value).__name__}.")
            if option not in users:
                raise ValueError(f"{where}: {_unused_message(name, stage, option, users)}")
        if self.focus is not None and not isinstance(self.focus, Focus):
            raise TypeError(f"{where}: `focus` must be a volshade.Focus, got "
                            f"{type(self.focus).__name__}.")
        if self.focus is not None and self.composition != "importance":
            raise ValueError(f"{where}: `focus` needs composition='importance'.")
        if self.clip is not None:
            if not isinstance(self.clip, Clip):
                raise TypeError(f"{where}: `clip` must be a volshade clip shape (e.g. "
                                f"volshade.SphereClip), got {type(self.clip).__name__}.")
            if self.ambient in ("feature_ao", "obscurance"):
                raise ValueError(f"{where}: ambient={self.ambient!r} does not take `clip` "
                                 f"into account; compute the ambient volume of the clipped "
                                 f"volume yourself and pass ambient='volume'.")
            if self.modulation != "none":
                raise ValueError(f"{where}: modulation={self.modulation!r} does not take "
                                 f"`clip` into account (the saliency would be that of the "
                                 f"unclipped volume); use modulation='none' with a clip.")

    def _unread_leaves(self) -> dict[str, "_Unread"]:
        """Leaves of the effect parameters that this scene's other settings leave unread,
        by path (refused when set: by the constructor, by :func:`render` where a copy or
        ``eqx.tree_at`` set them, and by :func:`volshade.fit` as parameters to fit)."""
        why = {}
        if self.focus is not None:
            why["importance.global_weight"] = ("the focus's `inside` and `outside` "
                                               "weights replace it on every ray")
        if self.shading == "obscurance":
            why["phong.ambient"] = ("shading='obscurance' takes the obscurance as its "
                                    "ambient term, with Phong's diffuse and specular")
        unread = {}
        for path, reason in why.items():
            stage, name = path.split(".")
            # the field's default as written (a Python number: under jit the built
            # module's leaves are traced)
            (default,) = (f.default for f in dataclasses.fields(_PARAMETERS[stage][0])
                          if f.name == name)
            unread[path] = _Unread(getattr(getattr(self, stage), name), default, reason,
                                   f"`{path}` is not read by this scene ({reason}); leave "
                                   f"it at its default, {default:g}.")
        return unread

    def plan(self) -> dict[str, str]:
        """The effects a render of this scene computes, by stage."""
        return {"ambient": self.ambient, "modulation": self.modulation,
                "shading": self.shading, "composition": self.composition}


def _minus_inf_allowed(tree, prefix: str) -> set[str]:
    """Names of the leaves whose module declares that they may be -inf
    (``may_be_minus_inf``, e.g. :class:`~volshade.importance.Importance`'s background)."""
    def declares(node):
        return isinstance(node, eqx.Module) and bool(getattr(node, "may_be_minus_inf", ()))

    nodes, _ = jax.tree_util.tree_flatten_with_path(
        tree, is_leaf=lambda node: node is not tree and declares(node))
    return {prefix + jax.tree_util.keystr((*path, jax.tree_util.GetAttrKey(field)))
            for path, node in nodes if declares(node) for field in node.may_be_minus_inf}


def _containers_as_arrays(tree: Any, name: str) -> Any:
    """``tree`` with each list or tuple of numbers or arrays in place of an array leaf (set
    with ``eqx.tree_at``, which skips the modules' converters) made an array, as the
    converter would have made it; what cannot be one is refused by its path (it would
    fail inside the render, unnamed). Sequences of modules (feature AO's features) are
    looked into."""
    def container(node):
        if node is tree or not isinstance(node, list | tuple | dict):
            return False
        children = node.values() if isinstance(node, dict) else node
        return not all(isinstance(child, eqx.Module) for child in children)

    def as_array(path, node):
        if not container(node):
            return node
        if not isinstance(node, dict):
            try:
                return jnp.asarray(node)
            except (TypeError, ValueError):
                pass  # (ragged, or not numbers)
        raise TypeError(f"volshade.render: `{name}{jax.tree_util.keystr(path)}` must be an "
                        f"array, got a {type(node).__name__} that is not one; pass "
                        f"jnp.asarray(...).")

    return jax.tree_util.tree_map_with_path(as_array, tree, is_leaf=container)


def _finite_parameters(scene: Scene, camera: Any) -> tuple[Scene, Any]:
    """Refuse NaN/inf in any floating-point leaf of the scene or camera(s) (naming it), so a
    bad parameter raises instead of rendering a NaN image. The volume has its own check;
    leaves a module declares in ``may_be_minus_inf`` may also be -inf. The traced leaves
    are checked together (one error site, :func:`volshade._checks.refuse`)."""
    flat, treedef = jax.tree_util.tree_flatten_with_path((scene, camera))
    allowed = (_minus_inf_allowed(scene, "scene") | _minus_inf_allowed(camera, "camera"))
    leaves = [leaf for _, leaf in flat]
    checked, checks = [], []
    for i, (path, leaf) in enumerate(flat):
        # the first key picks the scene or the camera(s) of the (scene, camera) pair
        name = ("scene", "camera")[path[0].idx] + jax.tree_util.keystr(path[1:])
        minus_inf = name in allowed
        message = (f"`{name}` contains NaN or inf; every scene and camera parameter "
                   f"must be finite{' (or -inf)' if minus_inf else ''}.")
        if isinstance(leaf, float):  # a static leaf (e.g. set with eqx.tree_at)
            bad = not (math.isfinite(leaf) or (minus_inf and leaf == -math.inf))
        elif eqx.is_inexact_array(leaf) and leaf is not scene.volume:
            bad = _checks.non_finite(leaf, minus_inf=minus_inf).any()
        else:
            continue
        checked.append(i)
        checks.append((bad, message))
    refused = _checks.refuse([leaves[i] for i in checked], checks, "volshade.render")
    for i, leaf in zip(checked, refused, strict=True):
        leaves[i] = leaf
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _unread_at_default(scene: Scene) -> Scene:
    """``scene``, refused where a leaf it does not read holds other than its default: the
    constructor refuses known values, but a leaf set with ``eqx.tree_at``, or a scene
    built under ``jit``, reaches the render unchecked (the render would ignore it)."""
    for path, unread in scene._unread_leaves().items():
        stage, name = path.split(".")
        checked = _checks.refuse(unread.leaf, [(unread.set(), unread.message)],
                                 "volshade.render")
        scene = eqx.tree_at(lambda s, stage=stage, name=name: getattr(getattr(s, stage), name),
                            scene, checked)
    return scene


def _check_cameras(camera: Any, where: str = "volshade.render") -> None:
    """Refuse anything but a camera or a non-empty list or tuple of cameras (for
    :func:`render` and :func:`volshade.fit`)."""
    if isinstance(camera, Camera):
        return
    if not isinstance(camera, list | tuple) or not camera:
        raise TypeError(f"{where}: `camera` must be a volshade.Camera or a non-empty "
                        f"sequence (list or tuple) of them, got {camera!r:.80}.")
    others = sorted({type(c).__name__ for c in camera if not isinstance(c, Camera)})
    if others:
        raise TypeError(f"{where}: every entry of `camera` must be a volshade.Camera, "
                        f"got {', '.join(others)}.")


def _each_view(shared: Medium, focus: Focus | None, cameras: list[Camera]) -> list[Array]:
    """The image of each camera: one compiled march for cameras of one structure
    (:func:`~volshade.render.march_views`), so that many views compile as fast as one;
    a march per camera otherwise."""
    def weights(cam: Camera) -> Array | None:
        return None if focus is None else focus.weights(cam.image_shape)

    try:
        alike = len({_structure(cam) for cam in cameras}) == 1
    except TypeError:  # a leaf that is no number (set with eqx.tree_at): march_view names it
        alike = False
    if len(cameras) == 1 or not alike:
        return [march_view(shared, cam, weights(cam)) for cam in cameras]
    images = march_views(shared, cameras, weights(cameras[0]))
    return [images[i] for i in range(len(cameras))]


def render(scene: Scene, camera: Camera | list[Camera] | tuple[Camera, ...]
           ) -> Float[Array, "H W 4"] | list[Float[Array, "H W 4"]]:
    """Render ``scene`` from ``camera``, computing only the effects the scene names.

    Args:
        scene: what to render.
        camera: a :class:`~volshade.camera.Camera`, or a list or tuple of them. The
            views of a sequence share everything that does not depend on the view,
            computed once: the ambient volume (LAO, feature AO, obscurance), the
            saliency modulation, the clip mask and the gradient volume. Cameras of
            one structure (image shape, projection, and the shapes and dtypes of
            their values) are marched by one compiled loop (``jax.lax.map``), so a
            turntable of many views compiles like one. The images equal those of
            one render per camera up to rounding (XLA may order the arithmetic of
            the two programs differently: a few 1e-6 in float32).

    Returns:
        ``(H, W, 4)`` RGB (background blended in) and accumulated opacity; for a
        sequence of cameras, a list of those images, one per camera, in order. The
        RGB is not clipped: Phong's terms can add up past 1 (the defaults, 0.35 +
        0.65 + 0.25, where a highlight falls on a bright colour). :func:`save_png`
        clips; for ``matplotlib.pyplot.imshow`` use ``jnp.clip(image[..., :3], 0, 1)``.

    Raises:
        TypeError: ``scene`` is not a :class:`Scene`; ``camera`` is not a camera or a
            non-empty list or tuple of them; a dict, or a list or tuple that is not
            an array, in place of an array leaf (set with ``eqx.tree_at``, named by
            its path; lists and tuples of numbers are made arrays).
        ValueError / EquinoxRuntimeError: NaN or inf in a scene or camera parameter
            (named); a parameter the scene does not read set to other than its default
            (``importance.global_weight`` with a ``focus``, ``phong.ambient`` with
            ``shading="obscurance"``); a camera field set with ``eqx.tree_at`` to what
            :class:`~volshade.camera.Camera` refuses; and the checks of the effects and
            of :func:`~volshade.render.march`.

    Example:
        >>> scene = Scene(volume=vs.data.phantom("shells", shape=16),
        ...               transfer=vs.transfer.preset("shells"))
        >>> render(scene, Camera.orbit(azimuth=30, elevation=20, image_shape=(8, 8))).shape
        (8, 8, 4)
        >>> views = [Camera.orbit(azimuth=a, image_shape=(8, 8)) for a in (0, 90, 180)]
        >>> [image.shape for image in render(scene, views)]
        [(8, 8, 4), (8, 8, 4), (8, 8, 4)]
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"volshade.render: `scene` must be a volshade.Scene, got "
                        f"{type(scene).__name__}; wrap a volume as "
                        f"volshade.Scene(volume=..., transfer=...).")
    _check_cameras(camera)
    scene = _containers_as_arrays(scene, "scene")
    scene._check_effects("volshade.render")
    camera = (_containers_as_arrays(camera, "camera") if isinstance(camera, Camera) else
              [_containers_as_arrays(cam, f"camera[{i}]") for i, cam in enumerate(camera)])
    scene, camera = _finite_parameters(scene, camera)
    scene = _unread_at_default(scene)
    # the volume first, so a NaN in it is named as the render's, not as the first effect's
    scene = eqx.tree_at(lambda s: s.volume, scene,
                        _checks.finite(scene.volume, "volume", "volshade.render"))
    # the render computes in float32 at least
    scene, camera = _checks.strongly_typed(
        (scene, camera), jnp.promote_types(scene.volume.dtype, jnp.float32))
    cameras = [camera] if isinstance(camera, Camera) else list(camera)
    ambient = AMBIENT[scene.ambient](scene)
    opacity_scale = MODULATION[scene.modulation](scene)
    kept = _kept(scene)
    if kept is not None:
        opacity_scale = kept if opacity_scale is None else opacity_scale * kept
    shared = medium(scene.volume, scene.transfer, spacing=scene.spacing, step=scene.step,
                    shading=scene.shading, phong=scene.phong, ambient=ambient,
                    opacity_scale=opacity_scale, composition=scene.composition,
                    importance=scene.importance, background=scene.background,
                    classification=scene.classification)
    images = _each_view(shared, scene.focus, cameras)
    return images[0] if isinstance(camera, Camera) else images
