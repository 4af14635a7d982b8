"""Direction sets on the unit sphere, for ambient occlusion and obscurance rays.

All functions return a ``(L, 3)`` array of unit vectors in volume axis order
``(d, h, w)``: a JAX array in JAX's default float dtype, but for
:func:`icosphere_points`, a read-only float64 NumPy array (concrete inside ``jit``).
They are static configuration:
the number of directions sets array shapes, so choose the set outside ``jit``.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._types import Array, Float

__all__ = ["fibonacci", "random_polar", "icosphere", "icosphere_points"]


def fibonacci(n: int) -> Float[Array, "n 3"]:
    """``n`` nearly uniform directions on the Fibonacci (golden-angle) spiral.

    Args:
        n: number of directions, ``>= 1``.

    Returns:
        ``(n, 3)`` unit vectors, spiralling from near $+d$ to near $-d$.

    Raises:
        ValueError / TypeError: ``n`` not an int ``>= 1``.

    Example:
        >>> fibonacci(16).shape
        (16, 3)
    """
    n = _checks.positive_int(n, "n", "volshade.directions.fibonacci")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * np.arange(n)
    return jnp.asarray(np.stack([z, r * np.sin(phi), r * np.cos(phi)], axis=-1), dtype=float)


def random_polar(n: int, *, key: jax.Array) -> Float[Array, "n 3"]:
    r"""``n`` pseudo-random directions, uniform on the sphere, drawn in polar coordinates.

    Azimuth $\phi \sim U[0, 2\pi)$ and $\cos\theta \sim U[-1, 1]$ (uniform in
    $\cos\theta$, not in $\theta$, so the poles are not over-sampled), as in the
    seeds' pseudo-random rays "uniformly scattered using polar coordinates"
    (Ancel et al. 2010, section 3).

    Args:
        n: number of directions, ``>= 1``.
        key: a ``jax.random`` key; the same key gives the same set.

    Returns:
        ``(n, 3)`` unit vectors.

    Raises:
        ValueError / TypeError: ``n`` not an int ``>= 1``.
        TypeError: ``key`` not a ``jax.random`` key.
    """
    where = "volshade.directions.random_polar"
    n = _checks.positive_int(n, "n", where)
    try:
        k1, k2 = jax.random.split(key)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{where}: `key` must be one jax.random key, e.g. "
                        f"jax.random.key(0) (for several sets, jax.vmap over a batch of "
                        f"keys), got {key!r:.200}.") from err
    dtype = jnp.result_type(float)
    cos_t = jax.random.uniform(k1, (n,), dtype, -1.0, 1.0)
    phi = jax.random.uniform(k2, (n,), dtype, 0.0, 2 * jnp.pi)
    sin_t = jnp.sqrt(jnp.clip(1 - cos_t**2, 0.0, None))
    return jnp.stack([cos_t, sin_t * jnp.sin(phi), sin_t * jnp.cos(phi)], axis=-1)


def _icosahedron() -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    t = (1.0 + np.sqrt(5.0)) / 2.0
    verts = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
         [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=float)
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
             (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
             (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
             (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    return verts / np.linalg.norm(verts, axis=1, keepdims=True), faces


def _check_level(level: int, where: str) -> int:
    level = _checks.positive_int(level, "level", where, minimum=0)
    if level > 4:
        raise ValueError(f"{where}: `level` must be <= 4 (2562 directions), got {level}.")
    return level


@functools.lru_cache(maxsize=8)
def _subdivided_icosahedron(level: int) -> np.ndarray:
    verts, faces = _icosahedron()
    points = list(verts)

    def middle(a: int, b: int, midpoint: dict[tuple[int, int], int]) -> int:
        edge = (min(a, b), max(a, b))
        if edge not in midpoint:
            m = points[a] + points[b]
            points.append(m / np.linalg.norm(m))
            midpoint[edge] = len(points) - 1
        return midpoint[edge]

    for _ in range(level):
        midpoint: dict[tuple[int, int], int] = {}
        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = middle(a, b, midpoint), middle(b, c, midpoint), middle(c, a, midpoint)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
    out = np.stack(points)
    out.setflags(write=False)
    return out


def icosphere(level: int) -> Float[Array, "n 3"]:
    """Vertices of a subdivided icosahedron: 12, 42, 162, 642, 2562 directions for
    levels 0-4.

    Each level splits every triangle into four and projects the new vertices
    onto the sphere; the count is ``10 * 4**level + 2``. Levels 0-2 are the
    direction sets of the obscurance paper (Ruiz et al. 2008, section 3.1).

    Args:
        level: subdivisions, 0 to 4.

    Returns:
        ``(10 * 4**level + 2, 3)`` unit vectors.

    Raises:
        ValueError / TypeError: ``level`` not an int from 0 to 4.

    Example:
        >>> icosphere(1).shape
        (42, 3)
    """
    level = _check_level(level, "volshade.directions.icosphere")
    return jnp.asarray(_subdivided_icosahedron(level), dtype=float)


def icosphere_points(level: int) -> np.ndarray:
    """:func:`icosphere` as a read-only float64 NumPy array.

    NumPy values stay concrete inside ``jax.jit`` (where ``jnp`` constants may be
    traced), which kernels need whose sweeps the directions define (obscurances).
    """
    return _subdivided_icosahedron(_check_level(level, "volshade.directions.icosphere_points"))
