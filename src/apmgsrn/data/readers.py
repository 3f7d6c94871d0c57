"""`open_volume`: pick the reader for a path by its suffix (or Zarr directory) and open it.

Every path goes through :mod:`apmgsrn.data.opener` first (regular files only, links resolved, inside the
root where one is given); each reader then judges the files its container reaches and the declared size.
"""

from __future__ import annotations

from pathlib import Path

from apmgsrn.data.hdf5 import HDF5Volume, check_hdf5_file
from apmgsrn.data.netcdf import check_netcdf_container, open_netcdf
from apmgsrn.data.numpy_file import NumpyVolume
from apmgsrn.data.opener import check_regular, real_path, walk_store
from apmgsrn.data.raw import RawVolume
from apmgsrn.data.volume import Volume, parse_shape
from apmgsrn.data.vtk_xml import VTKVolume
from apmgsrn.data.zarr_store import ZarrVolume, is_zarr_directory
from apmgsrn.errors import ApmgsrnError

#: Suffixes per format, as listed to users.
SUPPORTED_SUFFIXES = {
    "NetCDF": (".nc", ".nc4"),
    "HDF5": (".h5", ".hdf5"),
    "Zarr": (".zarr",),
    "raw": (".raw", ".bin"),
    "NumPy": (".npy",),
    "VTK XML": (".vti", ".vtr"),
}


def supported_formats() -> str:
    """One line listing the readable formats, for messages and ``--help``.

    Returns:
        E.g. ``"NetCDF (.nc, .nc4), HDF5 (.h5, .hdf5), ..."``.
    """
    listed = ", ".join(f"{name} ({', '.join(suffixes)})" for name, suffixes in SUPPORTED_SUFFIXES.items())
    return f"{listed}, or a Zarr directory"


def _refuse(path: Path, what: str, argument: str, value: object) -> None:
    if value is not None:
        raise ApmgsrnError(f"{path}: {argument}= does not apply to {what}; drop {argument}=", arguments=(argument,))


def open_volume(
    path: str | Path,
    variable: str | None = None,
    time: int | None = None,
    shape: tuple[int, int, int] | str | None = None,
    dtype: str | None = None,
    fill_nonfinite: float | None = None,
    root: str | Path | None = None,
) -> Volume:
    """Open a volume file lazily; nothing but metadata is read until `Volume.read`.

    Args:
        path: A ``.nc``, ``.h5``/``.hdf5``, ``.raw``/``.bin``, ``.npy``, ``.vti``/``.vtr`` file or
            a Zarr directory.
        variable: Variable (NetCDF), dataset path (HDF5), array path (Zarr group) or array name
            (VTK); default: the only 3-D one in the file.
        time: Index along a leading time dimension (NetCDF, HDF5, Zarr).
        shape: ``(X, Y, Z)`` of a raw file, x first as typed on the command line (or the text
            ``"X,Y,Z"``); stored as ``Volume.shape == (Z, Y, X)``.
        dtype: Voxel type of a raw file (``uint8``, ``float32``, ...).
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        root: The folder the file, and every file it reaches, must lie in (links followed); None: anywhere.
            A Zarr store's own files must lie in the store either way.

    Returns:
        The opened `Volume`.

    Raises:
        ApmgsrnError: For a missing or unreadable file, one that is not a regular file (a pipe, a device)
            or leads outside ``root``, an unknown format, a missing or ambiguous variable, data that is not
            3-D, raw dims that do not match the file size, or a declared size the file cannot hold.
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise ApmgsrnError(f"{path}: no such file or directory; check the path")
    root = Path(root).expanduser() if root is not None else None
    real_path(path, root)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES["raw"]:
        _refuse(path, "files with their own header (only raw .raw/.bin files)", "shape", shape)
        _refuse(path, "files with their own header (only raw .raw/.bin files)", "dtype", dtype)

    if path.is_dir():
        if suffix != ".zarr" and not is_zarr_directory(path):
            raise ApmgsrnError(
                f"{path}: is a directory but not a Zarr store (no zarr.json, .zarray or .zgroup); "
                f"give a volume file: {supported_formats()}"
            )
        return ZarrVolume(path, variable, time, fill_nonfinite, root=root)
    if not path.is_file():
        raise ApmgsrnError(f"{path}: not a regular file; give a volume file: {supported_formats()}")
    check_regular(path, root)

    if suffix in SUPPORTED_SUFFIXES["NetCDF"]:
        return open_netcdf(path, variable, time, fill_nonfinite, root=root)
    if suffix in SUPPORTED_SUFFIXES["HDF5"]:
        return HDF5Volume(path, variable, time, fill_nonfinite, root=root)
    if suffix in SUPPORTED_SUFFIXES["Zarr"]:
        return ZarrVolume(path, variable, time, fill_nonfinite, root=root)
    if suffix in SUPPORTED_SUFFIXES["raw"]:
        _refuse(path, "raw files (they hold a single array)", "variable", variable)
        _refuse(path, "raw files (they have no time dimension)", "time", time)
        if isinstance(shape, str):
            shape = parse_shape(shape)
        return RawVolume(path, shape, dtype, fill_nonfinite)
    if suffix in SUPPORTED_SUFFIXES["NumPy"]:
        _refuse(path, ".npy files (they hold a single array)", "variable", variable)
        _refuse(path, ".npy files (they have no time dimension)", "time", time)
        return NumpyVolume(path, fill_nonfinite)
    if suffix in SUPPORTED_SUFFIXES["VTK XML"]:
        _refuse(path, "VTK XML files (they have no time dimension)", "time", time)
        return VTKVolume(path, variable, fill_nonfinite)
    raise ApmgsrnError(
        f"{path}: unknown volume format {suffix or '(no suffix)'!r}; supported: {supported_formats()}"
    )


def check_volume_path(path: str | Path, root: str | Path | None = None) -> None:
    """The opener's checks of a volume that need no reader: the path and every file its container reaches
    (a Zarr store's files, an HDF5 or NetCDF-4 file's external storage and links), without reading any data.
    What the viewer lists is what passes here under its served folder.

    Args:
        path: a volume file or Zarr store.
        root: the folder everything must lie in (None: anywhere).

    Raises:
        ApmgsrnError: as :func:`open_volume` for these checks.
    """
    path = Path(path)
    real = real_path(path, root)
    if real.is_dir():
        walk_store(path, root)
        return
    check_regular(path, root)
    suffix = path.suffix.lower()
    if suffix in SUPPORTED_SUFFIXES["NetCDF"]:
        check_netcdf_container(path, root)
    elif suffix in SUPPORTED_SUFFIXES["HDF5"]:
        check_hdf5_file(path, root)
