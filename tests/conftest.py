import os
import pathlib
import shutil
import tempfile

# pytest-xdist runs one JAX process per worker; on a GPU each would otherwise take 75% of
# the device's memory on its first operation and the second worker would run out
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# The suite's volumes are tiny, so compiling dominates its time, and LLVM's optimisation
# of the generated code costs more than it saves: without it test_render.py and
# test_fit.py took 82-91 s instead of 101 s on 2 cores. Numerics are unchanged (these
# flags change code generation, not the HLO or its floating-point semantics). Code that
# runs long loops is slower so (an experiment's timings: 12 s -> 66 s), so the
# experiments run in their own processes with the user's flags, and the benchmarks do
# not go through this file.
_FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
os.environ.setdefault("VOLSHADE_TEST_USER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE}".strip()

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
    if _CACHE not in os.environ:
        os.environ[_CACHE] = tempfile.mkdtemp(prefix="volshade-test-xla-")
        config.volshade_owns_cache = True
    jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if getattr(config, "volshade_owns_cache", False):
        shutil.rmtree(os.environ.pop(_CACHE), ignore_errors=True)


@pytest.fixture(scope="session")
def data_dir() -> pathlib.Path:
    """The real-data folder from VOLSHADE_DATA (or ../shared/data); skips when absent."""
    path = pathlib.Path(os.environ.get("VOLSHADE_DATA", _SHARED))
    if not (path / "colin27_ch2_t1_head.nii.gz").exists():
        pytest.skip("real data not found: set VOLSHADE_DATA to the folder of shared/data")
    return path
