"""The corner colour-bleeding experiment runs (quick mode) and writes its figure and table."""

import pathlib
import runpy

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "corner_colour_bleeding.py"


@pytest.mark.slow
def test_corner_colour_bleeding_experiment(tmp_path, monkeypatch):
    monkeypatch.setenv("VOLSHADE_QUICK", "1")
    monkeypatch.setenv("VOLSHADE_DOCS", str(tmp_path))
    runpy.run_path(str(SCRIPT), run_name="__main__")
    assert (tmp_path / "corner_obscurance_rho.png").stat().st_size > 10_000
    assert "| sqrt |" in (tmp_path / "corner_obscurance_rho.md").read_text()
