"""Rendering throughput: rays x samples per second of the ray marcher.

Quick: a 256^2 image over a 128^3 shells phantom on whatever device JAX uses;
full: 512^2 over 256^3. Cases, all measured in this run: emission-absorption
(no shading, the baseline), Blinn-Phong (adds the regression-gradient volume
and three more trilinear lookups per sample), and forward + gradient with
respect to the transfer function's opacities.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

import volshade as vs
from volshade.render import n_samples

from ._timing import time_cases

BUDGET_NOTE = ("Gsamples_per_s counts every ray's full static sample budget (pixels x "
               "samples per ray), not the steps marched: the march skips the chunks past "
               "each ray group's longest ray (on this phantom it runs about 0.46 of the "
               "budget, 0.34 inside the volume)")


def run(quick: bool) -> dict:
    n, px = (128, 256) if quick else (256, 512)
    vol = vs.data.phantom("shells", shape=n)
    tf = vs.transfer.preset("shells")
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(px, px))
    step = 1.0
    samples = n_samples(vol.shape, (1.0, 1.0, 1.0), step)
    work = px * px * samples
    scenes = {shading: vs.Scene(volume=vol, transfer=tf, shading=shading, step=step)
              for shading in ("none", "phong")}

    @eqx.filter_jit
    def loss_and_grad(opacities, scene):
        # the scene is an argument: closed over, its volume would be constant-folded
        def loss(o):
            return jnp.mean(vs.render(eqx.tree_at(lambda s: s.transfer.opacities, scene, o), cam))
        return jax.value_and_grad(loss)(opacities)

    render = eqx.filter_jit(vs.render)
    # interleaved, so that the ratios hold on a shared machine
    timed = time_cases({"forward, shading=none": (render, (scenes["none"], cam)),
                        "forward, shading=phong": (render, (scenes["phong"], cam)),
                        "forward+grad(opacities), shading=none":
                            (loss_and_grad, (tf.opacities, scenes["none"]))},
                       repeats=3 if quick else 5)
    rows = [{"case": name, "median_s": t["median_s"],
             "compile_s": t["first_call_s"] - t["median_s"],
             "Gsamples_per_s": work / t["median_s"] / 1e9} for name, t in timed.items()]
    return {
        "title": "volshade.render throughput (rays x samples per second)",
        "sizes": {"volume": [n] * 3, "image": [px, px], "samples_per_ray": samples,
                  "step_mm": step, "rays_x_samples": work},
        "rows": rows,
        "ratios": {"phong / none": rows[1]["median_s"] / rows[0]["median_s"],
                   "forward+grad / forward": rows[2]["median_s"] / rows[0]["median_s"]},
        "notes": BUDGET_NOTE,
    }
