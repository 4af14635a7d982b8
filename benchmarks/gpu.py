"""The GPU goals of the issues, and GPU-against-CPU agreement, in one run.

    python -m benchmarks.run gpu [--quick]

Needs a GPU (the CPU backend of the same process computes the agreement
references). Cases:

* agreement: small render (Phong + LAO ambient + importance composition), LAO,
  bricked LAO and its gradient, colour-bleeding obscurance, saliency and importance
  compositing, each computed on the GPU and on the CPU in this process; max
  |GPU - CPU| in float32;
* LAO (issue 3): 512^3, L = 54, M = 50, R = 50: trilinear samples per second, forward
  and forward + gradient w.r.t. opacity and radius (``benchmarks.lao.run_gpu``); and
  bricked against plain on a sparse 256^3 ball (bricks of 32, R = 8). The same
  case with ``implementation="pallas"`` is ``benchmarks.run lao_pallas``, a process
  of its own (a fault of an untried kernel would end this run);
* obscurance (issue 4): 256^3, 162 directions, d_max 64 (goal <= 0.25 s on an H100);
* composition (issue 5): 512^2 rays x 512 samples, standard and importance-aware,
  forward (goal <= 10 ms on an H100) and forward + gradient, scan unrolled 1 and 8;
* rendering: a 512^2 image over the 256^3 shells phantom.
"""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import volshade as vs
from volshade.composition import composite
from volshade.directions import icosphere
from volshade.importance import Focus, Importance
from volshade.lao import LocalAmbientOcclusion, lao
from volshade.obscurance import obscurance
from volshade.render import n_samples
from volshade.saliency import saliency

from ._timing import report, report_ratios, time_fn
from .render import BUDGET_NOTE


def _agreement() -> list[dict]:
    rng = np.random.default_rng(0)
    alpha = jnp.asarray(rng.random((32, 32, 32)) ** 4, jnp.float32)
    head = vs.data.phantom("shells", shape=48)
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(64, 64))
    scene = vs.Scene(volume=head, transfer=vs.transfer.preset("shells"), shading="phong",
                     ambient="lao", lao=LocalAmbientOcclusion(6.0, directions=16, samples=8),
                     composition="importance", importance=Importance(intensity=3.0),
                     focus=Focus(radius=0.3))
    sparse = jnp.zeros((48, 48, 48), jnp.float32).at[8:20, 10:18, 30:40].set(
        jnp.asarray(rng.random((12, 8, 10)), jnp.float32))
    weights = jnp.asarray(rng.normal(size=sparse.shape), jnp.float32)

    def bricked(a):
        return lao(a, directions=16, radius=6.0, samples=8, brick_size=8)

    c = jnp.asarray(rng.random((1000, 64, 3)), jnp.float32)
    a = jnp.asarray(rng.random((1000, 64)) ** 3, jnp.float32)
    i = jnp.asarray(rng.normal(size=(1000, 64)) * 20, jnp.float32)
    cases = {
        "render phong+lao+importance 48^3 -> 64^2": lambda: eqx.filter_jit(vs.render)(scene, cam),
        "lao 32^3 L16 M8": lambda: lao(alpha, directions=16, radius=6.0, samples=8),
        "lao bricked 48^3 sparse": lambda: bricked(sparse),
        "lao bricked gradient w.r.t. alpha": lambda: jax.grad(
            lambda a: jnp.sum(weights * bricked(a)))(sparse),
        "obscurance+bleeding 32^3 42 dirs": lambda: obscurance(
            alpha, directions=icosphere(1), d_max=16.0,
            colors=jnp.stack([alpha, 1 - alpha, alpha**2], -1)),
        "saliency 32^3": lambda: saliency(obscurance(alpha, directions=icosphere(0), d_max=8.0)),
        "composite importance 1000x64": lambda: composite(c * a[..., None], a, importance=i),
    }
    rows = []
    for name, fn in cases.items():
        with jax.default_device(jax.devices("cpu")[0]):
            ref = np.asarray(fn())
        got = np.asarray(fn())
        report(rows, {"case": f"agree: {name}",
                      "max_abs_gpu_minus_cpu": float(np.max(np.abs(got - ref)))})
    return rows


# Problem sizes: the issues' (full), --quick, and a dry run that tests/test_benchmarks.py
# makes on the CPU so that this script, run only where a GPU is lent, cannot rot unseen.
SIZES = {
    "full": {"lao": {"n": 512, "n_gather": 256}, "obscurance": 256, "ball": (256, 32),
             "composite": (512, 512), "render": (256, 512), "repeats": 3},
    "quick": {"lao": {"n": 256, "n_gather": 256}, "obscurance": 128, "ball": (128, 16),
              "composite": (256, 256), "render": (128, 256), "repeats": 3},
    "dry": {"lao": {"n": 12, "n_gather": 12, "n_dirs": 6, "samples": 4, "radius": 4.0},
            "obscurance": 10, "ball": (16, 8), "composite": (4, 8), "render": (12, 8),
            "repeats": 1},
}


def run(quick: bool) -> dict:
    if jax.default_backend() == "cpu":
        raise SystemExit("benchmarks.run gpu needs a GPU (jax.default_backend() is 'cpu').")
    result = measure(SIZES["quick" if quick else "full"])
    result["sizes"] = {"quick": quick}
    return result


def measure(sizes: dict) -> dict:
    """Every case at ``sizes`` (an entry of :data:`SIZES`), on the default device.

    Each section's rows are printed as they come (device time is short: a run cut off
    by its time limit still reports what it measured), and a section that raises is
    recorded as an ``error`` row and the next one runs."""
    rows, ratios = [], {}
    t0 = time.perf_counter()
    for section in (_agreement_section, _lao_section, _obscurance_section, _bricks_section,
                    _composition_section, _render_section):
        try:
            section(sizes, rows, ratios)
        except Exception as err:  # noqa: BLE001 - one failing section must not lose the rest
            report(rows, {"case": section.__name__, "error": repr(err)[:500]})
        report_ratios(ratios)
    report(rows, {"case": "(all cases)", "elapsed_s": time.perf_counter() - t0})
    return {"title": "GPU goals and GPU/CPU agreement", "rows": rows, "ratios": ratios}


def _agreement_section(sizes: dict, rows: list, ratios: dict) -> None:
    rows += _agreement()


def _lao_section(sizes: dict, rows: list, ratios: dict) -> None:
    # LAO first of the large cases: the device's peak memory counts from process start,
    # so its peak ratios are the LAO's own only before the other large cases run
    from .lao import run_gpu

    lao_result = run_gpu(**sizes["lao"], repeats=sizes["repeats"])
    rows += lao_result["rows"]
    ratios.update({f"lao {k}": v for k, v in lao_result["ratios"].items()})


def _obscurance_section(sizes: dict, rows: list, ratios: dict) -> None:
    """256^3, 162 directions, d_max 64."""
    repeats = sizes["repeats"]
    n = sizes["obscurance"]
    density = 0.5 * vs.data.phantom("shells", shape=n)
    dirs162 = icosphere(2)  # concrete: the directions set the sweep, close over them
    obs = jax.jit(lambda d, dm: obscurance(d, directions=dirs162, d_max=dm))
    t = time_fn(obs, density, jnp.float32(64.0), repeats=repeats)
    report(rows, {"case": f"obscurance {n}^3 162 dirs d_max 64", "median_s": t["median_s"],
                  "compile_s": t["first_call_s"] - t["median_s"]})


def _bricks_section(sizes: dict, rows: list, ratios: dict) -> None:
    """LAO bricks on a sparse volume (a ball; 1/8 of the bricks within reach): bricked /
    plain."""
    from .lao import sparse_ball

    n, brick = sizes["ball"]
    ball = sparse_ball(n)
    med = {}
    for b in (None, brick):
        fn = jax.jit(lambda a, b=b: lao(a, directions=16, radius=8.0, samples=16, brick_size=b))
        med[b] = time_fn(fn, ball, repeats=sizes["repeats"])["median_s"]
        report(rows, {"case": f"lao sparse ball {n}^3 L16 M16 R8, bricks {b}",
                      "median_s": med[b]})
    ratios["lao bricked speed-up on the sparse ball"] = med[None] / med[brick]


def _composition_section(sizes: dict, rows: list, ratios: dict) -> None:
    """512^2 rays x 512 samples."""
    repeats = sizes["repeats"]
    side, samples = sizes["composite"]
    key = jax.random.split(jax.random.PRNGKey(0), 3)
    alphas = jax.random.uniform(key[0], (side * side, samples), jnp.float32, 0.0, 0.05)
    colors = jax.random.uniform(key[1], (side * side, samples, 3), jnp.float32) * alphas[..., None]
    imps = 4.0 * jax.random.normal(key[2], (side * side, samples), jnp.float32)
    med = {}
    for unroll in (1, 8):
        # every array is an argument (a closed-over one would be baked in as a constant),
        # and every input is differentiated, as in benchmarks/composition.py
        for name, args in (("standard", (colors, alphas)), ("importance", (colors, alphas, imps))):
            def fn(c, a, *i, u=unroll):
                return composite(c, a, unroll=u, importance=i[0] if i else None)

            t = time_fn(jax.jit(fn), *args, repeats=repeats + 2)
            med[(name, "fwd", unroll)] = t["median_s"]
            report(rows, {"case": f"composite {name} {side}^2x{samples} unroll {unroll}",
                          "median_s": t["median_s"],
                          "Gsamples_per_s": side * side * samples / t["median_s"] / 1e9})
            grad = jax.jit(jax.grad(lambda *xs, fn=fn: jnp.sum(fn(*xs)),
                                    argnums=tuple(range(len(args)))))
            t = time_fn(grad, *args, repeats=repeats)
            med[(name, "grad", unroll)] = t["median_s"]
            report(rows, {"case": f"composite {name} fwd+grad unroll {unroll}",
                          "median_s": t["median_s"]})
    for u in (1, 8):
        ratios[f"composite importance/standard forward (unroll {u})"] = (
            med[("importance", "fwd", u)] / med[("standard", "fwd", u)])
        ratios[f"composite importance/standard fwd+grad (unroll {u})"] = (
            med[("importance", "grad", u)] / med[("standard", "grad", u)])


def _render_section(sizes: dict, rows: list, ratios: dict) -> None:
    """512^2 over 256^3 (quick: 256^2 over 128^3)."""
    n, px = sizes["render"]
    vol = vs.data.phantom("shells", shape=n)
    cam = vs.Camera.orbit(azimuth=30, elevation=20, image_shape=(px, px))
    for shading in ("none", "phong"):
        scene = vs.Scene(volume=vol, transfer=vs.transfer.preset("shells"), shading=shading,
                         step=1.0)
        t = time_fn(eqx.filter_jit(vs.render), scene, cam, repeats=sizes["repeats"])
        work = px * px * n_samples(vol.shape, (1, 1, 1), 1.0)
        report(rows, {"case": f"render {px}^2 over {n}^3, shading={shading}",
                      "median_s": t["median_s"], "Gsamples_per_s": work / t["median_s"] / 1e9,
                      "note": BUDGET_NOTE})
