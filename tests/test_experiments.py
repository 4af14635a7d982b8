"""Every experiment runs at its small size, so none can rot."""

import pathlib
import runpy

import pytest

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"


@pytest.mark.slow
def test_lao_accuracy_cost(tmp_path, monkeypatch):
    monkeypatch.setenv("VOLSHADE_QUICK", "1")
    monkeypatch.setenv("VOLSHADE_DOCS", str(tmp_path))
    runpy.run_path(str(EXPERIMENTS / "lao_accuracy_cost.py"), run_name="__main__")
    assert (tmp_path / "lao_accuracy_cost.png").stat().st_size > 10_000
    assert "| icosphere 42 |" in (tmp_path / "lao_accuracy_cost.md").read_text()


@pytest.mark.slow
def test_corner_colour_bleeding(tmp_path, monkeypatch):
    monkeypatch.setenv("VOLSHADE_QUICK", "1")
    monkeypatch.setenv("VOLSHADE_DOCS", str(tmp_path))
    runpy.run_path(str(EXPERIMENTS / "corner_colour_bleeding.py"), run_name="__main__")
    assert (tmp_path / "corner_obscurance_rho.png").stat().st_size > 10_000
    assert (tmp_path / "corner_obscurance_render.png").stat().st_size > 10_000
    assert "| sqrt |" in (tmp_path / "corner_obscurance_rho.md").read_text()
