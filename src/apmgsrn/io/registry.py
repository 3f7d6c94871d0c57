"""One door to every model format: a loader per kind, registered by the layer that can build it.

Single-field and time-series files, float32 or packed, load here. Brick models need the brick router, which lives in
:mod:`apmgsrn.decomposition` (a layer above this one): it registers its loader on import, and
:func:`apmgsrn.load` imports it, so callers of the public API open every kind.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from apmgsrn.errors import ApmgsrnError
from apmgsrn.io.brick_folder import BRICKS_KIND, MANIFEST_NAME, is_brick_folder, read_manifest
from apmgsrn.io.container import PACKED_KIND, PACKED_SERIES_KIND, read_header
from apmgsrn.io.description import ModelDescription
from apmgsrn.io.field_file import FIELD_KIND, load_field
from apmgsrn.io.packed import load_packed
from apmgsrn.io.packed_series import load_packed_series
from apmgsrn.io.series_file import SERIES_KIND, load_series
from apmgsrn.io.series_folder import SERIES_BRICKS_KIND, is_series_brick_folder, read_series_manifest


@dataclass(frozen=True)
class LoadedModel:
    """A model opened from disk: the network and what its file says about it.

    Attributes:
        field: ``[N, 3]`` points in ``[-1, 1]^3`` -> ``[N, 1]`` values in data units (eval mode).
        description: the typed description.
    """

    field: nn.Module
    description: ModelDescription


#: kind -> loader(path, device) returning (field, description).
Loader = Callable[[Path, torch.device], tuple[nn.Module, ModelDescription]]
_LOADERS: dict[str, Loader] = {
    FIELD_KIND: lambda path, device: load_field(path, device),
    SERIES_KIND: lambda path, device: load_series(path, device),
    PACKED_KIND: lambda path, device: load_packed(path, device),
    PACKED_SERIES_KIND: lambda path, device: load_packed_series(path, device),
}


def register_loader(kind: str, loader: Loader) -> None:
    """Make :func:`open_model` open models of ``kind`` with ``loader``."""
    _LOADERS[kind] = loader


def model_kind(path: str | os.PathLike) -> str | None:
    """``"field"``, ``"series"``, ``"bricks"`` (or another registered kind) for a model file or folder, else None.

    Reads only a file's header or a folder's manifest, never tensors.
    """
    path = Path(path)
    try:
        if path.is_dir():
            if is_series_brick_folder(path):
                return SERIES_BRICKS_KIND if read_series_manifest(path) else None
            return BRICKS_KIND if is_brick_folder(path) and read_manifest(path) else None
        kind = read_header(path).kind
    except (ApmgsrnError, OSError):
        return None
    return kind if kind in _LOADERS or kind in (BRICKS_KIND, SERIES_BRICKS_KIND) else None


def open_model(path: str | os.PathLike, device: torch.device | str = "cpu") -> LoadedModel:
    """Open any model file or brick-model folder.

    Args:
        path: the model file or folder.
        device: where to put the network(s).

    Raises:
        ApmgsrnError: missing, corrupt, foreign, hostile or newer file; a kind nobody registered.
    """
    path = Path(path)
    device = torch.device(device)
    if path.is_dir() and not is_brick_folder(path) and not is_series_brick_folder(path):
        raise ApmgsrnError(
            f"{path}: folder has no {MANIFEST_NAME}, so it is not a brick model; pass a model file or a "
            "folder written by a brick training run"
        )
    if path.is_dir():
        kind = SERIES_BRICKS_KIND if is_series_brick_folder(path) else BRICKS_KIND
    else:
        kind = read_header(path).kind
    loader = _LOADERS.get(kind)
    if loader is None:
        if kind in (BRICKS_KIND, SERIES_BRICKS_KIND):
            raise ApmgsrnError(f"{path}: brick models open through apmgsrn.load (import apmgsrn.decomposition)")
        raise ApmgsrnError(f"{path}: is a {kind or 'unknown'} file, not a model; pass a model file")
    field, description = loader(path, device)
    return LoadedModel(field, description)
