"""Test helpers: tolerances per dtype, float64 finite differences, and scripts run with the
user's XLA flags."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

import volshade as vs


def tol(dtype) -> float:
    """About 100 x eps of ``dtype``."""
    return 100 * float(jnp.finfo(dtype).eps)


def central_difference(f, x, direction, h=1e-6):
    """Directional derivative of scalar ``f`` at ``x`` along ``direction`` (float64 only)."""
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        raise TypeError("finite differences need float64; enable jax_enable_x64")
    return (f(x + h * direction) - f(x - h * direction)) / (2 * h)


def temp_bytes(f, *specs) -> int:
    """The temporaries of ``jax.jit(f)`` compiled for ``specs`` (arrays or
    ``jax.ShapeDtypeStruct``), from its buffer plan: a memory figure that does not depend
    on the machine's load, for tests that reverse mode keeps few buffers."""
    return jax.jit(f).lower(*specs).compile().memory_analysis().temp_size_in_bytes


def check_grad_fd(f, x, *, key=0, h=1e-6, rtol=1e-4, n_dirs=3, directions=None):
    """Compare ``jax.grad(f)(x) . v`` with central differences along ``directions`` (an
    ``(n, *x.shape)`` array, each normalised here), by default ``n_dirs`` random ones."""
    g = jax.jit(jax.grad(f))(x)
    if directions is None:
        directions = np.random.default_rng(key).standard_normal((n_dirs, *np.shape(x)))
    for v in jnp.asarray(directions):
        v = v / jnp.linalg.norm(v)
        ad = float(jnp.vdot(g, v))
        fd = float(central_difference(f, x, v, h))
        assert abs(ad - fd) <= rtol * max(abs(fd), abs(ad), 1e-8), (ad, fd)
    return g


def one_medium_written_twice():
    """One uniform medium as two transfer functions: opacity 0.3 per 1 mm, and the same
    per 0.5 mm (``1 - 0.7 ** 0.5``). With the opacity correction, an effect must see
    no difference between them."""
    rows = [(0.0, 1, 1, 1, 0.3), (1.0, 1, 1, 1, 0.3)]
    per_mm = vs.TransferFunction.from_points(rows, step0=1.0)
    per_half_mm = vs.TransferFunction.from_points(
        [(x, r, g, b, 1 - (1 - a) ** 0.5) for x, r, g, b, a in rows], step0=0.5)
    return per_mm, per_half_mm


def run_with_user_xla_flags(script: str) -> list[str]:
    """Run a Python ``script`` in a subprocess on the CPU with the user's XLA flags (the
    suite's own fast-compile flags hide some of XLA's behaviour at its default
    optimisation) and return the words it printed."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": os.environ.get("VOLSHADE_TEST_USER_XLA_FLAGS", "")}
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout.split()
