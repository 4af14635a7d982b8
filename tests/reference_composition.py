"""Slow, obvious float64 transcriptions of Pinto & Freitas (2010), eq. 1 and 8, one
sample at a time in Python loops (numpy), checked against the fast ``lax.scan`` kernels."""

import numpy as np


def standard(colors, alphas, background=(0.0, 0.0, 0.0)):
    """Eq. 1 for one ray: ``colors`` (S, 3) premultiplied, ``alphas`` (S,) -> RGBA (4,)."""
    c, a = np.zeros(3), 0.0
    for cs, as_ in zip(np.asarray(colors, float), np.asarray(alphas, float), strict=True):
        c = c + (1 - a) * cs
        a = a * (1 - as_) + as_
    return np.concatenate([c + (1 - a) * np.asarray(background, float), [a]])


def vis(i_s, i_acc):
    """Eq. 3."""
    return 1 - np.exp(i_acc - i_s)


def modulation(alpha_acc, i_acc, i_s):
    """Eq. 2, the three cases literally."""
    if i_s <= i_acc:
        return 1.0
    if 1 - alpha_acc >= vis(i_s, i_acc):
        return 1.0
    # 1 - vis(i_s, i_acc), without the cancellation of 1 - (1 - e^x): a faint sample 30
    # above an opaque ray (m = e^-30) would lose 3 digits of its colour
    return np.exp(i_acc - i_s) / alpha_acc


def importance_step(c, a, i_acc, cs, as_, i_s):
    """Eq. 8a-8e literally; the empty ray has accumulated importance -inf.

    A sample with alpha_s = 0 returns the state unchanged, which is what 8a-8e give in
    exact arithmetic (C' = m C_i, alpha' = m alpha_i, C_{i+1} = alpha_i C' / alpha' = C_i);
    done literally, an underflowed m (importance gaps > ~745) would give 0 / 0."""
    if as_ == 0:
        return c, a, i_acc, modulation(a, i_acc, i_s)
    m = modulation(a, i_acc, i_s)
    c_p = m * c + (1 - m * a) * cs                           # 8a
    a_p = m * a * (1 - as_) + as_                            # 8b
    a_new = a * (1 - as_) + as_                              # 8c
    c_new = np.zeros(3) if a_p == 0 else a_new * c_p / a_p   # 8d
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        naive = np.log(as_ + (1 - as_) * np.exp(i_acc - i_s)) + i_s             # 8e
        if not np.isfinite(naive):  # exp overflow for gaps > ~700: same value via logaddexp
            naive = np.logaddexp(np.log(as_) + i_s, np.log1p(-as_) + i_acc)
    i_new = max(i_acc, naive)
    return c_new, a_new, i_new, m


def importance(colors, alphas, importances, background=(0.0, 0.0, 0.0),
               background_importance=-np.inf, return_state=False):
    """Eq. 8 for one ray, then the background as a final opaque layer (sec. IV-C).

    Returns RGBA where alpha is the volume's opacity after the background's
    modulation, ``m * alpha_n``."""
    c, a, i_acc = np.zeros(3), 0.0, -np.inf
    ms = []
    for cs, as_, i_s in zip(np.asarray(colors, float), np.asarray(alphas, float),
                            np.asarray(importances, float), strict=True):
        c, a, i_acc, m = importance_step(c, a, i_acc, cs, as_, i_s)
        ms.append(m)
    if return_state:
        return c, a, i_acc, ms
    m = 1.0 if background_importance == -np.inf else modulation(a, i_acc, background_importance)
    rgb = m * c + (1 - m * a) * np.asarray(background, float)
    return np.concatenate([rgb, [m * a]])
