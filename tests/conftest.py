import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

# pytest-xdist runs one JAX process per worker; on a GPU each would otherwise take 75% of
# the device's memory on its first operation and the second worker would run out
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# The suite's volumes are tiny, so compiling dominates its time, and LLVM's optimisation
# of the generated code costs more than it saves: without it test_lao.py and
# test_hard_cases.py take 104 s instead of 70 s on 2 cores (the whole suite ~15 min
# instead of ~9). XLA's older elemental emitters (instead of its fusion emitters) compile
# in about half the time: 33 s -> 18 s of compiling for 15 tests of test_render.py and
# test_transforms.py. These flags change code generation, not the HLO: results agree
# with the default build to a few float32 ulps (a 12^3 float32 render: 3e-7), and a
# vmapped program may round differently from the unbatched one by an ulp. One known
# miscompile of the pair (jaxlib 0.10.2): a float64 orthographic render of a (1, 5, 1)
# volume reads a wrong voxel (an error of 0.11; either flag alone, or the default build,
# is exact), so a render test that fails here alone is checked with the default build
# (a level set by the user, `XLA_FLAGS=--xla_backend_optimization_level=2 pytest ...`,
# keeps this file from setting any flag). Code that runs long loops is slower so (an
# experiment's timings: 12 s -> 66 s), so the experiments run in their own processes
# with the user's flags, and the benchmarks do not go through this file.
_FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
_OLD_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flags: str) -> bool:
    """Whether this jaxlib knows ``flags`` (XLA aborts the process on an unknown flag,
    and flags come and go between versions)."""
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    try:
        return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                              timeout=120).returncode == 0
    except subprocess.TimeoutExpired:
        return False


os.environ.setdefault("VOLSHADE_TEST_USER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
# set once, in the first process (pytest-xdist's workers inherit the environment), and
# never over a choice of the user's
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    _flags = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE}".strip()
    if "xla_cpu_use_fusion_emitters" not in _flags and _xla_accepts(f"{_flags} {_OLD_EMITTERS}"):
        _flags = f"{_flags} {_OLD_EMITTERS}"
    os.environ["XLA_FLAGS"] = _flags

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

_SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"
_CACHE = "VOLSHADE_TEST_COMPILATION_CACHE"


def pytest_configure(config):
    # One compilation cache for the test session, in a fresh folder that the pytest-xdist
    # workers inherit through the environment: many tests build the same XLA program
    # under a different Python function (a new lambda, a new Module), which the in-memory
    # caches of jit cannot see. Nothing outlives the session, so every run starts cold.
    # Only programs that took 0.3 s or more to compile are written: writing every one
    # (most compile in milliseconds) cost more than the hits saved (two sets of three
    # test files on 2 cores, summed: 214 s caching all, 209 s without a cache, 184-193 s
    # from 0.1-0.3 s, 238 s from 1 s).
    if _CACHE not in os.environ:
        os.environ[_CACHE] = tempfile.mkdtemp(prefix="volshade-test-xla-")
        config.volshade_owns_cache = True
    jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.3)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if getattr(config, "volshade_owns_cache", False):
        shutil.rmtree(os.environ.pop(_CACHE), ignore_errors=True)


def pytest_addoption(parser):
    parser.addoption("--experiments", action="store_true",
                     help="also run every experiment script at its small size (about 2 min "
                          "of CPU; .ci/run does, in a second pytest run)")
    parser.addoption("--dry-runs", action="store_true",
                     help="also run the GPU benchmarks' scripts at tiny sizes on the CPU "
                          "(about 1.5 min of CPU; .ci/run does, in a second pytest run)")


_SLOW_DOCTESTS = {"volshade/fit.py::volshade.fit.fit"}


def pytest_collection_modifyitems(config, items):
    # the experiments (real data, subprocesses at XLA's default optimisation: 120 s of
    # CPU, a fifth of the suite's) and the benchmarks' dry runs run when asked for, as
    # CI does
    for option, marker, what in (("--experiments", "experiment", "an experiment script"),
                                 ("--dry-runs", "dry_run", "a benchmark's dry run")):
        if config.getoption(option):
            continue
        skip = pytest.mark.skip(reason=f"{what}: run with {option} (.ci/run does)")
        for item in items:
            if item.get_closest_marker(marker):
                item.add_marker(skip)
    # docstring examples that take 6 s or more (a fit compiles its solver: 13 s); without
    # the mark, collected last, it ran at the very end of the session
    for item in items:
        if item.nodeid in _SLOW_DOCTESTS:
            item.add_marker(pytest.mark.slow)
    # the slow tests first (the sort is stable): pytest-xdist hands tests out in
    # collection order, and a long test started last keeps one core busy alone
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session")
def data_dir() -> pathlib.Path:
    """The real-data folder from VOLSHADE_DATA (or ../shared/data); skips when absent."""
    path = pathlib.Path(os.environ.get("VOLSHADE_DATA", _SHARED))
    if not (path / "colin27_ch2_t1_head.nii.gz").exists():
        pytest.skip("real data not found: set VOLSHADE_DATA to the folder of shared/data")
    return path
