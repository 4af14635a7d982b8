"""Feature-driven AO (Ancel et al. 2010, Tables 2 and 3) against classic LAO, in one run.

Two of the paper's datasets as phantoms: the orange (peel, pith and flesh: three
nested, dense features) and the bucky ball (balls and bonds: two sparse features).
For each, with the paper's parameters (16 pseudo-random polar rays, R = 16 voxels;
16 samples), float32:

* classic LAO of the whole classified opacity (the baseline), each feature's LAO
  alone, each merge operator, and ``feature_ao`` end to end: the paper's Table 2,
  where feature-driven AO costs about the sum of its features plus a small merge;
* ``feature_ao`` with per-feature bricks of 8 voxels (section 4.3, Table 3), at
  R = 16 and at R = 4 (at R = 16 nearly every brick of these phantoms has opacity
  within reach), and the brick structure itself (one max-pool and dilation per
  feature), which the paper's single global structure exists to save;
* forward + gradient (w.r.t. the radius and the opacity control values of the base
  transfer function) of feature AO and of classic AO.
"""

import math

import jax
import jax.numpy as jnp

import volshade as vs
from benchmarks._timing import time_cases
from volshade.feature_ao import MERGES
from volshade.lao import _active_bricks


def _pad(radius: float) -> tuple[int, int, int]:
    """The zero padding ``lao`` gives a march of this radius (its brick halo)."""
    return (math.ceil(radius) + 1,) * 3


def _datasets(n: int) -> dict:
    """name -> (volume, base transfer function, features)."""
    orange_tf = vs.TransferFunction.from_points(
        [(0.0, 0, 0, 0, 0.0), (0.3, 1.0, 0.6, 0.1, 0.0), (0.4, 1.0, 0.6, 0.1, 0.15),
         (0.5, 1.0, 0.6, 0.1, 0.0), (0.6, 1, 1, 0.9, 0.0), (0.7, 1, 1, 0.9, 0.3),
         (0.8, 1, 1, 0.9, 0.0), (0.9, 1.0, 0.5, 0.0, 0.0), (1.0, 1.0, 0.5, 0.0, 0.6)],
        dtype=jnp.float32)
    orange = [vs.IntervalFeature(0.3, 0.5), vs.IntervalFeature(0.6, 0.8),
              vs.IntervalFeature(0.9, 1.0)]
    bucky_tf = vs.TransferFunction.from_points(
        [(0.0, 0.5, 0.5, 1.0, 0.0), (0.1, 0.5, 0.5, 1.0, 0.0), (0.5, 0.5, 0.5, 1.0, 0.3),
         (1.0, 1.0, 0.3, 0.3, 0.9)], dtype=jnp.float32)
    bucky = [vs.IntervalFeature(0.05, 0.55), vs.IntervalFeature(0.55, 1.0)]
    return {"orange": (vs.data.phantom("orange", shape=n), orange_tf, orange),
            "bucky": (vs.data.phantom("bucky", shape=n), bucky_tf, bucky)}


def _measure(name, vol, tf, features, *, n, directions, radius, samples, brick, repeats,
             rows, ratios):
    """The rows and ratios of one dataset (a function, so closures bind its values); its
    cases are timed interleaved, so that their ratios hold on a shared machine."""
    lao_kw = dict(directions=directions, radius=radius, samples=samples)
    pad = _pad(radius)
    feature_alphas = vs.transfer.feature_opacities(vol, features, base=tf)
    occupied = [float(jnp.mean(a > 0)) for a in feature_alphas]
    per_feature = jnp.stack([vs.lao(a, **lao_kw) for a in feature_alphas])
    tag = f"{name} {n}^3 ({len(features)} features)"
    cases = {}

    def case(key, label, fn, *args):
        cases[key] = (label, jax.jit(fn), args)

    # every LAO case starts from the volume, as feature_ao does: the classification is
    # part of the work on both sides of the ratios
    case("classic", "classic LAO", lambda v: vs.lao(tf.opacity(v), **lao_kw), vol)
    for k, (f, occ) in enumerate(zip(features, occupied, strict=True)):
        case(("each", k), f"feature {k} LAO alone ({100 * occ:.1f}% of voxels)",
             lambda v, f=f: vs.lao(f.opacity(v, tf), **lao_kw), vol)
    for m in MERGES:
        case(("merge", m), f"merge {m}",
             lambda ao, op, m=m: vs.merge_feature_ao(ao, op, merge=m),
             per_feature, feature_alphas)
    case("fao", "feature_ao (max)",
         lambda v: vs.feature_ao(v, features=features, base=tf, **lao_kw), vol)
    case("bricked", f"feature_ao (max), bricks of {brick}",
         lambda v: vs.feature_ao(v, features=features, base=tf, **lao_kw, brick_size=brick),
         vol)
    case("structure", "brick structures (all features)",
         lambda fa: jnp.stack([_active_bricks(a, pad, brick) for a in fa]), feature_alphas)

    def classic_loss(r, opacities, v):
        base = vs.TransferFunction(tf.points, tf.colors, opacities)
        return jnp.sum(vs.lao(base.opacity(v), directions=directions, radius=r,
                              samples=samples, max_radius=2 * radius))

    def feature_loss(r, opacities, v):
        base = vs.TransferFunction(tf.points, tf.colors, opacities)
        return jnp.sum(vs.feature_ao(v, features=features, base=base, directions=directions,
                                     radius=r, samples=samples, max_radius=2 * radius))

    r0 = jnp.float32(radius)
    case("classic grad", "classic LAO forward+grad (radius, TF opacities)",
         jax.grad(classic_loss, argnums=(0, 1)), r0, tf.opacities, vol)
    case("fao grad", "feature_ao forward+grad (radius, TF opacities)",
         jax.grad(feature_loss, argnums=(0, 1)), r0, tf.opacities, vol)
    # the paper's R = 16 reaches nearly every brick of these phantoms; a short reach
    # leaves the empty ones out
    short = dict(lao_kw, radius=4.0)
    active = [float(jnp.mean(_active_bricks(a, _pad(short["radius"]), brick)))
              for a in feature_alphas]
    case("short", "feature_ao (max), R = 4",
         lambda v: vs.feature_ao(v, features=features, base=tf, **short), vol)
    case("short bricked", f"feature_ao (max), R = 4, bricks of {brick} "
                          f"({', '.join(f'{100 * a:.0f}%' for a in active)} active)",
         lambda v: vs.feature_ao(v, features=features, base=tf, **short, brick_size=brick),
         vol)
    timed = time_cases({key: (fn, args) for key, (_, fn, args) in cases.items()},
                       repeats=repeats)
    for key, (label, _, _) in cases.items():
        rows.append({"case": f"{tag}: {label}", "median_s": timed[key]["median_s"],
                     "first_call_s": timed[key]["first_call_s"]})
    t = {key: timing["median_s"] for key, timing in timed.items()}
    each = sum(t[("each", k)] for k in range(len(features)))
    ratios[f"{name}: bricked / unbricked feature_ao, R = 4"] = t["short bricked"] / t["short"]
    ratios[f"{name}: feature_ao / classic LAO"] = t["fao"] / t["classic"]
    ratios[f"{name}: feature_ao / sum of feature LAOs"] = t["fao"] / each
    ratios[f"{name}: max merge / classic LAO"] = t[("merge", "max")] / t["classic"]
    ratios[f"{name}: neighbourhood merge / classic LAO"] = (t[("merge", "neighbourhood")]
                                                            / t["classic"])
    ratios[f"{name}: bricked / unbricked feature_ao"] = t["bricked"] / t["fao"]
    ratios[f"{name}: brick structures / feature_ao"] = t["structure"] / t["fao"]
    ratios[f"{name}: forward+grad, feature_ao / classic"] = t["fao grad"] / t["classic grad"]


def run(quick: bool) -> dict:
    n = 64 if quick else 128
    repeats = 3 if quick else 5
    radius, samples, brick = 16.0, 16, 8
    directions = vs.directions.random_polar(16, key=jax.random.key(0)).astype(jnp.float32)
    rows, ratios = [], {}
    for name, (vol, tf, features) in _datasets(n).items():
        _measure(name, vol, tf, features, n=n, directions=directions, radius=radius,
                 samples=samples, brick=brick, repeats=repeats, rows=rows, ratios=ratios)
    return {
        "title": "feature-driven AO vs classic LAO (Ancel et al. 2010, Tables 2-3), float32",
        "sizes": {"volumes": f"orange and bucky phantoms, {n}^3",
                  "lao": f"16 random-polar rays, R = {radius}, M = {samples}",
                  "bricks": brick},
        "rows": rows,
        "ratios": ratios,
        "notes": "paper (GTX 295, no bricks): fdAO / AO = 3.85 for the bucky ball with 5 "
                 "features, 2.45 for the head with 3, 1.66 for the knee with 2; merge 5-11 ms "
                 "(0.4% of AO).",
    }
