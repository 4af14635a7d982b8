"""Slow, obvious local ambient occlusion: every sample gathered with ``map_coordinates``.

Eq. 3-4 of Ancel et al. (2010) written literally: for every direction and every
sample, the points ``x + s_i l`` of all voxels are interpolated (order 1, zero
outside), and ``I_l = sum_m (1/M) prod_{i<m} (1 - alpha_i)`` is summed term by
term. Same sample positions as ``volshade.lao``: ``s_i = a + (i + 1/2)(R - a)/M``.
Positions are computed in float64 so the reference is exact for any input dtype.
``opacity_correction`` applies the step correction from its definition,
``alpha' = 1 - (1 - alpha) ** (step / 1 voxel)``, not through the library's own helper.
"""

import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates


def lao_reference(alpha, directions, radius, offset, samples, *, weights=None,
                  opacity_correction=False):
    """AO of ``alpha`` in float64 (Python loops over directions and samples)."""
    alpha = jnp.asarray(alpha, jnp.float64)
    dirs = np.asarray(directions, np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    n_dirs = dirs.shape[0]
    w = np.ones(n_dirs) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    grid = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float64) for s in alpha.shape],
                                indexing="ij"), axis=-1)
    radius, offset = float(radius), float(offset)
    step = (radius - offset) / samples
    ao = jnp.zeros(alpha.shape, jnp.float64)
    for l_idx in range(n_dirs):
        opacities = []
        for i in range(samples):
            s = offset + (i + 0.5) * step
            pts = grid + s * dirs[l_idx]
            a = map_coordinates(alpha, [jnp.asarray(pts[..., k]) for k in range(3)],
                                order=1, mode="constant", cval=0.0)
            if opacity_correction:
                # map_coordinates' weighted sum of eight 1s comes out a few ulps either
                # side of 1: above it (1 - a) ** step is NaN, below it 1e-2 short of 1
                # for a step of 1/8 voxel; the library's lerps of equal values are exact
                a = jnp.where(a >= 1 - 4 * np.finfo(np.float64).epsneg, 1.0, a)
                a = 1 - (1 - a) ** step  # `a` is per voxel; `step` is in voxels
            opacities.append(a)
        intensity = jnp.zeros(alpha.shape, jnp.float64)
        for m in range(samples):
            prod = jnp.ones(alpha.shape, jnp.float64)
            for i in range(m):
                prod = prod * (1 - opacities[i])
            intensity = intensity + prod / samples
        ao = ao + w[l_idx] * intensity
    return ao
