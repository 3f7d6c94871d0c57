"""The time-series model file: one network for every step of a series (kind ``series``).

Layout (a :mod:`~apmgsrn.io.container` file): the tensors are the
:class:`~apmgsrn.series.field.SeriesField`'s ``state_dict`` (the basis grids ``[K, M, C, D, H, W]``, the
learned weights ``[T, M, C, K]`` unless they are keyframes, the shared grid maps and decoder); the description
holds every entry of a single-field file (:func:`~apmgsrn.io.field_file.field_description`: the spatial
field's config, the series' value scaling and transform, the shape of every step, source, training) plus
``series`` (steps, basis size, kind of weights) and ``steps`` (per step: its number, file name and value range).

As for single fields, the description is checked entry by entry and every declared tensor is compared with
the shapes the configs imply before anything is allocated; non-finite weights are refused.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from apmgsrn.io.container import (
    PACKED_SERIES_KIND,
    SERIES_KIND,
    Header,
    header_of_kind,
    load_tensors,
    read_header,
    save_tensors,
)
from apmgsrn.io.description import (
    DescriptionError,
    ModelDescription,
    SeriesLayout,
    SeriesStepInfo,
    SourceInfo,
    inconsistent,
    optional_str,
    require_dict,
    require_int,
    require_number,
)
from apmgsrn.io.field_file import (
    check_declared_tensors,
    field_description,
    loaded_description,
    parse_field_description,
    restore_field,
    stored_tensors,
)
from apmgsrn.io.packed import model_file_description  # noqa: F401 - where a series' bricks read theirs
from apmgsrn.models.encoders.adaptive_multigrid import MAX_RESOLUTION
from apmgsrn.series.field import SeriesConfig, SeriesField, SeriesFieldConfig
from apmgsrn.series.options import COEFFICIENT_KINDS, MAX_BASIS, MAX_STEPS, PLACEMENT_KINDS, STORAGE_KINDS


def save_series(path: str | os.PathLike, field: SeriesField, source: SourceInfo, training: dict,
                steps: list[SeriesStepInfo]) -> int:
    """Save a time-series field, atomically.

    Args:
        path: the model file.
        field: the trained series field.
        source: where the data came from.
        training: the training summary (JSON-able).
        steps: one entry per step, in order.

    Returns:
        Bytes written.
    """
    description = series_description(field, source, training, steps)
    return save_tensors(path, stored_tensors(field), SERIES_KIND, description)


def series_description(field: SeriesField, source: SourceInfo, training: dict, steps: list[SeriesStepInfo]) -> dict:
    """The description of a series file (a packed series file extends it): a single-field file's entries with
    the spatial field's config, plus ``series`` and ``steps``.

    Raises:
        ValueError: not one step entry per step of ``field``.
    """
    if len(steps) != field.steps:
        raise ValueError(f"{len(steps)} step entries for a series of {field.steps} steps")
    description = field_description(field, source, training)
    description["field"] = field.config.field.to_dict()  # the spatial field; the series part beside it
    description["series"] = field.config.series.to_dict()
    description["steps"] = [step.to_dict() for step in steps]
    return description


def parse_series_config(value) -> SeriesConfig:
    """A description's ``series`` entry, checked entry by entry (a packed series file reads it too).

    Raises:
        DescriptionError, ValueError: a missing, mistyped or out-of-range entry.
    """
    data = require_dict(value, "series")
    if set(data) - {"steps", "basis", "coefficients", "residual", "storage", "mixing", "placement"}:
        raise DescriptionError("series holds unknown entries")
    coefficients, storage = data.get("coefficients"), data.get("storage", "float32")
    placement = data.get("placement", "shared")
    if placement not in PLACEMENT_KINDS:
        raise DescriptionError("series.placement is not a known kind")
    if coefficients not in COEFFICIENT_KINDS:
        raise DescriptionError("series.coefficients is not a known kind")
    if storage not in STORAGE_KINDS:
        raise DescriptionError("series.storage is not a known dtype")
    return SeriesConfig(
        steps=require_int(data.get("steps"), "series.steps", 1, MAX_STEPS),
        basis=require_int(data.get("basis"), "series.basis", 1, MAX_BASIS),
        coefficients=coefficients,
        residual=require_int(data.get("residual", 0), "series.residual", 0, MAX_RESOLUTION),
        storage=storage,
        mixing=require_int(data.get("mixing", 1), "series.mixing", 1, MAX_RESOLUTION),
        placement=placement,
    )


def parse_step_entries(value, count: int) -> tuple[SeriesStepInfo, ...]:
    """A description's ``steps`` entry: ``count`` steps, each with its number, file name and value range.

    Raises:
        DescriptionError: not a list of ``count`` well-formed entries.
    """
    if not isinstance(value, list) or len(value) != count:
        raise DescriptionError(f"steps is not a list of {count} entries")
    entries = []
    for index, item in enumerate(value):
        item = require_dict(item, f"steps[{index}]")
        low = require_number(item.get("value_min"), f"steps[{index}].value_min")
        high = require_number(item.get("value_max"), f"steps[{index}].value_max")
        if low > high:
            raise DescriptionError(f"steps[{index}] has min > max")
        entries.append(SeriesStepInfo(
            label=require_number(item.get("label"), f"steps[{index}].label"),
            name=optional_str(item.get("name"), f"steps[{index}].name") or "",
            value_range=(low, high),
        ))
    return tuple(entries)


def declared_steps(path: str | os.PathLike) -> int:
    """Number of steps a time-series model file declares: from the header of a float32 one (no tensor is read),
    from the description section of a packed one (no parameter is decoded).

    Raises:
        ApmgsrnError: not a readable time-series model file.
    """
    header = read_header(path)
    if header.kind != PACKED_SERIES_KIND:
        header_of_kind(path, SERIES_KIND, "a time-series model", header)
    description = model_file_description(path)
    try:
        return parse_series_config(description.get("series")).steps
    except (DescriptionError, ValueError, TypeError) as exc:
        raise inconsistent(path, exc) from None


def load_series(path: str | os.PathLike, device: torch.device | str = "cpu",
                header: Header | None = None) -> tuple[SeriesField, ModelDescription]:
    """Load a time-series model file.

    Args:
        path: the file.
        device: where to put the field.
        header: its header if already read.

    Returns:
        The series field (eval mode) and its description (with :attr:`ModelDescription.series`).

    Raises:
        ApmgsrnError: unreadable, foreign, newer, inconsistent or hostile file.
    """
    path = Path(path)
    header = header_of_kind(path, SERIES_KIND, "a time-series model", header)
    try:
        parsed = parse_field_description(header.description)
        config = SeriesFieldConfig(parsed.config, parse_series_config(header.description.get("series")))
        steps = parse_step_entries(header.description.get("steps"), config.series.steps)
        check_declared_tensors(header, config)
    except (DescriptionError, ValueError, TypeError) as exc:
        raise inconsistent(path, exc) from None
    tensors = {name: tensor.float() for name, tensor in load_tensors(path).items()}
    field = restore_field(path, SeriesField, config, parsed, tensors)
    layout = SeriesLayout(config.series, steps)
    description = loaded_description(path, header, SERIES_KIND, parsed, field, series=layout)
    return field.to(device).eval(), description
