"""Benchmark harness.

    python -m benchmarks.run NAME [--quick] [--json OUT]

Each benchmark is a module ``benchmarks/NAME.py`` with a function
``run(quick: bool) -> dict`` returning::

    {"title": str,                 # one line
     "sizes": {...},               # problem sizes, for the record
     "rows": [{"case": str, "median_s": float, ...}, ...],   # one row per measured case
     "ratios": {"name": float, ...},                          # measured in this same run
     "notes": str}                 # optional

The harness adds the device, the JAX version, the date, the commit and a digest of the
sources it ran (``volshade/`` and ``benchmarks/``), prints a table and writes JSON (to
OUT, or to benchmarks/results/NAME.json). On a copy of the tree whose ``.git`` is not
current (the lent GPU machine's), pass the commit with ``--commit REV``; the digest
tells whether a record was made from that commit's sources
(``python -c "from benchmarks.run import sources_digest; print(sources_digest())"``
there gives the same).
"""

import argparse
import datetime
import hashlib
import importlib
import json
import math
import pathlib
import platform
import subprocess
import sys

import jax
import numpy as np

BENCHMARKS = ("render", "views", "lao", "feature_ao", "cao", "fit", "obscurance", "composition",
              "gpu", "gpu_recheck", "lao_pallas", "pallas_sass")


def _format_table(rows: list[dict]) -> str:
    cols: list[str] = []
    for row in rows:
        cols += [k for k in row if k not in cols]
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)
    cells = [[fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(lines)


def _strict(value):
    """``value`` with every non-finite number made ``None`` (JSON has no NaN or inf), a
    NumPy float too (it is no Python float: written through ``default=float``, it
    stopped the record at the end of the run)."""
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    return value


def _commit() -> str:
    """The checkout's commit (``+changes`` when the tree differs), or "unknown" without git."""
    root = pathlib.Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, check=True,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty.strip() else "")


def sources_digest(root: pathlib.Path | None = None) -> str:
    """SHA-256 (first 16 hex digits) of the Python sources under ``volshade/`` and
    ``benchmarks/`` of ``root`` (this checkout by default): their paths and contents, in
    path order, so that it depends on what ran, not on git."""
    root = pathlib.Path(__file__).resolve().parents[1] if root is None else root
    digest = hashlib.sha256()
    for path in sorted(p for d in ("volshade", "benchmarks") for p in (root / d).rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=BENCHMARKS)
    parser.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    parser.add_argument("--json", type=pathlib.Path, default=None, help="where to write JSON")
    parser.add_argument("--commit", default=None,
                        help="the commit to record instead of the checkout's (for a copied "
                             "tree whose .git is not current)")
    args = parser.parse_args(argv)

    module = importlib.import_module(f"benchmarks.{args.name}")
    result = module.run(quick=args.quick)
    device = jax.devices()[0]
    result.update(
        name=args.name,
        quick=args.quick,
        device=f"{device.platform}:{getattr(device, 'device_kind', '')}",
        jax_version=jax.__version__,
        python=platform.python_version(),
        machine=platform.machine(),
        commit=_commit() if args.commit is None else args.commit,
        sources=sources_digest(),
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    )
    print(f"# {result['title']}  [{result['device']}, jax {result['jax_version']}]")
    print(f"# sizes: {result.get('sizes', {})}")
    print(_format_table(result["rows"]))
    for key, value in result.get("ratios", {}).items():
        print(f"ratio {key}: {value:.3g}")
    if result.get("notes"):
        print(f"# {result['notes']}")
    out = args.json or pathlib.Path(__file__).parent / "results" / f"{args.name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    # strict JSON: a NaN or inf (a figure that could not be measured) is written as null
    out.write_text(json.dumps(_strict(result), indent=2, default=float, allow_nan=False))
    print(f"# wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
