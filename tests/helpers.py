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


def strongly_typed(tree):
    """``tree`` (numbers, a camera, effect parameters) with every leaf a strongly typed
    float64 array, as a render makes a scene's and a camera's leaves and as a finite
    difference's ``x + h v`` is: jit compiles a weakly typed input (a Python float,
    ``jnp.asarray(3.3)``) apart, so a test given these reuses the program."""
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), tree)


def check_grads_fd(value_and_grad, args, wrt=(0,), *, key=0, h=1e-6, rtol=1e-4, n_dirs=3,
                   directions=None):
    """Compare the gradients of a loss with central differences of the loss, in each
    argument ``args[i]``, ``i`` in ``wrt``, along ``directions`` (an ``(n, *shape)``
    array, each normalised here), by default ``n_dirs`` random ones (seed ``key``, the
    same for each argument). ``value_and_grad(*args)`` returns the loss and its gradients
    with respect to ``args[0], args[1], ...`` (``jax.jit(jax.value_and_grad(loss,
    argnums))``): the differences evaluate the same compiled program, so the values and
    the gradients of every argument compile once. Returns the gradients."""
    _, grads = value_and_grad(*args)
    for i in wrt:
        dirs = (np.random.default_rng(key).standard_normal((n_dirs, *np.shape(args[i])))
                if directions is None else directions)
        for v in jnp.asarray(dirs):
            v = v / jnp.linalg.norm(v)
            ad = float(jnp.vdot(grads[i], v))
            fd = float(central_difference(
                lambda x, i=i: value_and_grad(*args[:i], x, *args[i + 1:])[0], args[i], v, h))
            assert abs(ad - fd) <= rtol * max(abs(fd), abs(ad), 1e-8), (i, ad, fd)
    return grads


def check_grad_fd(f, x, **kwargs):
    """:func:`check_grads_fd` of a scalar ``f`` of one array ``x``; returns its gradient."""
    return check_grads_fd(jax.jit(jax.value_and_grad(f, (0,))), (x,), **kwargs)[0]


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
