"""Model files: the single-file and brick-folder formats, validation before allocation, atomic writes,
typed model descriptions and the loader registry.

Layer: above :mod:`apmgsrn.models` (it builds fields from files), below :mod:`apmgsrn.training` (which
saves through it); it imports no training, decomposition, render, series or CLI code. Time-series files are
:mod:`apmgsrn.series`'s (:mod:`apmgsrn.series.file`), which registers their loaders here.
"""

from apmgsrn.atomic import atomic_write, atomic_write_text, check_output_path
from apmgsrn.io.description import BrickEntry, BrickLayout, ModelDescription, SeriesLayout, SeriesStepInfo, SourceInfo
from apmgsrn.io.container import verify_file
from apmgsrn.io.field_file import load_field, save_field
from apmgsrn.io.registry import (
    LoadedModel,
    file_loader,
    model_kind,
    open_model,
    register_folder_kind,
    register_loader,
)
from apmgsrn.io.verify import FileCheck, verify_model

__all__ = [
    "BrickEntry",
    "BrickLayout",
    "FileCheck",
    "LoadedModel",
    "ModelDescription",
    "SeriesLayout",
    "SeriesStepInfo",
    "SourceInfo",
    "atomic_write",
    "atomic_write_text",
    "check_output_path",
    "file_loader",
    "load_field",
    "model_kind",
    "open_model",
    "register_folder_kind",
    "register_loader",
    "save_field",
    "verify_file",
    "verify_model",
]
