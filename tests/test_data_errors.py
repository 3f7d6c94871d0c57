"""Every user-caused problem with an input volume raises ApmgsrnError naming the file."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import netCDF4
import numpy as np
import pytest

from apmgsrn.data import check_finite, open_volume, parse_shape
from apmgsrn.errors import ApmgsrnError

VTI = "viscous_fingers_run01/030_density_030_064_2.0.vti"  # in tests/data


def _raises(path: Path, *fragments: str, **kwargs) -> str:
    """Open `path`, expect ApmgsrnError whose one-line message names the file and the fragments."""
    with pytest.raises(ApmgsrnError) as caught:
        open_volume(path, **kwargs)
    message = str(caught.value)
    assert str(path) in message
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


@pytest.fixture(scope="module")
def block(test_data: Path) -> np.ndarray:
    """A real 24x20x16 (z, y, x) block of the Richtmyer-Meshkov volume as float32.

    The voxels [100:124, 80:100, 30:46] of the 256^3 source; the crop starts at (88, 64, 0).
    """
    volume = open_volume(test_data / "richtmyer_meshkov_t20_96x64x48_uint8.raw")
    return volume.read(slice(12, 36), slice(16, 36), slice(30, 46))


def _netcdf(path: Path, variables: dict[str, tuple[tuple[str, ...], np.ndarray]]) -> Path:
    with netCDF4.Dataset(path, "w") as handle:
        for dims, data in variables.values():
            for name, size in zip(dims, data.shape):
                if name not in handle.dimensions:
                    handle.createDimension(name, size)
        for name, (dims, data) in variables.items():
            handle.createVariable(name, "f4", dims)[:] = data
    return path


# ----------------------------------------------------------------------------- paths and formats
def test_missing_file(tmp_path: Path) -> None:
    _raises(tmp_path / "nowhere.nc", "no such file")


def test_unknown_suffix_lists_the_supported_ones(test_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "volume.xyz"
    shutil.copy(test_data / "neghip_64x64x64_uint8.raw", path)
    _raises(path, "'.xyz'", ".nc", ".h5", ".raw", ".npy", ".vti", "Zarr")


def test_directory_that_is_not_zarr(tmp_path: Path) -> None:
    (tmp_path / "folder").mkdir()
    _raises(tmp_path / "folder", "not a Zarr store")
    (tmp_path / "empty.zarr").mkdir()
    _raises(tmp_path / "empty.zarr", "not a readable Zarr")


@pytest.mark.parametrize("suffix", [".nc", ".h5", ".hdf5", ".vti", ".vtr"])
def test_garbage_bytes_under_a_known_suffix(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    _raises(path, "not a readable")


@pytest.mark.parametrize("content", [b"", b"hello\n", bytes(range(256)) * 16])
def test_a_file_without_numpys_header_is_not_an_npy_array(tmp_path: Path, content: bytes) -> None:
    """Named .npy but not written by numpy.save (empty, text, garbage): said so, without numpy's advice to
    load it as a pickle."""
    path = tmp_path / "volume.npy"
    path.write_bytes(content)
    message = _raises(path, "not a .npy array (it lacks numpy's header)")
    assert "pickle" not in message


@pytest.mark.parametrize("name", ["miranda_density_80x64x48.nc", "darkmatter_density_64.h5", VTI])
def test_truncated_real_file(test_data: Path, tmp_path: Path, name: str) -> None:
    path = tmp_path / Path(name).name
    path.write_bytes((test_data / name).read_bytes()[:20_000])
    with pytest.raises(ApmgsrnError) as caught:
        # Some libraries only notice a missing tail when the data is read.
        open_volume(path).to_numpy()
    assert str(path) in str(caught.value)


def test_truncated_npy(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "cut.npy"
    np.save(path, block)
    path.write_bytes(path.read_bytes()[:5000])
    _raises(path, "not a readable .npy")


def test_vtk_missing_says_how_to_install(test_data: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "vtkmodules", None)
    _raises(test_data / VTI, "pip install apmgsrn[vtk]")


def test_importing_the_package_loads_no_optional_extra() -> None:
    code = ("import sys, apmgsrn, apmgsrn.data; "
            "print(sorted(m for m in ('vtk', 'vtkmodules', 'torch') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


# ----------------------------------------------------------------------------- raw files
def test_truncated_raw_names_both_sizes(test_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "neghip_64x64x64_uint8.raw"
    path.write_bytes((test_data / "neghip_64x64x64_uint8.raw").read_bytes()[:200_000])
    _raises(path, "200000 bytes", "262144 bytes", "truncated")


def test_wrong_shape_for_a_raw_file(test_data: Path) -> None:
    path = test_data / "c60_80x64x48_uint8.raw"
    _raises(path, "245760 bytes", "80x64x24", "shape=", shape=(80, 64, 24))
    # Right voxel count, wrong type: the size fits 1-byte voxels, not 2.
    _raises(path, "491520 bytes", "1-byte voxels", dtype="uint16")


def test_raw_without_dims_or_dtype(test_data: Path, tmp_path: Path) -> None:
    path = tmp_path / "volume.raw"
    shutil.copy(test_data / "neghip_64x64x64_uint8.raw", path)
    _raises(path, "shape=X,Y,Z and dtype=TYPE", "NAME_XxYxZ_dtype.raw")
    _raises(path, "dtype=TYPE", shape=(64, 64, 64))
    _raises(path, "unknown voxel type 'complex64'", shape=(64, 64, 64), dtype="complex64")
    assert open_volume(path, shape=(64, 64, 64), dtype="uint8").shape == (64, 64, 64)


def test_flags_that_do_not_apply(test_data: Path, hcci_oh: Path) -> None:
    _raises(hcci_oh, "shape=", shape=(187, 187, 187))
    _raises(test_data / "c60_80x64x48_uint8.raw", "variable=", variable="density")
    _raises(test_data / "c60_80x64x48_uint8.raw", "time=", time=0)


def test_parse_shape_rejects_junk() -> None:
    for text in ["256,256", "a,b,c", "0,4,4", "-1x2x3", "", "1.5,2,3"]:
        with pytest.raises(ApmgsrnError, match="X,Y,Z"):
            parse_shape(text)


# ----------------------------------------------------------------------------- variables and dims
def test_missing_variable_lists_those_available(test_data: Path) -> None:
    _raises(test_data / "miranda_density_80x64x48.nc", "'pressure'", "density (3-D z=48 y=64 x=80, float32)",
            variable="pressure")
    _raises(test_data / "darkmatter_density_64.h5", "'rho'", "densityfield", variable="rho")
    _raises(test_data / VTI, "'Pressure'", "ImageFile", variable="Pressure")


def test_several_3d_variables_need_a_choice(test_data: Path, tmp_path: Path, block: np.ndarray) -> None:
    dims = ("z", "y", "x")
    path = _netcdf(tmp_path / "two.nc", {"a": (dims, block), "b": (dims, block * 2)})
    _raises(path, "several 3-D variables", "'a'", "'b'", "variable=")
    np.testing.assert_array_equal(open_volume(path, variable="b").to_numpy(), block * 2)
    _raises(test_data / "cth_armor_penetration_88x32x32.vtr", "several 3-D arrays", "'Pressure'", "'X Velocity'")
    h5 = tmp_path / "two.h5"
    with h5py.File(h5, "w") as handle:
        handle["u"] = block
        handle["group/v"] = block
    _raises(h5, "several 3-D datasets", "'u'", "'group/v'")


def test_two_dimensional_data_states_its_dims(tmp_path: Path, block: np.ndarray) -> None:
    plane = block[0]  # [20, 16]
    _raises(_netcdf(tmp_path / "plane.nc", {"slice": (("y", "x"), plane)}), "no 3-D variable", "2-D y=20 x=16")
    _raises(_netcdf(tmp_path / "plane2.nc", {"slice": (("y", "x"), plane)}), "2-D", variable="slice")
    h5 = tmp_path / "plane.h5"
    with h5py.File(h5, "w") as handle:
        handle["image"] = plane
    _raises(h5, "no 3-D dataset", "image (2-D 20x16")
    npy = tmp_path / "plane.npy"
    np.save(npy, plane)
    _raises(npy, "2-D", "(20, 16)")
    flat = tmp_path / "flat.npy"
    np.save(flat, block[:1])  # [1, 20, 16]: 3-D in name only
    _raises(flat, "16x20x1", "at least 2 voxels")


def test_time_dimension_without_time_flag(tmp_path: Path, block: np.ndarray) -> None:
    series = np.stack([block, block + 1, block + 2, block + 3])
    path = _netcdf(tmp_path / "series.nc", {"rho": (("time", "z", "y", "x"), series)})
    _raises(path, "time dimension of length 4", "time=INDEX (0..3)")
    _raises(path, "time=4 is out of range", time=4)
    _raises(path, "out of range", time=-1)
    _raises(_netcdf(tmp_path / "still.nc", {"rho": (("z", "y", "x"), block)}), "no time dimension", time=0)


def test_five_dimensional_variable(tmp_path: Path, block: np.ndarray) -> None:
    data = block[None, None]
    path = _netcdf(tmp_path / "five.nc", {"v": (("a", "t", "z", "y", "x"), data)})
    _raises(path, "no 3-D variable", "5-D")
    _raises(path, "5-D", variable="v")


# ----------------------------------------------------------------------------- NaN / Inf
def test_nonfinite_voxels_are_counted_and_filled(tmp_path: Path, block: np.ndarray) -> None:
    data = block.copy()
    data[3, 4, 5] = np.nan
    data[10, 0, 0:3] = np.inf
    data[23, 19, 15] = -np.inf
    path = tmp_path / "holes_16x20x24_float32.raw"
    data.tofile(path)

    volume = open_volume(path)
    stats = volume.stats()
    assert stats.nonfinite == 5
    finite = data[np.isfinite(data)]
    assert (stats.min, stats.max) == (float(finite.min()), float(finite.max()))
    with pytest.raises(ApmgsrnError) as caught:
        check_finite(volume)
    message = str(caught.value)
    assert str(path) in message and "5 of 7680 voxels are NaN or Inf" in message and "fill_nonfinite=" in message

    filled = open_volume(path, fill_nonfinite=-1.0)
    check_finite(filled)  # the user chose a fill value
    values = filled.to_numpy()
    assert np.isfinite(values).all()
    assert values[3, 4, 5] == -1.0 and values[10, 0, 0:3].tolist() == [-1.0] * 3
    np.testing.assert_array_equal(values[np.isfinite(data)], finite)
    assert filled.stats().nonfinite == 5 and filled.stats().min == -1.0
    assert filled.stats().mean == pytest.approx((finite.sum(dtype=np.float64) - 5) / data.size)

    with pytest.raises(ApmgsrnError, match="finite number"):
        open_volume(path, fill_nonfinite=float("nan"))


def test_corrupt_compressed_chunk_is_reported_when_read(hcci_oh: Path, tmp_path: Path) -> None:
    data = bytearray(hcci_oh.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 50_000] = np.random.default_rng(1).integers(0, 256, 50_000, dtype=np.uint8).tobytes()
    path = tmp_path / "damaged.nc"
    path.write_bytes(bytes(data))
    volume = open_volume(path)  # the header is intact
    with pytest.raises(ApmgsrnError) as caught:
        volume.to_numpy()
    assert str(path) in str(caught.value) and "corrupt" in str(caught.value)
