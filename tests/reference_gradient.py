"""Brute-force reference for the 4D linear-regression gradient (Neumann et al. 2000)."""

import numpy as np


def regression_gradient_reference(vol, spacing=(1.0, 1.0, 1.0), size=5,
                                  weighting="distance"):
    """Neumann et al.'s fit written out: per voxel, the weighted least-squares plane
    ``f(k) ~ g . x(k) + b`` over the edge-replicated ``size^3`` neighbourhood, by lstsq on
    the full 4-parameter system (no use of its decoupling). The centre's weight is 0 for
    "distance" and "inverse_distance" (x = 0 there: it only moves b, never g)."""
    vol = np.asarray(vol, np.float64)
    h = size // 2
    offsets = np.stack(np.meshgrid(*[np.arange(-h, h + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = offsets * np.broadcast_to(np.asarray(spacing, np.float64), (3,))
    r = np.linalg.norm(x, axis=1)
    w = {"distance": r, "inverse_distance": np.where(r > 0, 1 / np.maximum(r, 1e-300), 0.0),
         "uniform": np.ones_like(r)}[weighting]
    design = np.sqrt(w)[:, None] * np.concatenate([x, np.ones((len(x), 1))], axis=1)
    padded = np.pad(vol, h, mode="edge")
    n = vol.shape
    values = np.stack([padded[h + i:h + i + n[0], h + j:h + j + n[1], h + k:h + k + n[2]].ravel()
                       for i, j, k in offsets])  # (K, voxels)
    coef = np.linalg.lstsq(design, np.sqrt(w)[:, None] * values, rcond=None)[0]
    return coef[:3].T.reshape(*n, 3)
