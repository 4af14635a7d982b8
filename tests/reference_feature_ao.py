"""Slow, obvious feature-driven AO (Ancel et al. 2010, section 4), voxel by voxel.

Each feature's occlusion volume is the gather reference LAO of its opacity alone;
the merge operators of section 4.2 are written as loops over voxels and their
neighbours, with the rules stated in ``volshade.feature_ao``'s docstring.
"""

import itertools

import numpy as np
from reference_lao import lao_reference


def _label(opacity_column):
    """The feature of one voxel: largest opacity (first on ties), -1 if none."""
    return int(np.argmax(opacity_column)) if opacity_column.max() > 0 else -1


def merge_reference(ao, opacities, merge):
    # the library's threshold: the epsilon of the dtype it merges in (ao's), taken before
    # the reference converts to float64
    eps = np.finfo(np.asarray(ao).dtype).eps
    ao = np.asarray(ao, np.float64)
    opacities = np.asarray(opacities, np.float64)
    shape = ao.shape[1:]
    out = np.empty(shape)
    labels = np.empty(shape, int)
    for x in np.ndindex(*shape):
        labels[x] = _label(opacities[(slice(None), *x)])

    def own(x):
        k = labels[x]
        return ao[(slice(None), *x)].min() if k < 0 else ao[(k, *x)]

    for x in np.ndindex(*shape):
        if merge == "max":
            out[x] = ao[(slice(None), *x)].min()
        elif merge == "feature":
            out[x] = own(x)
        elif merge == "neighbourhood":
            neighbours = [tuple(np.add(x, d)) for d in itertools.product((-1, 0, 1), repeat=3)]
            neighbours = [y for y in neighbours if all(0 <= y[a] < shape[a] for a in range(3))]
            if all(labels[y] == labels[x] for y in neighbours):
                out[x] = own(x)  # one feature, or none (then the min, as when empty)
                continue
            weights = [opacities[(slice(None), *y)].max() for y in neighbours]
            total = sum(weights)
            if total > eps:  # else: as empty (see volshade.feature_ao)
                out[x] = sum(w * own(y) for w, y in zip(weights, neighbours, strict=True)) / total
            else:
                out[x] = ao[(slice(None), *x)].min()
        else:
            raise ValueError(merge)
    return out


def feature_ao_reference(opacities, directions, radius, offset, samples, merge, **lao_options):
    """Feature-driven AO of the stacked feature opacities ``(F, D, H, W)``, float64."""
    ao = np.stack([np.asarray(lao_reference(a, directions, radius, offset, samples,
                                            **lao_options)) for a in opacities])
    # in the opacities' dtype, whose epsilon the merge's threshold is (merge_reference)
    return merge_reference(ao.astype(np.asarray(opacities).dtype), opacities, merge)
