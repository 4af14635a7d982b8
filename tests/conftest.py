import os
import pathlib

# pytest-xdist runs one JAX process per worker; on a GPU each would otherwise take 75% of
# the device's memory on its first operation and the second worker would run out
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

_SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def data_dir() -> pathlib.Path:
    """The real-data folder from VOLSHADE_DATA (or ../shared/data); skips when absent."""
    path = pathlib.Path(os.environ.get("VOLSHADE_DATA", _SHARED))
    if not (path / "colin27_ch2_t1_head.nii.gz").exists():
        pytest.skip("real data not found: set VOLSHADE_DATA to the folder of shared/data")
    return path
