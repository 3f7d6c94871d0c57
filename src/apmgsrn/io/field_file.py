"""The single-field model file: one network, its value scaling and transform, and how it was trained.

Layout (a :mod:`~apmgsrn.io.container` file of kind ``field``): the tensors are the field's ``state_dict``;
the description holds ``field`` (the :class:`~apmgsrn.models.registry.FieldConfig`), ``fit_min``/``fit_max``
(output scaling, fitted units), ``value_min``/``value_max`` (data units), ``transform`` (the value
transform), ``volume_shape`` (D, H, W), ``source`` and ``training`` (the summary).

Loading checks the description and compares every declared tensor with the shapes the config implies
*before* a module is built, so a file cannot make the loader allocate more than it really stores; it
refuses non-finite weights and singular grid maps (a model that would decode to NaN).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from apmgsrn.limits import LIMITS
from apmgsrn.io.container import FIELD_KIND, Header, header_of_kind, load_tensors, save_tensors
from apmgsrn.io.description import (
    DescriptionError,
    ModelDescription,
    SourceInfo,
    inconsistent,
    require_dict,
    require_ints,
    require_number,
    training_summary,
)
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig
from apmgsrn.models.value_transform import TRANSFORMS, ValueTransform

#: The safetensors name of each dtype a model file stores (:data:`apmgsrn.models.encoders.base.STORAGE_DTYPES`).
SAFETENSORS_DTYPES = {torch.float32: "F32", torch.float16: "F16"}


@dataclass(frozen=True)
class FieldDescription:
    """The parsed description of a single-field file (what the loader builds the field from)."""

    config: FieldConfig
    fit_range: tuple[float, float]
    value_range: tuple[float, float]
    transform: ValueTransform
    volume_shape: tuple[int, int, int]
    source: SourceInfo
    training: dict


def save_field(path: str | os.PathLike, field: NeuralField, source: SourceInfo, training: dict) -> int:
    """Save a field with everything needed to rebuild it, atomically.

    Args:
        path: the model file.
        field: the trained field.
        source: where the data came from.
        training: the training summary (JSON-able).

    Returns:
        Bytes written.
    """
    return save_tensors(path, stored_tensors(field), FIELD_KIND, field_description(field, source, training))


def stored_tensors(field) -> dict[str, torch.Tensor]:
    """A field's (or series field's) parameters in the dtypes its config stores them in."""
    stored = field.config.stored_dtypes()
    return {name: tensor.to(stored[name]) for name, tensor in field.state_dict().items()}


def field_description(field, source: SourceInfo, training: dict) -> dict:
    """The description entries every field file has (a series file and a packed file extend it): the field's
    config, value scaling and transform, volume shape, source and training summary."""
    return {
        "field": field.config.to_dict(),
        "fit_min": field.fit_min,
        "fit_max": field.fit_max,
        "value_min": field.value_min,
        "value_max": field.value_max,
        "transform": dataclasses.asdict(field.transform),
        "volume_shape": list(field.volume_shape),
        "source": source.to_dict(),
        "training": training,
    }


def parse_field_description(description: dict) -> FieldDescription:
    """Check a ``field`` file's description, field by field.

    Raises:
        DescriptionError, ValueError: a missing, mistyped or out-of-range entry.
    """
    config = FieldConfig.from_dict(description.get("field"))
    fit_range = (require_number(description.get("fit_min"), "fit_min"),
                 require_number(description.get("fit_max"), "fit_max"))
    value_range = (require_number(description.get("value_min"), "value_min"),
                   require_number(description.get("value_max"), "value_max"))
    if fit_range[0] > fit_range[1] or value_range[0] > value_range[1]:
        raise DescriptionError("value range has min > max")
    transform = require_dict(description.get("transform"), "transform")
    if transform.get("kind") not in TRANSFORMS or set(transform) - {"kind", "offset", "mean", "std"}:
        raise DescriptionError("transform is not a known value transform")
    numbers = {k: require_number(v, f"transform.{k}") for k, v in transform.items() if k != "kind"}
    volume_shape = require_ints(description.get("volume_shape"), "volume_shape", 3, 1, LIMITS.volume_axis)
    source = SourceInfo.from_dict(description.get("source", {}))
    source.check_shape(volume_shape)
    return FieldDescription(
        config=config,
        fit_range=fit_range,
        value_range=value_range,
        transform=ValueTransform(transform["kind"], **numbers),
        volume_shape=volume_shape,
        source=source,
        training=training_summary(description.get("training", {})),
    )


def check_declared_tensors(header: Header, config) -> None:
    """The file must store exactly the parameters the config implies, no more, no fewer, in their dtypes.

    Args:
        header: the file's validated header.
        config: anything with ``parameter_shapes()`` and ``stored_dtypes()`` (a field's or a series field's
            config).
    """
    expected = config.parameter_shapes()
    declared = {name: entry.shape for name, entry in header.tensors.items()}
    if declared != expected:
        missing = sorted(set(expected) - set(declared))
        extra = sorted(set(declared) - set(expected))
        wrong = sorted(k for k in set(expected) & set(declared) if expected[k] != declared[k])
        detail = (f"missing {missing[:3]}" if missing else f"unexpected {extra[:3]}" if extra
                  else f"{wrong[0]} is {list(declared[wrong[0]])}, the config says {list(expected[wrong[0]])}")
        raise DescriptionError(f"stored tensors do not match the model config: {detail}")
    stored = {name: SAFETENSORS_DTYPES[dtype] for name, dtype in config.stored_dtypes().items()}
    wrong = sorted(name for name, entry in header.tensors.items() if entry.dtype != stored[name])
    if wrong:
        raise DescriptionError(f"{wrong[0]} is stored as {header.tensors[wrong[0]].dtype}, not {stored[wrong[0]]}")


def load_field(path: str | os.PathLike, device: torch.device | str = "cpu",
               header: Header | None = None) -> tuple[NeuralField, ModelDescription]:
    """Load a single-field model file.

    Args:
        path: the file.
        device: where to put the field.
        header: its header if already read.

    Returns:
        The field (eval mode) and its description.

    Raises:
        ApmgsrnError: unreadable, foreign, newer, inconsistent or hostile file.
    """
    path = Path(path)
    header = header_of_kind(path, FIELD_KIND, "a single model; pass a model file", header)
    try:
        parsed = parse_field_description(header.description)
        check_declared_tensors(header, parsed.config)
    except (DescriptionError, ValueError, TypeError) as exc:
        raise inconsistent(path, exc) from None
    field = restore_field(path, NeuralField, parsed.config, parsed, load_tensors(path))
    description = loaded_description(path, header, FIELD_KIND, parsed, field)
    return field.to(device).eval(), description


def restore_field(path: Path | str, field_class: type, config, parsed: FieldDescription, tensors: dict,
                  prepare=None, **options):
    """``field_class(config, ..., **options)`` with the value ranges and transform of ``parsed``, then
    ``prepare(field)`` if given (before the tensors load: a correction to attach), its tensors loaded
    exactly (no missing or extra names, matching shapes) and its parameters checked.

    Raises:
        ApmgsrnError: the tensors do not fit the description, or hold values no trained model has.
    """
    try:
        field = field_class(
            config,
            fit_min=parsed.fit_range[0],
            fit_max=parsed.fit_range[1],
            value_min=parsed.value_range[0],
            value_max=parsed.value_range[1],
            transform=parsed.transform,
            volume_shape=parsed.volume_shape,
            **options,
        )
        if prepare is not None:
            prepare(field)
        field.load_state_dict(tensors, strict=True)
        problem = field.check_parameters()
        if problem is not None:
            raise DescriptionError(problem)
    except (DescriptionError, ValueError, RuntimeError) as exc:
        raise inconsistent(path, exc) from None
    return field


def loaded_description(
    path: Path, header: Header, kind: str, parsed: FieldDescription, field, **extra
) -> ModelDescription:
    """The :class:`ModelDescription` of a single-field file (``extra``: the fields of other kinds, as ``series``)."""
    return ModelDescription(
        kind=kind,
        config=parsed.config,
        volume_shape=parsed.volume_shape,
        value_range=parsed.value_range,
        transform=parsed.transform.kind,
        source=parsed.source,
        training=parsed.training,
        parameters=field.parameter_count(),
        file_bytes=path.stat().st_size,
        format_version=header.version,
        **extra,
    )
