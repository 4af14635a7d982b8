import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from skimage import io

import volshade as vs
from volshade import cli


def test_render_command_writes_a_png(tmp_path):
    out = tmp_path / "new" / "folder" / "shells.png"  # made if missing, as demo's is
    rc = cli.main(["render", "shells", "--out", str(out), "--size", "16", "--image", "24",
                   "--preset", "shells", "--shading", "phong"])
    assert rc == 0
    img = io.imread(out)
    assert img.shape == (24, 24, 3)
    assert img.std() > 5  # not a blank frame: the phantom is visible against the background


def test_render_picks_the_volumes_preset_and_classification(tmp_path, monkeypatch):
    """Without --preset, the corner phantom gets its own preset, classified before
    interpolation (its walls are labels): the floor is white and the walls pure blue and
    green; the grey preset would draw the walls grey."""
    presets, classifications = [], []
    render, preset = cli.render, cli.transfer.preset

    def spy_render(scene, cam):
        classifications.append(scene.classification)  # static: known while traced
        return render(scene, cam)

    monkeypatch.setattr(cli, "render", spy_render)
    monkeypatch.setattr(cli.transfer, "preset", lambda name: presets.append(name) or preset(name))
    out = tmp_path / "corner.png"
    assert cli.main(["render", "corner", "--out", str(out), "--size", "16", "--image", "24"]) == 0
    assert (presets, classifications) == (["corner"], ["pre"])
    img = io.imread(out).astype(int)
    # the walls in their own blue and green, and a white (grey-level) floor
    assert (img[..., 1] - img[..., 0] > 60).any() and (img[..., 2] - img[..., 0] > 60).any()
    assert (np.ptp(img, axis=-1) < 3)[img.max(axis=-1) > 60].mean() > 0.2
    assert cli.main(["render", "shells", "--out", str(out), "--size", "16", "--image", "8"]) == 0
    assert (presets, classifications) == (["corner", "shells"], ["pre", "post"])


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_the_default_view_holds_the_whole_visible_volume(tmp_path, projection):
    # the corner phantom's walls reach the corners of its cube: at the old default
    # distance, 2.5, they ran off the image's bottom, left and right; the default view
    # now holds the sphere about the centre that holds them, and nothing touches the
    # border (the background is black)
    out = tmp_path / "corner.png"
    assert cli.main(["render", "corner", "--out", str(out), "--size", "16", "--image", "48",
                     "--projection", projection]) == 0
    img = io.imread(out).astype(int).max(axis=-1)
    border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
    assert border.max() == 0 and (img > 0).mean() > 0.2


def test_the_render_help_shows_defaults_and_options(monkeypatch, capsys):
    # in this process (`python -m volshade` runs in a subprocess in
    # test_an_image_past_the_index_range_is_an_error_not_a_traceback), at the width of a
    # pipe's help, 80 columns
    monkeypatch.setenv("COLUMNS", "80")
    with pytest.raises(SystemExit) as done:
        cli.main(["render", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "(default: 256)" in out and "--classification" in out


def test_demo_writes_pngs(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("VOLSHADE_DATA", str(tmp_path / "nothing-here"))
    monkeypatch.setattr("volshade.data._DEBIAN_CH2", tmp_path / "no-ch2.nii.gz")
    # --size 8: the phantom's LAO radius (size / 8 = 1 voxel) keeps the offset below it
    rc = cli.main(["demo", "--out", str(tmp_path / "demo"), "--size", "8", "--image", "20"])
    assert rc == 0
    # the skipped head says where it was looked for and how to get it (the first line
    # alone ended at "Searched:")
    out = capsys.readouterr().out
    assert "skipping the Colin27 head" in out and "set VOLSHADE_DATA" in out
    pngs = sorted(p.name for p in pathlib.Path(tmp_path / "demo").glob("*.png"))
    assert "shells_phong.png" in pngs and "shells_side_by_side.png" in pngs
    # three 20-pixel panels 4 pixels apart, under a band with their captions
    row = io.imread(tmp_path / "demo" / "shells_side_by_side.png")
    assert row.shape[1] == 3 * 20 + 2 * 4 and row.shape[0] > 20
    band = row[: row.shape[0] - 20, :20]
    assert np.any(band != band[0, 0])  # a caption is drawn on it


def test_cli_errors(tmp_path, capsys):
    assert cli.main(["render", "shells", "--out", str(tmp_path / "x.png"), "--preset", "nope",
                     "--size", "8", "--image", "8"]) == 2
    assert "unknown transfer-function preset 'nope'" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # features cannot be given on a command line
        cli.main(["render", "shells", "--out", str(tmp_path / "x.png"), "--ambient",
                  "feature_ao"])
    assert "invalid choice: 'feature_ao'" in capsys.readouterr().err
    # an unknown option: the command's usage and name, not the top-level parser's
    with pytest.raises(SystemExit):
        cli.main(["render", "shells", "--out", str(tmp_path / "x.png"), "--bogus"])
    err = capsys.readouterr().err
    assert "usage: volshade render" in err
    assert "volshade render: error: unrecognized arguments: --bogus" in err
    # every bad value: one line on stderr and exit status 2, as argparse's own errors
    bogus = tmp_path / "bogus.nii.gz"
    bogus.write_text("not an image")
    for argv, message in [
        (["render", "teapot", "--out", str(tmp_path / "x.png")], "unknown volume 'teapot'"),
        (["render", "shells", "--out", str(tmp_path / "x.png"), "--size", "0"],
         "--size must be >= 1"),
        (["render", str(bogus), "--out", str(tmp_path / "x.png")], "not an image nibabel"),
        (["render", "shells", "--out", str(tmp_path)], "--out must name a .png file"),
        (["render", "shells", "--out", str(tmp_path / "noext")], "--out must name a .png"),
        (["render", "shells", "--out", str(tmp_path / "x.png"), "--background", "0", "2", "0"],
         "--background must be three numbers in [0, 1] (R G B), got 0 2 0"),
        (["render", "shells", "--out", str(tmp_path / "x.png"), "--background", "0", "0",
          "-0.5"], "--background must be three numbers in [0, 1]"),
    ]:
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("volshade render: error: ") and message in err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert cli.main(["render", str(tmp_path / "missing.nii.gz"), "--out",
                     str(tmp_path / "x.png")]) == 2
    assert "missing.nii.gz" in capsys.readouterr().err
    # a run-time check (a NaN parameter) is reported like the others, without a traceback
    assert cli.main(["render", "shells", "--out", str(tmp_path / "x.png"), "--size", "8",
                     "--image", "8", "--background", "nan", "0", "0"]) == 2
    err = capsys.readouterr().err
    assert "volshade render: error: volshade.render: `scene.background` contains NaN" in err
    assert "Traceback" not in err and "EQX_ON_ERROR" not in err


def test_an_image_past_the_index_range_is_an_error_not_a_traceback(tmp_path):
    # found by a review: OverflowError's traceback. Run as a user runs it, in a process
    # of its own without the suite's x64 (with 64-bit indices the render would try to
    # allocate the image instead), through `python -m volshade`: the suite's one
    # subprocess of the CLI, which so also checks that the module runs the CLI
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    done = subprocess.run([sys.executable, "-m", "volshade", "render", "shells", "--out",
                           str(tmp_path / "x.png"), "--size", "8", "--image", "3000000000"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "volshade render: error: a size is too large to index" in done.stderr
    assert "Traceback" not in done.stderr


class _Built(Exception):
    """Stops `volshade render` once its Scene is built, with the Scene."""


def _scene_of(argv, monkeypatch):
    """The Scene that `volshade render ARGV` would render (the render is skipped)."""
    def built(**kwargs):
        raise _Built(vs.Scene(**kwargs))

    monkeypatch.setattr(cli, "Scene", built)
    with pytest.raises(_Built) as stop:
        cli.main(["render", *argv])
    return stop.value.args[0]


def test_out_of_memory_is_one_line_and_status_2(tmp_path, monkeypatch, capsys):
    # found by a review: --size 100000 ended in NumPy's MemoryError traceback and
    # --image 200000 in XLA's RESOURCE_EXHAUSTED (simulated here: the machine would swap)
    argv = ["render", "shells", "--out", str(tmp_path / "x.png"), "--size", "8"]
    for err in (MemoryError(), jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory")):
        def fail(args, err=err):
            raise err
        monkeypatch.setattr(cli, "render_command", fail)
        assert cli.main(argv) == 2
        assert "out of memory; lower --size or --image" in capsys.readouterr().err
    # other run-time errors are bugs: their traceback is kept
    monkeypatch.setattr(cli, "render_command", lambda args: (_ for _ in ()).throw(
        jax.errors.JaxRuntimeError("INTERNAL: something else")))
    with pytest.raises(jax.errors.JaxRuntimeError, match="INTERNAL"):
        cli.main(argv)


def test_ambient_options_in_mm_and_the_defaults_for_real_data(tmp_path, monkeypatch):
    nib = pytest.importorskip("nibabel")
    path = tmp_path / "head.nii.gz"  # real data, 2 mm voxels
    volume = np.random.default_rng(0).random((8, 9, 10)).astype(np.float32)
    nib.save(nib.Nifti1Image(volume, np.diag([2.0, 2.0, 2.0, 1.0])), path)
    out = ["--out", str(tmp_path / "x.png"), "--image", "8"]
    # real data: smoothed by one voxel edge and displayed with high 0.6 unless told
    def values(params, *names):
        return [float(getattr(params, name)) for name in names]

    params = _scene_of([str(path), *out, "--ambient", "obscurance"], monkeypatch).obscurance
    np.testing.assert_allclose(values(params, "smoothing", "high", "d_max"), [1.0, 0.6, 16.0],
                               rtol=1e-7)
    params = _scene_of([str(path), *out, "--ambient", "obscurance", "--smoothing", "0",
                        "--high", "1", "--d-max", "8", "--low", "0.1", "--colour-bleeding"],
                       monkeypatch).obscurance
    np.testing.assert_allclose(values(params, "smoothing", "high", "d_max", "low"),
                               [0.0, 1.0, 4.0, 0.1], rtol=1e-7)
    assert params.color_bleeding is True
    lao = _scene_of([str(path), *out, "--ambient", "lao", "--radius", "6", "--offset", "1"],
                    monkeypatch).lao
    np.testing.assert_allclose(values(lao, "radius", "offset"), [3.0, 0.5], rtol=1e-7)
    # phantoms (1 mm voxels): the ObscuranceParams defaults
    params = _scene_of(["shells", *out, "--size", "8", "--ambient", "obscurance"],
                       monkeypatch).obscurance
    np.testing.assert_allclose(values(params, "smoothing", "high", "d_max"), [0.0, 1.0, 32.0],
                               rtol=1e-7)
    # but the corner phantom's walls are labels, smoothed by one voxel edge: unsmoothed,
    # no wall voxel has a strictly denser neighbour and the obscurance is 1 everywhere
    params = _scene_of(["corner", *out, "--size", "8", "--ambient", "obscurance"],
                       monkeypatch).obscurance
    np.testing.assert_allclose(values(params, "smoothing", "high"), [1.0, 1.0], rtol=1e-7)


def test_options_that_do_not_apply_are_refused(tmp_path, capsys):
    out = ["--out", str(tmp_path / "x.png"), "--image", "8"]
    for argv, message in [
        (["shells", "--downsample", "2"], "--downsample applies to real data; for the "
                                          "phantom 'shells' use --size"),
        (["shells", "--radius", "3"], "--radius is read only with --ambient lao, got "
                                      "--ambient none"),
        (["shells", "--ambient", "lao", "--d-max", "3", "--colour-bleeding"],
         "--d-max and --colour-bleeding are read only with --ambient obscurance"),
        # an explicit 0 is given too (0.0 == False)
        (["shells", "--low", "0"], "--low is read only with --ambient obscurance"),
        (["shells", "--ambient", "lao", "--smoothing", "0.0"], "--smoothing is read only"),
        (["shells", "--offset", "0"], "--offset is read only with --ambient lao"),
        (["shells", "--ambient", "lao", "--radius", "1", "--offset", "2"],
         "--radius and --offset must be finite numbers with radius > offset >= 0 (mm), "
         "got 1 and 2"),
        (["shells", "--ambient", "lao", "--radius", "inf"], "got inf and 1"),
        (["shells", "--ambient", "obscurance", "--smoothing", "-1"],
         "--smoothing must be a finite number >= 0 (mm), got -1"),
        (["shells", "--ambient", "obscurance", "--d-max", "inf"],
         "--d-max must be a finite number > 0 (mm), got inf"),
        (["shells", "--ambient", "obscurance", "--low", "0.7", "--high", "0.2"],
         "--low must be <= --high, got 0.7 and 0.2."),
        # found by a review: NaN was reported as out of order
        (["shells", "--ambient", "obscurance", "--low", "nan"],
         "--low must be a finite number, got nan."),
        (["shells", "--projection", "orthographic", "--distance", "3"],
         "--distance applies to perspective views"),
        (["shells", "--ambient", "obscurance", "--low", "1.5"],
         "--low must be <= --high, got 1.5 and 1 (the default for phantoms)"),
    ]:
        assert cli.main(["render", *argv, *out]) == 2
        err = capsys.readouterr().err
        assert err.startswith("volshade render: error: ") and message in err, err
    # (the checks come before the file is read)
    bogus = tmp_path / "x.nii.gz"
    assert cli.main(["render", str(bogus), *out, "--size", "16"]) == 2
    assert "--size sets a phantom's edge" in capsys.readouterr().err
    assert cli.main(["render", str(bogus), *out, "--radius", "3"]) == 2
    assert "--radius is read only with --ambient lao" in capsys.readouterr().err
    assert cli.main(["render", str(bogus), *out, "--ambient", "obscurance", "--low",
                     "0.7"]) == 2
    assert "got 0.7 and 0.6 (the default for real data)" in capsys.readouterr().err
