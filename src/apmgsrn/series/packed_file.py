"""The packed time-series model file: a series' parameters quantised and entropy-coded (kind ``packed-series``).

Built like the packed single-field file (:mod:`apmgsrn.io.packed`): a :mod:`~apmgsrn.io.container` file
holding one ``U8`` tensor, ``payload``, cut into sections whose compressed sizes the header lists:

0. the description: what a float32 series file's description holds
   (:func:`~apmgsrn.series.file.series_description`: the spatial field's config, value scaling and
   transform, the shape of every step, ``series``, ``steps``, source, and the training summary without its
   loss history) plus ``tensors`` (how each parameter is stored) and ``packing`` (what packing measured),
   coded with :func:`~apmgsrn.io.codec.compress_description`;
1. one section per parameter of :meth:`~apmgsrn.series.field.SeriesFieldConfig.parameter_shapes`, in
   that order, stored as a packed field stores it (``quantized`` or ``float32``). Only the tensors with a
   leading time (or basis) axis, the grids ``[K, M, C, D, H, W]`` and residuals ``[T, M, C, r, r, r]`` (a
   hybrid series: its grids ``[T, M, R, R, R, C]`` and level tables ``[T, P]``), may use the ``time``
   predictor (:func:`~apmgsrn.io.codec.series_predictors_for`).

Loading validates everything before it allocates: the header and section sizes, the description (the
field's entries, then the series config and step entries as a series file reads them), the declared tensors
against the shapes the configs imply and their total against
:attr:`~apmgsrn.limits.Limits.packed_parameters`; each section's decompressed size is computed from those
shapes, bounded by what LZMA can expand to, and decompression stops there. Dequantising gives a float32
:class:`~apmgsrn.series.field.SeriesField`, the same as a float32 series file gives.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from apmgsrn.limits import LIMITS
from apmgsrn.io import codec
from apmgsrn.io.container import PACKED_SERIES_KIND, write_file_bytes
from apmgsrn.io.description import (
    DescriptionError,
    ModelDescription,
    PackedPart,
    SeriesLayout,
    SeriesStepInfo,
    SourceInfo,
    inconsistent,
)
from apmgsrn.io.field_file import loaded_description, parse_field_description, restore_field
from apmgsrn.io.packed import (
    SUMMARY_KEYS,
    PackedTensor,
    decode_tensors,
    packing_summary,
    parse_report,
    parse_tensor_entries,
    payload_file_bytes,
    read_payload_file,
    trimmed_training,
)
from apmgsrn.series.file import parse_series_config, parse_step_entries, series_description
from apmgsrn.series.field import SeriesField, SeriesFieldConfig

#: Parameters with a leading time (or basis) axis: the only ones the ``time`` predictor may code.
TIME_AXIS_TENSORS = ("encoder.grids", "encoder.residuals", "encoder.level_table")
#: Entries of the training summary a packed series file keeps: a packed field's, plus ``steps`` (per-step
#: figures, which ``info`` shows; the packer stores those of the packed field), ``stepwise`` (the start
#: step and the steps' fine-tune of a stepwise run), and for the brick of a brick model its box (``brick``)
#: and figures over all its steps (what a rerun reports for bricks it reuses).
SERIES_SUMMARY_KEYS = (*SUMMARY_KEYS, "steps", "stepwise", "brick", "psnr", "max_abs_error")


def series_predictors(name: str, shape: tuple[int, ...]) -> tuple[str, ...]:
    """Predictors a packed series file may code parameter ``name`` of ``shape`` with."""
    if name in TIME_AXIS_TENSORS:
        return codec.series_predictors_for(shape)
    return codec.predictors_for(shape)


def packed_series_bytes(field: SeriesField, tensors: list[PackedTensor], source: SourceInfo, training: dict,
                        steps: list[SeriesStepInfo], report: dict) -> bytes:
    """The bytes of a packed series file (nothing written; :func:`save_packed_series` writes them).

    Args:
        field: the series field (configs, value ranges, transform and volume shape are taken from it).
        tensors: every parameter of ``field``, packed, in the config's order.
        source: where the data came from.
        training: the training summary (only :data:`SERIES_SUMMARY_KEYS` are kept).
        steps: one entry per step, in order.
        report: what packing measured (numbers, strings or None).
    """
    description = {
        **series_description(field, source, trimmed_training(training, SERIES_SUMMARY_KEYS), steps),
        "tensors": [t.entry() for t in tensors],
        "packing": report,
    }
    return payload_file_bytes(PACKED_SERIES_KIND, description, [t.data for t in tensors])


def save_packed_series(path: str | os.PathLike, data: bytes) -> int:
    """Write a packed series file's bytes atomically; it may replace an older series file of either kind.

    Returns:
        Bytes written.
    """
    return write_file_bytes(path, data, PACKED_SERIES_KIND)


def load_packed_series(path: str | os.PathLike, device: torch.device | str = "cpu"
                       ) -> tuple[SeriesField, ModelDescription]:
    """Load a packed series file as a series field (float32 parameters, dequantised).

    Args:
        path: the file.
        device: where to put the field.

    Returns:
        The series field (eval mode) and its description (``series`` and ``packing`` filled in).

    Raises:
        ApmgsrnError: unreadable, foreign, newer, inconsistent or hostile file.
    """
    path = Path(path)
    file = read_payload_file(path, PACKED_SERIES_KIND, "a packed time-series model")
    description = file.description
    try:
        parsed = parse_field_description(description)
        config = SeriesFieldConfig(parsed.config, parse_series_config(description.get("series")))
        shapes = config.parameter_shapes()
        if len(file.sections) != 1 + len(shapes):
            raise DescriptionError(f"the file has {len(file.sections)} sections, the description implies "
                                   f"{1 + len(shapes)}")
        entries = parse_tensor_entries(description.get("tensors"), shapes, file.sections[1:], series_predictors)
        steps = parse_step_entries(description.get("steps"), config.series.steps)
        report = parse_report(description.get("packing", {}))
        state, parts = decode_tensors(entries, shapes, file.chunks[1:], path)
    except (DescriptionError, ValueError, TypeError, KeyError) as exc:
        raise inconsistent(path, exc) from None
    field = restore_field(path, SeriesField, config, parsed, state)
    parts.insert(0, PackedPart("description", "json", 0, file.sections[0]))
    summary = packing_summary(path, file.sections, parts, field.parameter_count(), report)
    model_description = loaded_description(path, file.header, PACKED_SERIES_KIND, parsed, field,
                                           series=SeriesLayout(config.series, steps), packing=summary)
    return field.to(device).eval(), model_description
