"""Self-describing model files: safetensors weights plus JSON metadata; never pickle, atomic writes.

A model file is one safetensors file whose header metadata holds ``format = "apmgsrn"``, a
``format_version`` and a ``description`` JSON (field config, value range and transform, volume shape,
training summary). Loading parses the header as plain JSON first, so a corrupt, foreign, newer or
hostile file is refused with one clear message and nothing in it is ever executed.

A training checkpoint (``MODEL.ckpt``) has the same form with ``kind = "training-state"`` and also holds
the optimiser moments and random-generator state, so an interrupted run resumes exactly.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
from pathlib import Path

import torch

from apmgsrn.errors import ApmgsrnError

FORMAT = "apmgsrn"
FORMAT_VERSION = 1
MAX_HEADER_BYTES = 64 * 1024 * 1024


def atomic_write(path: Path, write) -> None:
    """Call ``write(temp_path)`` then rename the temp file onto ``path`` (same folder, so atomic)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ApmgsrnError(f"{path}: output folder {folder} does not exist; create it or choose another --out")
    try:
        handle, temp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot write to {folder} ({exc.strerror}); choose another --out") from None
    os.close(handle)
    try:
        write(temp)
        with open(temp, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temp, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
        os.replace(temp, path)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot write ({exc.strerror}); choose another --out") from None
    finally:
        if os.path.exists(temp):
            os.unlink(temp)


def save_tensors(path: Path, tensors: dict[str, torch.Tensor], kind: str, description: dict) -> None:
    """Write tensors and a JSON description atomically as one safetensors file."""
    from safetensors.torch import save_file

    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    metadata = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "kind": kind,
        "description": json.dumps(description, allow_nan=True),
    }
    atomic_write(Path(path), lambda temp: save_file(tensors, temp, metadata=metadata))


def read_header(path: Path) -> dict:
    """Validate a file's safetensors header and return its metadata (``kind``, parsed ``description``).

    Raises:
        ApmgsrnError: missing, unreadable, not a model file, corrupt, or from a newer format version.
    """
    path = Path(path)
    if not path.exists():
        raise ApmgsrnError(f"{path}: no such model file")
    if not path.is_file():
        raise ApmgsrnError(f"{path}: is not a model file (a folder?); pass the file written by 'apmgsrn train'")
    not_ours = f"{path}: not an apmgsrn model file (corrupt, truncated or another format)"
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            prefix = f.read(8)
            if len(prefix) < 8:
                raise ApmgsrnError(not_ours)
            (length,) = struct.unpack("<Q", prefix)
            if length > min(size - 8, MAX_HEADER_BYTES):
                raise ApmgsrnError(not_ours)
            header = json.loads(f.read(length).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ApmgsrnError(not_ours) from None
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    meta = header.get("__metadata__") if isinstance(header, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ApmgsrnError(not_ours)
    try:
        version = int(meta.get("format_version", ""))
    except ValueError:
        raise ApmgsrnError(not_ours) from None
    if version > FORMAT_VERSION:
        raise ApmgsrnError(
            f"{path}: written by a newer apmgsrn (model format {version}, this one reads up to "
            f"{FORMAT_VERSION}); upgrade apmgsrn to load it"
        )
    try:
        description = json.loads(meta.get("description", "{}"))
    except json.JSONDecodeError:
        raise ApmgsrnError(not_ours) from None
    # Data extent of every tensor must lie inside the file (a truncated file is caught here).
    body = size - 8 - length
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        offsets = entry.get("data_offsets") if isinstance(entry, dict) else None
        if not (isinstance(offsets, list) and len(offsets) == 2 and 0 <= offsets[0] <= offsets[1] <= body):
            raise ApmgsrnError(not_ours)
    return {"kind": meta.get("kind", ""), "description": description, "version": version}


def load_tensors(path: Path) -> dict[str, torch.Tensor]:
    """All tensors of a validated file (safetensors parsing only: no code runs)."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ApmgsrnError(f"{path}: not an apmgsrn model file (corrupt: {exc})") from None


def is_model_file(path) -> bool:
    """True if ``path`` is an apmgsrn model file (single field or brick model)."""
    try:
        return read_model_header(Path(path))["kind"] in MODEL_LOADERS
    except ApmgsrnError:
        return False


def save_field(path, field, training: dict | None = None, source: dict | None = None) -> None:
    """Save a :class:`~apmgsrn.models.field.NeuralField` with everything needed to rebuild it."""
    import dataclasses

    description = {
        "field": field.config.to_dict(),
        "fit_min": field.fit_min,
        "fit_max": field.fit_max,
        "value_min": field.value_min,
        "value_max": field.value_max,
        "transform": dataclasses.asdict(field.transform),
        "volume_shape": list(field.volume_shape),
        "source": source or {},
        "training": training or {},
    }
    save_tensors(path, dict(field.state_dict()), "field", description)


def _build_field(path: Path, description: dict, tensors: dict[str, torch.Tensor]):
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import FieldConfig
    from apmgsrn.models.value_transform import ValueTransform

    try:
        field = NeuralField(
            FieldConfig.from_dict(description["field"]),
            fit_min=description["fit_min"],
            fit_max=description["fit_max"],
            value_min=description["value_min"],
            value_max=description["value_max"],
            transform=ValueTransform(**description["transform"]),
            volume_shape=tuple(description["volume_shape"]),
        )
        field.load_state_dict(tensors, strict=True)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ApmgsrnError(f"{path}: model file is inconsistent ({first}); re-train or re-download it") from None
    field.source = description.get("source", {})
    field.training_summary = description.get("training", {})
    return field


def _load_field(path: Path, description: dict, device):
    field = _build_field(path, description, load_tensors(path))
    return field.to(device).eval()


def _load_bricks(path: Path, description: dict, device):
    from apmgsrn.decomposition.brick_model import load_brick_model

    return load_brick_model(path, description, device)


# model kind -> loader(path, description, device); a brick model is a folder with a manifest.
MODEL_LOADERS = {"field": _load_field, "bricks": _load_bricks}


def read_model_header(path: Path) -> dict:
    """Header of a model file, or of a brick model folder's ``manifest.json`` (JSON only)."""
    path = Path(path)
    if path.is_dir():
        from apmgsrn.decomposition.brick_model import read_manifest_header

        return read_manifest_header(path)
    return read_header(path)


def load_model(path, device="cpu"):
    """Load any apmgsrn model file as a torch module ``[N, 3] -> [N, 1]`` in data units.

    Raises:
        ApmgsrnError: the file is missing, corrupt, foreign, hostile or from a newer version.
    """
    path = Path(path)
    header = read_model_header(path)
    loader = MODEL_LOADERS.get(header["kind"])
    if loader is None:
        raise ApmgsrnError(f"{path}: is a {header['kind'] or 'unknown'} file, not a model; pass a model file")
    model = loader(path, header["description"], torch.device(device) if isinstance(device, str) else device)
    if not path.is_dir():  # a brick model folder counts its files itself
        model.file_bytes = path.stat().st_size
    return model
