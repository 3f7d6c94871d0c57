"""VTK XML volumes: ImageData (``.vti``) and RectilinearGrid (``.vtr``), point or cell arrays.

These files are small and zlib-compressed, so the chosen array is loaded whole at open. vtk is an
optional extra and is imported only here, when such a file is opened.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from apmgsrn.data.variables import ArrayInfo, choose_array
from apmgsrn.data.volume import ArrayVolume
from apmgsrn.errors import ApmgsrnError

#: Reader class and a human name per suffix.
_READERS = {
    ".vti": ("vtkXMLImageDataReader", "ImageData (.vti)"),
    ".vtr": ("vtkXMLRectilinearGridReader", "RectilinearGrid (.vtr)"),
}


def _read_vtk_arrays(path: Path) -> dict[str, tuple[ArrayInfo, np.ndarray]]:
    """Every point and cell array of a VTK XML file, reshaped to C order (z, y, x[, components])."""
    try:
        from vtkmodules import vtkIOXML
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkCommonCore import vtkObject
    except ImportError as exc:
        raise ApmgsrnError(
            f"{path}: reading VTK files needs the optional vtk package; run `pip install apmgsrn[vtk]`"
        ) from exc
    class_name, label = _READERS[path.suffix.lower()]
    reader = getattr(vtkIOXML, class_name)()
    if not reader.CanReadFile(str(path)):
        raise ApmgsrnError(
            f"{path}: not a readable VTK XML {label} file; check the file type and that it is not damaged"
        )
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
    arrays: dict[str, tuple[ArrayInfo, np.ndarray]] = {}
    for attributes, dims in ((grid.GetPointData(), (nz, ny, nx)), (grid.GetCellData(), cells)):
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
            arrays[name] = (ArrayInfo(name=name, shape=shape, dtype=values.dtype), values)
    return arrays


class VTKVolume(ArrayVolume):
    """A scalar point or cell array of a ``.vti``/``.vtr`` file, held in memory.

    Rectilinear coordinates are not used: voxels are treated as a regular grid, like every
    other format.

    Args:
        path: The ``.vti`` or ``.vtr`` file.
        variable: Array name; default: the only array in the file.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
    """

    def __init__(self, path: Path, variable: str | None = None, fill_nonfinite: float | None = None) -> None:
        path = Path(path)
        arrays = _read_vtk_arrays(path)
        info = choose_array(path, [info for info, _ in arrays.values()], variable, "array", default_ndims=(3, 4))
        if len(info.shape) == 4:
            raise ApmgsrnError(
                f"{path}: array {info.summary()} has {info.shape[3]} components; "
                "apmgsrn needs a scalar array: pass --variable with a 1-component array"
            )
        super().__init__(arrays[info.name][1], path, info.name, fill_nonfinite)
