"""Zarr volumes (a directory or ``.zarr``; format 2 or 3): a single array or an array in a group.

A store is read through :mod:`apmgsrn.data.opener`'s rules: every entry is walked before zarr reads any
(regular files only, links staying inside the store), the chosen array's declared size is checked against
what the store holds, and each file zarr then reads is opened by :class:`_GuardedStore` with the same checks
on the open descriptor.
"""

from __future__ import annotations

import functools
import io
import os
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.limits import LIMITS
from apmgsrn.data.grid import AxisCoordinates, VolumeMetadata, plain_attributes
from apmgsrn.data.opener import check_declared_array, declared_bytes, open_regular, walk_store
from apmgsrn.data.variables import ArrayInfo, choose_array, select_time
from apmgsrn.data.volume import Volume
from apmgsrn.errors import ApmgsrnError


def is_zarr_directory(path: Path) -> bool:
    """Whether a directory holds Zarr metadata at its root (format 3 or 2).

    Args:
        path: A directory.

    Returns:
        True for a Zarr array or group.
    """
    return any((path / name).is_file() for name in ("zarr.json", ".zarray", ".zgroup"))


def _read_store_file(path: Path, store: Path, prototype: Any, byte_range: Any) -> Any:
    """What zarr's local store reads for a key, opened by the opener's rules (None for a missing key)."""
    from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest

    if not os.path.lexists(path) or (path.is_dir() and not path.is_symlink()):
        return None  # a missing chunk is the fill value; a folder is no key
    with open_regular(path, store, container=store) as handle:
        if byte_range is None:
            return prototype.buffer.from_bytes(handle.read())
        size = handle.seek(0, io.SEEK_END)
        if isinstance(byte_range, RangeByteRequest):
            handle.seek(byte_range.start)
            return prototype.buffer.from_bytes(handle.read(max(0, byte_range.end - byte_range.start)))
        if isinstance(byte_range, OffsetByteRequest):
            handle.seek(byte_range.offset)
        elif isinstance(byte_range, SuffixByteRequest):
            handle.seek(max(0, size - byte_range.suffix))
        else:
            raise TypeError(f"unexpected byte range {byte_range!r}")
        return prototype.buffer.from_bytes(handle.read())


@functools.cache
def _guarded_store_class() -> type:
    """zarr's ``LocalStore`` whose reads open files through the opener (built once, on first use: zarr is
    imported only when a store is opened)."""
    import asyncio

    from zarr.core.buffer.core import default_buffer_prototype
    from zarr.storage import LocalStore

    class _GuardedStore(LocalStore):
        """A read-only local store: each file read must be a regular file inside the store (checked on the
        open descriptor, so a chunk swapped for a pipe or a link out after the walk is still refused)."""

        def _read(self, key: str, prototype: Any, byte_range: Any) -> Any:
            prototype = prototype or default_buffer_prototype()
            return _read_store_file(self.root / key, self.root, prototype, byte_range)

        def get_sync(self, key: str, *, prototype: Any = None, byte_range: Any = None) -> Any:
            self._ensure_open_sync()
            return self._read(key, prototype, byte_range)

        async def get(self, key: str, prototype: Any = None, byte_range: Any = None) -> Any:
            if not self._is_open:
                await self._open()
            return await asyncio.to_thread(self._read, key, prototype, byte_range)

        async def get_partial_values(self, prototype: Any, key_ranges: Any) -> list:
            return [await self.get(key, prototype, byte_range) for key, byte_range in key_ranges]

    return _GuardedStore


def _open_zarr_node(path: Path) -> Any:
    import zarr

    try:
        store = _guarded_store_class()(Path(path).resolve(), read_only=True)
        return zarr.open(store=store, mode="r")
    except ApmgsrnError:
        raise
    except Exception as exc:  # zarr raises many types (FileNotFound, GroupNotFound, JSON, ...)
        raise ApmgsrnError(
            f"{path}: not a readable Zarr array or group ({type(exc).__name__}: {exc}); "
            "check that it is a Zarr store and not damaged"
        ) from exc


def _numpy_dtype(array: Any) -> np.dtype | None:
    try:
        return np.dtype(array.dtype)
    except TypeError:
        return None


def _zarr_metadata(node: Any, array: Any) -> VolumeMetadata:
    """Attributes of a Zarr array, and its dimension names and coordinate arrays where xarray wrote them
    (``_ARRAY_DIMENSIONS`` or Zarr 3's ``dimension_names``; a dimension's coordinates are the 1-D array of its
    name in the same group)."""
    import zarr

    attributes = dict(array.attrs)
    # Zarr 2 stores: xarray's _ARRAY_DIMENSIONS attribute; Zarr 3: the array's own dimension_names.
    dimensions = attributes.pop("_ARRAY_DIMENSIONS", None) or getattr(getattr(array, "metadata", None),
                                                                      "dimension_names", None)
    dimensions = list(dimensions) if isinstance(dimensions, (list, tuple)) else None
    if not (isinstance(dimensions, list) and len(dimensions) >= 3 and all(isinstance(d, str) for d in dimensions)):
        return VolumeMetadata(attributes=plain_attributes(attributes))
    dimensions = tuple(dimensions[-3:])
    coordinates = []
    for dimension, length in zip(dimensions, array.shape[-3:]):
        member = node[dimension] if isinstance(node, zarr.Group) and dimension in node else None
        if isinstance(member, zarr.Array) and member.shape == (length,) and _numpy_dtype(member).kind in "uif":
            values = np.asarray(member[:], dtype=np.float64)
            attrs = {k: v for k, v in member.attrs.items() if k != "_ARRAY_DIMENSIONS"}
            coordinates.append(AxisCoordinates.from_values(dimension, values, plain_attributes(attrs))
                               if np.all(np.isfinite(values)) else None)
        else:
            coordinates.append(None)
    return VolumeMetadata(attributes=plain_attributes(attributes), dimensions=dimensions,
                          coordinates=tuple(coordinates) if any(c is not None for c in coordinates) else None)


def _check_store_sizes(path: Path, node: Any, info: ArrayInfo, shape: tuple[int, int, int], files: Any) -> None:
    """Refuse a store whose chosen array declares more than its files hold, or holding a data file larger
    than any of its arrays (a chunk is never larger than its array, plus a codec's few bytes)."""
    import zarr

    check_declared_array(path, info.name if info.name != path.name else None, shape, info.dtype, files.total_bytes)
    members = [node] if isinstance(node, zarr.Array) else [m for _, m in node.members(max_depth=None)
                                                          if isinstance(m, zarr.Array)]
    largest_array = max((declared_bytes(m.shape, _numpy_dtype(m)) for m in members), default=0)
    if files.largest is not None and files.largest_bytes > largest_array + LIMITS.declared_slack:
        raise ApmgsrnError(
            f"{path}: its file {files.largest} is {files.largest_bytes:,} bytes, more than its largest array "
            f"declares ({largest_array:,}); the store is damaged"
        )


class ZarrVolume(Volume):
    """A 3-D Zarr array, read chunk-wise (only the chunks of the requested region).

    Args:
        path: The Zarr directory (array or group).
        variable: Array path inside a group (e.g. ``"density"`` or ``"fields/density"``); default:
            the only 3-D array of the group. Must be ``None`` when `path` is a single array.
        time: Time index for a 4-D ``(t, z, y, x)`` array.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        root: The folder the store must lie in (None: anywhere); its files must lie in the store itself.
    """

    def __init__(
        self, path: Path, variable: str | None = None, time: int | None = None, fill_nonfinite: float | None = None,
        root: Path | None = None,
    ) -> None:
        import zarr

        path = Path(path)
        files = walk_store(path, root)
        node = _open_zarr_node(path)
        if isinstance(node, zarr.Array):
            if variable is not None:
                raise ApmgsrnError(f"{path}: is a single Zarr array, not a group; drop variable={variable!r}",
                                   arguments=("variable",))
            info = ArrayInfo(name=path.name, shape=tuple(node.shape), dtype=_numpy_dtype(node))
            name = None
        else:
            arrays = [
                ArrayInfo(name=key, shape=tuple(member.shape), dtype=_numpy_dtype(member))
                for key, member in node.members(max_depth=None)
                if isinstance(member, zarr.Array)
            ]
            info = choose_array(path, arrays, variable, "array")
            name = info.name
        time_index, shape = select_time(path, info, time, "array")
        _check_store_sizes(path, node, info, shape, files)
        super().__init__(path, name, shape, info.dtype, fill_nonfinite, time=time_index,
                         time_steps=info.shape[0] if len(info.shape) == 4 else None)
        self.metadata = _zarr_metadata(node, node if name is None else node[name])

    def _open_handle(self) -> Any:
        node = _open_zarr_node(self.path)  # every file it reads is opened by the store's rules
        return node if self.variable is None else node[self.variable]

    def _close_handle(self, handle: Any) -> None:
        return None  # a zarr.Array holds no open file

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        array = self._get_handle()
        key = (self.time, z, y, x) if self.time is not None else (z, y, x)
        try:
            return np.asarray(array[key])
        except ApmgsrnError:
            raise
        except Exception as exc:  # a damaged chunk surfaces as a codec-specific error type
            raise ApmgsrnError(
                f"{self.path}: cannot read region z={z.start}:{z.stop} y={y.start}:{y.stop} x={x.start}:{x.stop} "
                f"({type(exc).__name__}: {exc}); the Zarr store may be damaged"
            ) from exc
