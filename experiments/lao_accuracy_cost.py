# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # What LAO accuracy costs in time
#
# Local ambient occlusion (Ancel et al. 2010, eq. 3-4) approximates an integral over
# the sphere (L rays) and along each ray (M samples). This study measures, on the
# shells phantom, the error of `vs.lao` against a dense reference (642 icosphere
# directions, 64 samples) and the time of each (L, M), so the trade-off can be read
# off one table. Opacity correction is on (`opacity_correction=True`): the seeds' form
# applies each sample's opacity whatever the step, so its result changes with M and
# has no limit to converge to; corrected, more samples approach the continuous eq. 2.
# `VOLSHADE_QUICK=1` runs at 32^3 with fewer settings (the test suite
# does); `VOLSHADE_DOCS` sets the output folder (default `docs/results/`).

# %%
import os
import pathlib
import statistics
import time
from itertools import pairwise

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import volshade as vs  # noqa: E402

QUICK = os.environ.get("VOLSHADE_QUICK", "0") == "1"
N = 32 if QUICK else 64
RADIUS = N / 8
_default = pathlib.Path(__file__).resolve().parents[1] / "docs" / "results" \
    if "__file__" in globals() else pathlib.Path("docs/results")
OUT = pathlib.Path(os.environ.get("VOLSHADE_DOCS", _default))
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# Opacity: the shells phantom through its preset transfer function.

# %%
volume = vs.data.phantom("shells", shape=N)
alpha = vs.transfer.preset("shells").opacity(volume)


def timed(fn, repeats=3):
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


reference, t_ref = timed(lambda: vs.lao(alpha, directions=vs.directions.icosphere(3),
                                        radius=RADIUS, offset=1.0, samples=64,
                                        opacity_correction=True), repeats=1)
print(f"{N}^3, R = {RADIUS}: reference (642 directions, 64 samples) in {t_ref:.2f} s")

# %% [markdown]
# Direction sets: icosphere (12, 42, 162) and Fibonacci spirals of the same sizes;
# samples M in {4, 8, 16, 32}. Error: mean and max |AO - AO_ref| over voxels with
# any occluder in reach (AO_ref < 1).

# %%
dir_sets = {f"icosphere {len(vs.directions.icosphere(k))}": vs.directions.icosphere(k)
            for k in ((0, 1) if QUICK else (0, 1, 2))}
dir_sets |= {f"fibonacci {n}": vs.directions.fibonacci(n) for n in ((12, 42) if QUICK
                                                                    else (12, 42, 162))}
sample_counts = (4, 8, 16) if QUICK else (4, 8, 16, 32)
mask = np.asarray(reference) < 1
rows = []
for name, dirs in dir_sets.items():
    for m in sample_counts:
        ao, seconds = timed(lambda d=dirs, m=m: vs.lao(alpha, directions=d, radius=RADIUS,
                                                       offset=1.0, samples=m,
                                                       opacity_correction=True))
        err = np.abs(np.asarray(ao) - np.asarray(reference))[mask]
        rows.append({"directions": name, "L": len(dirs), "M": m, "seconds": seconds,
                     "mean_err": float(err.mean()), "max_err": float(err.max())})
        print(f"{name:14s} M={m:3d}  {seconds:7.3f} s  mean {err.mean():.4f}  "
              f"max {err.max():.4f}")

# %% [markdown]
# ## Error against time

# %%
fig, ax = plt.subplots(figsize=(6, 4))
for name in dir_sets:
    sel = [r for r in rows if r["directions"] == name]
    ax.loglog([r["seconds"] for r in sel], [r["mean_err"] for r in sel], "o-", label=name)
    for r in sel:
        ax.annotate(f"M={r['M']}", (r["seconds"], r["mean_err"]), fontsize=6)
ax.set_xlabel("time per LAO volume (s, this machine)")
ax.set_ylabel("mean |AO - AO_ref|")
ax.set_title(f"LAO accuracy against cost, shells {N}^3, R = {RADIUS:g}")
ax.legend(fontsize=7)
fig.tight_layout()
fig.savefig(OUT / "lao_accuracy_cost.png", dpi=100)
plt.close(fig)

lines = ["| directions | L | M | time (s) | mean error | max error |", "|---|---|---|---|---|---|"]
lines += [f"| {r['directions']} | {r['L']} | {r['M']} | {r['seconds']:.3f} | "
          f"{r['mean_err']:.4f} | {r['max_err']:.4f} |" for r in rows]
(OUT / "lao_accuracy_cost.md").write_text(
    f"LAO error against a 642-direction, 64-sample reference, shells phantom {N}^3, "
    f"R = {RADIUS:g}, offset 1, opacity correction on, on {jax.devices()[0].platform}.\n\n"
    + "\n".join(lines) + "\n")

# %% [markdown]
# More samples reduce the error for every direction set, and at the most samples more
# directions of a kind do too (with few samples the sampling error along the rays
# dominates, and the direction count hardly matters).

# %%
for name in dir_sets:
    errors = [r["mean_err"] for r in rows if r["directions"] == name]
    assert all(a > b for a, b in pairwise(errors)), (name, errors)
for kind in ("icosphere", "fibonacci"):
    errors = [r["mean_err"] for r in rows
              if r["directions"].startswith(kind) and r["M"] == sample_counts[-1]]
    assert all(a > b for a, b in pairwise(errors)), (kind, errors)
print("checks passed: the error falls with M for every set, and with L at the most samples")
