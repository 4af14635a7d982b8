"""Timing helpers shared by the benchmarks: warm-up, compile time apart, medians."""

import json
import statistics
import sys
import time
from collections.abc import Callable

import jax


def block(x):
    return jax.block_until_ready(x)


def time_fn(fn: Callable, *args, repeats: int = 5) -> dict:
    """Time ``fn(*args)``: the first call (compile + run) apart, then the median of ``repeats``.

    ``fn`` should be jitted; its output is blocked on so asynchronous dispatch
    is not mistaken for speed.
    """
    t0 = time.perf_counter()
    block(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        block(fn(*args))
        times.append(time.perf_counter() - t0)
    return {"first_call_s": first, "median_s": statistics.median(times), "times_s": times}


def time_fns(fns: dict[str, Callable], *args, repeats: int = 5) -> dict[str, dict]:
    """:func:`time_cases` of ``fns``, each called on the same ``args``."""
    return time_cases({name: (fn, args) for name, fn in fns.items()}, repeats=repeats)


def time_cases(cases: dict[str, tuple[Callable, tuple]], *, repeats: int = 5
               ) -> dict[str, dict]:
    """:func:`time_fn` of each case ``name: (fn, args)``, interleaved: every round times
    each case once, in an order rotated from round to round, so that a shared machine's
    slow spells fall on all of them alike and their ratios hold (timed one after the
    other, a bricked/unbricked ratio of about 1 measured 2 in one run, and a review
    measured feature AO against classic LAO at 5.7 in one run, 2.9 interleaved minutes
    later: the orange at 64^3). The first calls (compile + run) come before the
    rounds."""
    out = {}
    for name, (fn, args) in cases.items():
        t0 = time.perf_counter()
        block(fn(*args))
        out[name] = {"first_call_s": time.perf_counter() - t0, "times_s": []}
    names = list(cases)
    for k in range(repeats):
        for name in names[k % len(names):] + names[:k % len(names)]:
            fn, args = cases[name]
            t0 = time.perf_counter()
            block(fn(*args))
            out[name]["times_s"].append(time.perf_counter() - t0)
    for result in out.values():
        result["median_s"] = statistics.median(result["times_s"])
    return out


def fit_exponent(sizes: list[float], times: list[float]) -> float:
    """Least-squares slope of log(time) against log(size)."""
    import numpy as np

    slope, _ = np.polyfit(np.log(sizes), np.log(times), 1)
    return float(slope)


def report(rows: list[dict], row: dict) -> None:
    """Append ``row`` to ``rows`` and print it to stderr at once: a GPU run cut off by its
    time limit still shows what it measured."""
    rows.append(row)
    print(json.dumps(row, default=float), file=sys.stderr, flush=True)


def report_ratios(ratios: dict) -> None:
    """Print the ratios measured so far to stderr at once (as :func:`report` a row)."""
    print(json.dumps({"ratios so far": ratios}, default=float), file=sys.stderr, flush=True)
