"""The lazy `Volume`: a 3-D scalar field on disk, read region by region as float32.

Every reader (NetCDF, HDF5, Zarr, raw, npy, VTK XML) is a subclass that only knows how to fetch a
region of the stored array; this base class turns that into float32 C-contiguous arrays, replaces
non-finite values when asked, streams statistics over z-slabs and keeps file handles safe to use
after ``fork`` and to pickle (a brick worker reopens the file instead of receiving its contents).
"""

from __future__ import annotations

import math
import os
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.grid import VolumeMetadata
from apmgsrn.errors import ApmgsrnError
from apmgsrn.recipes import RUNTIME

#: Largest integer magnitude below which float32 holds every integer exactly (2^24).
FLOAT32_EXACT_INTEGER = 1 << 24


@dataclass(frozen=True)
class VolumeStats:
    """Value range of a volume, as `Volume.read` returns it.

    Attributes:
        min: Smallest finite value (the fill value counts when ``fill_nonfinite`` is set).
        max: Largest finite value (same rule).
        mean: Mean of the finite values (same rule).
        nonfinite: Number of NaN/+Inf/-Inf voxels stored in the file (counted before any fill).
    """

    min: float
    max: float
    mean: float
    nonfinite: int


def parse_shape(text: str) -> tuple[int, int, int]:
    """Parse a volume shape as users type it: ``"X,Y,Z"`` or ``"XxYxZ"`` (x first).

    Args:
        text: The shape text, e.g. ``"256,256,128"``, ``"256x256x128"`` or ``"256*256*128"``.

    Returns:
        ``(X, Y, Z)`` as positive integers, in the order typed.

    Raises:
        ApmgsrnError: If the text is not three positive integers.
    """
    parts = [p.strip() for p in re.split(r"[,xX*]", str(text).strip())]
    if len(parts) != 3 or not all(p.isdigit() for p in parts) or any(int(p) <= 0 for p in parts):
        raise ApmgsrnError(
            f"invalid shape {text!r}: give three positive integers X,Y,Z (x first), e.g. shape=256,256,128",
            arguments=("shape",),
        )
    return int(parts[0]), int(parts[1]), int(parts[2])


def format_xyz(shape_zyx: tuple[int, ...]) -> str:
    """Format a stored ``(Z, Y, X)`` shape the way users read it: ``"XxYxZ"``.

    Args:
        shape_zyx: Shape in C order (z, y, x).

    Returns:
        The dims joined by ``x`` with x first.
    """
    return "x".join(str(n) for n in reversed(shape_zyx))


def _normalise_slice(key: slice, length: int, axis: str) -> slice:
    """Resolve ``None``/negative bounds of a slice against an axis length; steps must be positive."""
    if not isinstance(key, slice):
        raise TypeError(f"Volume.read expects slices, got {type(key).__name__} for axis {axis}")
    start, stop, step = key.indices(length)
    if step <= 0:
        raise ValueError(f"Volume.read needs a positive step on axis {axis}, got {step}")
    # An empty range keeps start <= stop so the region shape comes out as 0, never negative.
    return slice(start, max(start, stop), step)


def _slice_length(key: slice) -> int:
    return len(range(key.start, key.stop, key.step))


class Volume:
    """A 3-D volume on disk; regions are read lazily as float32 ``[d, h, w]`` arrays.

    Attributes:
        path: The file (or Zarr directory) the data comes from.
        variable: Name of the variable/dataset/array used, or ``None`` for raw and npy files.
        time: Time index selected in a 4-D variable, or ``None`` if the data has no time axis.
        time_steps: Length of the variable's time axis, or ``None`` if it has none.
        shape: ``(D, H, W) = (z, y, x)``, C order, x fastest.
        dtype: The stored dtype (``uint8``, ``float32``, ...); reads always return float32.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        metadata: What the file says beside the voxels (attributes, units, dimension names, coordinates,
            compression); readers of formats that say nothing leave it empty.

    Subclasses implement `_read_stored` (and, for file-backed data, `_open_handle`).
    """

    def __init__(
        self,
        path: Path,
        variable: str | None,
        shape: tuple[int, int, int],
        dtype: np.dtype,
        fill_nonfinite: float | None = None,
        time: int | None = None,
        time_steps: int | None = None,
    ) -> None:
        self.path = Path(path)
        self.variable = variable
        self.time = time
        self.time_steps = time_steps
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        if fill_nonfinite is not None:
            fill_nonfinite = float(fill_nonfinite)
            if not math.isfinite(fill_nonfinite):
                raise ApmgsrnError(
                    f"{self.path}: fill_nonfinite={fill_nonfinite}: must be a finite number",
                    arguments=("fill_nonfinite",),
                )
        self.fill_nonfinite = fill_nonfinite
        self.metadata = VolumeMetadata()
        self._stats: VolumeStats | None = None
        self._lock = threading.RLock()
        self._handle: Any = None
        self._handle_pid: int | None = None
        self._check_shape()

    # ----------------------------------------------------------------- subclass hooks
    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        """Return the stored values of a region (any numeric dtype, possibly a masked array).

        The slices are already normalised (non-negative bounds, positive step). The result must
        own its memory (never a view of a memory map or of an array the caller still holds),
        because `read` hands it out without another copy when it is already float32.
        """
        raise NotImplementedError

    def _open_handle(self) -> Any:
        """Open the underlying file; called lazily, again after ``fork`` or unpickling."""
        return None

    def _close_handle(self, handle: Any) -> None:
        close = getattr(handle, "close", None)
        if close is not None:
            close()

    # ----------------------------------------------------------------- handle management
    def _get_handle(self) -> Any:
        """The open file handle for this process (HDF5/NetCDF handles must not cross a fork)."""
        pid = os.getpid()
        if self._handle is None or self._handle_pid != pid:
            # A handle inherited through fork is dropped without closing: closing it would
            # touch library state shared with the parent process.
            self._handle = self._open_handle()
            self._handle_pid = pid
        return self._handle

    def close(self) -> None:
        """Close the underlying file; a later read reopens it."""
        with self._lock:
            if self._handle is not None and self._handle_pid == os.getpid():
                try:
                    self._close_handle(self._handle)
                except Exception:  # noqa: BLE001 - closing a dead handle must not mask anything
                    pass
            self._handle = None
            self._handle_pid = None

    def __enter__(self) -> Volume:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __getstate__(self) -> dict:
        # Pickle the recipe, never the open file or a memory map (which would copy the data).
        state = self.__dict__.copy()
        state["_handle"] = None
        state["_handle_pid"] = None
        state["_lock"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()

    # ----------------------------------------------------------------- checks
    def _check_shape(self) -> None:
        if len(self.shape) != 3:
            raise ApmgsrnError(
                f"{self.path}: data is {len(self.shape)}-D with shape {self.shape}; apmgsrn needs a 3-D volume"
            )
        if min(self.shape) < 2:
            # The corner-aligned grid puts voxel i at -1 + 2 i / (n - 1): n = 1 has no extent.
            raise ApmgsrnError(
                f"{self.path}: volume {format_xyz(self.shape)} (x*y*z) has an axis with fewer than 2 voxels; "
                "apmgsrn needs at least 2 voxels along x, y and z"
            )
        if self.dtype.kind not in "uifb":
            raise ApmgsrnError(
                f"{self.path}: data type {self.dtype} is not numeric; apmgsrn needs integer or float voxels"
            )

    # ----------------------------------------------------------------- reading
    def _read_float(self, z: slice, y: slice, x: slice) -> np.ndarray:
        """Region as a float32 C-contiguous array that owns its memory, without the fill."""
        region = (_normalise_slice(z, self.shape[0], "z"),
                  _normalise_slice(y, self.shape[1], "y"),
                  _normalise_slice(x, self.shape[2], "x"))
        with self._lock:
            try:
                data = self._read_stored(*region)
            except (OSError, RuntimeError) as exc:
                raise ApmgsrnError(
                    f"{self.path}: cannot read region z={region[0].start}:{region[0].stop} "
                    f"y={region[1].start}:{region[1].stop} x={region[2].start}:{region[2].stop} "
                    f"({exc}); the file may be corrupt or truncated"
                ) from exc
        if np.ma.isMaskedArray(data):
            # NetCDF _FillValue / missing values become NaN, so check_finite reports them.
            data = np.ma.filled(data.astype(np.float32), np.nan)
        self._check_float32_range(data)
        out = np.asarray(data, dtype=np.float32, order="C")
        if not out.flags.writeable:
            out = out.copy()
        expected = tuple(_slice_length(s) for s in region)
        if out.shape != expected:  # an internal reader bug, not a user error
            raise RuntimeError(f"reader returned shape {out.shape} for a region of shape {expected}")
        return out

    def _check_float32_range(self, data) -> None:
        """Refuse stored values that float32, which everything here computes in, cannot hold: finite floats
        beyond its range, and integers it would round (:meth:`_check_integers_exact`). Every reader calls it on
        the stored values before converting them."""
        data = np.asarray(data)
        self._check_integers_exact(data)
        if data.dtype.kind != "f" or data.dtype.itemsize <= 4 or data.size == 0:
            return
        finite = data[np.isfinite(data)]
        largest = float(np.abs(finite).max()) if finite.size else 0.0
        if largest > float(np.finfo(np.float32).max):
            raise ApmgsrnError(
                f"{self.path}: holds {data.dtype} values up to {largest:.3g}, beyond float32's range "
                f"({float(np.finfo(np.float32).max):.3g}) in which apmgsrn computes; store the data in other "
                "units (rescaled) first"
            )

    def _check_integers_exact(self, data) -> None:
        """Refuse integers that float32 cannot hold exactly (beyond +-2^24, only some are): the conversion would
        round them silently, and values that differ, such as 2^62 + 1 and 2^62 + 2, would become one."""
        data = np.asarray(data)
        if data.dtype.kind not in "iu" or data.dtype.itemsize < 4 or data.size == 0:
            return
        beyond = data > FLOAT32_EXACT_INTEGER
        if data.dtype.kind == "i":
            beyond |= data < -FLOAT32_EXACT_INTEGER
        large = data[beyond]
        if large.size == 0:
            return
        rounded = large.astype(np.float32)
        inside = rounded < float(np.iinfo(data.dtype).max) + 1.0  # rounded up past the type's range: inexact
        exact = np.zeros(large.shape, dtype=bool)
        exact[inside] = rounded[inside].astype(data.dtype) == large[inside]
        if not exact.all():
            example = int(large[~exact][0])
            raise ApmgsrnError(
                f"{self.path}: holds {data.dtype} values such as {example} that float32, in which apmgsrn computes, "
                f"cannot hold exactly (integers beyond +-{FLOAT32_EXACT_INTEGER:,} round to their neighbours); "
                "subtract an offset (e.g. the minimum) or convert the data to float32 first, accepting its rounding"
            )

    def read(self, z: slice = slice(None), y: slice = slice(None), x: slice = slice(None)) -> np.ndarray:
        """Read a region; only that region is fetched from disk.

        Args:
            z: Slice along z (depth, axis 0).
            y: Slice along y (height, axis 1).
            x: Slice along x (width, axis 2, fastest).

        Returns:
            float32 C-contiguous array ``[d, h, w]``; NaN/Inf replaced if ``fill_nonfinite`` is set.
        """
        out = self._read_float(z, y, x)
        if self.fill_nonfinite is not None and self._may_hold_nonfinite():
            np.copyto(out, np.float32(self.fill_nonfinite), where=~np.isfinite(out))
        return out

    def _may_hold_nonfinite(self) -> bool:
        # Integers cannot be NaN, but NetCDF/HDF5 readers may mask missing values into NaN.
        return True

    def to_numpy(self) -> np.ndarray:
        """Read the whole volume.

        Returns:
            float32 array ``[D, H, W]``.
        """
        return self.read()

    def iter_slabs(self, max_voxels: int = RUNTIME.stats_slab_voxels) -> Iterator[tuple[slice, np.ndarray]]:
        """Stream the volume as consecutive z-slabs of bounded size.

        Args:
            max_voxels: Upper bound on voxels per slab (at least one z-slice is always read).

        Returns:
            Iterator of ``(z_slice, float32 [dz, H, W])`` covering z = 0..D-1 in order.
        """
        depth, height, width = self.shape
        step = max(1, int(max_voxels) // (height * width))
        for start in range(0, depth, step):
            z = slice(start, min(depth, start + step))
            yield z, self.read(z)

    def stats(self) -> VolumeStats:
        """Min, max and mean of the values `read` returns, plus the stored NaN/Inf count.

        Streamed over z-slabs of about 64 MiB, so it works on volumes larger than memory; the
        result is cached after the first call.

        Returns:
            The `VolumeStats` of this volume.
        """
        if self._stats is not None:
            return self._stats
        lowest, highest, total, finite_count, nonfinite = math.inf, -math.inf, 0.0, 0, 0
        depth, height, width = self.shape
        step = max(1, RUNTIME.stats_slab_voxels // (height * width))
        for start in range(0, depth, step):
            slab = self._read_float(slice(start, min(depth, start + step)), slice(None), slice(None))
            finite = np.isfinite(slab)
            count = int(finite.sum())
            if count < slab.size:
                nonfinite += slab.size - count
                slab = slab[finite]  # 1-D copy of the finite voxels only
            if count:
                lowest = min(lowest, float(slab.min()))
                highest = max(highest, float(slab.max()))
                # float64 accumulation: a float32 sum over 10^9 voxels loses the mean.
                total += float(slab.sum(dtype=np.float64))
                finite_count += count
        if self.fill_nonfinite is not None and nonfinite:
            lowest = min(lowest, self.fill_nonfinite)
            highest = max(highest, self.fill_nonfinite)
            total += self.fill_nonfinite * nonfinite
            finite_count += nonfinite
        if finite_count == 0:
            lowest = highest = mean = math.nan
        else:
            mean = total / finite_count
        self._stats = VolumeStats(min=lowest, max=highest, mean=mean, nonfinite=nonfinite)
        return self._stats

    # ----------------------------------------------------------------- description
    @property
    def raw_bytes(self) -> int:
        """Size of the volume as float32, ``D*H*W*4`` bytes: what it takes in memory here, and the second
        reference of compression ratios (docs/method.md §8)."""
        return math.prod(self.shape) * 4

    @property
    def stored_bytes(self) -> int:
        """Size of the volume in its stored dtype (a uint8 volume is 1 byte a voxel): the reference of
        compression ratios (docs/method.md §8)."""
        return math.prod(self.shape) * self.dtype.itemsize

    def describe(self) -> str:
        """One line naming file, variable, dims (x*y*z) and stored dtype.

        Returns:
            E.g. ``"miranda_density_256.nc:density 256x256x256 (x*y*z) float32"``.
        """
        name = self.path.name + (f":{self.variable}" if self.variable else "")
        if self.time is not None:
            name += f"[t={self.time}]"
        return f"{name} {format_xyz(self.shape)} (x*y*z) {self.dtype}"

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"


class ArrayVolume(Volume):
    """A volume held in memory (or a NumPy memory map): for small files, tests and demos.

    Args:
        array: 3-D array in C order ``(z, y, x)``.
        path: Name to report in messages (nothing is read from it).
        variable: Optional variable name to report.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
        metadata: attributes, dimension names and coordinates of the array (e.g. an xarray DataArray's).
    """

    def __init__(
        self,
        array: np.ndarray,
        path: str | Path = "array",
        variable: str | None = None,
        fill_nonfinite: float | None = None,
        metadata: VolumeMetadata | None = None,
    ) -> None:
        array = np.asarray(array)
        if array.ndim != 3:
            raise ApmgsrnError(f"{path}: data is {array.ndim}-D with shape {array.shape}; apmgsrn needs a 3-D volume")
        self._array = array
        super().__init__(Path(path), variable, array.shape, array.dtype, fill_nonfinite)
        if metadata is not None:
            self.metadata = metadata

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        # Always a fresh float32 array: never hand out a view of the caller's array or of a
        # memory map (the copy is also the integer -> float32 conversion, so it costs one pass).
        stored = self._source()[z, y, x]
        self._check_float32_range(stored)
        return np.array(stored, dtype=np.float32, order="C")

    def _source(self) -> np.ndarray:
        return self._array

    def _may_hold_nonfinite(self) -> bool:
        return self.dtype.kind == "f"


def check_finite(volume: Volume) -> None:
    """Refuse a volume with NaN/Inf voxels unless the user chose a fill value.

    Args:
        volume: The volume to check (its streamed `Volume.stats` are computed if not cached).

    Raises:
        ApmgsrnError: If it holds NaN/Inf voxels and ``fill_nonfinite`` is not set.
    """
    stats = volume.stats()
    if stats.nonfinite > 0 and volume.fill_nonfinite is None:
        total = volume.shape[0] * volume.shape[1] * volume.shape[2]
        raise ApmgsrnError(
            f"{volume.path}: {stats.nonfinite} of {total} voxels are NaN or Inf; "
            "pass fill_nonfinite=VALUE to replace them (e.g. fill_nonfinite=0)", arguments=("fill_nonfinite",),
        )
