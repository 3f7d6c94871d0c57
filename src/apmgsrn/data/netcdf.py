"""NetCDF volumes (``.nc``): netCDF4 by default, h5py for NetCDF-4 files if netCDF4 is missing."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.grid import AxisCoordinates, VolumeMetadata, plain_attributes
from apmgsrn.data.hdf5 import HDF5Volume, check_hdf5_container
from apmgsrn.data.opener import check_declared_array, check_regular, open_regular
from apmgsrn.data.variables import ArrayInfo, choose_array, select_time
from apmgsrn.data.volume import Volume
from apmgsrn.errors import ApmgsrnError

#: NetCDF convention: data variables are (z, y, x) or (time, z, y, x); 1-D ones are coordinates.
NETCDF_DEFAULT_NDIMS = (3, 4)


def open_netcdf(
    path: Path, variable: str | None = None, time: int | None = None, fill_nonfinite: float | None = None,
    root: Path | None = None,
) -> Volume:
    """Open a NetCDF file with netCDF4, or with h5py when netCDF4 cannot be imported.

    Args:
        path: The ``.nc`` file.
        variable: Variable name (a path such as ``"group/var"`` for grouped files); default: the
            only 3-D or (time, z, y, x) variable.
        time: Index along a leading time dimension.
        fill_nonfinite: If set, reads replace NaN/Inf (and missing values) by this value.
        root: The folder every file it reaches must lie in (None: anywhere).

    Returns:
        A `NetCDFVolume`, or a `NetCDFThroughHDF5Volume` without netCDF4.
    """
    try:
        import netCDF4  # noqa: F401
    except ImportError:
        return NetCDFThroughHDF5Volume(Path(path), variable, time, fill_nonfinite, root=root)
    return NetCDFVolume(Path(path), variable, time, fill_nonfinite, root=root)


#: Where HDF5 looks for its signature: offset 0, then 512, 1024, 2048, ... (a user block before it).
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _is_hdf5(path: Path) -> bool:
    """Whether a file is HDF5-based (NetCDF-4), by the signature at 0 or a power of two from 512 on."""
    with open_regular(path) as handle:
        size = os.fstat(handle.fileno()).st_size
        offset = 0
        while offset + len(_HDF5_SIGNATURE) <= size:
            handle.seek(offset)
            if handle.read(len(_HDF5_SIGNATURE)) == _HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else offset * 2
    return False


def check_netcdf_container(path: Path, root: Path | None = None) -> int:
    """Judge the files a NetCDF file makes the library read (a NetCDF-4 file is HDF5: its external storage
    and links, see :func:`~apmgsrn.data.hdf5.check_hdf5_container`), before netCDF4 opens it.

    Returns:
        The bytes the file and its external storage hold together.

    Raises:
        ApmgsrnError: not a regular file inside ``root``, or a NetCDF-4 file reaching a file it may not.
    """
    size = check_regular(path, root).st_size
    if not _is_hdf5(path):
        return size
    import h5py

    try:
        handle = h5py.File(path, "r", locking=False)
    except (OSError, ValueError):
        return size  # not readable as HDF5: netCDF4 says what is wrong with it
    with handle:
        return size + sum(check_hdf5_container(handle, path, root).values())


def _open_netcdf_file(path: Path) -> Any:
    import netCDF4

    try:
        handle = netCDF4.Dataset(path, "r")
    except (OSError, RuntimeError, ValueError) as exc:
        raise ApmgsrnError(
            f"{path}: not a readable NetCDF file ({exc}); check that it is NetCDF-3 or NetCDF-4 and not truncated"
        ) from exc
    # Plain arrays unless a value really is missing; missing values become NaN in Volume.read.
    handle.set_always_mask(False)
    return handle


def _list_variables(group: Any, prefix: str = "") -> list[ArrayInfo]:
    """Variables of a NetCDF group and its subgroups, named by path."""
    found = []
    for name, var in group.variables.items():
        dtype = var.dtype if isinstance(var.dtype, np.dtype) and var.dtype.kind != "V" else None
        if type(var.datatype).__name__ in ("VLType", "CompoundType"):
            dtype = None
        found.append(ArrayInfo(name=prefix + name, shape=tuple(var.shape), dtype=dtype, dims=tuple(var.dimensions)))
    for name, child in group.groups.items():
        found.extend(_list_variables(child, f"{prefix}{name}/"))
    return found


class NetCDFVolume(Volume):
    """A variable of a NetCDF-3/4 file read with netCDF4; only the requested region is read.

    Scale/offset attributes are applied and missing values (``_FillValue``) come back as NaN.

    Args:
        path: The ``.nc`` file.
        variable: Variable name or group path; default: the only 3-D or 4-D variable.
        time: Index along a leading time dimension (required when it has more than one step).
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        root: The folder every file it reaches must lie in (None: anywhere).
    """

    def __init__(
        self, path: Path, variable: str | None = None, time: int | None = None, fill_nonfinite: float | None = None,
        root: Path | None = None,
    ) -> None:
        path = Path(path)
        stored = check_netcdf_container(path, root)
        handle = _open_netcdf_file(path)
        try:
            info = choose_array(path, _list_variables(handle), variable, "variable", NETCDF_DEFAULT_NDIMS)
            time_index, shape = select_time(path, info, time, "variable")
            check_declared_array(path, info.name, shape, info.dtype, stored)
            self.dimensions = info.dims
            super().__init__(path, info.name, shape, info.dtype, fill_nonfinite, time=time_index,
                             time_steps=info.shape[0] if len(info.shape) == 4 else None)
            self.metadata = netcdf_metadata(handle, info.name)
        except BaseException:
            handle.close()
            raise
        self._handle, self._handle_pid = handle, os.getpid()
        self._root = root

    def _open_handle(self) -> Any:
        check_netcdf_container(self.path, self._root)  # the file may have changed since it was opened
        return _open_netcdf_file(self.path)

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        var = self._get_handle()[self.variable]
        if self.time is not None:
            return var[self.time, z, y, x]
        return var[z, y, x]


def netcdf_metadata(handle: Any, name: str) -> VolumeMetadata:
    """Attributes, dimension names, coordinate variables and compression of the variable ``name``.

    A dimension's coordinate variable is the 1-D variable of the same name over that dimension, in the
    variable's group or a parent group (the NetCDF convention); uneven coordinates are kept value by value.
    """
    variable = handle[name]
    dimensions = tuple(variable.dimensions[-3:])
    coordinates = []
    for dimension, length in zip(dimensions, variable.shape[-3:]):
        coordinate = _coordinate_variable(variable.group(), dimension)
        if coordinate is None or coordinate.shape != (length,) or coordinate.dtype.kind not in "uif":
            coordinates.append(None)
            continue
        values = np.ma.filled(np.ma.asarray(coordinate[:]).astype(np.float64), np.nan)
        if not np.all(np.isfinite(values)):  # missing coordinates place nothing
            coordinates.append(None)
            continue
        attributes = plain_attributes({k: coordinate.getncattr(k) for k in coordinate.ncattrs()})
        coordinates.append(AxisCoordinates.from_values(dimension, values, attributes))
    filters = variable.filters() or {}
    compression = None
    if filters.get("zlib"):
        compression = {"zlib": True, "complevel": int(filters.get("complevel") or 4),
                       "shuffle": bool(filters.get("shuffle"))}
    return VolumeMetadata(
        attributes=plain_attributes({k: variable.getncattr(k) for k in variable.ncattrs()}),
        dimensions=dimensions if len(dimensions) == 3 else None,
        coordinates=tuple(coordinates) if any(c is not None for c in coordinates) else None,
        compression=compression,
    )


def _coordinate_variable(group: Any, dimension: str) -> Any:
    """The coordinate variable of ``dimension`` seen from ``group`` (searching up to the root), or None."""
    while group is not None:
        if dimension in group.variables:
            return group.variables[dimension]
        group = group.parent
    return None


class NetCDFThroughHDF5Volume(HDF5Volume):
    """A NetCDF-4 variable read with h5py (the fallback when netCDF4 is not installed).

    NetCDF-4 files are HDF5 files whose variables are datasets; this applies the NetCDF
    conventions netCDF4 would: ``scale_factor``/``add_offset`` and ``_FillValue``/``missing_value``
    as NaN.
    """

    kind = "variable"

    def __init__(
        self, path: Path, variable: str | None = None, time: int | None = None, fill_nonfinite: float | None = None,
        root: Path | None = None,
    ) -> None:
        try:
            super().__init__(path, variable, time, fill_nonfinite, default_ndims=NETCDF_DEFAULT_NDIMS, root=root)
        except ApmgsrnError as exc:
            if "not a readable HDF5 file" in str(exc):
                raise ApmgsrnError(
                    f"{path}: cannot read this NetCDF file: netCDF4 is not installed and the file is not "
                    "NetCDF-4/HDF5 (NetCDF-3 needs netCDF4); run `pip install netCDF4`"
                ) from exc
            raise

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        data = super()._read_stored(z, y, x)
        attrs = self._dataset_attributes
        missing = [attrs[k] for k in ("_FillValue", "missing_value") if k in attrs]
        scale, offset = attrs.get("scale_factor"), attrs.get("add_offset")
        if not missing and scale is None and offset is None:
            return data
        values = data.astype(np.float64 if data.dtype.itemsize > 4 else np.float32)
        for marker in missing:
            values[data == marker] = np.nan
        if scale is not None:
            values *= scale
        if offset is not None:
            values += offset
        return values
