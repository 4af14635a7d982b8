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

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp

from . import _checks
from ._types import Array, Float
from .camera import Camera
from .composition import COMPOSITORS
from .render import march
from .shading import SHADERS, Phong
from .transfer import TransferFunction

_WHERE = "volshade.Scene"


def _no_ambient(scene: "Scene") -> None:
    return None


def _volume_ambient(scene: "Scene") -> Array:
    return scene.ambient_volume


AMBIENT: dict[str, Callable[["Scene"], Array | None]] = {
    "none": _no_ambient,
    "volume": _volume_ambient,
}


class Scene(eqx.Module):
    """A volume, its classification and the effects to render it with.

    Attributes:
        volume: ``(D, H, W)`` intensities.
        transfer: the transfer function.
        spacing: voxel size ``(sd, sh, sw)`` in mm (static).
        step: sampling distance along rays in mm (static).
        ambient: ambient term: ``"none"`` or ``"volume"`` (use ``ambient_volume``).
        ambient_volume: ``(D, H, W)`` or ``(D, H, W, 3)`` precomputed ambient
            factor in [0, 1] for ``ambient="volume"``.
        shading: ``"none"`` (emission-absorption) or ``"phong"``.
        phong: Blinn--Phong coefficients.
        composition: ``"standard"`` front-to-back compositing.
        background: ``(3,)`` RGB background colour.

    Example:
        >>> vol = jnp.zeros((8, 8, 8))
        >>> scene = Scene(volume=vol, transfer=preset("grey"))
        >>> render(scene, Camera.orbit(image_shape=(4, 4))).shape
        (4, 4, 4)
    """

    volume: Float[Array, "D H W"]
    transfer: TransferFunction
    spacing: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0),
                                                    converter=lambda s: _checks.spacing(s, _WHERE))
    step: float = eqx.field(static=True, default=0.5)
    ambient: str = eqx.field(static=True, default="none")
    ambient_volume: Array | None = None
    shading: str = eqx.field(static=True, default="none")
    phong: Phong = eqx.field(default_factory=Phong)
    composition: str = eqx.field(static=True, default="standard")
    background: Float[Array, "3"] = eqx.field(converter=jnp.asarray, default=(0.0, 0.0, 0.0))

    def __check_init__(self):
        _checks.as_float_array(self.volume, "volume", _WHERE)
        _checks.check_ndim(jnp.asarray(self.volume), 3, "volume", _WHERE, "(D, H, W)")
        if not isinstance(self.transfer, TransferFunction):
            raise TypeError(f"{_WHERE}: `transfer` must be a volshade.TransferFunction, "
                            f"got {type(self.transfer).__name__}.")
        _checks.positive_float(self.step, "step", _WHERE)
        _checks.option(self.ambient, AMBIENT, "ambient", _WHERE)
        _checks.option(self.shading, SHADERS, "shading", _WHERE)
        _checks.option(self.composition, COMPOSITORS, "composition", _WHERE)
        if self.ambient == "volume" and self.ambient_volume is None:
            raise ValueError(f"{_WHERE}: ambient='volume' needs `ambient_volume`.")
        if jnp.shape(self.background) != (3,):
            raise ValueError(f"{_WHERE}: `background` must be an RGB triple, "
                             f"got shape {jnp.shape(self.background)}.")

    def plan(self) -> dict[str, str]:
        """The effects a render of this scene computes, by stage."""
        return {"ambient": self.ambient, "shading": self.shading,
                "composition": self.composition}


def render(scene: Scene, camera: Camera) -> Float[Array, "H W 4"]:
    """Render ``scene`` from ``camera``, computing only the effects the scene names.

    Returns:
        ``(H, W, 4)`` RGB (background blended in) and accumulated opacity.

    Example:
        >>> scene = Scene(volume=vs.data.phantom("shells"), transfer=vs.transfer.preset("shells"))
        >>> image = render(scene, Camera.orbit(azimuth=30, elevation=20))
    """
    ambient = AMBIENT[scene.ambient](scene)
    return march(scene.volume, scene.transfer, camera, spacing=scene.spacing, step=scene.step,
                 shading=scene.shading, phong=scene.phong, ambient=ambient,
                 composition=scene.composition, background=scene.background)
