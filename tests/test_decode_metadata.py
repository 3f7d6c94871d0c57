"""Decode keeps what the input had: variable name, units and attributes, dimension names, coordinates (rescaled
for another resolution or a region), compression; ``.vti`` with origin and spacing; regions in voxel indices or
coordinates; uneven coordinates kept where the format can hold them and refused with a message where not.

The volumes are real (tests/data). The Miranda crop carries no units or coordinates, so one test writes the
same voxels to a NetCDF file with the metadata a simulation code would add (units, a standard name, dimension
names and coordinate variables, one of them uneven): the metadata is what is under test, the values are real.
The CTH ``.vtr`` has really uneven x coordinates.
"""

from __future__ import annotations

import json
from pathlib import Path

import netCDF4
import numpy as np
import pytest

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.data import open_volume

FIT = dict(iterations=40, batch_size=2048, grids=4, resolution=8, width=16, progress=False)


@pytest.fixture(scope="module")
def miranda_with_metadata(tmp_path_factory, test_data: Path) -> Path:
    """The Miranda crop's voxels in a NetCDF file with units, attributes, named dimensions and coordinates (z
    uneven: a stretched grid, as simulations refine near an interface), zlib level 3 without shuffle."""
    values = open_volume(test_data / "miranda_density_80x64x48.nc").to_numpy()  # [48, 64, 80]
    path = tmp_path_factory.mktemp("netcdf") / "miranda.nc"
    with netCDF4.Dataset(path, "w") as dataset:
        for name, size in zip(("depth", "north", "east"), values.shape):
            dataset.createDimension(name, size)
        east = dataset.createVariable("east", "f8", ("east",))
        east[:] = 100.0 + 0.25 * np.arange(values.shape[2])
        east.units = "km"
        north = dataset.createVariable("north", "f4", ("north",))
        north[:] = -2.0 + 0.5 * np.arange(values.shape[1])
        north.units = "km"
        depth = dataset.createVariable("depth", "f8", ("depth",))
        depth[:] = np.cumsum(np.linspace(0.1, 0.5, values.shape[0])) - 0.1  # uneven
        depth.units = "m"
        depth.positive = "down"
        density = dataset.createVariable("rho", "f4", ("depth", "north", "east"), zlib=True, complevel=3,
                                         shuffle=False)
        density[:] = values
        density.units = "g/cm^3"
        density.long_name = "mixing density"
        density.standard_name = "sea_water_density"
        density.valid_range = np.array([0.0, 10.0], dtype=np.float32)  # describes stored values: not carried
    return path


@pytest.fixture(scope="module")
def miranda_model(tmp_path_factory, miranda_with_metadata: Path, one_thread) -> Path:
    path = tmp_path_factory.mktemp("model") / "miranda.apmgsrn"
    apmgsrn.fit(miranda_with_metadata, **FIT).save(path)
    return path


@pytest.fixture(scope="module")
def cth_model(tmp_path_factory, test_data: Path, one_thread) -> Path:
    path = tmp_path_factory.mktemp("model") / "cth.apmgsrn"
    apmgsrn.fit(test_data / "cth_armor_penetration_88x32x32.vtr", variable="Pressure", **FIT).save(path)
    return path


@pytest.fixture(scope="module")
def fingers_model(tmp_path_factory, test_data: Path, one_thread) -> Path:
    path = tmp_path_factory.mktemp("model") / "fingers.apmgsrn"
    apmgsrn.fit(test_data / "viscous_fingers_run01" / "030_density_030_064_2.0.vti", **FIT).save(path)
    return path


def test_decoded_netcdf_keeps_name_units_attributes_dimensions_coordinates_compression(
    miranda_model: Path, miranda_with_metadata: Path, tmp_path: Path
) -> None:
    out = tmp_path / "decoded.nc"
    assert main(["decode", str(miranda_model), "--out", str(out), "--device", "cpu"]) == 0
    with netCDF4.Dataset(miranda_with_metadata) as source, netCDF4.Dataset(out) as decoded:
        assert list(decoded.variables["rho"].dimensions) == ["depth", "north", "east"]
        variable = decoded.variables["rho"]
        assert variable.units == "g/cm^3"
        assert variable.long_name == "mixing density"
        assert variable.standard_name == "sea_water_density"
        assert "valid_range" not in variable.ncattrs()
        filters = variable.filters()
        assert filters["zlib"] and filters["complevel"] == 3 and not filters["shuffle"]
        for name in ("depth", "north", "east"):
            np.testing.assert_allclose(decoded.variables[name][:], source.variables[name][:], rtol=1e-12)
            assert decoded.variables[name].units == source.variables[name].units
        assert decoded.variables["depth"].positive == "down"
        assert decoded.variables["rho"].shape == source.variables["rho"].shape
    assert out.stat().st_size < 0.9 * 4 * 48 * 64 * 80  # compressed


def test_coordinates_follow_a_shape_and_a_region(miranda_model: Path, miranda_with_metadata: Path,
                                                 tmp_path: Path) -> None:
    with netCDF4.Dataset(miranda_with_metadata) as source:
        depth = source.variables["depth"][:].astype(np.float64)
        east = source.variables["east"][:].astype(np.float64)
    out = tmp_path / "resampled.nc"
    # x voxels 10..49 at 79 samples (half-voxel steps), y whole at 16 samples, z voxels 5..14 as they are.
    assert main(["decode", str(miranda_model), "--out", str(out), "--region", "10:50,:,5:15",
                 "--shape", "79,16,10", "--device", "cpu"]) == 0
    with netCDF4.Dataset(out) as decoded:
        assert decoded.variables["rho"].shape == (10, 16, 79)
        np.testing.assert_allclose(decoded.variables["east"][:], 100.0 + 0.25 * np.linspace(10, 49, 79), rtol=1e-12)
        np.testing.assert_allclose(decoded.variables["north"][:], np.linspace(-2.0, 29.5, 16), rtol=1e-6)
        np.testing.assert_allclose(decoded.variables["depth"][:], depth[5:15], rtol=1e-12)  # uneven, as stored
    # Between voxels an uneven coordinate is interpolated the way the network interpolates the values.
    model = apmgsrn.load(miranda_model)
    halfway = model.decode(region={"z": (5, 7)}, shape=(3, 4, 4))
    np.testing.assert_allclose(halfway["depth"].values, [depth[5], 0.5 * (depth[5] + depth[6]), depth[6]])
    np.testing.assert_allclose(halfway["east"].values, np.interp(np.linspace(0, 79, 4), np.arange(80), east))


def test_region_decodes_the_same_values_as_the_whole_volume(miranda_model: Path) -> None:
    model = apmgsrn.load(miranda_model)
    whole = model.decode()
    part = model.decode(region="10:50,3:20,5:15")
    span = model.description.value_range[1] - model.description.value_range[0]
    np.testing.assert_allclose(part.values, whole.values[5:15, 3:20, 10:50], atol=1e-5 * span)
    np.testing.assert_allclose(part["east"].values, whole["east"].values[10:50])
    # The same box given in coordinates (closed interval: the first and last voxel's coordinates).
    east, north, depth = whole["east"].values, whole["north"].values, whole["depth"].values
    box = {"x": (east[10], east[49]), "y": (north[3], north[19]), "z": (depth[5], depth[14])}
    by_coordinates = model.decode(region=box, region_units="coordinates")
    assert by_coordinates.shape == part.shape
    np.testing.assert_allclose(by_coordinates.values, part.values, atol=1e-5 * span)


def test_region_outside_the_volume_is_refused(miranda_model: Path, tmp_path: Path, capsys) -> None:
    assert main(["decode", str(miranda_model), "--out", str(tmp_path / "x.nc"), "--region", "70:90,:,:",
                 "--device", "cpu"]) == 2
    assert "--region" in capsys.readouterr().err
    with pytest.raises(apmgsrn.ApmgsrnError, match="outside the volume's east coordinates"):
        apmgsrn.load(miranda_model).decode(region={"x": (0.0, 1.0)}, region_units="coordinates")
    assert not (tmp_path / "x.nc").exists()


def test_vti_output_has_origin_spacing_and_name(fingers_model: Path, tmp_path: Path) -> None:
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    out = tmp_path / "fingers.vti"
    assert main(["decode", str(fingers_model), "--out", str(out), "--shape", "16,16,64", "--device", "cpu"]) == 0
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(out))
    reader.Update()
    image = reader.GetOutput()
    assert image.GetDimensions() == (16, 16, 64)
    assert image.GetOrigin() == pytest.approx((16.0, 16.0, 32.0))  # the source file's origin
    assert image.GetSpacing() == pytest.approx((31 / 15, 31 / 15, 31 / 63))  # 32 points rescaled
    array = image.GetPointData().GetArray(0)
    assert array.GetName() == "ImageFile"
    npy = tmp_path / "fingers.npy"
    assert main(["decode", str(fingers_model), "--out", str(npy), "--shape", "16,16,64", "--device", "cpu"]) == 0
    np.testing.assert_array_equal(vtk_to_numpy(array).reshape(64, 16, 16), np.load(npy))


def test_uneven_vtr_coordinates_are_kept_in_netcdf_and_refused_in_vti(cth_model: Path, test_data: Path,
                                                                        tmp_path: Path, capsys) -> None:
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLRectilinearGridReader

    reader = vtkXMLRectilinearGridReader()
    reader.SetFileName(str(test_data / "cth_armor_penetration_88x32x32.vtr"))
    reader.Update()
    corners = vtk_to_numpy(reader.GetOutput().GetXCoordinates()).astype(np.float64)
    centres = 0.5 * (corners[:-1] + corners[1:])  # Pressure is a cell array
    assert np.ptp(np.diff(centres)) > 0.01  # really uneven
    out = tmp_path / "cth.nc"
    assert main(["decode", str(cth_model), "--out", str(out), "--device", "cpu"]) == 0
    with netCDF4.Dataset(out) as decoded:
        assert "Pressure" in decoded.variables
        np.testing.assert_allclose(decoded.variables["x"][:], centres, rtol=1e-12)
    assert main(["decode", str(cth_model), "--out", str(tmp_path / "cth.vti"), "--device", "cpu"]) == 2
    error = capsys.readouterr().err
    assert "x coordinates of this volume are uneven" in error and ".nc" in error
    assert not (tmp_path / "cth.vti").exists()
    # The plugin's question gets the same answer before anything is decoded.
    assert main(["decode", str(cth_model), "--out", str(tmp_path / "cth.vti"), "--dry-run", "--json"]) == 2


def test_dry_run_reports_the_lattice_and_writes_nothing(fingers_model: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "plan.vti"
    assert main(["decode", str(fingers_model), "--out", str(out), "--region", "4:20,:,8:9", "--dry-run",
                 "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["shape_xyz"] == [16, 32, 1]
    assert report["origin"] == [20.0, 16.0, 40.0]
    assert report["variable"] == "ImageFile" and report["time_steps"] == 1 and not report["written"]
    assert not out.exists()


def test_model_files_without_the_new_fields_still_load_and_decode(test_data: Path, tmp_path: Path) -> None:
    # Written before decode kept metadata (tests/data/REFERENCE_MODELS.md): no attributes, no coordinates.
    model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    assert model.description.source.metadata.coordinates is None
    out = tmp_path / "old.nc"
    assert main(["decode", str(test_data / "reference_field.apmgsrn"), "--out", str(out), "--device", "cpu"]) == 0
    with netCDF4.Dataset(out) as decoded:
        assert list(decoded.variables["value"].dimensions) == ["z", "y", "x"]
        assert decoded.variables["value"].shape == (24, 24, 24)
        assert "x" not in decoded.variables  # voxel indices are not written as coordinates


def test_time_steps_beyond_the_model_are_refused(fingers_model: Path) -> None:
    model = apmgsrn.load(fingers_model)
    assert model.decode(time=0, shape=(2, 2, 2)).shape == (2, 2, 2)
    with pytest.raises(apmgsrn.ApmgsrnError, match="one time step"):
        model.decode(time=1)


def test_hdf5_and_zarr_readers_record_what_they_hold(test_data: Path, tmp_path: Path) -> None:
    import h5py
    import xarray

    values = open_volume(test_data / "darkmatter_density_64.h5").to_numpy()[:16, :16, :16]
    with h5py.File(tmp_path / "dm.h5", "w") as handle:
        dataset = handle.create_dataset("fields/rho", data=values, compression="gzip", compression_opts=5,
                                        shuffle=True)
        dataset.attrs["units"] = "M_sun/Mpc^3"
        dataset.attrs["scale_factor"] = 2.0  # packing: never carried over
    metadata = open_volume(tmp_path / "dm.h5").metadata
    assert metadata.attributes == {"units": "M_sun/Mpc^3"}
    assert metadata.compression == {"zlib": True, "complevel": 5, "shuffle": True}

    array = xarray.DataArray(values, name="rho", dims=("k", "j", "i"), attrs={"units": "M_sun/Mpc^3"},
                             coords={"i": ("i", 0.5 + np.arange(16) * 3.125, {"units": "Mpc/h"})})
    array.to_dataset().to_zarr(tmp_path / "dm.zarr")
    metadata = open_volume(tmp_path / "dm.zarr", variable="rho").metadata
    assert metadata.dimensions == ("k", "j", "i") and metadata.units == "M_sun/Mpc^3"
    x = metadata.coordinates[2]
    assert (x.name, x.start, x.step, x.even, x.attributes) == ("i", 0.5, 3.125, True, {"units": "Mpc/h"})
    assert metadata.coordinates[0] is None
