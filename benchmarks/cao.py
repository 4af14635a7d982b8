"""Contextual AO (Titov et al.) against a full LAO recompute, for a moving clip, in one run.

A sphere clip moves along a path through the volume; for every frame both
``contextual_ao`` (only the bricks within reach of the clip marched, the rest from
the unclipped LAO computed once) and ``lao`` of the clipped opacity (every voxel
marched, the naive method of the paper's evaluation) run, float32, jitted once (the
clip's pose is traced). Reported: median time per frame of each, their ratio (the
paper measured 2-5x on a GPU), the fraction of bricks marched, and the largest
difference between the two (they are the same computation). Volumes: the shells
phantom and, when the real data are found, the Colin27 head (downsampled 2x, "head"
preset). LAO: 16 Fibonacci rays, R = 8 voxels, 16 samples, bricks of 8.
"""

import jax
import jax.numpy as jnp
import numpy as np

import volshade as vs
from benchmarks._timing import time_fns
from volshade.cao import affected_fraction


def _volumes(n: int) -> dict:
    shells = vs.transfer.preset("shells").opacity(vs.data.phantom("shells", shape=n))
    volumes = {f"shells {n}^3": shells}
    try:
        head, _ = vs.data.load("colin27", downsample=2)
    except (FileNotFoundError, ImportError):
        return volumes
    volumes[f"colin27 {'x'.join(map(str, head.shape))}"] = vs.transfer.preset("head").opacity(head)
    return volumes


def run(quick: bool) -> dict:
    n = 64 if quick else 128
    repeats = 3 if quick else 5
    radius, brick = 8.0, 8
    kw = dict(directions=vs.directions.fibonacci(16).astype(jnp.float32), radius=radius,
              samples=16)
    rows, ratios = [], {}
    for name, alpha in _volumes(n).items():
        alpha = alpha.astype(jnp.float32)
        shape = np.asarray(alpha.shape, np.float32)
        clip_radius = float(shape.min()) / 6
        unclipped = jax.block_until_ready(jax.jit(lambda a: vs.lao(a, **kw))(alpha))

        # the volumes are arguments, not constants XLA would fold while compiling
        def contextual(centre, alpha, unclipped, r=clip_radius):
            clip = vs.SphereClip(center=centre, radius=r)
            return vs.contextual_ao(alpha, clip=clip, unclipped=unclipped, brick_size=brick,
                                    **kw)

        def full(centre, alpha, unclipped, r=clip_radius):
            return vs.lao(vs.clip_opacity(alpha, vs.SphereClip(center=centre, radius=r)), **kw)

        fast, slow = jax.jit(contextual), jax.jit(full)
        # a path from a corner of the volume to its centre: the clip cuts in deeper
        path = [shape * t for t in (0.15, 0.3, 0.5)]
        t_fast, t_slow, diffs, fractions = [], [], [], []
        for centre in path:
            centre = jnp.asarray(centre)
            args = (centre, alpha, unclipped)
            a, b = time_fns({"contextual": fast, "full": slow}, *args,
                            repeats=repeats).values()
            t_fast.append(a["median_s"])
            t_slow.append(b["median_s"])
            diffs.append(float(jnp.max(jnp.abs(fast(*args) - slow(*args)))))
            fractions.append(affected_fraction(alpha.shape, vs.SphereClip(
                center=centre, radius=clip_radius), radius=radius, brick_size=brick))
        for centre, tf_, ts, d, f in zip(path, t_fast, t_slow, diffs, fractions, strict=True):
            where = "(" + ", ".join(f"{c:.0f}" for c in centre) + ")"
            rows.append({"case": f"{name}, clip at {where}: full recompute", "median_s": ts})
            rows.append({"case": f"{name}, clip at {where}: contextual", "median_s": tf_,
                         "speed_up": ts / tf_, "bricks_marched": f, "max_abs_diff": d})
        ratios[f"{name}: full recompute / contextual (median over the path)"] = float(
            np.median(np.asarray(t_slow) / np.asarray(t_fast)))
        # the whole path at once, vmapped over the clip's centre: each pose still marches
        # only its own bricks (a loop over the poses, not a batched lax.cond)
        centres = jnp.asarray(np.stack(path))
        batched = [jax.jit(jax.vmap(f, in_axes=(0, None, None))) for f in (contextual, full)]
        a, b = (t["median_s"] for t in time_fns(
            {"contextual": batched[0], "full": batched[1]}, centres, alpha, unclipped,
            repeats=repeats).values())
        diff = float(jnp.max(jnp.abs(batched[0](centres, alpha, unclipped)
                                     - batched[1](centres, alpha, unclipped))))
        rows.append({"case": f"{name}, the path vmapped: full recompute", "median_s": b})
        rows.append({"case": f"{name}, the path vmapped: contextual", "median_s": a,
                     "speed_up": b / a, "max_abs_diff": diff})
        ratios[f"{name}: full recompute / contextual, the path vmapped"] = b / a
    return {
        "title": "contextual AO vs full LAO recompute under a moving sphere clip (float32)",
        "sizes": {"lao": f"16 Fibonacci rays, R = {radius}, M = 16", "bricks": brick,
                  "clip": "sphere of radius min(shape) / 6, centre at 15%, 30%, 50% of the "
                          "volume's diagonal"},
        "rows": rows,
        "ratios": ratios,
        "notes": "paper (RX 6700 XT, 512^3, 54 rays x 50 samples): 2-5x over recomputing "
                 "every voxel. Both columns time the whole function, clip mask included. "
                 "The vmapped rows time the three poses in one call.",
    }
