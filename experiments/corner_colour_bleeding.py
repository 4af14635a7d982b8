# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Colour bleeding on the corner phantom (Ruiz et al. 2008, Figure 4, first row)
#
# Three adjacent opaque walls (floor at low d: white, wall at low h: green, wall
# at low w: blue), the rest transparent. We compute colour-bleeding obscurances
# with 42 directions for the four rho functions of section 3.2, show slices of
# the RGB obscurance volume (wall voxels drawn in their own colour), and render
# the scene with the obscurance as its ambient term.
#
# `VOLSHADE_QUICK=1` runs at 32^3 with small renders (the test suite does);
# `VOLSHADE_DOCS` sets the output folder (default `docs/results/`).

# %%
import os
import pathlib
import time
from itertools import pairwise

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import equinox as eqx  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from skimage.filters import gaussian  # noqa: E402

import volshade as vs  # noqa: E402
from volshade.obscurance import RHO_FUNCTIONS  # noqa: E402

QUICK = os.environ.get("VOLSHADE_QUICK", "0") == "1"
N = 32 if QUICK else 128
D_MAX = N / 2
_default = pathlib.Path(__file__).resolve().parents[1] / "docs" / "results" \
    if "__file__" in globals() else pathlib.Path("docs/results")
OUT = pathlib.Path(os.environ.get("VOLSHADE_DOCS", _default))
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# The phantom: intensities 1.0 / 0.75 / 0.5 on the walls (`vs.data.CORNER_VALUES`).
# The visibility test uses the opacity (1 on the walls, 0 elsewhere), as in the paper;
# the transfer function gives each wall its colour.

# %%
values = vs.data.CORNER_VALUES
vol = vs.data.phantom("corner", shape=N)
opacity = (vol > 0).astype(jnp.float32)
palette = {"white": (1.0, 1.0, 1.0), "blue": (0.15, 0.35, 1.0), "green": (0.1, 0.9, 0.2)}
colors = jnp.zeros((*vol.shape, 3), jnp.float32)
for name, value in values.items():
    colors = jnp.where((vol == value)[..., None], jnp.asarray(palette[name], jnp.float32), colors)
thickness = int(np.argmax(np.asarray(vol[:, N // 2, N // 2]) == 0))
print(f"{N}^3 corner phantom, walls {thickness} voxels thick, d_max = {D_MAX}")

# %%
directions = vs.directions.icosphere(1)
results = {}
for rho in RHO_FUNCTIONS:
    t0 = time.perf_counter()
    rgb = vs.obscurance(opacity, directions=directions, d_max=D_MAX, rho=rho, colors=colors)
    rgb.block_until_ready()
    results[rho] = np.asarray(rgb)
    print(f"rho={rho:12s} {time.perf_counter() - t0:6.2f} s")

# %% [markdown]
# ## Slices
# Row 1: the plane just above the floor (d = wall + 1): the corner where the
# three walls meet is at the top left. Row 2: the central plane d = N/2.

# %%
walls = np.asarray(vol > 0)
wall_rgb = np.asarray(colors)
rows = {"just above the floor": thickness, "central slice": N // 2}
fig, axes = plt.subplots(len(rows), len(results), figsize=(3.2 * len(results), 3.3 * len(rows)))
for r, (label, d) in enumerate(rows.items()):
    for c, (rho, rgb) in enumerate(results.items()):
        image = np.where(walls[d][..., None], wall_rgb[d], rgb[d])
        ax = axes[r, c]
        ax.imshow(np.clip(image, 0, 1), origin="upper")
        ax.set_title(f"rho = {rho}\n{label} (d = {d})", fontsize=9)
        ax.set_xlabel("w (blue wall at left)", fontsize=8)
        ax.set_ylabel("h (green wall at top)", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
fig.suptitle(f"Colour-bleeding obscurances, corner phantom {N}^3, 42 directions, "
             f"d_max = {D_MAX:g}", fontsize=11)
fig.tight_layout()
fig.savefig(OUT / "corner_obscurance_rho.png", dpi=90)
plt.close(fig)

# %% [markdown]
# ## Probe table
# RGB obscurance at a few voxels: the corner (one voxel off all three walls), the
# middle of the floor, next to the green wall only, next to the blue wall only,
# and the centre of the box.

# %%
t = thickness
probes = {
    "corner": (t, t, t),
    "floor middle": (t, N // 2, N // 2),
    "next to green": (N // 2, t, N // 2),
    "next to blue": (N // 2, N // 2, t),
    "centre": (N // 2, N // 2, N // 2),
}
lines = ["| rho | " + " | ".join(probes) + " |", "|---" * (len(probes) + 1) + "|"]
for rho, rgb in results.items():
    cells = ["(" + ", ".join(f"{x:.3f}" for x in rgb[p]) + ")" for p in probes.values()]
    lines.append(f"| {rho} | " + " | ".join(cells) + " |")
table = "\n".join(lines)
print(table)
(OUT / "corner_obscurance_rho.md").write_text(
    f"Corner phantom {N}^3, 42 directions, d_max = {D_MAX:g}; RGB obscurance at probe "
    f"voxels (wall thickness {t}).\n\n{table}\n")

# %% [markdown]
# ## Rendered views
# Walls with sharp faces are their own occluders only where the density rises: in
# the binary phantom a wall voxel has no *strictly* denser neighbour, so its
# obscurance is 1. For the views, the visibility test therefore uses the walls'
# opacity smoothed by a Gaussian of one voxel (scikit-image), so surface voxels are
# occluded by the wall behind them and by the other walls. The renderer shows one
# white opaque material whose ambient term is (own colour) x (colour-bleeding
# obscurance): the walls keep their colours and the floor picks up the others'.

# %%
smooth = jnp.asarray(gaussian(np.asarray(opacity), sigma=1.0), jnp.float32)
white = vs.TransferFunction.from_points([(0.0, 1, 1, 1, 0.0), (1.0, 1, 1, 1, 0.9)])
camera = vs.Camera.orbit(azimuth=45, elevation=35, distance=2.4,
                         image_shape=(64, 64) if QUICK else (192, 192))
views = []
for rho in RHO_FUNCTIONS:
    ambient = colors * vs.obscurance(smooth, directions=directions, d_max=D_MAX, rho=rho,
                                     colors=colors)
    # The empty space keeps white ambient so the wall faces are not tinted by the
    # black colour of empty voxels when the ambient volume is interpolated.
    ambient = jnp.where((opacity > 0)[..., None], ambient, 1.0)
    scene = vs.Scene(volume=opacity, transfer=white, ambient="volume", ambient_volume=ambient,
                     background=(0.2, 0.2, 0.2), step=0.25)
    views.append(np.asarray(eqx.filter_jit(vs.render)(scene, camera))[..., :3])
fig, axes = plt.subplots(1, len(views), figsize=(3.2 * len(views), 3.4))
for ax, rho, view in zip(axes, RHO_FUNCTIONS, views, strict=True):
    ax.imshow(np.clip(view, 0, 1))
    ax.set_title(f"rho = {rho}", fontsize=10)
    ax.axis("off")
fig.suptitle(f"Corner phantom {N}^3 rendered with colour-bleeding obscurance "
             f"(42 directions, d_max = {D_MAX:g})", fontsize=11)
fig.tight_layout()
fig.savefig(OUT / "corner_obscurance_render.png", dpi=90)
plt.close(fig)

# %% [markdown]
# ## Checks
# The tint next to the green wall, the dark corner, and the order of the rho functions:
# for d in [0, d_max], 0 (all-or-nothing) <= 1 - exp(-d/d_max) <= d/d_max <=
# sqrt(d/d_max), so with the same occluders their obscurances are ordered in every
# voxel and channel, and where anything occludes (d > 0) the square root and the
# exponential are strictly lighter than all-or-nothing.

# %%
sqrt, ao = results["sqrt"], results["ao"]
near_green = sqrt[probes["next to green"]]
assert near_green[1] > near_green[0] and near_green[1] > near_green[2], near_green
assert sqrt[probes["corner"]].sum() < sqrt[probes["floor middle"]].sum()
order = [results[rho] for rho in ("ao", "exponential", "linear", "sqrt")]
for darker, lighter in pairwise(order):
    assert np.all(lighter >= darker - 1e-6)
occluded = ao.sum(-1) < 3 - 1e-6
assert occluded.any()
for rho in ("exponential", "sqrt"):
    assert np.all(results[rho].sum(-1)[occluded] > ao.sum(-1)[occluded]), rho
print("checks passed: green bleeding, dark corner, ao <= exponential <= linear <= sqrt")
