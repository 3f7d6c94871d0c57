"""`VolumeWriter`: write a float32 volume (or a series of them) slab by slab (``.nc``, ``.vti``, ``.raw``/``.bin``,
``.npy``).

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from apmgsrn.atomic import check_output_target
from apmgsrn.data.grid import AXES, AxisCoordinates
from apmgsrn.errors import ApmgsrnError

#: Output suffixes and their format names, as listed to users.
WRITABLE_SUFFIXES = {".nc": "NetCDF-4", ".vti": "VTK ImageData", ".raw": "raw float32", ".bin": "raw float32",
                     ".npy": "NumPy"}


@dataclass(frozen=True)
class OutputAxis:
    """One axis of a written volume: its name and where its samples lie.

    Attributes:
        name: the dimension's name (NetCDF).
        values: ``[n]`` coordinate of every sample.
        attributes: the coordinate variable's attributes (``units``...).
        recorded: the values are the source's coordinates (a NetCDF output writes them as a coordinate
            variable); False: voxel indices of the training volume, which only place a ``.vti``'s origin and
            spacing.
    """

    name: str
    values: np.ndarray
    attributes: dict = field(default_factory=dict)
    recorded: bool = False


def index_axes(shape: tuple[int, int, int]) -> tuple[OutputAxis, OutputAxis, OutputAxis]:
    """Axes ``z, y, x`` placed at voxel indices 0..n-1 (a volume nothing else is known about)."""
    return tuple(OutputAxis(name, np.arange(n, dtype=np.float64)) for name, n in zip(AXES, shape))


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


def check_axes_writable(path: str | Path, axes) -> None:
    """Refuse, before anything is written, axes the output format cannot place (uneven ones in ``.vti``).

    Raises:
        ApmgsrnError: naming the uneven axis and the format that keeps it.
    """
    if Path(path).suffix.lower() == ".vti":
        _even_geometry(Path(path), axes)


def _even_geometry(path: Path, axes) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Origin and spacing ``(x, y, z)`` of evenly spaced axes.

    Raises:
        ApmgsrnError: an axis is uneven (VTK ImageData cannot place it).
    """
    origin, spacing = [], []
    for axis in reversed(axes):  # x, y, z
        placed = AxisCoordinates.from_values(axis.name, axis.values)
        if not placed.even:
            raise ApmgsrnError(
                f"{path}: the {axis.name} coordinates of this volume are uneven, and VTK ImageData (.vti) holds "
                "evenly spaced points only; write .nc instead (it keeps every coordinate)"
            )
        origin.append(placed.start)
        spacing.append(placed.step if len(axis.values) > 1 else 1.0)
    return tuple(origin), tuple(spacing)


def _vti_frame(name: str, shape: tuple[int, int, int], origin, spacing) -> tuple[bytes, bytes]:
    """The XML before and after the raw appended float32 data of a ``.vti`` file (x fastest, as VTK)."""
    depth, height, width = shape
    extent = f"0 {width - 1} 0 {height - 1} 0 {depth - 1}"

    def numbers(values) -> str:
        return " ".join(repr(float(v)) for v in values)  # repr: every digit, read back exactly

    header = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
        f'  <ImageData WholeExtent="{extent}" Origin="{numbers(origin)}" Spacing="{numbers(spacing)}">\n'
        f'    <Piece Extent="{extent}">\n'
        f'      <PointData Scalars={quoteattr(name)}>\n'
        f'        <DataArray type="Float32" Name={quoteattr(name)} format="appended" offset="0"/>\n'
        '      </PointData>\n'
        '    </Piece>\n'
        '  </ImageData>\n'
        '  <AppendedData encoding="raw">\n   _'
    ).encode("utf-8")
    size = np.array([depth * height * width * 4], dtype="<u8").tobytes()  # the block's byte count (UInt64)
    return header + size, b"\n  </AppendedData>\n</VTKFile>\n"


class VolumeWriter:
    """Write a ``[D, H, W]`` float32 volume to ``.nc``, ``.vti``, ``.raw``/``.bin`` or ``.npy``, by z-slabs.

    Use it as a context manager; slabs may come in any order, but all of z must be written
    before a clean exit, which renames the temporary file into place. An exception inside the
    ``with`` block removes the temporary file and leaves any existing target untouched.

    Formats: ``.nc`` NetCDF-4 with the axes' dimension names, one float32 variable with its attributes
    (compressed as asked), coordinate variables for the axes that have recorded coordinates and `attributes`
    as global attributes; ``.vti`` VTK ImageData (raw appended float32 point data named `variable`, origin
    and spacing from the axes, which must be evenly spaced); ``.raw``/``.bin`` headerless little-endian
    float32, x fastest; ``.npy`` a float32 array (the last two hold no names, coordinates or attributes).
    With `steps`, a time series (not ``.vti``): a leading time dimension (NetCDF dims ``(time, z, y, x)`` and a
    ``time`` coordinate of `time_values`; raw and ``.npy`` steps one after the other), every step written slab by
    slab.

    Args:
        path: Output file; its folder must exist.
        shape: ``(D, H, W) = (z, y, x)``, as `Volume.shape`.
        variable: Variable (NetCDF) or point array (VTK) name.
        attributes: Global attributes of a NetCDF output (numbers, strings, numeric lists;
            anything else is stored as JSON text).
        variable_attributes: The variable's attributes in a NetCDF output (``units``, ``long_name``...).
        axes: The ``(z, y, x)`` axes (default: voxel indices named z, y, x).
        compression: ``{"zlib": bool, "complevel": int, "shuffle": bool}`` for a NetCDF output, or None.
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
        variable_attributes: dict | None = None,
        axes: tuple[OutputAxis, OutputAxis, OutputAxis] | None = None,
        compression: dict | None = None,
        steps: int | None = None,
        time_values=None,
    ) -> None:
        self.path = Path(path).expanduser()
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3 or min(self.shape) <= 0:
            raise ValueError(f"VolumeWriter needs a shape (D, H, W) of positive sizes, got {shape}")
        self.axes = index_axes(self.shape) if axes is None else tuple(axes)
        if tuple(len(a.values) for a in self.axes) != self.shape:
            raise ValueError(f"VolumeWriter: axes of {[len(a.values) for a in self.axes]} values for shape {shape}")
        if steps is not None and steps < 1:
            raise ValueError(f"VolumeWriter needs a positive number of steps, got {steps}")
        self.steps = steps
        if steps is not None and Path(path).suffix.lower() == ".vti":
            raise ApmgsrnError(f"{path}: a VTK ImageData file holds one step; write several steps to .nc, .raw "
                               "or .npy, or one file per step")
        self._time_values = list(time_values) if time_values is not None else list(range(steps or 0))
        self.variable = variable
        self.variable_attributes = dict(variable_attributes or {})
        self.compression = compression
        self.suffix = self.path.suffix.lower()
        if self.suffix not in WRITABLE_SUFFIXES:
            listed = ", ".join(f"{s} ({name})" for s, name in WRITABLE_SUFFIXES.items())
            raise ApmgsrnError(
                f"{self.path}: cannot write format {self.suffix or '(no suffix)'!r}; use one of {listed}"
            )
        check_output_target(self.path, "volume")  # never a device, pipe or socket, nor inside a model folder
        folder = self.path.parent
        if not folder.is_dir():
            raise ApmgsrnError(f"{self.path}: output folder {folder} does not exist; create it or choose another path")
        if self.path.is_dir():
            example = self.path / ("volume" + self.suffix)
            raise ApmgsrnError(f"{self.path}: is a directory; give a file name such as {example}")
        if self.suffix == ".vti":
            self._origin, self._spacing = _even_geometry(self.path, self.axes)
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
            if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
                raise ApmgsrnError(f"{self.path}: cannot create the output file ({exc}); decode a smaller shape or "
                                   "region, or write to a folder with room", arguments=("shape",)) from exc
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
                names = tuple(axis.name for axis in self.axes)
                if self.steps is not None:
                    dataset.createDimension("time", self.steps)
                    dataset.createVariable("time", "f8", ("time",))[:] = np.asarray(self._time_values, np.float64)
                    names = ("time", *names)
                for axis, size in zip(self.axes, self.shape):
                    dataset.createDimension(axis.name, size)
                    if axis.recorded:
                        coordinate = dataset.createVariable(axis.name, "f8", (axis.name,))
                        coordinate.setncatts({str(k): _attribute_value(v) for k, v in axis.attributes.items()})
                        coordinate[:] = axis.values
                if self.compression and self.compression.get("zlib"):
                    # One chunk per z-slice: every slab write fills whole chunks, none is compressed twice.
                    options = dict(zlib=True, complevel=int(self.compression.get("complevel", 4)),
                                   shuffle=bool(self.compression.get("shuffle", True)),
                                   chunksizes=(1, height, width) if self.steps is None else (1, 1, height, width))
                else:
                    options = dict(contiguous=True)
                variable = dataset.createVariable(self.variable, "f4", names, **options)
                variable.setncatts({str(k): _attribute_value(v) for k, v in self.variable_attributes.items()})
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
            footer = b""
            if self.suffix == ".npy":
                shape = self.shape if self.steps is None else (self.steps, *self.shape)
                header = {"descr": "<f4", "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(handle, header)
            elif self.suffix == ".vti":
                header, footer = _vti_frame(self.variable, self.shape, self._origin, self._spacing)
                handle.write(header)
            self._data_offset = handle.tell()
            # Size the file up front (sparse) so slabs can be written in any order.
            handle.truncate(self._data_offset + needed)
            handle.seek(self._data_offset + needed)
            handle.write(footer)
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
