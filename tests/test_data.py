"""Tests for volshade.data: phantoms, NIfTI loading and the real-data lookup."""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.measure import label

from volshade import data

nib = pytest.importorskip("nibabel")

SHAPES = [(16, 16, 16), (17, 24, 32)]


def _runs(profile: np.ndarray) -> list[float]:
    """Values of the maximal constant non-zero runs of a 1-D profile, in order."""
    out: list[float] = []
    prev = 0.0
    for v in profile:
        if v != 0.0 and v != prev:
            out.append(float(v))
        prev = v
    return out


# ------------------------------------------------------------------------------------------
# Phantoms: generic properties
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("name", data.PHANTOMS)
def test_phantom_shape_dtype_range(name, shape):
    vol = data.phantom(name, shape=shape)
    assert isinstance(vol, jax.Array)
    assert vol.shape == shape
    assert vol.dtype == jnp.float32  # float32 even though the test suite runs with x64
    v = np.asarray(vol)
    assert np.all(np.isfinite(v))
    assert v.min() >= 0.0 and v.max() <= 1.0
    assert v.max() > 0.0  # not empty


@pytest.mark.parametrize("name", data.PHANTOMS)
def test_phantom_deterministic(name):
    a = data.phantom(name, shape=20, seed=3)
    b = data.phantom(name, shape=20, seed=3)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_phantom_default_shape_and_int_shape():
    assert data.phantom("shells").shape == (64, 64, 64)
    np.testing.assert_array_equal(np.asarray(data.phantom("orange", shape=24)),
                                  np.asarray(data.phantom("orange", shape=(24, 24, 24))))
    np.testing.assert_array_equal(np.asarray(data.phantom("corner", shape=np.int64(20))),
                                  np.asarray(data.phantom("corner", shape=[20, 20, 20])))


def test_phantom_under_jit_is_a_constant():
    eager = data.phantom("shells", shape=16)
    jitted = jax.jit(lambda: data.phantom("shells", shape=16))()
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))
    # and it feeds differentiable code directly
    g = jax.grad(lambda s: jnp.sum(s * eager.astype(jnp.float64)))(jnp.float64(2.0))
    assert np.isclose(float(g), float(np.asarray(eager, np.float64).sum()))


@pytest.mark.parametrize("bad", [0, -4, (16, 16), (16, 16, 0), (16, -1, 16), 16.0, True,
                                 "16", (16, 16, 16.5), (16, 16, 16, 16), None])
def test_phantom_bad_shape(bad):
    with pytest.raises(ValueError, match=r"volshade\.data\.phantom: `shape`"):
        data.phantom("shells", shape=bad)


def test_phantom_unknown_name_lists_valid():
    with pytest.raises(ValueError, match="volshade.data.phantom") as info:
        data.phantom("sphere", shape=16)
    for name in data.PHANTOMS:
        assert repr(name) in str(info.value)


@pytest.mark.parametrize("seed", [1.5, "0", True, None])
def test_phantom_bad_seed(seed):
    with pytest.raises(TypeError, match="`seed`"):
        data.phantom("noise", shape=16, seed=seed)


# ------------------------------------------------------------------------------------------
# Phantoms: each one's geometry
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [16, 32, 64])
def test_shells_three_rising_levels(n):
    v = np.asarray(data.phantom("shells", shape=n))
    levels = tuple(np.float32(x) for x in data.SHELL_VALUES)
    assert set(np.unique(v).tolist()) == {0.0, *[float(x) for x in levels]}
    c = n // 2
    # Walking from the centre outwards along each axis (both ways) we meet the inner shell
    # (densest) first, then the middle, then the outer one, separated by empty space.
    rising_inwards = [float(x) for x in levels[::-1]]
    for profile in (v[c, c, c:], v[c, c, c::-1], v[c, c:, c], v[c::-1, c, c], v[c:, c, c]):
        assert _runs(profile) == rising_inwards
        nonzero = np.flatnonzero(profile)
        assert np.any(profile[nonzero[0]:nonzero[-1]] == 0.0)  # gaps between shells
    assert v[0, 0, 0] == 0.0 and v[c, c, c] == 0.0  # empty outside and at the very centre


@pytest.mark.parametrize("shape", [(32, 32, 32), (32, 48, 64), (8, 8, 8)])
def test_corner_walls(shape):
    v = np.asarray(data.phantom("corner", shape=shape))
    td, th, tw = (max(2, n // 16) for n in shape)
    white, blue, green = (np.float32(data.CORNER_VALUES[k]) for k in ("white", "blue", "green"))
    assert (white, blue, green) == (1.0, 0.75, 0.5)
    assert np.all(v[:td] == white)  # floor at small d, wins where it meets the others
    assert np.all(v[td:, :, :tw] == blue)  # wall at small w (max with green at the edge)
    assert np.all(v[td:, :th, tw:] == green)  # wall at small h
    assert np.all(v[td:, th:, tw:] == 0.0)  # empty interior
    assert set(np.unique(v).tolist()) == {0.0, 0.5, 0.75, 1.0}


def test_corner_paper_size():
    v = np.asarray(data.phantom("corner", shape=128))
    assert np.all(v[:8] == 1.0) and np.all(v[8:, 8:, 8:] == 0.0)
    assert v[8, 7, 64] == 0.5 and v[8, 64, 7] == 0.75


@pytest.mark.parametrize("n", [32, 64])
def test_orange_layers_and_segments(n):
    v = np.asarray(data.phantom("orange", shape=n))
    vals = {k: float(np.float32(x)) for k, x in data.ORANGE_VALUES.items()}
    assert set(np.unique(v).tolist()) == {0.0, vals["flesh"], vals["pith"], vals["peel"]}
    c = n // 2
    # From outside along the w axis: peel, then pith, then flesh (in a segment's middle).
    profile = v[c, c, ::-1][: n // 2]
    assert _runs(profile)[:3] == [vals["peel"], vals["pith"], vals["flesh"]]
    # The flesh of the equatorial slice is cut into 10 segments by the membranes.
    flesh = v[c] == vals["flesh"]
    assert label(flesh, connectivity=1).max() == 10


def test_fullerene_layout():
    verts, edges = data._fullerene()
    assert verts.shape == (60, 3) and edges.shape == (90, 2)
    radii = np.linalg.norm(verts, axis=1)
    np.testing.assert_allclose(radii, radii[0])
    degree = np.bincount(edges.ravel(), minlength=60)
    assert np.all(degree == 3)  # every carbon has three bonds


def test_bucky_sixty_balls():
    v = np.asarray(data.phantom("bucky", shape=64))
    # Above the bond peak only the balls remain: 60 separate blobs.
    above = v > data.BUCKY_VALUES["bond"] + 0.1
    assert label(above, connectivity=1).max() == 60
    assert v[32, 32, 32] == 0.0  # hollow
    # bonds are there: the whole cage is one connected object
    assert label(v > 0.05, connectivity=3).max() == 1


def test_noise_seeded_and_smooth():
    a = np.asarray(data.phantom("noise", shape=24, seed=0))
    b = np.asarray(data.phantom("noise", shape=24, seed=1))
    assert not np.array_equal(a, b)
    assert a.min() == 0.0 and a.max() == 1.0
    # smoothed: neighbouring voxels differ far less than white noise would
    assert np.mean(np.abs(np.diff(a, axis=0))) < 0.1
    c = np.asarray(data.phantom("noise", shape=(1, 1, 1)))
    assert c.shape == (1, 1, 1) and np.all(c == 0.0)


# ------------------------------------------------------------------------------------------
# NIfTI loading
# ------------------------------------------------------------------------------------------


def _write(path: pathlib.Path, arr: np.ndarray, affine: np.ndarray) -> pathlib.Path:
    nib.save(nib.Nifti1Image(arr, affine), str(path))
    return path


@pytest.fixture
def xyz() -> np.ndarray:
    return np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6) * 3 - 7


def test_load_nifti_roundtrip_transposes_to_zyx(tmp_path, xyz):
    path = _write(tmp_path / "tiny.nii.gz", xyz, np.diag([1.0, 2.0, 3.0, 1.0]))
    vol, spacing = data.load_nifti(path, normalize=False)
    assert vol.shape == (6, 5, 4) and vol.dtype == jnp.float32
    assert spacing == (3.0, 2.0, 1.0) and all(type(s) is float for s in spacing)
    np.testing.assert_array_equal(np.asarray(vol), np.transpose(xyz, (2, 1, 0)).astype(np.float32))
    assert np.asarray(vol)[5, 4, 3] == xyz[3, 4, 5]


def test_load_nifti_normalize(tmp_path, xyz):
    path = _write(tmp_path / "tiny.nii", xyz, np.eye(4))
    vol, _ = data.load_nifti(str(path))  # normalize=True by default; str paths work
    v = np.asarray(vol)
    assert v.min() == 0.0 and v.max() == 1.0
    expected = (xyz - xyz.min()) / (xyz.max() - xyz.min())
    np.testing.assert_allclose(v, np.transpose(expected, (2, 1, 0)), rtol=1e-6)
    const = _write(tmp_path / "const.nii", np.full((3, 3, 3), 5.0, np.float32), np.eye(4))
    assert np.all(np.asarray(data.load_nifti(const)[0]) == 0.0)
    with pytest.raises(TypeError, match="`normalize` must be True or False"):
        data.load_nifti(path, normalize="no")  # a truthy string would normalise


def test_load_nifti_reorients_to_ras(tmp_path, xyz):
    # A LPS image (x and y flipped) and one whose voxel axes are permuted (i -> y, j -> x).
    lps = _write(tmp_path / "lps.nii", xyz, np.diag([-1.0, -2.0, 3.0, 1.0]))
    vol, spacing = data.load_nifti(lps, normalize=False)
    np.testing.assert_array_equal(np.asarray(vol), np.transpose(xyz[::-1, ::-1, :], (2, 1, 0)))
    assert spacing == (3.0, 2.0, 1.0)
    perm = np.array([[0.0, 1.5, 0, 0], [2.5, 0, 0, 0], [0, 0, 0.5, 0], [0, 0, 0, 1]])
    img = nib.load(str(_write(tmp_path / "perm.nii", xyz, perm)))
    vol, spacing = data.load_nifti(tmp_path / "perm.nii", normalize=False)
    # voxel axis j (5 long, 1.5 mm) is x; axis i (4 long, 2.5 mm) is y
    assert vol.shape == (6, 4, 5) and spacing == (0.5, 2.5, 1.5)
    np.testing.assert_array_equal(np.asarray(vol), np.transpose(xyz, (2, 0, 1)))
    assert nib.aff2axcodes(img.affine) == ("A", "R", "S")


def test_load_nifti_spacing_follows_the_affine_not_pixdim(tmp_path, xyz):
    # pixdim (1, 1, 1) disagreeing with the affine's (2, 3, 4) mm: the same geometry stored
    # as RAS (not reoriented) or LAS (reoriented) must give the same spacing
    spacings = []
    for name, sign in (("ras.nii", 1.0), ("las.nii", -1.0)):
        img = nib.Nifti1Image(xyz, np.diag([2.0 * sign, 3.0, 4.0, 1.0]))
        img.header.set_zooms((1.0, 1.0, 1.0))
        nib.save(img, str(tmp_path / name))
        spacings.append(data.load_nifti(tmp_path / name, normalize=False)[1])
    assert spacings == [(4.0, 3.0, 2.0), (4.0, 3.0, 2.0)]


def test_load_nifti_4d(tmp_path, xyz):
    single = _write(tmp_path / "one.nii", xyz[..., None], np.eye(4))
    vol, _ = data.load_nifti(single, normalize=False)
    np.testing.assert_array_equal(np.asarray(vol), np.transpose(xyz, (2, 1, 0)))
    series = _write(tmp_path / "two.nii", np.stack([xyz, xyz], -1), np.eye(4))
    with pytest.raises(ValueError, match="4-D"):
        data.load_nifti(series)


def test_load_nifti_nan_is_refused(tmp_path):
    arr = np.ones((3, 3, 3), np.float32)
    arr[1, 1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        data.load_nifti(_write(tmp_path / "nan.nii", arr, np.eye(4)))


def test_load_nifti_refuses_what_float32_cannot_hold_and_normalizes_huge_ranges(tmp_path):
    # found by a review: 1e40 was checked finite in float64, then returned as inf; and
    # normalising +-1.7e308 overflowed hi - lo (NaN)
    arr = np.ones((3, 3, 3), np.float64)
    arr[0, 0, 0] = 1e40
    path = _write(tmp_path / "big.nii", arr, np.eye(4))
    with pytest.raises(ValueError, match="beyond float32's range"):
        data.load_nifti(path, normalize=False)
    vol, _ = data.load_nifti(path, normalize=True)
    assert float(vol.max()) == 1.0 and float(vol.min()) == 0.0
    arr[1, 1, 1] = -1.7e308
    arr[2, 2, 2] = 1.7e308
    vol, _ = data.load_nifti(_write(tmp_path / "huge.nii", arr, np.eye(4)), normalize=True)
    assert np.all(np.isfinite(vol)) and float(vol.max()) == 1.0 and float(vol.min()) == 0.0
    np.testing.assert_allclose(float(vol[1, 1, 1]), 0.0)


def test_load_nifti_downsample(tmp_path):
    arr = np.arange(4 * 6 * 8, dtype=np.float32).reshape(4, 6, 8)
    path = _write(tmp_path / "ds.nii", arr, np.diag([1.0, 2.0, 3.0, 1.0]))
    vol, spacing = data.load_nifti(path, normalize=False, downsample=2)
    assert vol.shape == (4, 3, 2) and spacing == (6.0, 4.0, 2.0)
    zyx = np.transpose(arr, (2, 1, 0))
    np.testing.assert_allclose(np.asarray(vol)[1, 2, 0], zyx[2:4, 4:6, 0:2].mean())
    with pytest.raises(ValueError, match="`downsample`"):
        data.load_nifti(path, downsample=0)
    # partial blocks at the far faces average the voxels they hold (they were padded with
    # zeros: a uniform 5^3 volume came out 100, 100, 50 along an axis; found by a review)
    path = _write(tmp_path / "uniform.nii", np.full((5, 5, 7), 100.0, np.float32), np.eye(4))
    vol, _ = data.load_nifti(path, normalize=False, downsample=2)
    assert vol.shape == (4, 3, 3)
    np.testing.assert_allclose(np.asarray(vol), 100.0, rtol=1e-6)
    vol, _ = data.load_nifti(path, normalize=False, downsample=3)
    np.testing.assert_allclose(np.asarray(vol), 100.0, rtol=1e-6)
    arr = np.random.default_rng(0).random((5, 6, 7)).astype(np.float32)
    vol, _ = data.load_nifti(_write(tmp_path / "rand.nii", arr, np.eye(4)), normalize=False,
                             downsample=4)
    np.testing.assert_allclose(np.asarray(vol)[1, 1, 1], np.transpose(arr)[4:, 4:, 4:].mean(),
                               rtol=1e-6)


def test_load_nifti_missing_file(tmp_path):
    missing = tmp_path / "nope.nii.gz"
    with pytest.raises(FileNotFoundError, match="nope.nii.gz"):
        data.load_nifti(missing)
    with pytest.raises(IsADirectoryError, match="`path` is a folder, not a NIfTI file"):
        data.load_nifti(tmp_path)  # (a review: it said "no such file")
    bogus = tmp_path / "bogus.nii.gz"
    bogus.write_text("not an image")
    with pytest.raises(ValueError, match="bogus.nii.gz' is not an image nibabel can read"):
        data.load_nifti(bogus)
    # found by a review: os.fspath's and NumPy's messages, naming neither argument nor file
    for path in (None, 3):
        with pytest.raises(TypeError, match=r"load_nifti: `path` must be a file path \(str or "
                                            r"os.PathLike\), got"):
            data.load_nifti(path)
    empty = _write(tmp_path / "empty.nii", np.zeros((4, 0, 3), np.float32), np.eye(4))
    with pytest.raises(ValueError, match=r"empty.nii' has shape \(4, 0, 3\): no voxels"):
        data.load_nifti(empty)


def test_load_nifti_refuses_cut_short_and_complex_files(tmp_path, xyz):
    noise = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)  # incompressible
    whole = _write(tmp_path / "whole.nii.gz", noise, np.eye(4)).read_bytes()
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(whole[: int(len(whole) * 0.9)])  # the header reads, the voxels do not
    with pytest.raises(ValueError, match="could not be read whole"):
        data.load_nifti(cut)
    # get_fdata would keep the real part, with only a NumPy warning
    complex_path = _write(tmp_path / "complex.nii", xyz.astype(np.complex64), np.eye(4))
    with pytest.raises(ValueError, match="holds complex64 voxels"):
        data.load_nifti(complex_path)


def test_load_nifti_without_nibabel(tmp_path, xyz, monkeypatch):
    path = _write(tmp_path / "tiny.nii", xyz, np.eye(4))
    monkeypatch.setitem(sys.modules, "nibabel", None)
    with pytest.raises(ImportError, match=r'pip install "volshade\[data\]"'):
        data.load_nifti(path)


# ------------------------------------------------------------------------------------------
# Real data lookup
# ------------------------------------------------------------------------------------------


def test_load_colin27(data_dir, monkeypatch):
    monkeypatch.setenv("VOLSHADE_DATA", str(data_dir))
    path = data.data_path("colin27")
    assert path == data_dir / "colin27_ch2_t1_head.nii.gz"
    vol, spacing = data.load("colin27")
    assert vol.shape == (181, 217, 181) and vol.dtype == jnp.float32
    assert spacing == (1.0, 1.0, 1.0)
    v = np.asarray(vol)
    assert v.min() == 0.0 and v.max() == 1.0
    raw = np.asarray(nib.load(str(path)).dataobj).astype(np.float64)  # (x, y, z), RAS already
    expected = np.transpose((raw - raw.min()) / (raw.max() - raw.min()), (2, 1, 0))
    np.testing.assert_allclose(v, expected, atol=1e-6)
    # d is z (inferior -> superior): the top of the head is empty, the neck is not.
    assert v[-3].max() == 0.0 and v[3].max() > 0.1


def test_load_mni152_downsampled(data_dir, monkeypatch):
    monkeypatch.setenv("VOLSHADE_DATA", str(data_dir))
    vol, spacing = data.load("mni152", downsample=4)
    assert vol.shape == (48, 59, 50) and spacing == (4.0, 4.0, 4.0)
    v = np.asarray(vol)
    assert v.min() >= 0.0 and v.max() <= 1.0 and v.max() > 0.5
    for name in ("mni152_gm", "mni152_wm"):
        assert data.data_path(name).is_file()


def test_data_path_search_order(tmp_path, monkeypatch):
    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    second.mkdir()
    (second / "mni152_2009a_wm.nii.gz").write_bytes(b"")
    (first / "mni152_2009a_wm.nii.gz").write_bytes(b"")
    monkeypatch.setenv("VOLSHADE_DATA", f"{tmp_path / 'missing'}:{second}:{first}")
    assert data.data_path("mni152_wm") == second / "mni152_2009a_wm.nii.gz"
    # Debian's mricron-data location is the fallback for colin27
    ch2 = tmp_path / "ch2.nii.gz"
    ch2.write_bytes(b"")
    monkeypatch.setattr(data, "_DEBIAN_CH2", ch2)
    assert data.data_path("colin27") == ch2
    monkeypatch.delenv("VOLSHADE_DATA")
    assert data.data_path("colin27") == ch2


@pytest.mark.parametrize("name", data.DATASETS)
def test_missing_data_says_how_to_get_it(name, tmp_path, monkeypatch):
    monkeypatch.setenv("VOLSHADE_DATA", str(tmp_path))
    monkeypatch.setattr(data, "_DEBIAN_CH2", tmp_path / "no" / "ch2.nii.gz")
    for fn in (data.data_path, data.load):
        with pytest.raises(FileNotFoundError) as info:
            fn(name)
        msg = str(info.value)
        assert "VOLSHADE_DATA" in msg and "mricron-data" in msg and "nilearn==0.14.1" in msg
        assert str(tmp_path) in msg


def test_unknown_dataset_lists_names():
    for fn in (data.data_path, data.load):
        with pytest.raises(ValueError) as info:
            fn("colin")
        for name in data.DATASETS:
            assert repr(name) in str(info.value)


def test_load_bad_downsample(data_dir, monkeypatch):
    monkeypatch.setenv("VOLSHADE_DATA", str(data_dir))
    with pytest.raises(ValueError, match="`downsample`"):
        data.load("colin27", downsample=0)
    with pytest.raises(TypeError, match="`downsample`"):
        data.load("colin27", downsample=2.0)
    with pytest.raises(TypeError, match="`normalize` must be True or False"):
        data.load("colin27", normalize=None)


def test_load_points_a_file_path_to_load_nifti(tmp_path, xyz):
    path = _write(tmp_path / "tiny.nii.gz", xyz, np.eye(4))
    for given in (path, str(path), "missing.nii"):
        with pytest.raises(ValueError, match=r"names a file, not a dataset; read a NIfTI "
                                             r"file with volshade.data.load_nifti\(path\)"):
            data.load(given)
    with pytest.raises(ValueError, match="unknown dataset name 'colin28'"):
        data.load("colin28")
