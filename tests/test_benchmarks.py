"""Dry runs of the GPU benchmarks on the CPU, at tiny sizes.

These scripts measure the issues' GPU goals and run only where a device is lent, which
is rare and short: without a dry run here a change to the library can break them unseen
(it did: ``benchmarks/gpu.py`` called the obscurance kernel with an argument it had
lost, and would have failed after its LAO cases, on the device). The figures of a dry
run mean nothing; what is checked is that every case runs and that each agreement it
reports holds on the CPU.
"""

import math

import jax
import pytest

from benchmarks import gpu
from benchmarks.lao import run_gpu_pallas

pytestmark = pytest.mark.dry_run


def _check_rows(rows):
    errors = [row for row in rows if "error" in row]
    assert not errors, errors
    for row in rows:
        if "median_s" in row and not row["case"].startswith("agree:"):
            assert math.isfinite(row["median_s"]) and row["median_s"] > 0, row


def test_gpu_benchmark_runs_every_case():
    with jax.enable_x64(False):  # as `python -m benchmarks.run` runs (the suite sets x64)
        result = gpu.measure(gpu.SIZES["dry"])
    _check_rows(result["rows"])
    # the "GPU" and the CPU are one device here: each agreement check compares a program
    # with itself
    agreement = [row for row in result["rows"] if row["case"].startswith("agree:")]
    assert len(agreement) == 7
    for row in agreement:
        assert row["max_abs_gpu_minus_cpu"] == 0.0, row
    ratios = result["ratios"]
    assert ratios["lao max_abs_diff_vs_gather_12"] < 1e-6
    assert all(math.isfinite(v) for k, v in ratios.items() if "peak_bytes" not in k), ratios


def test_lao_pallas_benchmark_runs_every_case():
    # on a CPU the kernels run in Pallas' interpreter
    with jax.enable_x64(False):
        result = run_gpu_pallas(n=8, n_dirs=4, samples=3, radius=3.0)
    _check_rows(result["rows"])
    ratios = result["ratios"]
    assert ratios["pallas_max_abs_diff_vs_xla"] < 1e-6
    assert ratios["pallas_grad_alpha_max_rel_diff_vs_xla"] < 1e-5
    assert ratios["pallas_grad_radius_rel_diff_vs_xla"] < 1e-5
    assert ratios["pallas_jvp_over_forward"] > 0
    assert "pallas_bricked_speedup_sparse_ball" in ratios
    for row in result["rows"]:
        if row["case"].startswith("agree:"):
            assert row["max_abs_diff"] <= 1e-5 * row["max_abs"], row
