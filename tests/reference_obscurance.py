"""Slow, obvious obscurance: march every voxel along its digital line, step by step.

Independent of the library's shear / sparse-table machinery; only the definition
of the digital lines is shared (it *is* the specification): for direction ``l``
with major axis ``a`` (first on ties) the line through voxel ``p`` visits
``p + t * e_a' + (o_b(i + t) - o_b(i)) e_b + (o_c(i + t) - o_c(i)) e_c`` where ``i``
is p's coordinate along ``a`` counted in the direction's sense and
``o(i) = floor(i * l_x / |l_a| + 1/2)``, the ratio taken of the direction as given
(normalised first, (3, 4, 0) would give 0.7499999999999999, not 3/4).
Distance = ``t * |l| / |l_a|``.
"""

import numpy as np


def occluder_distances(density: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(L, D, H, W) distance (voxels) to the first strictly denser voxel ahead; inf if none."""
    density = np.asarray(density, dtype=np.float64)
    shape = np.array(density.shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in density.shape], indexing="ij"), -1)
    out = np.full((len(directions), *density.shape), np.inf)
    for n_dir, vec in enumerate(np.asarray(directions, dtype=np.float64)):
        a = int(np.argmax(np.abs(vec)))
        sign = 1 if vec[a] > 0 else -1
        s = vec / abs(vec[a])
        step = np.linalg.norm(s)
        n_a = shape[a]

        def offset(i, s=s):  # i: frame coordinate along a (counted in the direction's sense)
            return np.floor(i[..., None] * s[None, :] + 0.5).astype(np.int64)

        i0 = grid[..., a] if sign > 0 else n_a - 1 - grid[..., a]
        dist = np.full(density.shape, np.inf)
        pending = np.ones(density.shape, bool)
        here = density
        for t in range(1, n_a):
            i1 = i0 + t
            inside_a = i1 < n_a
            delta = offset(np.minimum(i1, n_a - 1)) - offset(i0)
            q = grid + delta
            q[..., a] = grid[..., a] + sign * t
            inside = inside_a & np.all((q >= 0) & (q < shape), axis=-1)
            qc = np.clip(q, 0, shape - 1)
            ahead = density[qc[..., 0], qc[..., 1], qc[..., 2]]
            hit = pending & inside & (ahead > here)
            dist[hit] = t * step
            pending &= ~hit
        out[n_dir] = dist
    return out


def occluder_index(density: np.ndarray, directions: np.ndarray, n_dir: int) -> np.ndarray:
    """(D, H, W, 3) voxel index of the occluder along direction ``n_dir`` (-1 if none)."""
    density = np.asarray(density, dtype=np.float64)
    vec = np.asarray(directions, dtype=np.float64)[n_dir]
    a = int(np.argmax(np.abs(vec)))
    sign = 1 if vec[a] > 0 else -1
    s = vec / abs(vec[a])
    shape = np.array(density.shape)
    out = -np.ones((*density.shape, 3), np.int64)
    for p in np.ndindex(*density.shape):
        i = p[a] if sign > 0 else shape[a] - 1 - p[a]
        o_i = np.floor(i * s + 0.5)
        for t in range(1, shape[a]):
            q = np.array(p) + (np.floor((i + t) * s + 0.5) - o_i).astype(np.int64)
            q[a] = p[a] + sign * t
            if np.any(q < 0) or np.any(q >= shape):
                break
            if density[tuple(q)] > density[p]:
                out[p] = q
                break
    return out


RHO = {
    "ao": lambda d, dm: np.zeros_like(d),
    "linear": lambda d, dm: d / dm,
    "exponential": lambda d, dm: 1 - np.exp(-d / dm),
    "sqrt": lambda d, dm: np.sqrt(d / dm),
}


def obscurance(density, directions, d_max, rho="sqrt", colors=None, ambient=(1.0, 1.0, 1.0)):
    """Eq. (1)/(3) by brute force: mean over directions of rho(d) (times the occluder colour)."""
    dists = occluder_distances(density, directions)
    occluded = dists <= d_max
    value = np.where(occluded, RHO[rho](np.where(occluded, dists, d_max), d_max), 1.0)
    if colors is None:
        return value.mean(0)
    colors = np.asarray(colors, np.float64)
    total = np.zeros((*np.shape(density), 3))
    for n_dir in range(len(directions)):
        q = occluder_index(density, directions, n_dir)
        hit = colors[q[..., 0], q[..., 1], q[..., 2]]
        occ = occluded[n_dir][..., None]
        total += np.where(occ, value[n_dir][..., None] * hit, np.asarray(ambient))
    return total / len(directions)
