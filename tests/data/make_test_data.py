"""Write the small real volumes in tests/data from the project's shared sample data (run once, by hand).

Every file is a byte copy or a crop (contiguous index ranges, no resampling) of a file in
``../shared/data``; README.md beside this script lists where each came from and the exact slicing, which
is the table ``CUTS`` below. Values are never changed: crops keep the stored dtype and the source's
layout (NetCDF dims, variable and attributes; VTK array names, point vs cell arrays, rectilinear
coordinates), so the readers see the same kinds of metadata the tests exercise.

Usage: ``python tests/data/make_test_data.py [--shared PATH]`` (default: ``../shared/data`` beside the repo).
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_SHARED = HERE.parents[2] / "shared" / "data"

#: Inclusive-exclusive (z, y, x) index ranges of each crop; for a .vtr they count cells, else voxels/points.
Box = tuple[tuple[int, int], tuple[int, int], tuple[int, int]]
CUTS: dict[str, tuple[str, Box | None]] = {
    # output name: (shared source, (z, y, x) ranges or None for a byte copy)
    "neghip_64x64x64_uint8.raw": ("neghip_64x64x64_uint8.raw", None),
    "darkmatter_density_64.h5": ("darkmatter_density_64.h5", None),
    "c60_80x64x48_uint8.raw": ("c60_128x128x128_uint8.raw", ((16, 64), (16, 80), (16, 96))),
    "richtmyer_meshkov_t20_96x64x48_uint8.raw": (
        "richtmyer_meshkov_t20_256x256x256_uint8.raw", ((88, 136), (64, 128), (0, 96))),
    "miranda_density_80x64x48.nc": ("miranda_density_256.nc", ((96, 144), (48, 112), (16, 96))),
    "channel_pressure_96x64x48.nc": ("channel_pressure_640x240x48.nc", ((0, 48), (96, 160), (288, 384))),
    "cth_armor_penetration_88x32x32.vtr": ("cth_armor_penetration.vtr", ((16, 48), (16, 48), (32, 120))),
    **{
        f"viscous_fingers_run01/{step:03d}_density_{step:03d}_064_2.0.vti": (
            f"viscous_fingers_run01/{step:03d}_density_{step:03d}_064_2.0.vti", ((32, 64), (16, 48), (16, 48)))
        for step in (30, 31, 32, 33)
    },
}

#: Stored shape (z, y, x) and dtype of the shared raw files (from their names).
RAW_SOURCES = {
    "c60_128x128x128_uint8.raw": ((128, 128, 128), np.uint8),
    "richtmyer_meshkov_t20_256x256x256_uint8.raw": ((256, 256, 256), np.uint8),
}


def _slices(box: Box) -> tuple[slice, slice, slice]:
    return tuple(slice(start, stop) for start, stop in box)


def _temporary(target: Path) -> Path:
    """A temporary name in the target's folder; the caller renames it over the target when complete."""
    target.parent.mkdir(parents=True, exist_ok=True)
    return target.with_name(f".{target.name}.partial")


def crop_raw(source: Path, target: Path, box: Box) -> None:
    """Crop a headerless raw volume (C order, x fastest)."""
    shape, dtype = RAW_SOURCES[source.name]
    data = np.fromfile(source, dtype=dtype).reshape(shape)  # [Z, Y, X]
    temporary = _temporary(target)
    np.ascontiguousarray(data[_slices(box)]).tofile(temporary)
    os.replace(temporary, target)


def crop_netcdf(source: Path, target: Path, box: Box) -> None:
    """Crop every (z, y, x) variable of a NetCDF4 file, keeping its dims, attributes and zlib compression."""
    import netCDF4

    temporary = _temporary(target)
    with netCDF4.Dataset(source) as src, netCDF4.Dataset(temporary, "w", format=src.file_format) as dst:
        dst.setncatts({name: src.getncattr(name) for name in src.ncattrs()})
        for name, (start, stop) in zip(("z", "y", "x"), box):
            assert src.dimensions[name].size >= stop, (source, name)
            dst.createDimension(name, stop - start)
        for name, variable in src.variables.items():
            assert variable.dimensions == ("z", "y", "x"), (source, name)
            filters = variable.filters()
            # Chunks: the source's, halved along each axis, so a crop still spans several chunks.
            chunks = [max(1, min(c // 2, stop - start)) for c, (start, stop) in zip(variable.chunking(), box)]
            out = dst.createVariable(name, variable.dtype, variable.dimensions, zlib=filters["zlib"],
                                     shuffle=filters["shuffle"], complevel=filters["complevel"], chunksizes=chunks)
            out.setncatts({attr: variable.getncattr(attr) for attr in variable.ncattrs()})
            out[:] = variable[_slices(box)]
        dst.setncattr("cut", f"{source.name} [{box[0][0]}:{box[0][1]}, {box[1][0]}:{box[1][1]}, "
                             f"{box[2][0]}:{box[2][1]}] (z, y, x) by tests/data/make_test_data.py")
    os.replace(temporary, target)


def _vtk_arrays(attributes, shape: tuple[int, int, int], box: Box):
    """(name, cropped numpy array) of every array of a vtkPointData/vtkCellData laid out as ``shape``."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    for index in range(attributes.GetNumberOfArrays()):
        values = vtk_to_numpy(attributes.GetArray(index)).reshape(shape)  # [Z, Y, X], x fastest
        yield attributes.GetArrayName(index), np.ascontiguousarray(values[_slices(box)])


def _add_arrays(attributes, arrays, scalars: str | None) -> None:
    from vtkmodules.util.numpy_support import numpy_to_vtk

    for name, values in arrays:
        vtk_array = numpy_to_vtk(values.reshape(-1), deep=True)
        vtk_array.SetName(name)
        attributes.AddArray(vtk_array)
    if scalars:
        attributes.SetActiveScalars(scalars)


def _write_vtk(writer, grid, target: Path) -> None:
    temporary = _temporary(target)
    writer.SetFileName(str(temporary))
    writer.SetInputData(grid)
    writer.SetCompressorTypeToZLib()
    writer.SetDataModeToAppended()
    writer.EncodeAppendedDataOff()  # raw appended bytes, as in the source files
    if not writer.Write():
        raise RuntimeError(f"could not write {target}")
    os.replace(temporary, target)


def crop_vti(source: Path, target: Path, box: Box) -> None:
    """Crop the point arrays of a VTK ImageData; the origin moves to the crop's first point, spacing kept."""
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader, vtkXMLImageDataWriter

    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(source))
    reader.Update()
    image = reader.GetOutput()
    nx, ny, nz = image.GetDimensions()
    assert image.GetCellData().GetNumberOfArrays() == 0, source
    origin, spacing = image.GetOrigin(), image.GetSpacing()
    (z0, z1), (y0, y1), (x0, x1) = box
    cropped = vtkImageData()
    cropped.SetDimensions(x1 - x0, y1 - y0, z1 - z0)
    cropped.SetSpacing(spacing)
    cropped.SetOrigin(origin[0] + x0 * spacing[0], origin[1] + y0 * spacing[1], origin[2] + z0 * spacing[2])
    points = image.GetPointData()
    _add_arrays(cropped.GetPointData(), _vtk_arrays(points, (nz, ny, nx), box),
                points.GetScalars().GetName() if points.GetScalars() else None)
    writer = vtkXMLImageDataWriter()
    writer.SetHeaderTypeToUInt64()  # as the source .vti files (the .vtr source uses the default UInt32)
    _write_vtk(writer, cropped, target)


def crop_vtr(source: Path, target: Path, box: Box) -> None:
    """Crop the cell arrays of a VTK RectilinearGrid by cell ranges, with the matching point coordinates."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkRectilinearGrid
    from vtkmodules.vtkIOXML import vtkXMLRectilinearGridReader, vtkXMLRectilinearGridWriter

    reader = vtkXMLRectilinearGridReader()
    reader.SetFileName(str(source))
    reader.Update()
    grid = reader.GetOutput()
    nx, ny, nz = grid.GetDimensions()  # point counts
    assert grid.GetPointData().GetNumberOfArrays() == 0, source
    cropped = vtkRectilinearGrid()
    (z0, z1), (y0, y1), (x0, x1) = box
    cropped.SetDimensions(x1 - x0 + 1, y1 - y0 + 1, z1 - z0 + 1)  # n cells have n + 1 points
    for axis, (start, stop) in zip("XYZ", ((x0, x1), (y0, y1), (z0, z1))):
        coordinates = vtk_to_numpy(getattr(grid, f"Get{axis}Coordinates")())[start : stop + 1]
        vtk_coordinates = numpy_to_vtk(np.ascontiguousarray(coordinates), deep=True)
        vtk_coordinates.SetName(axis)  # else VTK names it after its memory address: the file would vary by run
        getattr(cropped, f"Set{axis}Coordinates")(vtk_coordinates)
    cells = grid.GetCellData()
    _add_arrays(cropped.GetCellData(), _vtk_arrays(cells, (nz - 1, ny - 1, nx - 1), box),
                cells.GetScalars().GetName() if cells.GetScalars() else None)
    _write_vtk(vtkXMLRectilinearGridWriter(), cropped, target)


def make(shared: Path, out: Path) -> None:
    """Write every file of ``CUTS`` from ``shared`` into ``out``."""
    for name, (source_name, box) in CUTS.items():
        source, target = shared / source_name, out / name
        if box is None:
            temporary = _temporary(target)
            shutil.copyfile(source, temporary)
            os.replace(temporary, target)
        else:
            crop = {".raw": crop_raw, ".nc": crop_netcdf, ".vti": crop_vti, ".vtr": crop_vtr}[source.suffix]
            crop(source, target, box)
        print(f"{name}: {target.stat().st_size:,} bytes")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED, help="the shared sample data folder")
    make(parser.parse_args().shared, HERE)
