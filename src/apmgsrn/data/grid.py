"""Where a volume's voxels lie and what they are called, and which of them a decode samples.

Readers describe a volume with :class:`VolumeMetadata` (the variable's attributes, units, dimension names,
coordinates per axis, compression); the model file keeps it (``apmgsrn.io.SourceInfo``), and a decode
writes it back. A decode samples a :class:`SampleGrid`: a box of the training volume, in continuous voxel
indices, at any number of samples per axis, chosen by a :class:`Region` (an index or a coordinate box).

The network only ever sees voxel indices (docs/method.md §1: voxel ``i`` of ``n`` at ``-1 + 2 i / (n - 1)``).
Coordinates map indices to the source's units: evenly (``start + i * step``) or through every voxel's value
(an uneven axis, kept as it is and interpolated linearly between voxels for another resolution).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from apmgsrn.arguments import check_choice
from apmgsrn.choices import REGION_UNITS
from apmgsrn.errors import ApmgsrnError

#: Axis names in storage order (C order: z slowest, x fastest).
AXES = ("z", "y", "x")
#: Variable attributes that describe how a file packs its values, not what they are: a float32 decode that
#: kept them would be read wrongly (scaled twice, values taken for missing), so they are never carried over.
PACKING_ATTRIBUTES = frozenset({
    "_FillValue", "missing_value", "scale_factor", "add_offset", "_Unsigned", "valid_range", "valid_min",
    "valid_max", "actual_range", "_ChunkSizes", "_Netcdf4Dimid", "_Netcdf4Coordinates", "_Storage",
    "_Endianness", "_DeflateLevel", "_Shuffle", "_NCProperties", "DIMENSION_LIST", "REFERENCE_LIST",
    "CLASS", "NAME",
})


@dataclass(frozen=True)
class AxisCoordinates:
    """Where the voxels of one axis lie, in the source's units.

    Attributes:
        name: the coordinate's (dimension's) name.
        start: coordinate of voxel 0.
        step: distance between neighbouring voxels (negative for a descending axis); on an uneven axis the
            mean step.
        values: every voxel's coordinate on an uneven axis; None on an even one (``start + i * step``).
        attributes: the coordinate variable's attributes (``units``, ``long_name``, ...).
    """

    name: str
    start: float = 0.0
    step: float = 1.0
    values: tuple[float, ...] | None = None
    attributes: dict = field(default_factory=dict)

    @property
    def even(self) -> bool:
        """Whether the voxels lie evenly spaced."""
        return self.values is None

    def at(self, index: np.ndarray) -> np.ndarray:
        """Coordinates at continuous voxel indices (between voxels: linear, the way the model interpolates).

        Args:
            index: float array of voxel indices.

        Returns:
            float64 array of the same shape.
        """
        index = np.asarray(index, dtype=np.float64)
        if self.values is None:
            return self.start + index * self.step
        return np.interp(index, np.arange(len(self.values)), np.asarray(self.values, dtype=np.float64))

    def index_of(self, coordinate: float, length: int) -> float:
        """The continuous voxel index of a coordinate (the inverse of :meth:`at`).

        Raises:
            ApmgsrnError: the coordinate lies outside the axis.
        """
        first, last = float(self.at(np.array(0.0))), float(self.at(np.array(length - 1.0)))
        low, high = min(first, last), max(first, last)
        if not low <= coordinate <= high:
            raise ApmgsrnError(
                f"region={coordinate:g} on {self.name} lies outside the volume's {self.name} coordinates "
                f"[{low:g}, {high:g}]; give a box inside them", arguments=("region",),
            )
        if self.values is None:
            return (coordinate - self.start) / self.step if self.step else 0.0
        values = np.asarray(self.values, dtype=np.float64)
        if not (np.all(np.diff(values) > 0) or np.all(np.diff(values) < 0)):
            raise ApmgsrnError(f"the {self.name} coordinates are not monotonic, so a coordinate box cannot be "
                               "placed on them; give region= in voxel indices", arguments=("region",))
        if values[0] > values[-1]:
            return float(length - 1 - np.interp(coordinate, values[::-1], np.arange(length, dtype=np.float64)))
        return float(np.interp(coordinate, values, np.arange(length, dtype=np.float64)))

    @staticmethod
    def from_values(name: str, values, attributes: dict | None = None) -> AxisCoordinates:
        """An axis from every voxel's coordinate: even (start and step only) when the values are evenly
        spaced to their own precision, else uneven with every value kept.

        Args:
            name: the axis' name.
            values: 1-D coordinates, one per voxel.
            attributes: the coordinate variable's attributes.
        """
        stored = np.asarray(values)
        array = stored.astype(np.float64).reshape(-1)
        attributes = dict(attributes or {})
        if array.size < 2:
            return AxisCoordinates(name, float(array[0]) if array.size else 0.0, 1.0, None, attributes)
        step = (array[-1] - array[0]) / (array.size - 1)
        even = array[0] + step * np.arange(array.size)
        # Even to the values' own precision: float32 coordinates of large magnitude carry rounding of a few
        # units in the last place, which is no unevenness.
        resolution = np.finfo(stored.dtype).eps * np.abs(array).max() * 4 if stored.dtype.kind == "f" else 0.0
        tolerance = max(1e-6 * abs(step), resolution)
        if np.all(np.isfinite(array)) and np.abs(array - even).max() <= tolerance:
            return AxisCoordinates(name, float(array[0]), float(step), None, attributes)
        return AxisCoordinates(name, float(array[0]), float(step), tuple(float(v) for v in array), attributes)


@dataclass(frozen=True)
class VolumeMetadata:
    """What a volume file says about its variable beside the voxels.

    Attributes:
        attributes: the variable's attributes (``units``, ``long_name``, ...), packing attributes left out
            (:data:`PACKING_ATTRIBUTES`).
        dimensions: the names of the ``(z, y, x)`` dimensions, or None (the format has none).
        coordinates: per ``(z, y, x)`` axis, where its voxels lie (None: the format says nothing, voxel
            indices), or None for all three.
        compression: how the variable was compressed (``{"zlib": True, "complevel": 4, "shuffle": True}``),
            or None (uncompressed or unknown).
    """

    attributes: dict = field(default_factory=dict)
    dimensions: tuple[str, str, str] | None = None
    coordinates: tuple[AxisCoordinates | None, AxisCoordinates | None, AxisCoordinates | None] | None = None
    compression: dict | None = None

    @property
    def units(self) -> str | None:
        """The variable's ``units`` attribute, or None."""
        units = self.attributes.get("units")
        return units if isinstance(units, str) else None

    def crop(self, start: tuple[int, int, int], stop: tuple[int, int, int]) -> VolumeMetadata:
        """The metadata of the voxels ``[start, stop)`` per ``(z, y, x)`` axis (a brick): coordinates sliced."""
        if self.coordinates is None:
            return self
        cropped = []
        for axis, a, b in zip(self.coordinates, start, stop):
            if axis is None:
                cropped.append(None)
            elif axis.values is None:
                cropped.append(replace(axis, start=axis.start + a * axis.step))
            else:
                cropped.append(AxisCoordinates.from_values(axis.name, axis.values[a:b], axis.attributes))
        return replace(self, coordinates=tuple(cropped))

    def axis(self, index: int) -> AxisCoordinates:
        """Coordinates of axis ``index`` (0: z, 1: y, 2: x): the recorded ones, else voxel indices named
        after the dimension."""
        recorded = self.coordinates[index] if self.coordinates is not None else None
        if recorded is not None:
            return recorded
        name = self.dimensions[index] if self.dimensions is not None else AXES[index]
        return AxisCoordinates(name)


def plain_attributes(attributes: dict) -> dict:
    """A variable's attributes as JSON-able values (strings, numbers, lists of numbers), packing attributes
    and values of other types left out."""
    plain = {}
    for key, value in attributes.items():
        key = str(key)
        if key in PACKING_ATTRIBUTES:
            continue
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        if isinstance(value, np.ndarray):
            value = value.item() if value.size == 1 else value.tolist()
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bool):
            value = int(value)
        if isinstance(value, float) and not math.isfinite(value):
            continue  # JSON has no NaN
        if isinstance(value, (str, int, float)):
            plain[key] = value
        elif isinstance(value, (list, tuple)) and value and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
        ):
            plain[key] = list(value)
    return plain


# ------------------------------------------------------------------------------------------ regions
@dataclass(frozen=True)
class Region:
    """A box of the training volume to decode.

    ``units="index"``: per axis ``(start, stop)`` voxel indices, half-open as in slicing (``(10, 40)`` is
    voxels 10..39; negative counts from the end, as in Python). ``units="coordinates"``: per axis a closed
    interval ``(low, high)`` in the source's coordinates. An axis left None is taken whole.

    Attributes:
        x, y, z: the box along each axis, or None.
        units: ``"index"`` or ``"coordinates"``.
    """

    x: tuple[float, float] | None = None
    y: tuple[float, float] | None = None
    z: tuple[float, float] | None = None
    units: str = "index"

    def __post_init__(self) -> None:
        check_choice("region_units", self.units, REGION_UNITS)
        for name in ("x", "y", "z"):
            bounds = getattr(self, name)
            if bounds is None:
                continue
            if not isinstance(bounds, (tuple, list)) or len(bounds) != 2 or not all(
                b is None or (isinstance(b, (int, float, np.integer, np.floating)) and math.isfinite(b))
                for b in bounds
            ):
                raise ApmgsrnError(f"region={bounds!r} for {name}: give two finite numbers (start, stop)",
                                   arguments=("region",))
            if self.units == "index" and not all(b is None or float(b).is_integer() for b in bounds):
                raise ApmgsrnError(f"region={bounds!r} for {name}: voxel indices are integers; for a box in the "
                                   "source's coordinates pass region_units=coordinates", arguments=("region",))
            object.__setattr__(self, name, tuple(bounds))

    @staticmethod
    def parse(text: str, units: str = "index") -> Region:
        """A region as users type it: ``"X0:X1,Y0:Y1,Z0:Z1"`` (x first; an empty side or ``:`` is the whole
        axis), e.g. ``"10:40,:,0:16"`` or, in coordinates, ``"0.5:1.5,-1:1,:"``.

        Raises:
            ApmgsrnError: not three ``start:stop`` parts of numbers.
        """
        parts = [p.strip() for p in str(text).split(",")]
        if len(parts) != 3:
            raise ApmgsrnError(f"region={text!r}: give X0:X1,Y0:Y1,Z0:Z1 (x first; ':' for a whole axis)",
                               arguments=("region",))
        bounds = []
        for part in parts:
            pieces = part.split(":") if part else ["", ""]
            if len(pieces) != 2:
                raise ApmgsrnError(f"region={text!r}: each axis is START:STOP (either may be empty), got {part!r}",
                                   arguments=("region",))
            try:
                low, high = (None if not p.strip() else float(p) for p in pieces)
            except ValueError:
                raise ApmgsrnError(f"region={text!r}: {part!r} is not START:STOP of numbers",
                                   arguments=("region",)) from None
            bounds.append(None if low is None and high is None else (low, high))
        return Region(x=bounds[0], y=bounds[1], z=bounds[2], units=units)


@dataclass(frozen=True)
class SampleGrid:
    """The lattice a decode samples: per axis, ``n`` samples evenly from index ``low`` to ``high`` of the
    training volume (continuous voxel indices, both ends included).

    Attributes:
        volume_shape: ``(D, H, W)`` of the training volume.
        low, high: first and last sampled index per ``(z, y, x)`` axis.
        shape: ``(D, H, W)`` samples.
    """

    volume_shape: tuple[int, int, int]
    low: tuple[float, float, float]
    high: tuple[float, float, float]
    shape: tuple[int, int, int]

    def indices(self, axis: int) -> np.ndarray:
        """Training-volume voxel indices (float64) sampled along axis ``axis`` (0: z, 1: y, 2: x)."""
        n = self.shape[axis]
        if n == 1:  # one sample: the middle of the span (as the field's lattice puts it)
            return np.array([0.5 * (self.low[axis] + self.high[axis])], dtype=np.float64)
        return self.low[axis] + (self.high[axis] - self.low[axis]) * np.arange(n, dtype=np.float64) / (n - 1)

    def box(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """The sampled box in the field's ``[-1, 1]^3`` coordinates, ``((x0, x1), (y0, y1), (z0, z1))``."""
        def field_coordinate(index: float, n: int) -> float:
            return -1.0 + 2.0 * index / (n - 1) if n > 1 else 0.0

        return tuple(
            (field_coordinate(self.low[a], self.volume_shape[a]), field_coordinate(self.high[a], self.volume_shape[a]))
            for a in (2, 1, 0)
        )


def sample_grid(
    volume_shape: tuple[int, int, int],
    shape: tuple[int, int, int] | None = None,
    region: Region | None = None,
    metadata: VolumeMetadata | None = None,
) -> SampleGrid:
    """The lattice of a decode: a region of the training volume (default: all of it) at a resolution
    (default: the training volume's voxel spacing over the region).

    Args:
        volume_shape: ``(D, H, W)`` of the training volume.
        shape: ``(D, H, W)`` samples, or None.
        region: the box, or None for the whole volume.
        metadata: the source's coordinates (needed for a region in coordinates).

    Returns:
        The sample grid.

    Raises:
        ApmgsrnError: a region outside the volume, empty or inverted; a shape of non-positive sizes.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    metadata = metadata or VolumeMetadata()
    region = region or Region()
    low, high, default = [], [], []
    for axis, name in enumerate(AXES):
        n = volume_shape[axis]
        bounds = getattr(region, name)
        if bounds is None:
            a, b = 0.0, float(n - 1)
        elif region.units == "index":
            if any(v is not None and not -n <= v <= n for v in bounds):
                raise ApmgsrnError(f"region={_text(bounds)} on {name} reaches beyond the {n} voxels there; give "
                                   f"START:STOP within 0..{n}", arguments=("region",))
            start, stop, _ = slice(*(None if v is None else int(v) for v in bounds)).indices(n)
            if stop <= start:
                raise ApmgsrnError(f"region={_text(bounds)} on {name} holds no voxel of the {n} there; give "
                                   f"START < STOP within 0..{n}", arguments=("region",))
            a, b = float(start), float(stop - 1)
        else:
            coordinates = metadata.axis(axis)
            first, last = coordinates.at(np.array([0.0, n - 1.0]))
            lo_value = min(first, last) if bounds[0] is None else float(bounds[0])
            hi_value = max(first, last) if bounds[1] is None else float(bounds[1])
            if hi_value < lo_value:
                raise ApmgsrnError(f"region={lo_value:g}:{hi_value:g} on {name} is inverted; give LOW:HIGH",
                                   arguments=("region",))
            a, b = sorted((coordinates.index_of(lo_value, n), coordinates.index_of(hi_value, n)))
        low.append(a)
        high.append(b)
        default.append(int(math.floor(b - a + 1e-9)) + 1)  # the training voxels' spacing over the box
    if shape is None:
        shape = tuple(default)
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ApmgsrnError(f"shape={shape}: give three positive sizes", arguments=("shape",))
    return SampleGrid(volume_shape, tuple(low), tuple(high), shape)


def _text(bounds: tuple) -> str:
    """``(10, None)`` -> ``"10:"``, as typed."""
    return ":".join("" if v is None else f"{v:g}" for v in bounds)
