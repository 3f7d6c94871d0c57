"""The packed model file: quantised, entropy-coded parameters and an optional voxel correction.

A :mod:`~apmgsrn.io.container` file of kind ``packed-field`` holding one ``U8`` tensor, ``payload``, cut
into sections whose compressed sizes the header lists (``{"sections": [n0, n1, ...]}``):

0. the description: the JSON of a single-field file (``field``, value ranges, ``transform``,
   ``volume_shape``, ``source``, ``training`` without the loss history) plus ``tensors`` (how each
   parameter is stored), ``packing`` (what packing measured) and ``correction`` (the error bound, or null),
   coded as the header's ``coding`` says (deflate primed with a typical description,
   :func:`~apmgsrn.io.codec.compress_description`; files of format version 1 have no such entry and use
   LZMA) and at most :attr:`~apmgsrn.limits.Limits.description_bytes` once decompressed;
1. one section per stored parameter, in the config's order: ``quantized`` (float16 group steps, then the
   coded integers of :mod:`apmgsrn.io.quantization`) or ``float32`` (the raw values, LZMA-compressed);
2. with an error bound, two more: the corrected voxels' flat indices (gaps between them) and their
   integers (a correction is ``integer * step``).

Loading validates everything before it allocates: the header and section sizes, then the description (as a
single-field file's, :func:`~apmgsrn.io.field_file.parse_field_description`), then every declared
parameter against the shapes the config implies; each section's decompressed size is computed from those
shapes (never read from the file), bounded by what LZMA can expand to, and decompression stops there.
Dequantising gives float32 parameters, so the loaded field evaluates any point on CPU or GPU like any other.

The packed time-series file (:mod:`apmgsrn.series.packed_file`) is laid out and read the same way, through the
public helpers here (:func:`payload_file_bytes`, :func:`read_payload_file`, :func:`parse_tensor_entries`,
:func:`decode_tensors`, :func:`packing_summary`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import codec
from apmgsrn.io.container import (
    PACKED_KIND,
    Header,
    file_bytes,
    header_of_kind,
    load_tensors,
    parse_json,
    read_header,
    write_file_bytes,
)
from apmgsrn.io.description import (
    DescriptionError,
    ModelDescription,
    PackedPart,
    PackingSummary,
    SourceInfo,
    inconsistent,
    require_dict,
    require_int,
    require_number,
)
from apmgsrn.io.field_file import FieldDescription, field_description, parse_field_description, restore_field
from apmgsrn.io.quantization import MAX_GROUPS, QuantizedTensor, dequantize, group_count
from apmgsrn.models.corrected_field import CorrectedField
from apmgsrn.models.field import NeuralField

PAYLOAD = "payload"
#: LZMA expands at most about 7,100-fold (measured on zeros); a section declaring more cannot be genuine.
MAX_EXPANSION, EXPANSION_SLACK = 8192, 4096
ENCODINGS = ("quantized", "float32")
#: Entries of the training summary a packed file keeps (the loss history alone would outweigh a small
#: network; the float32 PSNR is in the packing report).
SUMMARY_KEYS = ("iterations", "batch_size", "seconds", "frozen_at", "stopped_early", "device")


# ---------------------------------------------------------------------------------------------- parts
@dataclass(frozen=True)
class PackedTensor:
    """One parameter as the file stores it.

    Attributes:
        name: its ``state_dict`` name.
        encoding: ``quantized`` or ``float32``.
        data: the section (``quantized``: float16 steps, then the coded integers; ``float32``: coded values).
        group, predictor, width: how a ``quantized`` parameter is laid out (see :mod:`apmgsrn.io.codec`).
        bits: largest bit width of its integers (``quantized``).
    """

    name: str
    encoding: str
    data: bytes
    group: int = 0
    predictor: str = "none"
    width: int = 0
    bits: int | None = None

    def entry(self) -> list:
        """Its description entry: ``["float32"]`` or ``["quantized", group, predictor, width]`` (the name is
        the config's, by position: every byte counts in a file of a few kilobytes)."""
        if self.encoding == "float32":
            return ["float32"]
        return ["quantized", self.group, self.predictor, self.width]


def encode_quantized(name: str, quantized: QuantizedTensor, predictors: tuple[str, ...] | None = None) -> PackedTensor:
    """A quantised parameter as a section, with whichever of ``predictors`` (default: all that apply) codes
    it smallest."""
    return encode_quantized_all([(name, quantized, predictors)])[0]


def encode_quantized_all(parameters: list[tuple[str, QuantizedTensor, tuple[str, ...] | None]]
                         ) -> list[PackedTensor]:
    """:func:`encode_quantized` of every ``(name, quantized, predictors)``, coded side by side
    (:func:`~apmgsrn.io.codec.best_encodings`)."""
    coded = codec.best_encodings([(quantized.levels, quantized.shape, predictors)
                                  for _, quantized, predictors in parameters])
    out = []
    for (name, quantized, _), (data, width, predictor) in zip(parameters, coded):
        top = int(np.abs(quantized.levels).max()) if quantized.levels.size else 0
        out.append(PackedTensor(name, "quantized", quantized.steps.astype("<f2").tobytes() + data, quantized.group,
                                predictor, width, bits=top.bit_length() + 1))
    return out


def encode_float32(name: str, tensor: torch.Tensor) -> PackedTensor:
    """A parameter kept exactly (float32, LZMA-compressed)."""
    values = tensor.detach().cpu().contiguous().numpy().astype("<f4")
    return PackedTensor(name, "float32", codec.compress(values.tobytes()))


@dataclass(frozen=True)
class VoxelCorrection:
    """A sparse correction of the network at voxels: ``levels * step`` at flat ``indices``.

    Attributes:
        max_error: the bound it guarantees at every voxel (data units).
        step: the correction's quantisation step (data units).
        indices: ``[K]`` int64 flat voxel indices ``(z * H + y) * W + x``, strictly increasing.
        levels: ``[K]`` nonzero int64 integers.
    """

    max_error: float
    step: float
    indices: np.ndarray
    levels: np.ndarray

    def values(self) -> torch.Tensor:
        """``[K]`` float32 corrections in data units (float32 arithmetic, the same everywhere)."""
        return torch.from_numpy(self.levels.astype(np.float32) * np.float32(self.step))

    def encode(self) -> tuple[bytes, bytes, int, int]:
        """(gaps section, levels section, gap width, level width)."""
        gaps = np.diff(self.indices, prepend=0) if self.indices.size else self.indices
        gap_width, level_width = codec.width_of(gaps), codec.width_of(self.levels)
        return (codec.compress(codec.to_bytes(gaps, gap_width)),
                codec.compress(codec.to_bytes(self.levels, level_width)), gap_width, level_width)


# ---------------------------------------------------------------------------------------------- writing
def packed_file_bytes(
    field: NeuralField,
    tensors: list[PackedTensor],
    source: SourceInfo,
    training: dict,
    report: dict,
    correction: VoxelCorrection | None = None,
) -> bytes:
    """The bytes of a packed model file (nothing written; :func:`save_packed` writes them).

    Args:
        field: the network (config, value ranges, transform and volume shape are taken from it).
        tensors: every parameter of ``field``, packed, in the config's order.
        source: where the data came from.
        training: the training summary (only :data:`SUMMARY_KEYS` are kept).
        report: what packing measured (numbers, strings or None).
        correction: the voxel correction of an error bound, or None.
    """
    description = {
        **field_description(field, source, trimmed_training(training)),
        "tensors": [t.entry() for t in tensors],
        "packing": report,
        "correction": None,
    }
    sections = [t.data for t in tensors]
    if correction is not None:
        gaps, levels, gap_width, level_width = correction.encode()
        description["correction"] = {
            "max_error": correction.max_error, "step": correction.step, "count": int(correction.indices.size),
            "gap_width": gap_width, "level_width": level_width,
        }
        sections += [gaps, levels]
    return payload_file_bytes(PACKED_KIND, description, sections)


def trimmed_training(training: dict, keys: tuple[str, ...] = SUMMARY_KEYS) -> dict:
    """The entries ``keys`` of a training summary (what a packed file keeps of it)."""
    return {k: v for k, v in training.items() if k in keys}


def payload_file_bytes(kind: str, description: dict, sections: list[bytes]) -> bytes:
    """The bytes of a packed container file of ``kind``: the description (coded with
    :func:`~apmgsrn.io.codec.compress_description`) and then ``sections``, one after another in the ``payload``
    tensor, their sizes in the header."""
    sections = [codec.compress_description(_json_bytes(description)), *sections]
    payload = torch.frombuffer(bytearray(b"".join(sections)), dtype=torch.uint8)
    return file_bytes({PAYLOAD: payload}, kind,
                      {"sections": [len(s) for s in sections], "coding": codec.DESCRIPTION_CODING})


def save_packed(path: str | os.PathLike, data: bytes) -> int:
    """Write a packed model file's bytes atomically; it may replace an older model file of either kind.

    Returns:
        Bytes written.
    """
    return write_file_bytes(path, data, PACKED_KIND)


def _json_bytes(value) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=True).encode()


# ---------------------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class _Layout:
    """What a validated description says each section must decompress to."""

    parsed: FieldDescription
    entries: list[dict]
    shapes: dict[str, tuple[int, ...]]
    correction: dict | None
    report: dict


@dataclass(frozen=True)
class PayloadFile:
    """A packed container file as read, before its description is checked.

    Attributes:
        header: the validated header.
        sections: the compressed size of every section, description first (sums to the payload).
        chunks: the sections' bytes.
        description: the decompressed description (a JSON object, nothing in it checked yet).
    """

    header: Header
    sections: list[int]
    chunks: list[bytes]
    description: dict


def model_file_description(path: str | os.PathLike) -> dict:
    """A model file's description, read without decoding its parameters: a float32 file's header, a packed
    file's description section.

    Raises:
        ApmgsrnError: not a readable model file.
    """
    header = read_header(path)
    if set(header.tensors) == {PAYLOAD}:  # a packed file: the description is its first coded section
        return read_payload_file(Path(path), header.kind, "a model file").description
    return header.description


def read_payload_file(path: Path, kind: str, what: str) -> PayloadFile:
    """Read a packed container file of ``kind``: header, section sizes against the payload, and the
    description (decompressed to at most :attr:`~apmgsrn.limits.Limits.description_bytes`).

    Args:
        path: the file.
        kind: the kind it must be.
        what: the file wanted, for the message (``"a packed model"``).

    Raises:
        ApmgsrnError: unreadable, of another kind, or a payload or description that is not ours.
    """
    header = header_of_kind(path, kind, what)
    not_ours = f"{path}: not an apmgsrn model file (corrupt, truncated or another format)"
    sections = _section_sizes(header, not_ours)
    payload = load_tensors(path)[PAYLOAD].numpy().tobytes()
    offsets = np.cumsum([0] + sections).tolist()
    chunks = [payload[offsets[i]:offsets[i + 1]] for i in range(len(sections))]
    text = _description_text(header, chunks[0], f"{path}: description", not_ours)
    description = parse_json(text, not_ours)
    if not isinstance(description, dict):
        raise ApmgsrnError(not_ours)
    return PayloadFile(header, sections, chunks, description)


def _section_sizes(header: Header, not_ours: str) -> list[int]:
    """The header's section list, checked against the payload."""
    entry = header.tensors.get(PAYLOAD)
    if set(header.tensors) != {PAYLOAD} or entry.dtype != "U8" or len(entry.shape) != 1:
        raise ApmgsrnError(not_ours)
    sections = header.description.get("sections")
    if (
        not isinstance(sections, list) or not 1 <= len(sections) <= MAX_GROUPS
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in sections)
        or sum(sections) != entry.shape[0]
    ):
        raise ApmgsrnError(not_ours)
    return sections


def _description_text(header: Header, data: bytes, what: str, not_ours: str) -> bytes:
    """The description's JSON text: primed deflate (the header names it), or LZMA in files of version 1."""
    coding = header.description.get("coding")
    if coding is None and header.version == 1:
        return codec.decompress_bounded(data, LIMITS.description_bytes, what, "text")
    if coding != codec.DESCRIPTION_CODING:
        raise ApmgsrnError(not_ours)
    return codec.decompress_description(data, LIMITS.description_bytes, what)


def _tensor_entry(name: str, entry: list) -> dict:
    """A stored tensor's entry (see :meth:`PackedTensor.entry`) as a dict, its form checked."""
    if entry == ["float32"]:
        return {"name": name, "encoding": "float32"}
    if len(entry) != 4 or entry[0] != "quantized" or not isinstance(entry[2], str):
        raise DescriptionError(f"tensor {name} has an unknown encoding")
    return {"name": name, "encoding": "quantized", "group": entry[1], "predictor": entry[2], "width": entry[3]}


def _check_expansion(name: str, expected: int, stored: int) -> None:
    if expected > stored * MAX_EXPANSION + EXPANSION_SLACK:
        raise DescriptionError(f"{name} declares {expected} bytes, more than its {stored} stored bytes can hold")


def parse_tensor_entries(value, shapes: dict[str, tuple[int, ...]], stored: list[int],
                         predictors: Callable[[str, tuple[int, ...]], tuple[str, ...]] | None = None) -> list[dict]:
    """Check the ``tensors`` entry of a packed description against the parameters the config implies and the
    sizes of their sections (nothing decompressed yet).

    Args:
        value: the description's ``tensors`` (one entry per parameter, in the config's order).
        shapes: name -> shape of every parameter, from the validated config.
        stored: the compressed size of each parameter's section, in the same order.
        predictors: ``(name, shape) -> predictors allowed`` (default: :func:`~apmgsrn.io.codec.predictors_for`
            of the shape).

    Returns:
        One dict per parameter: ``name``, ``encoding`` and, when quantised, ``group``, ``predictor``, ``width``.

    Raises:
        DescriptionError, ValueError, TypeError: anything missing, mistyped, out of range or inconsistent.
    """
    if sum(math.prod(s) for s in shapes.values()) > LIMITS.packed_parameters:
        raise DescriptionError("the model config declares more parameters than a packed file may hold")
    if not isinstance(value, list) or len(value) != len(shapes) or not all(isinstance(e, list) for e in value):
        raise DescriptionError("stored tensors do not match the model config")
    entries = [_tensor_entry(name, entry) for name, entry in zip(shapes, value)]
    for entry, size in zip(entries, stored, strict=True):
        name, numel = entry["name"], math.prod(shapes[entry["name"]])
        if entry["encoding"] == "float32":
            _check_expansion(name, numel * 4, size)
            continue
        group = require_int(entry["group"], f"{name} group", 1, max(numel, 1))
        groups = group_count(numel, group)
        if groups > MAX_GROUPS:
            raise DescriptionError(f"tensor {name} declares more than {MAX_GROUPS} groups")
        allowed = predictors(name, shapes[name]) if predictors is not None else codec.predictors_for(shapes[name])
        if entry["predictor"] not in allowed:
            raise DescriptionError(f"tensor {name} names an unknown predictor")
        if entry["width"] not in (1, 2, 4):
            raise DescriptionError(f"tensor {name} has an invalid width")
        if size < 2 * groups:
            raise DescriptionError(f"tensor {name} is shorter than its steps")
        _check_expansion(name, numel * entry["width"], size - 2 * groups)
    return entries


def parse_report(value) -> dict:
    """A packed description's ``packing`` report: an object of numbers, strings or null."""
    report = require_dict(value, "packing")
    if not all(isinstance(k, str) and (v is None or isinstance(v, (int, float, str))) for k, v in report.items()):
        raise DescriptionError("packing report holds something other than numbers and text")
    return report


def decode_tensors(entries: list[dict], shapes: dict[str, tuple[int, ...]], chunks: list[bytes], path: Path
                   ) -> tuple[dict[str, torch.Tensor], list[PackedPart]]:
    """Every parameter from its section (entries from :func:`parse_tensor_entries`): float32 tensors by name,
    and a part per section for the :class:`PackingSummary`.

    Raises:
        ApmgsrnError: a section that does not decompress to what its entry declares.
        DescriptionError: steps that are not positive and finite.
    """
    state, parts = {}, []
    for entry, data in zip(entries, chunks, strict=True):
        name, shape = entry["name"], shapes[entry["name"]]
        state[name], bits = _decode_tensor(entry, shape, data, f"{path}: {name}")
        parts.append(PackedPart(name, entry["encoding"], math.prod(shape), len(data), bits))
    return state, parts


def packing_summary(path: Path, sections: list[int], parts: list[PackedPart], parameters: int, report: dict,
                    correction: VoxelCorrection | None = None) -> PackingSummary:
    """What a loaded packed file holds: its parts, the container framing around them, the float32 size of its
    ``parameters``, the packing ``report`` and the error bound of ``correction``."""
    return PackingSummary(
        parts=tuple(parts),
        container_bytes=path.stat().st_size - sum(sections),
        float32_bytes=4 * parameters,
        report=report,
        max_error=correction.max_error if correction is not None else None,
        corrected_voxels=int(correction.indices.size) if correction is not None else 0,
    )


def _parse_layout(description: dict, sections: list[int]) -> _Layout:
    """Check a packed description and the section sizes it implies (nothing decompressed yet).

    Raises:
        DescriptionError, ValueError, TypeError: anything missing, mistyped, out of range or inconsistent.
    """
    parsed = parse_field_description(description)
    shapes = parsed.config.parameter_shapes()
    correction = description.get("correction")
    expected_sections = 1 + len(shapes) + (2 if correction is not None else 0)
    if len(sections) != expected_sections:
        raise DescriptionError(f"the file has {len(sections)} sections, the description implies {expected_sections}")
    entries = parse_tensor_entries(description.get("tensors"), shapes, sections[1:1 + len(shapes)])
    if correction is not None:
        correction = require_dict(correction, "correction")
        if set(correction) != {"max_error", "step", "count", "gap_width", "level_width"}:
            raise DescriptionError("correction has unknown or missing entries")
        require_number(correction["max_error"], "correction.max_error")
        require_number(correction["step"], "correction.step")
        if not correction["max_error"] > 0 or not correction["step"] > 0:
            raise DescriptionError("correction bound and step must be positive")
        voxels = math.prod(parsed.volume_shape)
        if voxels >= LIMITS.corrected_voxels:
            raise DescriptionError("a correction needs a volume whose flat voxel indices fit in int64")
        count = require_int(correction["count"], "correction.count", 0, min(voxels, LIMITS.corrections))
        for key, stored in zip(("gap_width", "level_width"), sections[-2:]):
            if correction[key] not in (1, 2, 4):
                raise DescriptionError(f"correction.{key} is invalid")
            _check_expansion(f"correction {key}", count * correction[key], stored)
    return _Layout(parsed, entries, shapes, correction, parse_report(description.get("packing", {})))


def load_packed(path: str | os.PathLike, device: torch.device | str = "cpu") -> tuple[NeuralField, ModelDescription]:
    """Load a packed model file as a field (float32 parameters, dequantised).

    Args:
        path: the file.
        device: where to put the field.

    Returns:
        The field (a :class:`~apmgsrn.models.corrected_field.CorrectedField` when the file carries an error
        bound) in eval mode, and its description (``packing`` filled in).

    Raises:
        ApmgsrnError: unreadable, foreign, newer, inconsistent or hostile file.
    """
    path = Path(path)
    file = read_payload_file(path, PACKED_KIND, "a packed model")
    sections, chunk = file.sections, file.chunks
    try:
        layout = _parse_layout(file.description, sections)
        state, parts = decode_tensors(layout.entries, layout.shapes, chunk[1:1 + len(layout.entries)], path)
        parts.insert(0, PackedPart("description", "json", 0, sections[0]))
        correction = None
        if layout.correction is not None:
            correction = _decode_correction(layout.correction, layout.parsed.volume_shape, chunk[-2], chunk[-1],
                                            f"{path}: correction")
            count = int(correction.indices.size)
            parts += [PackedPart("correction indices", "voxels", count, len(chunk[-2])),
                      PackedPart("correction values", "voxels", count, len(chunk[-1]))]
    except (DescriptionError, ValueError, TypeError, KeyError) as exc:
        raise inconsistent(path, exc) from None
    field = build_field(layout.parsed, state, correction, path)
    parameters = field.parameter_count()
    summary = packing_summary(path, sections, parts, parameters, layout.report, correction)
    model_description = ModelDescription(
        kind=PACKED_KIND,
        config=layout.parsed.config,
        volume_shape=layout.parsed.volume_shape,
        value_range=layout.parsed.value_range,
        transform=layout.parsed.transform.kind,
        source=layout.parsed.source,
        training=layout.parsed.training,
        parameters=parameters,
        file_bytes=path.stat().st_size,
        format_version=file.header.version,
        packing=summary,
    )
    return field.to(device).eval(), model_description


def _decode_tensor(entry: dict, shape: tuple[int, ...], data: bytes, what: str) -> tuple[torch.Tensor, int | None]:
    """A parameter from its section (sizes already validated): (float32 tensor, bit width or None)."""
    numel = math.prod(shape)
    if entry["encoding"] == "float32":
        raw = codec.decompress(data, numel * 4, what)
        return torch.from_numpy(np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(shape)), None
    groups = group_count(numel, entry["group"])
    steps = np.frombuffer(data[: 2 * groups], dtype="<f2").astype(np.float16)
    if not np.isfinite(steps).all() or not (steps > 0).all():
        raise DescriptionError(f"tensor {entry['name']} has steps that are not positive and finite")
    raw = codec.decompress(data[2 * groups:], numel * entry["width"], what)
    residuals = codec.from_bytes(raw, numel, entry["width"])
    levels = codec.reconstruct(residuals, shape, entry["predictor"])
    top = int(np.abs(levels).max()) if levels.size else 0
    return dequantize(levels, steps, entry["group"], shape), top.bit_length() + 1


def _decode_correction(entry: dict, volume_shape: tuple[int, int, int], gaps_data: bytes, levels_data: bytes,
                       what: str) -> VoxelCorrection:
    count = entry["count"]
    gaps = codec.from_bytes(codec.decompress(gaps_data, count * entry["gap_width"], f"{what} indices"), count,
                            entry["gap_width"])
    levels = codec.from_bytes(codec.decompress(levels_data, count * entry["level_width"], f"{what} values"), count,
                              entry["level_width"])
    # The first gap is the first index; the others at least 1, so the indices strictly increase.
    if count and (gaps[0] < 0 or (gaps[1:] < 1).any()):
        raise DescriptionError("correction indices are not strictly increasing")
    indices = np.cumsum(gaps)
    if count and indices[-1] >= math.prod(volume_shape):
        raise DescriptionError("a correction index lies outside the volume")
    if (levels == 0).any():
        raise DescriptionError("a correction holds a zero value")
    return VoxelCorrection(float(entry["max_error"]), float(entry["step"]), indices, levels)


def build_field(parsed: FieldDescription, state: dict[str, torch.Tensor], correction: VoxelCorrection | None,
                path: str | os.PathLike = "model") -> NeuralField:
    """The field a packed file describes, with its (dequantised) parameters and correction, on the CPU.

    Raises:
        ApmgsrnError: the parameters do not fit the config, or hold NaN/Inf or a singular grid map.
    """
    if correction is None:
        return restore_field(path, NeuralField, parsed.config, parsed, state)

    def attach(field: CorrectedField) -> None:
        field.set_correction(torch.from_numpy(correction.indices), correction.values())

    return restore_field(path, CorrectedField, parsed.config, parsed, state, prepare=attach,
                         max_error=correction.max_error)

