"""Importance-aware composition (Pinto & Freitas 2010, eq. 8) against standard compositing.

Both run through :func:`volshade.composite` on the same random float32 rays
(premultiplied colours, opacities, importances), forward and forward + reverse
gradient (w.r.t. colours and opacities, plus importances for the importance
compositor), in one process. Goal: importance <= 1.5x standard.
"""

import jax
import jax.numpy as jnp

from benchmarks._timing import time_fn
from volshade.composition import composite


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

    cases = {"standard": standard, "importance": importance_aware}
    rows, medians = [], {}
    n_total = n_rays * n_samples
    for name, fn in cases.items():
        fwd = jax.jit(fn)
        argnums = (0, 1) if name == "standard" else (0, 1, 2)
        grad = jax.jit(jax.grad(lambda c, a, i, fn=fn: jnp.sum(fn(c, a, i)), argnums=argnums))
        for mode, f in (("forward", fwd), ("forward+grad", grad)):
            t = time_fn(f, colors, alphas, importance, repeats=repeats)
            medians[(name, mode)] = t["median_s"]
            rows.append({"case": f"{name} {mode}", "median_s": t["median_s"],
                         "first_call_s": t["first_call_s"],
                         "Msamples_per_s": n_total / t["median_s"] / 1e6})
    ratios = {
        "importance/standard forward": medians[("importance", "forward")]
        / medians[("standard", "forward")],
        "importance/standard forward+grad": medians[("importance", "forward+grad")]
        / medians[("standard", "forward+grad")],
    }
    return {
        "title": "importance-aware vs standard compositing (volshade.composite, float32)",
        "sizes": {"rays": n_rays, "image": f"{side}x{side}", "samples_per_ray": n_samples},
        "rows": rows,
        "ratios": ratios,
        "notes": "same rays for both; lax.scan over samples, all rays per step; "
                 "goal importance/standard <= 1.5; GPU goal 512^2 x 512 forward <= 10 ms (H100).",
    }
