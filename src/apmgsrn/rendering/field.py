"""What the renderer samples: any field ``[N, 3] -> [N, 1]``, evaluated in bounded batches, and the raw
volume as such a field (trilinear interpolation of the voxels: the reference image's source)."""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from apmgsrn.ops.trilinear import sample_volume

# Points (x, y, z) in [-1, 1]^3 -> values in data units; a model, a brick model, a VolumeField, a lambda.
Field = Callable[[torch.Tensor], torch.Tensor]


def field_device(field: Field) -> torch.device:
    """Where a field computes: its ``device`` attribute, else its first parameter's device, else the CPU.

    Args:
        field: the field.

    Returns:
        The device.
    """
    device = getattr(field, "device", None)
    if isinstance(device, (torch.device, str)):
        return torch.device(device)
    parameters = getattr(field, "parameters", None)
    if callable(parameters):
        for parameter in parameters():
            return parameter.device
    return torch.device("cpu")


def evaluate_field(field: Field, points: torch.Tensor, batch_size: int) -> torch.Tensor:
    """Field values at points, at most ``batch_size`` points per call (bounds the working memory).

    Args:
        field: the field.
        points: ``[S, 3]`` points in [-1, 1]^3.
        batch_size: most points per call.

    Returns:
        ``[S]`` float32 values.
    """
    if points.shape[0] <= batch_size:
        return field(points).reshape(-1).to(torch.float32)
    out = torch.empty(points.shape[0], dtype=torch.float32, device=points.device)
    for start in range(0, points.shape[0], batch_size):
        out[start : start + batch_size] = field(points[start : start + batch_size]).reshape(-1)
    return out


class VolumeField:
    """Callable ``[N, 3] -> [N, 1]`` that trilinearly samples a dense volume (docs/method.md §1's ground truth).

    Attributes:
        volume: ``[D, H, W]`` float32 tensor on the field's device.
        value_min, value_max: the volume's value range.
        volume_shape: ``(D, H, W)``.
    """

    def __init__(self, volume: torch.Tensor | np.ndarray, device: torch.device | str = "cpu") -> None:
        """Args:
        volume: ``[D, H, W]`` values, C order (z, y, x).
        device: where to keep the voxels and evaluate.
        """
        tensor = torch.as_tensor(np.ascontiguousarray(volume) if isinstance(volume, np.ndarray) else volume)
        if tensor.dim() != 3:
            raise ValueError(f"volume must be [D, H, W], got shape {tuple(tensor.shape)}")
        self.volume = tensor.to(device=device, dtype=torch.float32).contiguous()
        finite = self.volume[torch.isfinite(self.volume)]
        self.value_min = float(finite.min()) if finite.numel() else 0.0
        self.value_max = float(finite.max()) if finite.numel() else 1.0
        self.volume_shape = tuple(int(n) for n in self.volume.shape)

    @property
    def device(self) -> torch.device:
        return self.volume.device

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """Args: points ``[N, 3]`` (x, y, z) in [-1, 1]^3. Returns: ``[N, 1]`` float32 values."""
        return sample_volume(self.volume, points.to(self.volume.device))[:, None]
