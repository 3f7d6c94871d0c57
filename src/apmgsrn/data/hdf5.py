"""HDF5 volumes (``.h5``/``.hdf5``) through h5py, read lazily by hyperslab.

An HDF5 file may make the library read other files: a dataset's external storage (raw bytes in files named
in the dataset), a virtual dataset's sources, and external links. Before a dataset is chosen,
:func:`check_hdf5_container` judges every such file by :mod:`apmgsrn.data.opener`'s rules: external
storage must be regular files (inside the root, where one is given); links to other files, user-defined
links and virtual datasets reading other files are refused.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.grid import VolumeMetadata, plain_attributes
from apmgsrn.data.opener import check_declared_array, check_regular
from apmgsrn.data.variables import ArrayInfo, choose_array, select_time
from apmgsrn.data.volume import Volume
from apmgsrn.errors import ApmgsrnError


def _open_hdf5_file(path: Path) -> Any:
    """Open an HDF5 file read-only, turning library errors into a message naming the file."""
    import h5py

    check_regular(path)
    try:
        # No file locking: sample data often sits on read-only or network file systems where
        # HDF5's lock fails, and nothing here writes to the file.
        return h5py.File(path, "r", locking=False)
    except (OSError, ValueError) as exc:
        raise ApmgsrnError(
            f"{path}: not a readable HDF5 file ({exc}); check that the file is HDF5 and not truncated"
        ) from exc


def _external_base(path: Path) -> Path:
    """Where HDF5 looks for relative external-storage names: ``HDF5_EXTFILE_PREFIX`` when set (``${ORIGIN}``
    standing for the file's folder), else the current folder (the library's default)."""
    prefix = os.environ.get("HDF5_EXTFILE_PREFIX")
    if prefix:
        return Path(prefix.replace("${ORIGIN}", str(Path(path).resolve().parent)))
    return Path.cwd()


def _external_bytes(path: Path, name: str, dataset: Any, root: Path | None) -> int:
    """Check a dataset's external storage files; the bytes they really hold for it."""
    stored = 0
    for file, offset, size in dataset.external or ():
        file = os.fsdecode(file)
        target = Path(file) if os.path.isabs(file) else _external_base(path) / file
        status = check_regular(target, root, container=path, role=f"dataset {name!r}: its external storage")
        stored += max(0, min(int(size), status.st_size - int(offset)))
    return stored


def check_hdf5_container(handle: Any, path: Path, root: Path | None = None) -> dict[str, int]:
    """Judge every file an open HDF5 file makes the library read, before any data is read.

    Args:
        handle: the open ``h5py.File``.
        path: its path, for messages and relative names.
        root: the folder every file reached must lie in (None: anywhere).

    Returns:
        The bytes each dataset's external storage really holds, by dataset name (datasets without external
        storage are absent).

    Raises:
        ApmgsrnError: an external or user-defined link, a virtual dataset reading another file, or external
            storage that is not a regular file inside ``root``.
    """
    import h5py

    links: list[tuple[str, int]] = []
    handle.id.links.visit(lambda name, info: links.append((os.fsdecode(name), info.type)), info=True)
    for name, kind in links:
        if kind == h5py.h5l.TYPE_EXTERNAL:
            raise ApmgsrnError(f"{path}: {name!r} is a link to another file; apmgsrn reads self-contained HDF5 "
                               "files only (copy the data in, e.g. with h5copy)")
        if kind not in (h5py.h5l.TYPE_HARD, h5py.h5l.TYPE_SOFT):
            raise ApmgsrnError(f"{path}: {name!r} is a user-defined link; apmgsrn reads plain HDF5 files only")
    external: dict[str, int] = {}

    def visit(name: str, obj: Any) -> None:
        if not isinstance(obj, h5py.Dataset):
            return
        if obj.is_virtual and any(source.file_name != "." for source in obj.virtual_sources()):
            raise ApmgsrnError(f"{path}: dataset {name!r} is a virtual dataset reading other files; apmgsrn reads "
                               "self-contained HDF5 files only (copy the data in, e.g. with h5repack)")
        if obj.external:
            external[name] = _external_bytes(path, name, obj, root)

    handle.visititems(visit)
    return external


def check_hdf5_file(path: Path, root: Path | None = None) -> None:
    """Open an HDF5 file and :func:`check_hdf5_container` it (for a check without a reader).

    Raises:
        ApmgsrnError: not a readable HDF5 file, or one reaching a file it may not.
    """
    handle = _open_hdf5_file(path)
    with handle:
        check_hdf5_container(handle, path, root)


def stored_bytes(handle: Any, name: str, external: dict[str, int]) -> int:
    """Bytes an HDF5 file really stores for a dataset: its external storage, else its allocated storage
    (never more than the file itself)."""
    if name in external:
        return external[name]
    try:
        allocated = handle[name].id.get_storage_size()
    except (OSError, ValueError, KeyError):
        allocated = 0
    return min(int(allocated), int(handle.id.get_filesize())) if allocated else 0


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
        root: The folder every file it reaches (external storage) must lie in (None: anywhere).
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
        root: Path | None = None,
    ) -> None:
        path = Path(path)
        handle = _open_hdf5_file(path)
        try:
            external = check_hdf5_container(handle, path, root)
            info = choose_array(path, list_hdf5_datasets(handle), variable, self.kind, default_ndims)
            time_index, shape = select_time(path, info, time, self.kind)
            check_declared_array(path, info.name, shape, info.dtype, stored_bytes(handle, info.name, external))
            self._dataset_attributes = {k: _plain(v) for k, v in handle[info.name].attrs.items()}
            super().__init__(path, info.name, shape, info.dtype, fill_nonfinite, time=time_index,
                             time_steps=info.shape[0] if len(info.shape) == 4 else None)
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
        self._root = root

    def _open_handle(self) -> Any:
        handle = _open_hdf5_file(self.path)
        try:
            check_hdf5_container(handle, self.path, self._root)  # the file may have changed since it was opened
        except BaseException:
            handle.close()
            raise
        return handle

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
