"""Every experiment runs at its small size (VOLSHADE_QUICK=1), so none can rot."""

import pathlib
import runpy

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
@pytest.mark.parametrize("script", sorted(CASES))
def test_experiment_runs_and_writes_its_results(script, tmp_path, monkeypatch, request):
    if script in NEEDS_DATA:
        monkeypatch.setenv("VOLSHADE_DATA", str(request.getfixturevalue("data_dir")))
    monkeypatch.setenv("VOLSHADE_QUICK", "1")
    monkeypatch.setenv("VOLSHADE_DOCS", str(tmp_path))
    runpy.run_path(str(EXPERIMENTS / script), run_name="__main__")
    figures, (table, line) = CASES[script]
    for figure in figures:
        assert (tmp_path / figure).stat().st_size > 10_000
    assert line in (tmp_path / table).read_text()
