"""Importance-aware composition (Pinto & Freitas 2010, eq. 8) against standard compositing.

Both run through :func:`volshade.composite` on the same random float32 rays
(premultiplied colours, opacities, importances), forward and forward + reverse
gradient (w.r.t. colours and opacities, plus importances for the importance
compositor), in one process, the two compositors of each mode timed interleaved.
Goal: importance <= 1.5x standard.

On a CPU, ``composite`` computes values reading 8 (importance: 4) samples of every ray
per loop iteration where they lie. The rows "steps in place" and "steps (scan)" time
the compositing steps alone (no input checks, no finish), four cases interleaved: the
loop ``composite`` runs on a CPU, and a ``lax.scan`` over the samples moved in front (a
transpose of the inputs), which is what reverse mode and other platforms run, and what
the CPU ran before.
"""

import jax
import jax.numpy as jnp

from benchmarks._timing import time_fns
from volshade.composition import (
    IMPORTANCE_CHUNK,
    STANDARD_CHUNK,
    _samples,
    _scan,
    _scan_in_place,
    composite,
    importance_init,
    importance_step,
    standard_init,
    standard_step,
)


def _rays(n_rays: int, n_samples: int, key):
    k1, k2, k3 = jax.random.split(key, 3)
    alphas = jax.random.uniform(k1, (n_rays, n_samples), jnp.float32, 0.0, 0.2)
    colors = jax.random.uniform(k2, (n_rays, n_samples, 3), jnp.float32) * alphas[..., None]
    importance = 4.0 * jax.random.normal(k3, (n_rays, n_samples), jnp.float32)
    return colors, alphas, importance


def run(quick: bool) -> dict:
    side, n_samples = (128, 256) if quick else (512, 512)
    repeats = 5 if quick else 10
    n_rays = side * side
    colors, alphas, importance = jax.block_until_ready(
        _rays(n_rays, n_samples, jax.random.PRNGKey(0)))
    bg = jnp.asarray([1.0, 1.0, 1.0], jnp.float32)

    def standard(c, a, i):
        return composite(c, a, background=bg)

    def importance_aware(c, a, i):
        return composite(c, a, importance=i, background=bg, background_importance=jnp.float32(0))

    # the steps alone, as composite runs them: in place (composite's chunks on a CPU)
    # and scanned
    steps = {"standard": (standard_step, standard_init, STANDARD_CHUNK),
             "importance": (importance_step, importance_init, IMPORTANCE_CHUNK)}

    def in_place(name):
        step, init, chunk = steps[name]
        return lambda c, a, i: _scan_in_place(step, chunk, init((n_rays,), jnp.float32), c, a,
                                              i if name == "importance" else None)

    def scan(name):
        step, init, _ = steps[name]
        return lambda c, a, i: _scan(step, init((n_rays,), jnp.float32),
                                     _samples(c, a, i if name == "importance" else None), 1)

    cases = {"standard": standard, "importance": importance_aware}
    rows, medians = [], {}
    n_total = n_rays * n_samples

    def gradient(name, fn):
        argnums = (0, 1) if name == "standard" else (0, 1, 2)
        return jax.jit(jax.grad(lambda c, a, i: jnp.sum(fn(c, a, i)), argnums=argnums))

    # the cases of each group timed interleaved (benchmarks._timing.time_fns)
    groups = {"forward": {(name, "forward"): jax.jit(fn) for name, fn in cases.items()},
              "forward+grad": {(name, "forward+grad"): gradient(name, fn)
                               for name, fn in cases.items()},
              "steps": {(name, mode): jax.jit(make(name)) for name in cases
                        for mode, make in (("steps in place", in_place),
                                           ("steps (scan)", scan))}}
    for fns in groups.values():
        timed = time_fns(fns, colors, alphas, importance, repeats=repeats)
        for (name, mode), t in timed.items():
            medians[(name, mode)] = t["median_s"]
            rows.append({"case": f"{name} {mode}", "median_s": t["median_s"],
                         "first_call_s": t["first_call_s"],
                         "Msamples_per_s": n_total / t["median_s"] / 1e6})
    ratios = {
        "importance/standard forward": medians[("importance", "forward")]
        / medians[("standard", "forward")],
        "importance/standard forward+grad": medians[("importance", "forward+grad")]
        / medians[("standard", "forward+grad")],
        "importance/standard steps (scan)": medians[("importance", "steps (scan)")]
        / medians[("standard", "steps (scan)")],
        "scan/in place, standard steps": medians[("standard", "steps (scan)")]
        / medians[("standard", "steps in place")],
        "scan/in place, importance steps": medians[("importance", "steps (scan)")]
        / medians[("importance", "steps in place")],
    }
    return {
        "title": "importance-aware vs standard compositing (volshade.composite, float32)",
        "sizes": {"rays": n_rays, "image": f"{side}x{side}", "samples_per_ray": n_samples},
        "rows": rows,
        "ratios": ratios,
        "notes": "same rays for both, all rays per step; on a CPU composite reads 8 "
                 "(importance: 4) samples per iteration in place; the 'steps' rows time "
                 "the steps alone (no input checks, no finish), in place and scanned over "
                 "the samples moved in front; goal importance/standard <= 1.5; "
                 "GPU goal 512^2 x 512 forward <= 10 ms (H100).",
    }
