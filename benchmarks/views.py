"""Several views of one scene: ``vs.render`` of a list of cameras against a render per camera.

A turntable of the shells phantom with LAO as the Phong ambient term (float32).
The LAO volume and the gradient volume do not depend on the view; a render of a
list of cameras computes them once, a render per camera once per view. Baselines
in the same run (and the LAO volume alone, the share of a view that the views
can share):

- forward: a jitted render called once per camera (the notebook loop), against
  one call with the list;
- forward + gradient w.r.t. the LAO radius (what a fit to several views evaluates
  at every step): one jitted function that sums one render per camera, against
  the same function rendering the list.

Reported: medians, compile times apart, the ratios, and the largest difference
between the images of the two ways (the same arithmetic, which XLA may order
differently in the two programs: equal up to float32 rounding).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

import volshade as vs

from ._timing import block, time_cases


def _scene(n: int) -> vs.Scene:
    return vs.Scene(volume=vs.data.phantom("shells", shape=n).astype(jnp.float32),
                    transfer=vs.transfer.preset("shells"), shading="phong", step=1.0,
                    ambient="lao",
                    lao=vs.LocalAmbientOcclusion(6.0, directions=54, samples=16))


def _loss(radius, scene, cameras, together: bool):
    scene = eqx.tree_at(lambda s: s.lao.radius, scene, radius)
    images = vs.render(scene, cameras) if together else [vs.render(scene, c) for c in cameras]
    return sum(jnp.mean(image[..., :3]) for image in images)


def run(quick: bool) -> dict:
    n, pixels, views = (48, 64, 4) if quick else (96, 128, 8)
    repeats = 3 if quick else 5
    scene = _scene(n)
    cameras = [vs.Camera.orbit(azimuth=360.0 * i / views, elevation=20.0,
                               image_shape=(pixels, pixels)) for i in range(views)]
    render = eqx.filter_jit(vs.render)

    def each(scene, cameras):
        return [render(scene, c) for c in cameras]

    # each group interleaved, so that its ratios hold on a shared machine (the loop's
    # first call comes after the one view's, whose compiled render it reuses)
    timed = time_cases({
        "ambient": (eqx.filter_jit(lambda s: s.lao(s.transfer.opacity(s.volume))), (scene,)),
        "one": (render, (scene, cameras[0])), "loop": (each, (scene, cameras)),
        "together": (render, (scene, cameras))}, repeats=repeats)
    ambient, one, loop, together = (timed[k] for k in ("ambient", "one", "loop", "together"))
    difference = max(float(jnp.max(jnp.abs(a - b)))
                     for a, b in zip(each(scene, cameras), block(render(scene, cameras)),
                                     strict=True))
    grad = eqx.filter_jit(jax.value_and_grad(_loss))  # (compiled per value of the flag)
    grads = time_cases({name: (grad, (scene.lao.radius, scene, cameras, flag))
                        for name, flag in (("per camera", False), ("list", True))},
                       repeats=repeats)
    rows = [
        {"case": "the LAO volume alone (the shared work)", **_row(ambient)},
        {"case": "one view, render(scene, camera)", **_row(one)},
        {"case": f"{views} views, a render call per camera", "median_s": loop["median_s"]},
        {"case": f"{views} views, one render(scene, cameras)", **_row(together),
         "max_abs_diff_vs_per_camera": difference},
        {"case": f"{views} views, forward+grad(radius), a render per camera in one jit",
         **_row(grads["per camera"])},
        {"case": f"{views} views, forward+grad(radius), render(scene, cameras)",
         **_row(grads["list"])},
    ]
    return {
        "title": "Several views: a list of cameras against a render per camera",
        "sizes": {"volume": [n] * 3, "image": [pixels, pixels], "views": views,
                  "lao": "54 Fibonacci rays x 16 samples, radius 6"},
        "rows": rows,
        "ratios": {
            "forward: render per camera / list": loop["median_s"] / together["median_s"],
            "forward: list / one view": together["median_s"] / one["median_s"],
            "LAO volume / one view": ambient["median_s"] / one["median_s"],
            "forward+grad: render per camera / list":
                grads["per camera"]["median_s"] / grads["list"]["median_s"],
            "compile: list / one view":
                _row(together)["compile_s"] / _row(one)["compile_s"],
            "compile forward+grad: render per camera / list":
                _row(grads["per camera"])["compile_s"] / _row(grads["list"])["compile_s"],
        },
        "notes": "the render-per-camera loop reuses the one-view row's compiled render "
                 "(so it has no compile time of its own); the list's views of one image "
                 "shape share one compiled march (jax.lax.map)",
    }


def _row(timing: dict) -> dict:
    return {"median_s": timing["median_s"],
            "compile_s": timing["first_call_s"] - timing["median_s"]}
