"""VTK XML volumes: ImageData (``.vti``) and RectilinearGrid (``.vtr``), point or cell arrays.

These files are small and zlib-compressed, so the chosen array is loaded whole at open. vtk is an
optional extra and is imported only here, when such a file is opened.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from apmgsrn.data.grid import AxisCoordinates, VolumeMetadata
from apmgsrn.data.opener import check_regular, memory_budget, open_regular
from apmgsrn.data.variables import ArrayInfo, choose_array
from apmgsrn.data.volume import ArrayVolume
from apmgsrn.errors import ApmgsrnError

#: Reader class and a human name per suffix.
_READERS = {
    ".vti": ("vtkXMLImageDataReader", "ImageData (.vti)"),
    ".vtr": ("vtkXMLRectilinearGridReader", "RectilinearGrid (.vtr)"),
}


#: Largest expansion of stored bytes each compressor can give (zlib's is 1032:1, LZ4's about 255:1);
#: a file declaring more data than this times its own size cannot hold it. LZMA has no small bound.
COMPRESSION_BOUND = {"": 1.0, "vtkZLibDataCompressor": 1100.0, "vtkLZ4DataCompressor": 300.0}


def check_declared_size(path: Path, header_bytes: int = 16 << 20) -> None:
    """Refuse a VTK XML file whose declared extents it cannot hold, or that would not fit in memory,
    before VTK allocates anything (a 335-byte file declaring 2001^3 points would abort the process).
    The first ``header_bytes`` are searched for the extents (the appended data follows the XML header).

    Raises:
        ApmgsrnError: the declared data is larger than the file could hold or than the memory budget (half the
            free memory, :func:`~apmgsrn.data.opener.memory_budget`).
    """
    with open_regular(path) as f:
        head = f.read(header_bytes)
    head = head.split(b"<AppendedData", 1)[0].decode("latin-1")
    extents = re.findall(r'\b(?:Whole)?Extent\s*=\s*"([^"]*)"', head)
    arrays = max(1, len(re.findall(r"<DataArray\b", head)))
    compressor = re.search(r'\bcompressor\s*=\s*"([^"]*)"', head)
    largest = 0
    for text in extents:
        try:
            low_x, high_x, low_y, high_y, low_z, high_z = (int(v) for v in text.split())
        except ValueError:
            raise ApmgsrnError(f"{path}: extent {text!r} is not six integers; the file is damaged") from None
        counts = [high_x - low_x + 1, high_y - low_y + 1, high_z - low_z + 1]
        if min(counts) < 1:
            raise ApmgsrnError(f"{path}: extent {text!r} is empty or inverted; the file is damaged")
        largest = max(largest, counts[0] * counts[1] * counts[2])
    declared = largest * 4  # bytes of one float32 array of that many points
    bound = COMPRESSION_BOUND.get(compressor.group(1) if compressor else "")
    size = check_regular(path).st_size
    if bound is not None and declared > bound * size + 4096:
        raise ApmgsrnError(
            f"{path}: declares {largest:,} points ({declared / 2**30:.1f} GiB a float32 array) but the file is only "
            f"{size:,} bytes; it is damaged or truncated"
        )
    if declared * arrays > memory_budget():
        raise ApmgsrnError(
            f"{path}: declares {arrays} array(s) of {largest:,} points ({declared * arrays / 2**30:.1f} GiB), more "
            "than half the free memory; this reader holds .vti/.vtr data in memory: convert the file to NetCDF, "
            "HDF5 or Zarr, which are read lazily"
        )


def _read_vtk_arrays(path: Path) -> tuple[dict[str, tuple[ArrayInfo, np.ndarray, bool]], object]:
    """Every point and cell array of a VTK XML file, reshaped to C order (z, y, x[, components]), each with
    whether it is a cell array; and the grid (for its geometry)."""
    try:
        from vtkmodules import vtkIOXML
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkCommonCore import vtkObject
    except ImportError as exc:
        raise ApmgsrnError(
            f"{path}: reading VTK files needs the optional vtk package; run `pip install apmgsrn[vtk]`"
        ) from exc
    class_name, label = _READERS[path.suffix.lower()]
    check_regular(path)  # VTK opens the file by name: a pipe would block it
    reader = getattr(vtkIOXML, class_name)()
    if not reader.CanReadFile(str(path)):
        raise ApmgsrnError(
            f"{path}: not a readable VTK XML {label} file; check the file type and that it is not damaged"
        )
    check_declared_size(path)
    reader.SetFileName(str(path))
    # VTK prints parse errors of damaged files to stderr; silence them and check the output instead.
    warnings_were_on = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    try:
        reader.Update()
    finally:
        vtkObject.SetGlobalWarningDisplay(warnings_were_on)
    grid = reader.GetOutput()
    nx, ny, nz = grid.GetDimensions()  # point counts, x first
    if min(nx, ny, nz) <= 0:
        raise ApmgsrnError(f"{path}: VTK could not read the data (damaged or truncated {label} file)")
    # A cell spans two points, except along an axis with a single point (a flat grid).
    cells = tuple(max(n - 1, 1) for n in (nz, ny, nx))
    arrays: dict[str, tuple[ArrayInfo, np.ndarray, bool]] = {}
    for attributes, dims, cell in ((grid.GetPointData(), (nz, ny, nx), False), (grid.GetCellData(), cells, True)):
        for index in range(attributes.GetNumberOfArrays()):
            vtk_array = attributes.GetArray(index)
            name = attributes.GetArrayName(index)
            if vtk_array is None or name in arrays:  # non-numeric arrays; point data wins a name clash
                continue
            components = vtk_array.GetNumberOfComponents()
            if vtk_array.GetNumberOfTuples() != int(np.prod(dims)):
                raise ApmgsrnError(f"{path}: array {name!r} has the wrong length for the grid; the file is damaged")
            # VTK stores x fastest, which is C order (z, y, x): a plain reshape, no transpose.
            values = np.array(vtk_to_numpy(vtk_array), copy=True)
            shape = dims + ((components,) if components > 1 else ())
            values = values.reshape(shape)  # [Z, Y, X] or [Z, Y, X, C]
            arrays[name] = (ArrayInfo(name=name, shape=shape, dtype=values.dtype), values, cell)
    return arrays, grid


def _grid_coordinates(path: Path, grid, cell: bool) -> tuple[AxisCoordinates, AxisCoordinates, AxisCoordinates]:
    """Where the points (or cell centres) of a VTK grid lie, per (z, y, x) axis: ImageData's origin and
    spacing, RectilinearGrid's coordinate arrays (uneven ones kept value by value).

    Raises:
        ApmgsrnError: ImageData turned by a direction matrix (its axes are not x, y and z).
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if hasattr(grid, "GetXCoordinates"):
        corners = [vtk_to_numpy(c).astype(np.float64) for c in
                   (grid.GetZCoordinates(), grid.GetYCoordinates(), grid.GetXCoordinates())]
    else:
        if hasattr(grid, "GetDirectionMatrix"):
            matrix = grid.GetDirectionMatrix()
            direction = np.array([[matrix.GetElement(i, j) for j in range(3)] for i in range(3)])
            if not np.allclose(direction, np.eye(3)):
                raise ApmgsrnError(
                    f"{path}: its image axes are turned (Direction is not the identity); apmgsrn reads axis-aligned "
                    "grids only: resample the image onto x, y and z first"
                )
        nx, ny, nz = grid.GetDimensions()
        origin, spacing = grid.GetOrigin(), grid.GetSpacing()
        corners = [origin[a] + spacing[a] * np.arange(n, dtype=np.float64) for a, n in ((2, nz), (1, ny), (0, nx))]
    axes = []
    for name, values in zip(("z", "y", "x"), corners):
        if cell and values.size > 1:
            values = 0.5 * (values[:-1] + values[1:])  # a cell array's voxels sit at the cell centres
        axes.append(AxisCoordinates.from_values(name, values))
    return tuple(axes)


class VTKVolume(ArrayVolume):
    """A scalar point or cell array of a ``.vti``/``.vtr`` file, held in memory.

    The grid's geometry is kept (``metadata.coordinates``): ImageData's origin and spacing, RectilinearGrid's
    coordinates, uneven ones value by value (the network is fitted on voxel indices; a decode writes the
    coordinates back, and refuses formats that cannot hold uneven ones).

    Args:
        path: The ``.vti`` or ``.vtr`` file.
        variable: Array name; default: the only array in the file.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
    """

    def __init__(self, path: Path, variable: str | None = None, fill_nonfinite: float | None = None) -> None:
        path = Path(path)
        arrays, grid = _read_vtk_arrays(path)
        info = choose_array(path, [entry[0] for entry in arrays.values()], variable, "array", default_ndims=(3, 4))
        if len(info.shape) == 4:
            raise ApmgsrnError(
                f"{path}: array {info.summary()} has {info.shape[3]} components; "
                "apmgsrn needs a scalar array: pass variable= with a 1-component array", arguments=("variable",)
            )
        _, values, cell = arrays[info.name]
        metadata = VolumeMetadata(coordinates=_grid_coordinates(path, grid, cell))
        super().__init__(values, path, info.name, fill_nonfinite, metadata=metadata)
