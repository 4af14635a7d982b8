"""Every experiment runs at its small size (VOLSHADE_QUICK=1), so none can rot: with
``pytest --experiments`` (``.ci/run`` runs them so, after the suite), since they take
about 120 s of CPU, a fifth of the suite's time on 2 cores.

Each runs as a user runs it: a fresh Python process (float32, XLA's default
optimisation: the suite's compile-time flags would make their timed loops several
times slower)."""

import os
import pathlib
import subprocess
import sys

import pytest

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"

# script -> (figures it must write, (table, a line the table must hold))
CASES = {
    "contextual_ao_head.py": (["contextual_ao_head.png"],
                              ("contextual_ao_head.md", "| clip centre (voxels) |")),
    "feature_ao_brain.py": (["feature_ao_brain.png", "feature_ao_brain_radius.png"],
                            ("feature_ao_brain.md", "| white matter |")),
    "fit_head.py": (["fit_head.png"], ("fit_head.md", "| noisy images (sigma 0.02) |")),
    "lao_accuracy_cost.py": (["lao_accuracy_cost.png"],
                             ("lao_accuracy_cost.md", "| icosphere 42 |")),
    "corner_colour_bleeding.py": (["corner_obscurance_rho.png", "corner_obscurance_render.png"],
                                  ("corner_obscurance_rho.md", "| sqrt |")),
}

# skipped, with the reason, without the real data
NEEDS_DATA = {"contextual_ao_head.py", "feature_ao_brain.py", "fit_head.py"}


@pytest.mark.slow
@pytest.mark.experiment
@pytest.mark.parametrize("script", sorted(CASES))
def test_experiment_runs_and_writes_its_results(script, tmp_path, request):
    # the checkout's volshade, installed or not
    path = os.pathsep.join(filter(None, [str(EXPERIMENTS.parent), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "VOLSHADE_QUICK": "1", "VOLSHADE_DOCS": str(tmp_path),
           "XLA_FLAGS": os.environ.get("VOLSHADE_TEST_USER_XLA_FLAGS", ""), "PYTHONPATH": path}
    if script in NEEDS_DATA:
        env["VOLSHADE_DATA"] = str(request.getfixturevalue("data_dir"))
    run = subprocess.run([sys.executable, str(EXPERIMENTS / script)], env=env,
                         capture_output=True, text=True, timeout=900)
    # each script asserts what it shows (values against a full recompute or the truth,
    # orderings the paper's equations imply), then says so
    assert run.returncode == 0, run.stderr[-4000:]
    assert "checks passed" in run.stdout, run.stdout[-2000:]
    figures, (table, line) = CASES[script]
    for figure in figures:
        assert (tmp_path / figure).stat().st_size > 10_000
    assert line in (tmp_path / table).read_text()
