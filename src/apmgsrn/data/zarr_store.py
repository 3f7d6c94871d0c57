"""Zarr volumes (a directory or ``.zarr``; format 2 or 3): a single array or an array in a group."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.grid import AxisCoordinates, VolumeMetadata, plain_attributes
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


def _open_zarr_node(path: Path) -> Any:
    import zarr

    try:
        return zarr.open(store=str(path), mode="r")
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


class ZarrVolume(Volume):
    """A 3-D Zarr array, read chunk-wise (only the chunks of the requested region).

    Args:
        path: The Zarr directory (array or group).
        variable: Array path inside a group (e.g. ``"density"`` or ``"fields/density"``); default:
            the only 3-D array of the group. Must be ``None`` when `path` is a single array.
        time: Time index for a 4-D ``(t, z, y, x)`` array.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
    """

    def __init__(
        self, path: Path, variable: str | None = None, time: int | None = None, fill_nonfinite: float | None = None
    ) -> None:
        import zarr

        path = Path(path)
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
        super().__init__(path, name, shape, info.dtype, fill_nonfinite, time=time_index)
        self.metadata = _zarr_metadata(node, node if name is None else node[name])

    def _open_handle(self) -> Any:
        node = _open_zarr_node(self.path)
        return node if self.variable is None else node[self.variable]

    def _close_handle(self, handle: Any) -> None:
        return None  # a zarr.Array holds no open file

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        array = self._get_handle()
        key = (self.time, z, y, x) if self.time is not None else (z, y, x)
        try:
            return np.asarray(array[key])
        except Exception as exc:  # a damaged chunk surfaces as a codec-specific error type
            raise ApmgsrnError(
                f"{self.path}: cannot read region z={z.start}:{z.stop} y={y.start}:{y.stop} x={x.start}:{x.stop} "
                f"({type(exc).__name__}: {exc}); the Zarr store may be damaged"
            ) from exc
