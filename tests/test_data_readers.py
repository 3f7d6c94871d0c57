"""Readers of apmgsrn.data on the small real volumes in tests/data (and copies of them in other formats)."""

from __future__ import annotations

import importlib.util
import pickle
import re
import sys
from pathlib import Path

import h5py
import netCDF4
import numpy as np
import pytest
import zarr

from apmgsrn.data import ArrayVolume, Volume, VolumeStats, check_finite, open_volume, parse_shape

VF = "viscous_fingers_run01/{:03d}_density_{:03d}_064_2.0.vti".format
# file in tests/data (or the demo's HCCI field in examples/data)
#   -> (variable to pass, (X, Y, Z) from tests/data/README.md, stored dtype, variable reported, plausible value range)
DATA_FILES = {
    "darkmatter_density_64.h5": (None, (64, 64, 64), "float32", "densityfield", (0.2, 3.0e5)),
    "cth_armor_penetration_88x32x32.vtr": ("Pressure", (88, 32, 32), "float32", "Pressure", (-1e11, 1e12)),
    **{VF(step, step): (None, (32, 32, 32), "float32", "ImageFile", (0.0, 200.0)) for step in (30, 31, 32, 33)},
    "richtmyer_meshkov_t20_96x64x48_uint8.raw": (None, (96, 64, 48), "uint8", None, (0.0, 255.0)),
    "c60_80x64x48_uint8.raw": (None, (80, 64, 48), "uint8", None, (0.0, 255.0)),
    "neghip_64x64x64_uint8.raw": (None, (64, 64, 64), "uint8", None, (0.0, 255.0)),
    "miranda_density_80x64x48.nc": (None, (80, 64, 48), "float32", "density", (0.4, 3.7)),
    "hcci_oh_187.nc": (None, (187, 187, 187), "float32", "oh", (-1.5, 13.0)),
    "channel_pressure_96x64x48.nc": (None, (96, 64, 48), "float32", "pressure", (-0.5, 1.5)),
}


@pytest.fixture(scope="module")
def path_of(test_data: Path, hcci_oh: Path):
    """The path of a DATA_FILES entry: a file in tests/data, or the demo's HCCI field."""
    return lambda name: hcci_oh if name == hcci_oh.name else test_data / name


@pytest.fixture(scope="module")
def miranda(test_data: Path) -> np.ndarray:
    """The whole 80x64x48 Miranda density crop, read once for the module."""
    return open_volume(test_data / "miranda_density_80x64x48.nc").to_numpy()


@pytest.fixture(scope="module")
def miranda_block(miranda: np.ndarray) -> np.ndarray:
    """A non-cubic block of real data (D, H, W all different, to catch axis mix-ups).

    The voxels [100:130, 60:100, 20:70] of the 256^3 source; the crop starts at (96, 48, 16).
    """
    return np.ascontiguousarray(miranda[4:34, 12:52, 4:54])  # [30, 40, 50]


def _readme_rows(readme: Path) -> dict[str, list[str]]:
    """File name -> the cells of its row in the markdown table of tests/data/README.md."""
    rows = {}
    for line in readme.read_text(encoding="utf-8").splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] != "file" and not set(cells[0]) <= set("-: "):
            rows[cells[0].strip("`")] = cells
    return rows


def test_every_bundled_file_is_listed_with_provenance_and_its_cut(test_data: Path) -> None:
    spec = importlib.util.spec_from_file_location("make_test_data", test_data / "make_test_data.py")
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    tooling = {"README.md", "make_test_data.py", ".gitattributes"}
    notes = {path.name: path.read_text(encoding="utf-8") for path in test_data.glob("*.md") if path.name != "README.md"}
    present = {path.relative_to(test_data).as_posix() for path in test_data.rglob("*")
               if path.is_file() and "__pycache__" not in path.parts} - tooling - set(notes)
    rows = _readme_rows(test_data / "README.md")
    # Files made by the tests' own code (reference models and images) are described in their own notes.
    made_here = {name for name in present - set(rows) if any(Path(name).parts[0] in text for text in notes.values())}
    # Every volume is listed, written by the script, and opened by the tests below; nothing else is listed.
    assert present - made_here == set(rows) == set(maker.CUTS) == set(DATA_FILES) - {"hcci_oh_187.nc"}
    for name, cells in rows.items():
        assert len(cells) == 8 and all(cells), f"{name}: a README row needs all 8 cells filled"
        _, _, dims, dtype, _, origin, _, cut = cells
        assert dims.split()[0] == "x".join(map(str, DATA_FILES[name][1])), name
        assert dtype.split()[0].rstrip(",") == DATA_FILES[name][2], name
        source, box = maker.CUTS[name]
        assert f"`{source}`" in cut, name
        if box is None:
            assert "byte copy" in cut, name
        else:  # the exact slicing, as the script applies it
            assert "[{}:{}, {}:{}, {}:{}]".format(*(i for pair in box for i in pair)) in cut, name
        assert re.search(r"\S+/\S+", origin), f"{name}: origin names no repository"


@pytest.mark.parametrize("name", sorted(DATA_FILES))
def test_every_bundled_file_opens_with_its_shape_dtype_and_range(path_of, name: str) -> None:
    variable, xyz, dtype, reported, (low, high) = DATA_FILES[name]
    volume = open_volume(path_of(name), variable=variable)
    assert isinstance(volume, Volume)
    assert volume.shape == (xyz[2], xyz[1], xyz[0])
    assert volume.dtype == np.dtype(dtype)
    assert volume.variable == reported
    assert volume.raw_bytes == xyz[0] * xyz[1] * xyz[2] * 4
    assert f"{xyz[0]}x{xyz[1]}x{xyz[2]} (x*y*z) {dtype}" in volume.describe()
    assert volume.describe().startswith(Path(name).name)
    # A central block: values finite, inside the physical range and not constant.
    d, h, w = volume.shape
    block = volume.read(slice(d // 4, 3 * d // 4), slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
    assert block.dtype == np.float32 and block.flags.c_contiguous
    assert block.shape == (3 * d // 4 - d // 4, 3 * h // 4 - h // 4, 3 * w // 4 - w // 4)
    assert np.isfinite(block).all()
    assert low <= block.min() and block.max() <= high
    assert block.max() > block.min()


@pytest.mark.parametrize(
    "name",
    ["miranda_density_80x64x48.nc", "channel_pressure_96x64x48.nc", "darkmatter_density_64.h5",
     "richtmyer_meshkov_t20_96x64x48_uint8.raw", VF(31, 31)],
)
def test_stats_match_numpy_on_the_full_array(test_data: Path, name: str) -> None:
    volume = open_volume(test_data / name, variable=DATA_FILES[name][0])
    stats = volume.stats()
    full = volume.to_numpy()
    assert full.shape == volume.shape and full.dtype == np.float32
    assert stats == VolumeStats(min=float(full.min()), max=float(full.max()),
                                mean=pytest.approx(float(full.mean(dtype=np.float64)), rel=1e-9), nonfinite=0)
    assert volume.stats() is stats  # cached
    check_finite(volume)  # real data is finite: no error


def test_uint8_raw_converts_exactly_to_float32(test_data: Path) -> None:
    path = test_data / "neghip_64x64x64_uint8.raw"
    expected = np.fromfile(path, dtype=np.uint8).reshape(64, 64, 64).astype(np.float32)
    volume = open_volume(path)
    np.testing.assert_array_equal(volume.to_numpy(), expected)
    np.testing.assert_array_equal(volume.read(slice(5, 9), slice(60, None), slice(0, 3)), expected[5:9, 60:, 0:3])


def test_explicit_shape_and_dtype_override_the_file_name(test_data: Path, tmp_path: Path) -> None:
    data = np.fromfile(test_data / "c60_80x64x48_uint8.raw", dtype=np.uint8)
    plain = tmp_path / "c60.bin"
    data.tofile(plain)
    # Same bytes seen as x=160, y=64, z=24: x stays the fastest axis.
    volume = open_volume(plain, shape="160,64,24", dtype="uint8")
    assert volume.shape == (24, 64, 160)
    np.testing.assert_array_equal(volume.to_numpy(), data.reshape(24, 64, 160).astype(np.float32))
    assert open_volume(plain, shape=(80, 64, 48), dtype="uchar").shape == (48, 64, 80)


def test_vti_arrays_are_x_fastest(test_data: Path) -> None:
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    path = test_data / VF(33, 33)
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    data = open_volume(path).to_numpy()
    for i, j, k in [(3, 10, 20), (30, 2, 7), (20, 31, 13), (31, 0, 31)]:
        assert data[k, j, i] == pytest.approx(image.GetScalarComponentAsDouble(i, j, k, 0), rel=1e-6)


def test_vtr_cell_arrays_by_name(test_data: Path) -> None:
    path = test_data / "cth_armor_penetration_88x32x32.vtr"
    fraction = open_volume(path, variable="Volume Fraction for Armor Plate")
    assert fraction.shape == (32, 32, 88)  # 88x32x32 cells (x*y*z)
    values = fraction.to_numpy()
    # A volume fraction lies in [0, 1]; the plate fills about 10 % of the crop's cells (5 % of the source's).
    assert 0.0 <= values.min() and values.max() <= 1.0 + 1e-6
    assert 0.001 < np.count_nonzero(values) / values.size < 0.2


# ----------------------------------------------------------------------------- other formats
def _write_copies(block: np.ndarray, folder: Path) -> dict[str, tuple[Path, dict]]:
    """The same real block in every readable format; returns label -> (path, open_volume kwargs)."""
    depth, height, width = block.shape
    copies: dict[str, tuple[Path, dict]] = {}

    npy = folder / "block.npy"
    np.save(npy, block)
    copies["npy"] = (npy, {})

    raw = folder / f"block_{width}x{height}x{depth}_float32.raw"
    block.astype("<f4").tofile(raw)
    copies["raw"] = (raw, {})

    raw16 = folder / "block16.bin"
    np.round(block * 1000).astype("<u2").tofile(raw16)
    copies["raw uint16 with flags"] = (raw16, {"shape": (width, height, depth), "dtype": "uint16"})

    h5 = folder / "block.h5"
    with h5py.File(h5, "w") as handle:
        handle.create_dataset("fields/density", data=block, chunks=(8, 8, 8), compression="gzip")
        handle.create_dataset("coords/x", data=np.arange(width))
    copies["h5 in a group"] = (h5, {})

    zarr_array = folder / "array.zarr"
    zarr.create_array(store=str(zarr_array), data=block, chunks=(7, 9, 11))
    copies["zarr array"] = (zarr_array, {})

    zarr_group = folder / "group_store"  # no .zarr suffix: recognised by its metadata
    group = zarr.open_group(str(zarr_group), mode="w")
    group.create_array("sim/density", data=block, chunks=(16, 16, 16))
    group.create_array("time", data=np.arange(3.0))
    copies["zarr group"] = (zarr_group, {"variable": "sim/density"})

    nc = folder / "block.nc"
    with netCDF4.Dataset(nc, "w") as handle:
        for name, size in zip(("z", "y", "x"), block.shape):
            handle.createDimension(name, size)
            handle.createVariable(name, "f8", (name,))[:] = np.arange(size)
        handle.createVariable("density", "f4", ("z", "y", "x"), chunksizes=(8, 8, 8), zlib=True)[:] = block
    copies["nc"] = (nc, {})
    return copies


@pytest.fixture(scope="module")
def copies(miranda_block: np.ndarray, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict]]:
    return _write_copies(miranda_block, tmp_path_factory.mktemp("copies"))


REGIONS = [
    (slice(None), slice(None), slice(None)),
    (slice(3, 17), slice(5, 6), slice(40, None)),
    (slice(-4, None), slice(None, 11), slice(-30, -2)),
    (slice(1, 29, 4), slice(0, 40, 3), slice(2, 50, 5)),
    (slice(12, 12), slice(None), slice(None)),
]


@pytest.mark.parametrize(
    "label", ["npy", "raw", "raw uint16 with flags", "h5 in a group", "zarr array", "zarr group", "nc"]
)
def test_copies_in_every_format_read_regions_lazily(copies, miranda_block: np.ndarray, label: str) -> None:
    path, kwargs = copies[label]
    volume = open_volume(path, **kwargs)
    expected = miranda_block
    if label.startswith("raw uint16"):
        expected = np.round(miranda_block * 1000).astype(np.uint16).astype(np.float32)
    assert volume.shape == miranda_block.shape
    full = volume.to_numpy()
    np.testing.assert_array_equal(full, expected)
    for region in REGIONS:
        part = volume.read(*region)
        assert part.dtype == np.float32 and part.flags.c_contiguous and part.flags.writeable
        np.testing.assert_array_equal(part, full[region])
    # Reads are copies: writing to one never changes the file or the next read.
    part = volume.read(slice(0, 2))
    part[:] = -1
    np.testing.assert_array_equal(volume.read(slice(0, 2)), expected[0:2])


@pytest.mark.parametrize("name", ["hcci_oh_187.nc", "c60_80x64x48_uint8.raw", "cth_armor_penetration_88x32x32.vtr"])
def test_region_reads_equal_slices_of_the_whole_volume(path_of, name: str) -> None:
    volume = open_volume(path_of(name), variable=DATA_FILES[name][0])
    full = volume.to_numpy()
    d, h, w = volume.shape
    for region in [(slice(1, d // 3), slice(h // 2, h - 1), slice(5, 9)),
                   (slice(d - 7, d), slice(0, 3), slice(w // 3, None)),
                   (slice(0, d, 9), slice(2, h, 13), slice(w - 20, w, 4))]:
        np.testing.assert_array_equal(volume.read(*region), full[region])


def test_reported_variable_names(copies) -> None:
    assert open_volume(copies["h5 in a group"][0]).variable == "fields/density"
    assert open_volume(copies["zarr group"][0]).variable == "sim/density"  # the only 3-D array
    assert open_volume(copies["zarr array"][0]).variable is None
    assert open_volume(copies["npy"][0]).variable is None
    assert open_volume(copies["nc"][0]).variable == "density"  # coordinate variables ignored


@pytest.mark.parametrize("max_voxels", [1, 40 * 50 * 7, 40 * 50 * 30, 2**24])
def test_iter_slabs_cover_the_volume_exactly_in_order(copies, miranda_block: np.ndarray, max_voxels: int) -> None:
    volume = open_volume(copies["nc"][0])
    slabs = list(volume.iter_slabs(max_voxels=max_voxels))
    starts = [z.start for z, _ in slabs]
    assert starts[0] == 0 and slabs[-1][0].stop == 30
    assert all(a.stop == b.start for (a, _), (b, _) in zip(slabs, slabs[1:]))
    assert all(block.shape[0] * 40 * 50 <= max(max_voxels, 40 * 50) for _, block in slabs)
    assert all(block.shape == (z.stop - z.start, 40, 50) for z, block in slabs)
    np.testing.assert_array_equal(np.concatenate([block for _, block in slabs]), miranda_block)


def test_netcdf_time_dimension_selects_one_step(miranda_block: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / "series.nc"
    steps = np.stack([miranda_block, miranda_block * 2, miranda_block + 1])  # [3, 30, 40, 50]
    with netCDF4.Dataset(path, "w") as handle:
        handle.createDimension("time", None)
        for name, size in zip(("z", "y", "x"), miranda_block.shape):
            handle.createDimension(name, size)
        handle.createVariable("time", "f8", ("time",))[:] = [0.0, 1.0, 2.0]
        handle.createVariable("rho", "f4", ("time", "z", "y", "x"))[:] = steps
    volume = open_volume(path, time=1)
    assert volume.shape == (30, 40, 50) and volume.time == 1 and volume.variable == "rho"
    np.testing.assert_array_equal(volume.read(slice(2, 5), slice(None), slice(7, 8)), steps[1, 2:5, :, 7:8])
    assert "rho[t=1]" in volume.describe()
    np.testing.assert_array_equal(open_volume(path, time=2).to_numpy(), steps[2])


def test_netcdf_single_time_step_needs_no_time_flag(miranda_block: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / "one_step.nc"
    with netCDF4.Dataset(path, "w") as handle:
        for name, size in zip(("t", "z", "y", "x"), (1,) + miranda_block.shape):
            handle.createDimension(name, size)
        handle.createVariable("v", "f4", ("t", "z", "y", "x"))[:] = miranda_block[None]
    volume = open_volume(path)
    assert volume.time == 0
    np.testing.assert_array_equal(volume.to_numpy(), miranda_block)


def test_netcdf_missing_values_count_as_nonfinite(miranda_block: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / "holes.nc"
    with netCDF4.Dataset(path, "w") as handle:
        for name, size in zip(("z", "y", "x"), miranda_block.shape):
            handle.createDimension(name, size)
        var = handle.createVariable("density", "f4", ("z", "y", "x"), fill_value=-999.0)
        holes = miranda_block.copy()
        holes[4, 5, 6:9] = -999.0  # three missing voxels
        var[:] = holes
    volume = open_volume(path)
    assert np.isnan(volume.read(slice(4, 5), slice(5, 6), slice(6, 9))).all()
    assert volume.stats().nonfinite == 3
    filled = open_volume(path, fill_nonfinite=0.0)
    assert filled.read(slice(4, 5), slice(5, 6), slice(6, 9)).tolist() == [[[0.0, 0.0, 0.0]]]


def test_netcdf_without_netcdf4_falls_back_to_h5py(hcci_oh: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = hcci_oh
    region = (slice(50, 60), slice(0, 187, 10), slice(90, 100))
    expected = open_volume(path).read(*region)
    monkeypatch.setitem(sys.modules, "netCDF4", None)  # makes `import netCDF4` fail
    volume = open_volume(path)
    assert type(volume).__name__ == "NetCDFThroughHDF5Volume"
    assert volume.shape == (187, 187, 187) and volume.variable == "oh"
    np.testing.assert_array_equal(volume.read(*region), expected)


def test_volumes_pickle_as_recipes_and_reopen(test_data: Path, copies) -> None:
    for path, kwargs in [(test_data / "richtmyer_meshkov_t20_96x64x48_uint8.raw", {}),
                         (test_data / "miranda_density_80x64x48.nc", {}),
                         (test_data / "darkmatter_density_64.h5", {}),
                         copies["zarr group"], copies["npy"]]:
        volume = open_volume(path, **kwargs)
        region = (slice(3, 6), slice(10, 20), slice(0, 8))
        expected = volume.read(*region)
        payload = pickle.dumps(volume)
        assert len(payload) < 10_000  # the file name and metadata, never the voxels
        clone = pickle.loads(payload)
        np.testing.assert_array_equal(clone.read(*region), expected)
        volume.close()
        np.testing.assert_array_equal(volume.read(*region), expected)  # reopens after close


def test_array_volume_wraps_memory(miranda_block: np.ndarray) -> None:
    volume = ArrayVolume(miranda_block, path="block")
    assert volume.shape == (30, 40, 50)
    np.testing.assert_array_equal(volume.read(slice(1, 2)), miranda_block[1:2])
    assert volume.stats().max == float(miranda_block.max())


@pytest.mark.parametrize(
    "text, expected",
    [("256,256,128", (256, 256, 128)), ("640x240x48", (640, 240, 48)), (" 1 , 2 , 3 ", (1, 2, 3)),
     ("4X5X6", (4, 5, 6)), ("7*8*9", (7, 8, 9))],
)
def test_parse_shape_keeps_x_first(text: str, expected: tuple[int, int, int]) -> None:
    assert parse_shape(text) == expected
