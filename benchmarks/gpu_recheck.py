"""A short GPU re-check after a change: GPU/CPU agreement and the LAO 512^3 case only
(XLA and Pallas).

    python -m benchmarks.run gpu_recheck

The cheap subset of ``benchmarks.gpu`` for when device time is short.
"""

from .gpu import _agreement
from .lao import run_gpu, run_gpu_pallas


def run(quick: bool) -> dict:
    rows = _agreement()
    n = 256 if quick else 512
    lao, pallas = run_gpu(n=n), run_gpu_pallas(n=n)
    return {"title": "GPU re-check: agreement and LAO", "sizes": {"quick": quick},
            "rows": rows + lao["rows"] + pallas["rows"],
            "ratios": {f"lao {k}": v for k, v in {**lao["ratios"], **pallas["ratios"]}.items()}}
