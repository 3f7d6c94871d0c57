"""Small data for the viewer tests: an off-centre blob volume, a tiny model, a preset, a broken model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def blob_volume(size: int = 24) -> np.ndarray:
    """``[size]^3`` float32: two Gaussian blobs away from the centre, so turning the view moves them."""
    axis = np.linspace(-1.0, 1.0, size, dtype=np.float32)
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    big = np.exp(-((x - 0.4) ** 2 + (y - 0.1) ** 2 + (z - 0.3) ** 2) / 0.08)
    small = 0.6 * np.exp(-((x + 0.5) ** 2 + (y + 0.3) ** 2 + (z + 0.2) ** 2) / 0.03)
    return (big + small).astype(np.float32)


def write_tiny_model(path: Path) -> Path:
    """An untrained two-grid APMGSRN model file (what matters is that it loads and has grid boxes)."""
    import torch

    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import preset_config
    from apmgsrn.io import SourceInfo, save_field

    torch.manual_seed(0)
    field = NeuralField(
        preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4)),
        value_min=0.0,
        value_max=1.0,
        volume_shape=(24, 24, 24),
    )
    save_field(path, field, SourceInfo(), {})
    return path


PRESET = [
    {
        "Name": "Two Reds",
        "ColorSpace": "RGB",
        "RGBPoints": [0.0, 0.2, 0.0, 0.0, 1.0, 1.0, 0.3, 0.3],
        "Points": [0.0, 0.0, 0.5, 0.0, 0.5, 0.1, 0.5, 0.0, 1.0, 0.9, 0.5, 0.0],
    }
]


def make_viewer_folder(root: Path) -> Path:
    """A folder as a user would serve: volume, model, preset, broken model, a nested folder, and a
    secret file beside (outside) it with a symbolic link pointing out to it."""
    folder = root / "served"
    (folder / "nested").mkdir(parents=True)
    np.save(folder / "a_blob.npy", blob_volume())
    write_tiny_model(folder / "tiny.apmgsrn")
    (folder / "reds.json").write_text(json.dumps(PRESET), encoding="utf-8")
    (folder / "broken.apmgsrn").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not a model at all")
    np.save(folder / "nested" / "small.npy", blob_volume(8))
    (folder / "notes.txt").write_text("not data", encoding="utf-8")
    (folder / ".hidden.npy").write_bytes(b"")
    secret = root / "secret.npy"
    np.save(secret, blob_volume(8))
    (folder / "link_out.npy").symlink_to(secret)
    (folder / "link_in.npy").symlink_to(folder / "a_blob.npy")
    return folder
