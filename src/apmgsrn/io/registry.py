"""One door to every model format: a loader per kind, registered by the layer that can build it.

Single-field files, float32 or packed, load here. Brick models need the brick router, which lives in
:mod:`apmgsrn.decomposition` (a layer above this one), and time-series models the series package
(:mod:`apmgsrn.series`): each registers its loaders on import (a kind of folder with :func:`register_folder_kind`),
and :func:`apmgsrn.load` imports both, so callers of the public API open every kind.
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
from apmgsrn.io.container import PACKED_KIND, read_header
from apmgsrn.io.description import ModelDescription
from apmgsrn.io.field_file import FIELD_KIND, load_field
from apmgsrn.io.packed import load_packed


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
    PACKED_KIND: lambda path, device: load_packed(path, device),
}
#: Kinds of model folders other than a brick folder: kind -> (is_folder(path), is_readable(path)), asked in the
#: order registered, before a brick folder (a time series' brick folder holds brick folders).
_FOLDER_KINDS: dict[str, tuple[Callable[[Path], bool], Callable[[Path], object]]] = {}


def register_loader(kind: str, loader: Loader) -> None:
    """Make :func:`open_model` open models of ``kind`` with ``loader``."""
    _LOADERS[kind] = loader


def register_folder_kind(kind: str, is_folder: Callable[[Path], bool], is_readable: Callable[[Path], object]) -> None:
    """Make :func:`model_kind` and :func:`open_model` tell folders of ``kind`` (``is_folder``: by their names;
    ``is_readable``: a true value when the folder's manifest reads, else false or an
    :class:`~apmgsrn.errors.ApmgsrnError`); its loader is registered with :func:`register_loader`."""
    _FOLDER_KINDS[kind] = (is_folder, is_readable)


def file_loader(kind: str) -> Loader:
    """The loader of model files of ``kind`` (the brick files of a brick folder).

    Raises:
        ApmgsrnError: a kind nobody registered.
    """
    loader = _LOADERS.get(kind)
    if loader is None:
        raise ApmgsrnError(f"no loader for model files of kind {kind!r}; import the package that writes them")
    return loader


def _folder_kind(path: Path) -> str | None:
    """The registered folder kind of ``path`` (a directory), else None."""
    return next((kind for kind, (is_folder, _) in _FOLDER_KINDS.items() if is_folder(path)), None)


def model_kind(path: str | os.PathLike) -> str | None:
    """``"field"``, ``"series"``, ``"bricks"`` (or another registered kind) for a model file or folder, else None.

    Reads only a file's header or a folder's manifest, never tensors.
    """
    path = Path(path)
    try:
        if path.is_dir():
            folder = _folder_kind(path)
            if folder is not None:
                return folder if _FOLDER_KINDS[folder][1](path) else None
            return BRICKS_KIND if is_brick_folder(path) and read_manifest(path) else None
        kind = read_header(path).kind
    except (ApmgsrnError, OSError):
        return None
    return kind if kind in _LOADERS or kind == BRICKS_KIND else None


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
    folder = _folder_kind(path) if path.is_dir() else None
    if path.is_dir() and folder is None and not is_brick_folder(path):
        raise ApmgsrnError(
            f"{path}: folder has no {MANIFEST_NAME}, so it is not a brick model; pass a model file or a "
            "folder written by a brick training run"
        )
    if path.is_dir():
        kind = folder or BRICKS_KIND
    else:
        kind = read_header(path).kind
    loader = _LOADERS.get(kind)
    if loader is None:
        if kind == BRICKS_KIND:
            raise ApmgsrnError(f"{path}: brick models open through apmgsrn.load (import apmgsrn.decomposition)")
        raise ApmgsrnError(f"{path}: is a {kind or 'unknown'} file, not a model; pass a model file")
    field, description = loader(path, device)
    return LoadedModel(field, description)
