"""A short GPU re-check after a change: GPU/CPU agreement and the LAO 512^3 case only.

    python -m benchmarks.run gpu_recheck

The cheap subset of ``benchmarks.gpu`` for when device time is short.
"""

import jax

from .gpu import SIZES, _agreement
from .lao import run_gpu


def run(quick: bool) -> dict:
    if jax.default_backend() != "gpu":
        raise SystemExit("benchmarks.run gpu_recheck needs a GPU (jax.default_backend() is "
                         f"{jax.default_backend()!r}).")
    rows = _agreement()
    lao = run_gpu(**SIZES["quick" if quick else "full"]["lao"])
    return {"title": "GPU re-check: agreement and LAO", "sizes": {"quick": quick},
            "rows": rows + lao["rows"], "ratios": {f"lao {k}": v for k, v in lao["ratios"].items()}}
