"""What a model file says about itself, as typed values: the description every consumer reads.

Loading returns the network *and* a :class:`ModelDescription`; nothing is patched onto the module. The
JSON a file holds is checked field by field here (types, shapes, bounds), so that a malformed or hostile
description is refused with one message before anything is built from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from apmgsrn.limits import LIMITS
from apmgsrn.data.grid import AxisCoordinates, VolumeMetadata
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io.container import (
    CHECKSUMS_VERSION,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST_CHECKSUM,
    manifest_checksum,
    note_unchecked,
    parse_json,
)
from apmgsrn.models.registry import FieldConfig


class DescriptionError(ValueError):
    """A description field of the wrong type or value; the loader adds the file name."""


@dataclass(frozen=True)
class SourceInfo:
    """Where the training data came from.

    Attributes:
        path: the data file's name (no folder: models travel between machines).
        variable: the variable / dataset / array name, or None (raw, npy).
        text: one line describing the volume as the reader saw it.
        dtype: the stored data type (``uint8``, ``float32``, ...), for compression ratios against the
            stored bytes; None in files written before it was recorded.
        metadata: the variable's attributes (units...), dimension names, coordinates and compression, which a
            decode writes back; empty in files written before they were recorded.
    """

    path: str = ""
    variable: str | None = None
    text: str = ""
    dtype: str | None = None
    metadata: VolumeMetadata = VolumeMetadata()

    def to_dict(self) -> dict:
        data = {"path": self.path, "variable": self.variable, "description": self.text, "dtype": self.dtype}
        metadata = self.metadata
        if metadata.attributes:
            data["attributes"] = dict(metadata.attributes)
        if metadata.dimensions is not None:
            data["dimensions"] = list(metadata.dimensions)
        if metadata.coordinates is not None:
            data["coordinates"] = [None if axis is None else _axis_to_dict(axis) for axis in metadata.coordinates]
        if metadata.compression is not None:
            data["compression"] = dict(metadata.compression)
        return data

    @property
    def itemsize(self) -> int | None:
        """Bytes one stored voxel takes (a uint8 volume: 1), or None when the dtype is unknown."""
        return None if self.dtype is None else np.dtype(self.dtype).itemsize

    @staticmethod
    def of_volume(volume) -> "SourceInfo":
        """What a :class:`apmgsrn.data.Volume` (anything with ``path``, ``variable``, ``describe()``,
        ``dtype`` and, optionally, ``metadata``) was."""
        return SourceInfo(Path(str(volume.path)).name, volume.variable, volume.describe(), str(volume.dtype),
                          getattr(volume, "metadata", VolumeMetadata()))

    @staticmethod
    def from_dict(data) -> "SourceInfo":
        data = require_dict(data, "source")
        return SourceInfo(
            path=optional_str(data.get("path"), "source.path") or "",
            variable=optional_str(data.get("variable"), "source.variable"),
            text=optional_str(data.get("description"), "source.description") or "",
            dtype=_numeric_dtype(data.get("dtype")),
            metadata=VolumeMetadata(
                attributes=_attributes(data.get("attributes"), "source.attributes"),
                dimensions=_dimensions(data.get("dimensions")),
                coordinates=_coordinates(data.get("coordinates")),
                compression=_compression(data.get("compression")),
            ),
        )

    def crop(self, start: tuple[int, int, int], stop: tuple[int, int, int]) -> SourceInfo:
        """The source of the voxels ``[start, stop)`` per ``(z, y, x)`` axis (a brick's): coordinates sliced."""
        return replace(self, metadata=self.metadata.crop(start, stop))

    def check_shape(self, volume_shape: tuple[int, int, int]) -> None:
        """Uneven coordinates must give one value per voxel of the volume.

        Raises:
            DescriptionError: an axis' coordinate count differs from the volume's.
        """
        for axis, coordinates in enumerate(self.metadata.coordinates or ()):
            uneven = coordinates is not None and coordinates.values is not None
            if uneven and len(coordinates.values) != volume_shape[axis]:
                raise DescriptionError(f"source.coordinates of {coordinates.name} do not match the volume shape")


def _axis_to_dict(axis: AxisCoordinates) -> dict:
    data = {"name": axis.name, "start": axis.start, "step": axis.step}
    if axis.values is not None:
        data["values"] = list(axis.values)
    if axis.attributes:
        data["attributes"] = dict(axis.attributes)
    return data


def _attributes(value, name: str) -> dict:
    """Attributes: an object of at most :attr:`~apmgsrn.limits.Limits.attributes` strings, finite numbers and
    number lists."""
    if value is None:
        return {}
    attributes = require_dict(value, name)
    if len(attributes) > LIMITS.attributes:
        raise DescriptionError(f"{name} has more than {LIMITS.attributes} entries")
    for key, item in attributes.items():
        if len(key) > 256:
            raise DescriptionError(f"{name} has a key longer than 256 characters")
        if isinstance(item, str):
            if len(item) > LIMITS.text:
                raise DescriptionError(f"{name}.{key} is longer than {LIMITS.text} characters")
        elif isinstance(item, list):
            if len(item) > LIMITS.list_entries:
                raise DescriptionError(f"{name}.{key} has more than {LIMITS.list_entries} values")
            for v in item:
                require_number(v, f"{name}.{key}")
        else:
            require_number(item, f"{name}.{key}")
    return dict(attributes)


def _dimensions(value) -> tuple[str, str, str] | None:
    if value is None:
        return None
    names = isinstance(value, list) and all(isinstance(v, str) and 0 < len(v) <= 256 for v in value)
    if not names or len(value) != 3:
        raise DescriptionError("source.dimensions is not a list of three names")
    return tuple(value)


def _coordinates(value) -> tuple | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 3:
        raise DescriptionError("source.coordinates is not a list of three axes")
    axes = []
    for axis in value:
        if axis is None:
            axes.append(None)
            continue
        axis = require_dict(axis, "source.coordinates")
        name = optional_str(axis.get("name"), "source.coordinates.name")
        if not name or len(name) > 256:
            raise DescriptionError("source.coordinates.name is not a name")
        values = axis.get("values")
        if values is not None:
            if not isinstance(values, list) or not 2 <= len(values) <= LIMITS.coordinates:
                raise DescriptionError(f"source.coordinates.values of {name} is not a list of coordinates")
            values = tuple(require_number(v, f"source.coordinates.values of {name}") for v in values)
        axes.append(AxisCoordinates(
            name=name,
            start=require_number(axis.get("start"), f"source.coordinates.start of {name}"),
            step=require_number(axis.get("step"), f"source.coordinates.step of {name}"),
            values=values,
            attributes=_attributes(axis.get("attributes"), f"source.coordinates.attributes of {name}"),
        ))
    return tuple(axes)


def _compression(value) -> dict | None:
    if value is None:
        return None
    value = require_dict(value, "source.compression")
    if not isinstance(value.get("zlib"), bool) or not isinstance(value.get("shuffle"), bool):
        raise DescriptionError("source.compression is not a zlib setting")
    level = require_int(value.get("complevel"), "source.compression.complevel", 0, 9)
    return {"zlib": value["zlib"], "complevel": level, "shuffle": value["shuffle"]}


def _numeric_dtype(value) -> str | None:
    """A stored data type name as numpy spells it, or None; anything but an integer, float or bool type of
    at most 8 bytes is refused."""
    name = optional_str(value, "source.dtype")
    if name is None:
        return None
    try:
        dtype = np.dtype(name) if len(name) <= 16 else None
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in "uifb" or dtype.itemsize > 8:
        raise DescriptionError("source.dtype is not a numeric data type")
    return str(dtype)


@dataclass(frozen=True)
class BrickEntry:
    """One brick of a brick model: its box in voxels and the figures its training left."""

    name: str
    index: int
    position: tuple[int, int, int]
    start: tuple[int, int, int]  # (z, y, x), inclusive
    stop: tuple[int, int, int]  # (z, y, x), exclusive
    file: str
    summary: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BrickLayout:
    """The brick grid of a brick model (docs/method.md §6)."""

    counts: tuple[int, int, int]  # bricks along x, y, z
    ghost_cells: int
    blend: bool
    entries: tuple[BrickEntry, ...]


@dataclass(frozen=True)
class SeriesStepInfo:
    """One step of a time-series model: its number, where it came from and its value range (data units)."""

    label: float
    name: str
    value_range: tuple[float, float]

    def to_dict(self) -> dict:
        label = int(self.label) if float(self.label).is_integer() else self.label
        return {"label": label, "name": self.name, "value_min": self.value_range[0], "value_max": self.value_range[1]}


@dataclass(frozen=True)
class SeriesLayout:
    """The time axis of a time-series model (docs/method.md §10): what the core layers (rendering, decoding,
    ``info``) need of a model with several steps. The series themselves live in :mod:`apmgsrn.series`.

    Attributes:
        config: steps, basis size and kind of weights (a :class:`apmgsrn.series.field.SeriesConfig`).
        steps: one entry per step, in order.
    """

    config: object
    steps: tuple[SeriesStepInfo, ...]

    def step_index(self, time: int) -> int:
        """Check a step index (``--time K``) against the series.

        Raises:
            ApmgsrnError: outside ``0 .. T-1``.
        """
        count = len(self.steps)
        if isinstance(time, bool) or not isinstance(time, int) or not 0 <= time < count:
            raise ApmgsrnError(f"time={time} is outside the model's series of {count} steps; pass 0..{count - 1}",
                               arguments=("time",))
        return time


@dataclass(frozen=True)
class PackedPart:
    """One stored part of a packed model file and what it costs.

    Attributes:
        name: ``description``, a parameter's name, ``correction indices`` or ``correction values``.
        encoding: ``json``, ``quantized``, ``float32`` or ``voxels``.
        values: numbers it holds (0 for the description).
        bytes: compressed bytes in the file.
        bits: largest bit width of its integers before entropy coding (quantized parts), else None.
    """

    name: str
    encoding: str
    values: int
    bytes: int
    bits: int | None = None

    @property
    def bits_per_value(self) -> float | None:
        """Stored bits per value after entropy coding (None for the description)."""
        return 8 * self.bytes / self.values if self.values else None


@dataclass(frozen=True)
class PackingSummary:
    """What a packed model file holds beside the network's config, and what packing cost.

    Attributes:
        parts: every stored part, in file order.
        container_bytes: the safetensors framing around them.
        float32_bytes: the same parameters as float32 (4 bytes each).
        report: figures measured when the file was packed (``float32_psnr``, ``psnr``, ``psnr_cost``,
            ``max_abs_error``, ``mode``, ``qat_iterations``, ...): numbers, strings or None.
        max_error: the error bound promised at every voxel (data units), or None without one.
        corrected_voxels: voxels that carry a correction.
    """

    parts: tuple[PackedPart, ...]
    container_bytes: int
    float32_bytes: int
    report: dict
    max_error: float | None = None
    corrected_voxels: int = 0

    @property
    def correction_bytes(self) -> int:
        """Bytes the error bound costs (its correction parts)."""
        return sum(part.bytes for part in self.parts if part.encoding == "voxels")


@dataclass(frozen=True)
class ModelDescription:
    """Everything a model file says about the model it holds.

    Attributes:
        kind: ``"field"`` (one network), ``"bricks"`` (a folder of one network per brick) or ``"series"`` (one
            network for every step of a time series).
        config: the network's config (of every brick, for a brick model); ``model`` is its kind.
        volume_shape: ``(D, H, W)`` of the training volume.
        value_range: ``(min, max)`` of the training data, data units.
        transform: the value transform's kind (``none``, ``log10``, ``zscore``).
        source: where the data came from.
        training: the training summary as saved (iterations, seconds, psnr, max_abs_error, history, config...).
        parameters: stored parameters of the network(s).
        file_bytes: bytes on disk (a brick model: all of its files).
        format_version: the file's format version.
        bricks: the brick grid of a brick model, else None.
        series: the time axis of a time-series model (kind ``series``), else None.
        packing: what a packed model file stores and what packing cost, else None.
    """

    kind: str
    config: FieldConfig
    volume_shape: tuple[int, int, int]
    value_range: tuple[float, float]
    transform: str
    source: SourceInfo
    training: dict
    parameters: int
    file_bytes: int
    format_version: int
    bricks: BrickLayout | None = None
    series: SeriesLayout | None = None
    packing: PackingSummary | None = None

    @property
    def model(self) -> str:
        """The network kind users type (``apmgsrn``, ``fvsrn``, ``ngp``, ...)."""
        return self.config.model


# ------------------------------------------------------------------------------------ typed JSON readers
def require_dict(value, name: str) -> dict:
    if not isinstance(value, dict):
        raise DescriptionError(f"{name} is not an object")
    return value


def optional_str(value, name: str) -> str | None:
    if value is not None and not isinstance(value, str):
        raise DescriptionError(f"{name} is not a string")
    return value


def require_number(value, name: str, finite: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DescriptionError(f"{name} is not a number")
    if finite and not math.isfinite(value):
        raise DescriptionError(f"{name} is not finite")
    return float(value)


def require_int(value, name: str, minimum: int | None = None, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise DescriptionError(f"{name} is not an integer")
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        raise DescriptionError(f"{name} = {value} is out of range")
    return value


def require_ints(value, name: str, count: int, minimum: int, maximum: int) -> tuple[int, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != count:
        raise DescriptionError(f"{name} is not a list of {count} integers")
    return tuple(require_int(v, name, minimum, maximum) for v in value)


def training_summary(value) -> dict:
    """The training summary: an object whose history, if any, is an object of number lists."""
    summary = require_dict(value, "training")
    history = summary.get("history")
    if history is not None:
        history = require_dict(history, "training.history")
        for key, series in history.items():
            if not isinstance(series, list) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in series
            ):
                raise DescriptionError(f"training.history.{key} is not a list of numbers")
    return summary


def inconsistent(path, error: Exception) -> ApmgsrnError:
    """The one message for a model file whose contents do not fit together."""
    first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    return ApmgsrnError(f"{path}: model file is inconsistent ({first}); re-train or re-download it")


def time_steps(description: ModelDescription) -> int:
    """How many time steps a model holds: those of a time-series model, else 1.

    The one place consumers (decode, the notebook API, the ParaView reader) ask.
    """
    return 1 if description.series is None else len(description.series.steps)


def check_time(description: ModelDescription, time: int | None) -> int:
    """The time step to evaluate: ``time``, or 0 when None.

    Raises:
        ApmgsrnError: ``time`` is not a step of the model.
    """
    steps = time_steps(description)
    if time is None:
        return 0
    if isinstance(time, bool) or not isinstance(time, (int, np.integer)) or not 0 <= int(time) < steps:
        held = "one time step (time=0)" if steps == 1 else f"{steps} time steps (time=0..{steps - 1})"
        raise ApmgsrnError(f"time={time!r}: the model holds {held}", arguments=("time",))
    return int(time)


def read_manifest_file(path: Path, kind: str, max_bytes: int, what: str, check: Callable[[dict], None]) -> dict:
    """Read a folder's JSON manifest of ``kind`` (nothing in it is executed): size capped before reading,
    format, kind and version checked, its own checksum verified (``manifest_checksum``; one written without it
    loads with a note), then ``check`` (which raises :class:`DescriptionError`). The dict returned holds every
    field but the checksum.

    Args:
        path: the manifest file.
        kind: the ``kind`` it must declare.
        max_bytes: the largest manifest read at all.
        what: its name in messages (``"brick model manifest"``).
        check: checks every field the product reads.

    Raises:
        ApmgsrnError: unreadable, not ours, corrupt, inconsistent or from a newer format version.
    """
    not_ours = f"{path}: not an apmgsrn {what} (corrupt or another format); re-train the model"
    try:
        if path.stat().st_size > max_bytes:
            raise ApmgsrnError(not_ours)
        text = path.read_bytes()
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    manifest = parse_json(text, not_ours)
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or manifest.get("kind") != kind:
        raise ApmgsrnError(not_ours)
    version = manifest.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise ApmgsrnError(not_ours)
    if version > FORMAT_VERSION:
        raise ApmgsrnError(
            f"{path}: written by a newer apmgsrn (model format {version}, this one reads up to {FORMAT_VERSION}); "
            "upgrade apmgsrn to load it"
        )
    recorded = manifest.pop(MANIFEST_CHECKSUM, None)
    if recorded is None and version >= CHECKSUMS_VERSION:  # older formats: the caller notes what is unchecked
        note_unchecked(path, f"{what} written without its own checksum (by an older apmgsrn): a change to it "
                       "cannot be detected")
    elif recorded is not None and recorded != manifest_checksum(manifest):
        raise ApmgsrnError(f"{path}: damaged: the {what}'s checksum does not match its contents (it was changed "
                           "after it was written); re-train the model")
    try:
        check(manifest)
    except DescriptionError as exc:
        raise ApmgsrnError(f"{path}: {what} is inconsistent ({exc}); re-train the model") from None
    return manifest
