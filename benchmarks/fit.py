"""What a fit costs: ``vs.fit`` against the render and gradient it is built from, in one run.

A scene of the shells phantom with LAO as the Phong ambient term and importance-aware
compositing (float32, one view) is rendered with known LAO radius and intensity
weight; ``vs.fit`` recovers both from the image. Baselines in the same run: one
render, and one render with the gradient of the loss w.r.t. both parameters (what a
minimiser's step needs). Reported: the first fit (compilation included), the
median of fits of the same structure from other starting points (the compiled
solver reused), their time per solver step against the gradient's time, and
optimistix's Levenberg--Marquardt on the same problem (it barely moves: its
damping starts far above the curvature of image residuals).
"""

import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

import volshade as vs
from benchmarks._timing import time_cases

TRUE = (6.0, 2.0)  # LAO radius (voxels), importance intensity weight
STARTS = ((3.0, 0.5), (8.5, 4.0), (4.5, 1.0))
BOUNDS = {"lao.radius": (1.0, 10.0), "importance.intensity": (0.0, None)}


def _scene(n: int, radius: float, intensity: float) -> vs.Scene:
    return vs.Scene(
        volume=vs.data.phantom("shells", shape=n).astype(jnp.float32),
        transfer=vs.transfer.preset("shells"), shading="phong", ambient="lao",
        lao=vs.LocalAmbientOcclusion(radius, offset=1.0, directions=16, samples=8,
                                     max_radius=10.0),
        composition="importance", importance=vs.Importance(intensity=intensity))


def _with(scene: vs.Scene, radius: float, intensity: float) -> vs.Scene:
    return eqx.tree_at(lambda s: (s.lao.radius, s.importance.intensity), scene,
                       (jnp.asarray(radius, jnp.float32), jnp.asarray(intensity, jnp.float32)))


def _timed_fit(start, cam, target, **kw):
    t0 = time.perf_counter()
    result = vs.fit(start, cam, target, params=BOUNDS, throw=False, **kw)
    jax.block_until_ready(result.loss)
    return result, time.perf_counter() - t0


def _error(result) -> float:
    return max(abs(float(result.values["lao.radius"]) - TRUE[0]),
               abs(float(result.values["importance.intensity"]) - TRUE[1]))


def run(quick: bool) -> dict:
    n, pixels = (32, 48) if quick else (64, 96)
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(pixels, pixels))
    truth = _scene(n, *TRUE)
    render = eqx.filter_jit(vs.render)
    target = jax.block_until_ready(render(truth, cam))

    def loss(params, scene):
        return jnp.mean((vs.render(_with(scene, *params), cam) - target) ** 2)

    gradient = eqx.filter_jit(jax.value_and_grad(loss))
    start = jnp.asarray(STARTS[0], jnp.float32)
    timed = time_cases({"render": (render, (_with(truth, *STARTS[0]), cam)),
                        "gradient": (gradient, (start, truth))})
    t_render, t_grad = timed["render"]["median_s"], timed["gradient"]["median_s"]

    first, t_first = _timed_fit(_with(truth, *STARTS[0]), cam, target)
    # the same start again takes the same steps: the difference is the compilation
    same, t_same = _timed_fit(_with(truth, *STARTS[0]), cam, target)
    again = [_timed_fit(_with(truth, *s), cam, target) for s in STARTS[1:] * 2]
    t_again = statistics.median(t for _, t in again)
    steps_again = statistics.median(int(r.steps) for r, _ in again)
    tol = float(jnp.sqrt(jnp.finfo(jnp.float32).eps))
    lm, t_lm = _timed_fit(_with(truth, *STARTS[0]), cam, target,
                          solver=optx.LevenbergMarquardt(rtol=tol, atol=tol**2))
    rows = [
        {"case": "render (baseline)", "median_s": t_render},
        {"case": "render + gradient w.r.t. both parameters", "median_s": t_grad},
        {"case": "vs.fit, first (compiles; one call)", "time_s": t_first,
         "steps": int(first.steps), "max_abs_error": _error(first)},
        {"case": "vs.fit, the same start again (one call)", "time_s": t_same,
         "steps": int(same.steps), "max_abs_error": _error(same)},
        {"case": "vs.fit, same structure, two other starts, each twice (median of the 4 "
                 "calls)", "median_s": t_again, "steps": steps_again,
         "max_abs_error": max(_error(r) for r, _ in again)},
        {"case": "vs.fit with optx.LevenbergMarquardt (compiles; one call)", "time_s": t_lm,
         "steps": int(lm.steps), "max_abs_error": _error(lm)},
    ]
    return {
        "title": "vs.fit: LAO radius and importance weight from one image (float32)",
        "sizes": {"volume": f"shells {n}^3", "image": f"{pixels}x{pixels}",
                  "lao": "16 Fibonacci rays, 8 samples, max_radius 10",
                  "truth": {"lao.radius": TRUE[0], "importance.intensity": TRUE[1]},
                  "starts": [list(s) for s in STARTS]},
        "rows": rows,
        "ratios": {
            "first fit / the same fit again (compilation)": t_first / t_same,
            "later fit per step / render + gradient": t_again / steps_again / t_grad,
            "render + gradient / render": t_grad / t_render,
        },
        "notes": "A later fit's time per step includes its share of the loss evaluated "
                 "before and after. Levenberg-Marquardt runs with the default solver's "
                 "tolerances.",
    }
