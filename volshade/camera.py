r"""Cameras and ray generation.

Scene coordinates: the volume's box of voxel cells is centred at the origin and
scaled so that its longest physical side has length 1 (so one camera works for
any volume); axes are in volume order ``(d, h, w)``. For NIfTI data loaded with
:func:`volshade.data.load_nifti`, ``d`` points superior, ``h`` anterior and
``w`` to the subject's right: ``(d, h, w) = (z, y, x)`` is a *left-handed*
frame, which is why the camera's right vector is ``up x forward``.

Image conventions: an image is ``(H, W)`` with row 0 at the top; pixel centres
are at half-integer positions.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._numerics import safe_div, safe_norm, safe_normalize, scaled_down
from ._types import Array, Float

_PROJECTIONS = ("perspective", "orthographic")


def _image_shape(shape) -> tuple:
    """``(H, W)``; one int ``n`` means a square ``(n, n)`` image."""
    if isinstance(shape, int | np.integer) and not isinstance(shape, bool):
        return (int(shape), int(shape))
    # an ordered sequence only: a set's order is not (H, W), and would transpose the image
    if isinstance(shape, np.ndarray) and shape.ndim == 1:
        return tuple(shape.tolist())  # Python numbers: NumPy scalars are arrays to equinox
    if isinstance(shape, list | tuple):
        return tuple(_checks.python_scalar(n) for n in shape)
    raise TypeError(f"volshade.Camera: `image_shape` must be (H, W), a tuple or list of "
                    f"two ints, or one int, got {shape!r:.80}.")


def _vanishing(v: Array, xp) -> tuple[Array, Array]:
    """``(vanishes, direction)``: whether :func:`safe_normalize` makes ``v`` the zero
    vector, and ``v`` normalised (computed with ``xp``, NumPy for concrete values). It
    does where ``|v|^2`` (of ``v`` divided by its largest component above 1) is below
    the smallest normal number of the dtype, which XLA flushes to 0: a view ``1e-20``
    long, or an ``up`` ``1e-20`` off the view direction, in float32. NaN does not
    vanish (the finiteness checks name it)."""
    peak = xp.max(xp.abs(v))
    v = v / xp.where(peak > 1, peak, xp.ones_like(peak))
    square = xp.sum(v * v)
    vanishes = square < xp.finfo(v.dtype).tiny
    return vanishes, v / xp.sqrt(xp.where(vanishes, xp.ones_like(square), square))


@jax.jit
def _orbit_pose(azimuth: Array, elevation: Array, target: Array, distance: Array
                ) -> tuple[Array, Array]:
    """:meth:`Camera.orbit`'s eye and up vector (degrees in): one compiled program,
    where an eager call compiled each of its operations (the first call 0.8 s)."""
    a, e = jnp.deg2rad(azimuth), jnp.deg2rad(elevation)
    direction = jnp.stack([jnp.sin(e), jnp.cos(e) * jnp.cos(a), jnp.cos(e) * jnp.sin(a)])
    # Looking straight along d, "up" must come from the azimuth instead.
    toward_azimuth = jnp.stack([jnp.zeros_like(a), -jnp.cos(a), -jnp.sin(a)])
    up = jnp.where(jnp.abs(jnp.sin(e)) > 1 - 1e-6, toward_azimuth * jnp.sign(jnp.sin(e)),
                   jnp.asarray([1.0, 0.0, 0.0], a.dtype))
    return target + distance * direction, up


@jax.jit
def _view_angles(view: Array, spacing: Array) -> tuple[Array, Array]:
    """:meth:`Camera.from_view`'s azimuth and elevation (degrees) of a checked ``view``
    (one compiled program: an eager call compiled each operation, 1.3 s the first)."""
    # scaled to a largest component of 1 first: |view|^2 would overflow or underflow
    # for directions given in very large or very small numbers (scaled_down: a CPU
    # divides through the reciprocal, which above 8.5e37 in float32 is flushed to 0)
    view = scaled_down(view, jnp.max(jnp.abs(view)))
    v = safe_normalize(view * spacing)
    # arctan2 of the distance to the d axis rather than arcsin(v_d): a finite slope
    # at the poles, where the azimuth (undefined) is 0 with a zero gradient; "at the
    # pole" is where v_h^2 + v_w^2, the denominator of arctan2's slope, is 0
    pole = jnp.square(v[1]) + jnp.square(v[2]) == 0
    elevation = jnp.rad2deg(jnp.arctan2(v[0], safe_norm(v[1:])))
    azimuth = jnp.where(pole, 0, jnp.rad2deg(jnp.arctan2(jnp.where(pole, 0, v[2]),
                                                          jnp.where(pole, 1, v[1]))))
    return azimuth, elevation


class Camera(eqx.Module):
    """A pinhole (perspective) or orthographic camera in scene coordinates.

    A camera with no image (``eye == target``, ``up`` zero or along the view, ``fov``
    outside (0, 180) degrees, ``width <= 0``) is refused: with ``ValueError`` when
    built from concrete values, at run time when they are traced.

    Attributes:
        eye: ``(3,)`` camera position.
        target: ``(3,)`` point looked at.
        up: ``(3,)`` approximate up direction (made orthogonal to the view).
        fov: vertical field of view in degrees (perspective).
        width: height of the view in scene units (orthographic); the width
            follows from the aspect ratio.
        image_shape: ``(H, W)`` pixels, or one int for a square image (static).
        projection: ``"perspective"`` or ``"orthographic"`` (static).

    Raises:
        ValueError: ``eye``, ``target`` or ``up`` not of shape ``(3,)``; ``image_shape``
            not ``(H, W)`` or with a size < 1; an unknown ``projection``; ``fov`` or
            ``width`` not scalars where the rays are made (a batch is for vmap).
        TypeError: non-numeric (or bool) ``eye``, ``target``, ``up``, ``fov`` or
            ``width``; ``image_shape`` not ints.
        ValueError / equinox.EquinoxRuntimeError (traced: at run time): ``fov``
            outside (0, 180) (perspective) or ``width <= 0`` (orthographic), checked
            when its rays are made (:meth:`rays`, a render); NaN or inf, refused by
            :func:`~volshade.render`.
    """

    eye: Float[Array, "3"] = eqx.field(converter=_checks.leaf("volshade.Camera", "eye"))
    target: Float[Array, "3"] = eqx.field(converter=_checks.leaf("volshade.Camera", "target"))
    up: Float[Array, "3"] = eqx.field(converter=_checks.leaf("volshade.Camera", "up"))
    fov: Float[Array, ""] = eqx.field(converter=_checks.leaf("volshade.Camera", "fov"))
    width: Float[Array, ""] = eqx.field(converter=_checks.leaf("volshade.Camera", "width"))
    image_shape: tuple[int, int] = eqx.field(static=True, default=(256, 256),
                                             converter=lambda s: _image_shape(s))
    projection: str = eqx.field(static=True, default="perspective",
                                converter=_checks.python_scalar)

    def __check_init__(self):
        where = "volshade.Camera"
        if self.projection not in _PROJECTIONS:
            raise ValueError(f"{where}: unknown projection {self.projection!r}; valid values are "
                             f"{', '.join(map(repr, _PROJECTIONS))}.")
        if len(self.image_shape) != 2:
            raise ValueError(f"{where}: `image_shape` must be (H, W), got {self.image_shape!r}.")
        for n in self.image_shape:
            _checks.positive_int(n, "image_shape", where)
        _checks.refuse(self, self._degenerate(), where, traced=False)  # traced: in rays

    def _degenerate(self) -> list[tuple[Array, str]]:
        """``(is_bad, message)`` for each way the camera can have no image: every
        pixel would get the same ray, or the image would be flipped. First the fields'
        types and shapes are checked (raising at once): a field set with ``eqx.tree_at``
        skips the constructor's checks."""
        for name in ("eye", "target", "up", "fov", "width"):
            _checks.float_leaf(getattr(self, name), name, "volshade.Camera")
        for name in ("eye", "target", "up"):
            if jnp.shape(getattr(self, name)) != (3,):
                raise ValueError(f"volshade.Camera: `{name}` must have shape (3,), "
                                 f"got {jnp.shape(getattr(self, name))}.")
        # NaN compares false here: non-finite values are the finiteness checks' to name
        xp, eye, target, up, fov, width = _checks.for_check(self.eye, self.target, self.up,
                                                            self.fov, self.width)
        # as :meth:`basis` normalises them, in the rays' dtype
        dtype = np.result_type(eye.dtype, target.dtype, up.dtype, np.float32)
        no_view, forward = _vanishing(xp.asarray(target - eye, dtype), xp)
        no_right, _ = _vanishing(xp.cross(xp.asarray(up, dtype), forward), xp)
        tiny = f"{np.sqrt(np.finfo(dtype).tiny):.0e}"
        checks = [
            (no_view, f"`eye` and `target` must differ, by more than about {tiny} in "
             f"{np.dtype(dtype).name} (for Camera.orbit: `distance` must be > 0)."),
            (no_right, f"`up` must be non-zero and not parallel to the view direction "
             f"`target - eye` (its part across the view longer than about {tiny} in "
             f"{np.dtype(dtype).name})."),
        ]
        if self.projection == "perspective":
            checks.append(((fov <= 0) | (fov >= 180), "`fov` must lie in (0, 180) degrees."))
        else:
            checks.append((width <= 0, "`width` must be > 0 (scene units)."))
        return checks

    def _valid(self) -> "Camera":
        """This camera with the checks of :meth:`_degenerate` (run time for traced
        values); ``fov`` and ``width`` must be scalars here (built with a batch axis, a
        camera is for vmap: they would broadcast against the image)."""
        for name in ("fov", "width"):
            if jnp.ndim(getattr(self, name)) != 0:
                raise ValueError(f"volshade.Camera: `{name}` must be a scalar where the "
                                 f"rays are made, got shape {jnp.shape(getattr(self, name))}"
                                 f"; for several views pass a list of cameras to the "
                                 f"render, or jax.vmap over the camera.")
        return _checks.refuse(self, self._degenerate(), "volshade.Camera")

    @classmethod
    def orbit(
        cls,
        *,
        azimuth: float = 0.0,
        elevation: float = 0.0,
        distance: float = 2.5,
        image_shape: tuple[int, int] = (256, 256),
        projection: str = "perspective",
        fov: float | None = None,
        width: float | None = None,
        target=(0.0, 0.0, 0.0),
    ) -> "Camera":
        r"""A camera on a sphere around ``target``, up along ``+d``.

        The eye sits at ``target + distance * (sin e, cos e cos a, cos e sin a)``
        for azimuth $a$ and elevation $e$ in degrees: azimuth 0 looks along
        $-h$ (for a head: from the front), elevation 90 looks down from $+d$.

        Args:
            azimuth, elevation: degrees.
            distance: distance from the target in scene units (the volume's
                longest side is 1).
            image_shape: ``(H, W)``.
            projection: ``"perspective"`` or ``"orthographic"``.
            fov: vertical field of view in degrees (perspective only; default 30).
            width: view height in scene units (orthographic only; default 1.2).
            target: ``(3,)`` point looked at.

        Raises:
            ValueError: ``fov`` given for an orthographic view or ``width`` for a
                perspective one (it would be ignored); ``target`` not of shape
                ``(3,)``; a non-scalar ``azimuth``,
                ``elevation`` or ``distance``; the errors of :class:`Camera` for
                ``image_shape`` and ``projection``.
            TypeError: non-numeric (or bool) arguments; ``image_shape`` not ints.
            ValueError / equinox.EquinoxRuntimeError (traced: at run time):
                ``distance <= 0``; ``fov`` outside (0, 180) (perspective) or
                ``width <= 0`` (orthographic), traced: when the rays are made; NaN or
                inf in an argument, traced: refused by the render.

        Example:
            >>> cam = Camera.orbit(azimuth=30, elevation=20, image_shape=(64, 64))
            >>> cam.rays()[1].shape
            (64, 64, 3)
        """
        where = "volshade.Camera.orbit"
        for name, value, other, own in (("fov", fov, "orthographic", "perspective"),
                                        ("width", width, "perspective", "orthographic")):
            if value is not None and isinstance(projection, str) and projection == other:
                raise ValueError(f"{where}: `{name}` does not apply to {other} views (it would "
                                 f"be ignored); leave it out, or set projection={own!r}.")
        fov = 30.0 if fov is None else fov
        width = 1.2 if width is None else width
        dtype = jnp.result_type(float)
        given = {"azimuth": azimuth, "elevation": elevation, "target": target,
                 "distance": distance, "fov": fov, "width": width}
        leaves = {name: _checks.float_leaf(x, name, where).astype(dtype)
                  for name, x in given.items()}
        if leaves["target"].shape != (3,):
            raise ValueError(f"{where}: `target` must be a point (d, h, w), got shape "
                             f"{leaves['target'].shape}.")
        for name in ("azimuth", "elevation", "distance"):
            if leaves[name].ndim != 0:
                raise ValueError(f"{where}: `{name}` must be a scalar, got shape "
                                 f"{leaves[name].shape}; for several views pass a list of "
                                 f"cameras to the render, or jax.vmap a function that "
                                 f"builds one.")
        for name, value in leaves.items():
            # traced values: the render refuses a non-finite eye or target, at run time
            _checks.refuse(value, [(_checks.non_finite(value).any(),
                                    f"`{name}` must be finite, got {given[name]!r}.")],
                           where, traced=False)
        a, e, target, length, fov, width = leaves.values()
        # on the input: under jit, even an array made from a Python number is traced
        dist = _checks.concrete(distance)
        if dist is not None and not np.all(dist > 0):
            raise ValueError(f"{where}: `distance` must be > 0 (scene units), got "
                             f"{dist.tolist()!r}; to look from the other side, change "
                             f"`azimuth` and `elevation`.")
        if dist is None:  # traced: a negative distance would look from the other side
            length = _checks.refuse(length, [(~jnp.all(length > 0), "`distance` must be > 0 "
                                              "(scene units).")], where)
        eye, up = _orbit_pose(a, e, target, length)
        return cls(eye, target, up, fov, width, image_shape=image_shape, projection=projection)

    @classmethod
    def from_view(cls, view, *, spacing=(1.0, 1.0, 1.0), **orbit_kwargs) -> "Camera":
        """:meth:`orbit` camera whose eye lies along ``view`` from the target.

        ``view`` is a ``(3,)`` direction from the volume towards the viewer in
        ``(d, h, w)`` order, as :func:`volshade.most_salient_view` returns; the
        other keywords are :meth:`orbit`'s (``distance``, ``image_shape``, ...).
        Straight along ``±d`` the azimuth is undefined and taken as 0 (with a zero
        gradient, so a render's gradient in ``view`` stays finite there).

        The viewpoint functions score directions in voxel index space (digital
        lines through the voxel grid); give the volume's voxel ``spacing`` (mm) to
        look along the same direction in the scene, ``view * spacing``. With voxels
        of 4 x 1 x 1 mm, ``(1, 1, 0)`` is 76 degrees above the h axis, not 45.

        Raises:
            ValueError: ``view`` not of shape ``(3,)``, or zero (every component
                subnormal counts as zero) or not finite (when
                traced: ``equinox.EquinoxRuntimeError`` at run time); a bad
                ``spacing``; the errors of :meth:`orbit` for its other keywords.
            TypeError: a non-numeric (or bool) ``view``; ``azimuth`` or ``elevation``
                given (the view sets them); a non-numeric or traced ``spacing``.

        Example:
            >>> cam = Camera.from_view(jnp.array([0.0, 1.0, 0.0]), image_shape=(8, 8))
            >>> [round(float(x), 6) + 0.0 for x in cam.eye]  # +h: azimuth 0, from the front
            [0.0, 2.5, 0.0]
        """
        if "azimuth" in orbit_kwargs or "elevation" in orbit_kwargs:
            raise TypeError("volshade.Camera.from_view: the view sets azimuth and elevation; "
                            "use Camera.orbit to give them.")
        where = "volshade.Camera.from_view"
        view = _checks.at_least_float32(_checks.float_leaf(view, "view", where))
        if view.shape != (3,):
            raise ValueError(f"{where}: `view` must be a (3,) direction, got shape "
                             f"{view.shape}.")
        xp, host = _checks.for_check(view)
        # a view of subnormal components counts as zero: XLA on a CPU flushes them to 0
        tiny = np.finfo(view.dtype).tiny
        view = _checks.refuse(view, [(~xp.all(xp.isfinite(host))
                                      | ~(xp.max(xp.abs(host)) >= tiny),
                                      f"`view` must be a finite, non-zero (3,) direction "
                                      f"(with a component of magnitude {tiny:.3g} or more "
                                      f"in its dtype).")],
                              where)
        spacing = jnp.asarray(_checks.spacing(spacing, where), view.dtype)
        azimuth, elevation = _view_angles(view, spacing)
        return cls.orbit(azimuth=azimuth, elevation=elevation, **orbit_kwargs)

    def basis(self) -> tuple[Array, Array, Array]:
        """Orthonormal ``(forward, right, up)`` of the camera."""
        forward = safe_normalize(self.target - self.eye)
        right = safe_normalize(jnp.cross(self.up, forward))
        up = jnp.cross(forward, right)
        return forward, right, up

    def rays(self) -> tuple[Float[Array, "H W 3"], Float[Array, "H W 3"]]:
        """Ray origins and unit directions, each ``(H, W, 3)``, row 0 at the top; in
        the camera's dtype, float32 at least (a half-precision pixel grid and basis
        would misplace the rays by a whole pixel)."""
        h, w = self.image_shape
        camera = _checks.float_leaves(self, ("eye", "target", "up", "fov", "width"),
                                      "volshade.Camera")
        camera = jax.tree.map(lambda x: _checks.as_working_float(x, "camera", "volshade.Camera"),
                              camera._valid())
        forward, right, up = camera.basis()
        dtype = forward.dtype
        y = 1 - 2 * (jnp.arange(h, dtype=dtype) + 0.5) / h
        x = (2 * (jnp.arange(w, dtype=dtype) + 0.5) / w - 1) * (w / h)
        yy, xx = jnp.meshgrid(y, x, indexing="ij")
        offset = xx[..., None] * right[None, None] + yy[..., None] * up[None, None]
        if self.projection == "perspective":
            half = jnp.tan(jnp.deg2rad(camera.fov) / 2)
            directions = safe_normalize(forward[None, None] + half * offset)
            origins = jnp.broadcast_to(camera.eye, directions.shape)
        else:
            origins = camera.eye[None, None] + 0.5 * camera.width * offset
            directions = jnp.broadcast_to(forward, origins.shape)
        return origins, directions


def box_half_extent(shape: tuple[int, int, int], spacing) -> tuple[Array, float]:
    """Half extents of the volume's box in scene units, and mm per scene unit."""
    physical = np.asarray(shape, dtype=float) * np.asarray(spacing, dtype=float)
    scale = float(np.max(physical))
    return jnp.asarray(physical / scale / 2), scale


def intersect_box(
    origins: Float[Array, "*batch 3"], directions: Float[Array, "*batch 3"],
    half_extent: Float[Array, "3"],
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """Slab-method ray--box clipping against ``[-half_extent, half_extent]``.

    Returns ``(t_near, t_far)`` with ``t_near >= 0``; a ray misses when
    ``t_far <= t_near``. Direction components equal to 0 are handled exactly
    (no division by zero, finite gradients).
    """
    half_extent = jnp.broadcast_to(half_extent, origins.shape)
    moving = directions != 0
    inside = jnp.abs(origins) <= half_extent
    t1 = safe_div(-half_extent - origins, directions)
    t2 = safe_div(half_extent - origins, directions)
    big = jnp.asarray(jnp.finfo(origins.dtype).max, origins.dtype)
    t_lo = jnp.where(moving, jnp.minimum(t1, t2), jnp.where(inside, -big, big))
    t_hi = jnp.where(moving, jnp.maximum(t1, t2), jnp.where(inside, big, -big))
    t_near = jnp.maximum(jnp.max(t_lo, axis=-1), 0)
    t_far = jnp.min(t_hi, axis=-1)
    return t_near, t_far
