"""HDF5 volumes (``.h5``/``.hdf5``) through h5py, read lazily by hyperslab."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.grid import VolumeMetadata, plain_attributes
from apmgsrn.data.variables import ArrayInfo, choose_array, select_time
from apmgsrn.data.volume import Volume
from apmgsrn.errors import ApmgsrnError


def _open_hdf5_file(path: Path) -> Any:
    """Open an HDF5 file read-only, turning library errors into a message naming the file."""
    import h5py

    try:
        # No file locking: sample data often sits on read-only or network file systems where
        # HDF5's lock fails, and nothing here writes to the file.
        return h5py.File(path, "r", locking=False)
    except (OSError, ValueError) as exc:
        raise ApmgsrnError(
            f"{path}: not a readable HDF5 file ({exc}); check that the file is HDF5 and not truncated"
        ) from exc


def list_hdf5_datasets(handle: Any) -> list[ArrayInfo]:
    """Every dataset in an open HDF5 file, searching all groups.

    Args:
        handle: An open ``h5py.File``.

    Returns:
        One `ArrayInfo` per dataset, named by its path without the leading ``/``.
    """
    import h5py

    found: list[ArrayInfo] = []

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            found.append(ArrayInfo(name=name, shape=tuple(obj.shape or ()), dtype=obj.dtype))

    handle.visititems(visit)
    return found


class HDF5Volume(Volume):
    """A 3-D dataset of an HDF5 file, read by hyperslab (only the requested region).

    Args:
        path: The ``.h5``/``.hdf5`` file.
        variable: Dataset path (e.g. ``"densityfield"`` or ``"fields/rho"``); default: the only
            3-D dataset in the file.
        time: Time index for a named 4-D ``(t, z, y, x)`` dataset.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        default_ndims: Dimension counts eligible for the default choice.
    """

    #: What error messages call the arrays of this format.
    kind = "dataset"

    def __init__(
        self,
        path: Path,
        variable: str | None = None,
        time: int | None = None,
        fill_nonfinite: float | None = None,
        default_ndims: tuple[int, ...] = (3,),
    ) -> None:
        path = Path(path)
        handle = _open_hdf5_file(path)
        try:
            info = choose_array(path, list_hdf5_datasets(handle), variable, self.kind, default_ndims)
            time_index, shape = select_time(path, info, time, self.kind)
            self._dataset_attributes = {k: _plain(v) for k, v in handle[info.name].attrs.items()}
            super().__init__(path, info.name, shape, info.dtype, fill_nonfinite, time=time_index)
            dataset = handle[info.name]
            compression = None
            if dataset.compression == "gzip":
                compression = {"zlib": True, "complevel": int(dataset.compression_opts or 4),
                               "shuffle": bool(dataset.shuffle)}
            self.metadata = VolumeMetadata(attributes=plain_attributes(self._dataset_attributes),
                                           compression=compression)
        except BaseException:
            handle.close()
            raise
        # Keep the handle opened for inspection, so the first read does not reopen the file.
        self._handle, self._handle_pid = handle, os.getpid()

    def _open_handle(self) -> Any:
        return _open_hdf5_file(self.path)

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        dataset = self._get_handle()[self.variable]
        if self.time is not None:
            return dataset[self.time, z, y, x]
        return dataset[z, y, x]


def _plain(value: Any) -> Any:
    """HDF5 attribute values as plain Python/NumPy scalars (bytes decoded)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.size == 1:
        return value.reshape(()).item()
    return value
