"""The LAO Pallas kernels on a GPU: launch sweeps (forward; forward + gradient over the
reverse-mode launches), agreement.

    python -m benchmarks.run lao_pallas [--quick]

Issue 3's GPU case (512^3, L = 54, M = 50, R = 50; ``--quick``: 256^3) with
``lao(..., implementation="pallas")`` against the XLA march in the same run
(``benchmarks.lao.run_gpu_pallas``), and bricked against plain on a sparse ball of
half the edge (256^3; ``--quick``: 128^3). Needs a GPU: on a CPU the kernels would
run in Pallas' interpreter.
"""

import jax

from .lao import run_gpu_pallas


def run(quick: bool) -> dict:
    if jax.default_backend() != "gpu":
        raise SystemExit("benchmarks.run lao_pallas needs a GPU (jax.default_backend() is "
                         f"{jax.default_backend()!r}).")
    result = run_gpu_pallas(n=256 if quick else 512)
    result["sizes"] = {"quick": quick}
    return result
