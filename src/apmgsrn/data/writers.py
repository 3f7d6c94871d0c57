"""`VolumeWriter`: write a float32 volume (or a series of them) slab by slab (``.nc``, ``.raw``/``.bin``, ``.npy``).

Used by ``apmgsrn decode``, which produces the volume chunk by chunk, so outputs larger than
memory work. The file is written under a temporary name beside the target and renamed into place
only when every slab has been written and the writer closes without error: a crash or an
interrupted run never leaves a half-written file under the requested name.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.errors import ApmgsrnError

#: Output suffixes and their format names, as listed to users.
WRITABLE_SUFFIXES = {".nc": "NetCDF-4", ".raw": "raw float32", ".bin": "raw float32", ".npy": "NumPy"}


def _attribute_value(value: Any) -> Any:
    """A NetCDF-storable form of an attribute: numbers, strings and numeric lists as they are,
    booleans as 0/1, anything else (dicts, None, nested lists) as JSON text."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (str, int, float, np.integer, np.floating)):
        return value
    if isinstance(value, (list, tuple, np.ndarray)):
        array = np.asarray(value)
        if array.ndim == 1 and array.size and array.dtype.kind in "iuf":
            return array
    return json.dumps(value, default=str)


class VolumeWriter:
    """Write a ``[D, H, W]`` float32 volume to ``.nc``, ``.raw``/``.bin`` or ``.npy``, by z-slabs.

    Use it as a context manager; slabs may come in any order, but all of z must be written
    before a clean exit, which renames the temporary file into place. An exception inside the
    ``with`` block removes the temporary file and leaves any existing target untouched.

    Formats: ``.nc`` NetCDF-4 with dims ``(z, y, x)``, one float32 variable and `attributes`
    as global attributes; ``.raw``/``.bin`` headerless little-endian float32, x fastest (no
    attributes); ``.npy`` a float32 array (no attributes). With `steps`, a time series: a leading
    time dimension (NetCDF dims ``(time, z, y, x)`` and a ``time`` coordinate of `time_values`; raw and
    ``.npy`` steps one after the other), and every step is written slab by slab.

    Args:
        path: Output file; its folder must exist.
        shape: ``(D, H, W) = (z, y, x)``, as `Volume.shape`.
        variable: Variable name in a NetCDF output.
        attributes: Global attributes of a NetCDF output (numbers, strings, numeric lists;
            anything else is stored as JSON text).
        steps: Number of time steps of a series (None: one volume, no time dimension).
        time_values: The ``time`` coordinate of a NetCDF series (default 0, 1, ...).

    Raises:
        ApmgsrnError: For an unknown suffix, a missing or unwritable output folder, or a
            failed write (e.g. a full disk).
    """

    def __init__(
        self,
        path: str | Path,
        shape: tuple[int, int, int],
        variable: str = "value",
        attributes: dict | None = None,
        steps: int | None = None,
        time_values=None,
    ) -> None:
        self.path = Path(path).expanduser()
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3 or min(self.shape) <= 0:
            raise ValueError(f"VolumeWriter needs a shape (D, H, W) of positive sizes, got {shape}")
        if steps is not None and steps < 1:
            raise ValueError(f"VolumeWriter needs a positive number of steps, got {steps}")
        self.steps = steps
        self._time_values = list(time_values) if time_values is not None else list(range(steps or 0))
        self.variable = variable
        self.suffix = self.path.suffix.lower()
        if self.suffix not in WRITABLE_SUFFIXES:
            listed = ", ".join(f"{s} ({name})" for s, name in WRITABLE_SUFFIXES.items())
            raise ApmgsrnError(
                f"{self.path}: cannot write format {self.suffix or '(no suffix)'!r}; use one of {listed}"
            )
        folder = self.path.parent
        if not folder.is_dir():
            raise ApmgsrnError(f"{self.path}: output folder {folder} does not exist; create it or choose another path")
        if self.path.is_dir():
            example = self.path / ("volume" + self.suffix)
            raise ApmgsrnError(f"{self.path}: is a directory; give a file name such as {example}")
        # Same folder as the target, so the final rename is atomic (same file system); the real
        # suffix is kept so libraries that look at it behave.
        self._temporary = folder / f".{self.path.stem}.{uuid.uuid4().hex[:12]}.partial{self.suffix}"
        self._written = np.zeros((steps or 1, self.shape[0]), dtype=bool)  # [steps, D]
        self._handle: Any = None
        self._closed = False
        try:
            self._handle = self._create(attributes or {})
        except BaseException as exc:
            self._remove_temporary()
            if isinstance(exc, (OSError, RuntimeError, ValueError, TypeError, AttributeError)):
                raise ApmgsrnError(
                    f"{self.path}: cannot create the output file ({exc}); check that the folder is writable "
                    "and the variable and attribute names are valid"
                ) from exc
            raise

    # ----------------------------------------------------------------- per format
    def _create(self, attributes: dict) -> Any:
        depth, height, width = self.shape
        if self.suffix == ".nc":
            import netCDF4

            dataset = netCDF4.Dataset(self._temporary, "w", format="NETCDF4")
            try:
                # Every voxel gets written, so skip netCDF's pre-fill (it would write the file twice).
                dataset.set_fill_off()
                for name, size in zip(("z", "y", "x"), self.shape):
                    dataset.createDimension(name, size)
                dims = ("z", "y", "x")
                if self.steps is not None:
                    dataset.createDimension("time", self.steps)
                    dataset.createVariable("time", "f8", ("time",))[:] = np.asarray(self._time_values, np.float64)
                    dims = ("time", *dims)
                dataset.createVariable(self.variable, "f4", dims, contiguous=True)
                for key, value in attributes.items():
                    dataset.setncattr(str(key), _attribute_value(value))
            except BaseException:
                dataset.close()
                raise
            return dataset
        # raw and .npy: plain writes at known offsets (never a memory map: on a full disk a write to a mapped
        # page kills the process with SIGBUS, where a write() call fails with ENOSPC that we can report).
        needed = (self.steps or 1) * depth * height * width * 4
        free = shutil.disk_usage(self.path.parent).free
        if needed > free:
            raise OSError(errno.ENOSPC, f"needs {needed:,} bytes, {free:,} free")
        handle = open(self._temporary, "wb")
        try:
            if self.suffix == ".npy":
                shape = self.shape if self.steps is None else (self.steps, *self.shape)
                header = {"descr": "<f4", "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(handle, header)
            self._data_offset = handle.tell()
            # Size the file up front (sparse) so slabs can be written in any order.
            handle.truncate(self._data_offset + needed)
        except BaseException:
            handle.close()
            raise
        return handle

    def _store(self, z: slice, block: np.ndarray, step: int | None = None) -> None:
        if self.suffix == ".nc":
            if step is None:
                self._handle[self.variable][z.start:z.stop, :, :] = block
            else:
                self._handle[self.variable][step, z.start:z.stop, :, :] = block
        else:
            depth, height, width = self.shape
            self._handle.seek(self._data_offset + ((step or 0) * depth + z.start) * height * width * 4)
            self._handle.write(np.ascontiguousarray(block, dtype="<f4").data)

    def _finish(self) -> None:
        if self.suffix != ".nc":
            self._handle.flush()
            os.fsync(self._handle.fileno())
        self._handle.close()
        self._handle = None

    # ----------------------------------------------------------------- public
    def write(self, z: slice, block: np.ndarray, step: int | None = None) -> None:
        """Write the slab ``z`` of the volume (of step ``step`` of a series).

        Args:
            z: Range of z-slices, step 1, within ``[0, D)``.
            block: float32 (or convertible) array ``[dz, H, W]`` with ``dz`` = length of `z`.
            step: the time step, ``0 .. steps-1``, when writing a series (else None).

        Raises:
            ApmgsrnError: If the disk write fails (full disk, lost folder).
        """
        if self._closed:
            raise ValueError(f"VolumeWriter for {self.path} is closed")
        if (step is None) != (self.steps is None) or (step is not None and not 0 <= step < self.steps):
            raise ValueError(f"VolumeWriter.write: step {step} for a writer of {self.steps} steps")
        start, stop, stride = z.indices(self.shape[0])
        if stride != 1 or stop <= start:
            raise ValueError(f"VolumeWriter.write needs a non-empty z slice with step 1, got {z}")
        block = np.asarray(block, dtype=np.float32)
        expected = (stop - start, self.shape[1], self.shape[2])
        if block.shape != expected:
            raise ValueError(
                f"VolumeWriter.write: block shape {block.shape} does not match z={start}:{stop} -> {expected}"
            )
        try:
            if step is None:  # one volume: the two-argument call (tests stand in for it to fail a disk)
                self._store(slice(start, stop), block)
            else:
                self._store(slice(start, stop), block, step)
        except (OSError, RuntimeError) as exc:
            raise ApmgsrnError(f"{self.path}: writing failed ({exc}); check free disk space and the folder") from exc
        self._written[step or 0, start:stop] = True

    def close(self) -> None:
        """Finish the file and rename it into place (all of z must have been written).

        Raises:
            ValueError: If some z-slices were never written (the temporary file is removed).
            ApmgsrnError: If flushing or renaming fails.
        """
        if self._closed:
            return
        if not self._written.all():
            missing = np.argwhere(~self._written)  # [n, 2] (step, z)
            self.abort()
            first = f"step {missing[0][0]}, z={missing[0][1]}" if self.steps is not None else f"z={missing[0][1]}"
            raise ValueError(
                f"VolumeWriter for {self.path}: {len(missing)} z-slices were never written "
                f"(first missing: {first}); nothing was saved"
            )
        try:
            self._finish()
            os.replace(self._temporary, self.path)
        except (OSError, RuntimeError) as exc:
            self.abort()
            raise ApmgsrnError(f"{self.path}: cannot finish the output file ({exc}); check free disk space") from exc
        self._closed = True

    def abort(self) -> None:
        """Drop the temporary file without touching the target."""
        handle, self._handle = self._handle, None
        if handle is not None:
            try:
                handle.close()
            except Exception:  # noqa: BLE001 - the handle may already be broken; cleanup goes on
                pass
        self._closed = True
        self._remove_temporary()

    def _remove_temporary(self) -> None:
        try:
            self._temporary.unlink()
        except FileNotFoundError:
            pass

    def __enter__(self) -> VolumeWriter:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, traceback: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
