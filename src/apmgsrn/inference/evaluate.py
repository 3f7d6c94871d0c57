"""Full-volume quality measures (SPEC section 8), streamed over z-slabs of the volume."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from apmgsrn.inference.query import query
from apmgsrn.ops.trilinear import voxel_coordinates


@dataclass(frozen=True)
class Evaluation:
    """PSNR over every voxel and friends; ``psnr`` is ``inf`` for an exact fit."""

    psnr: float
    mse: float
    max_abs_error: float
    data_min: float
    data_max: float
    model_bytes: int
    raw_bytes: int
    compression_ratio: float

    def to_dict(self) -> dict:
        return asdict(self)


def psnr_from_mse(mse: float, data_range: float) -> float:
    """``20 log10(range) - 10 log10(MSE)``; ``inf`` when the MSE is zero."""
    if mse <= 0:
        return math.inf
    if data_range <= 0:
        return -math.inf
    return 20 * math.log10(data_range) - 10 * math.log10(mse)


def evaluate(field, volume, model_bytes: int, batch_size: int = 2**18, slab_voxels: int = 2**22) -> Evaluation:
    """Compare ``field`` with every voxel of ``volume`` (a :class:`apmgsrn.data.Volume`), slab by slab.

    Args:
        field: module ``[N, 3] -> [N, 1]`` in data units.
        volume: the ground truth; only one slab is in memory at a time.
        model_bytes: size of the model file (for the compression ratio).
        batch_size: points per forward pass.
        slab_voxels: voxels per slab read from disk.
    """
    shape = volume.shape
    squared, count, max_abs = 0.0, 0, 0.0
    data_min, data_max = math.inf, -math.inf
    for z, block in volume.iter_slabs(slab_voxels):
        points = voxel_coordinates(shape, z)  # [dz * H * W, 3]
        prediction = query(field, points, batch_size).numpy().astype(np.float64)
        truth = block.reshape(-1).astype(np.float64)
        diff = prediction - truth
        squared += float(np.dot(diff, diff))
        count += diff.size
        max_abs = max(max_abs, float(np.abs(diff).max()))
        data_min = min(data_min, float(truth.min()))
        data_max = max(data_max, float(truth.max()))
    mse = squared / count
    raw_bytes = int(np.prod(shape)) * 4
    return Evaluation(
        psnr=psnr_from_mse(mse, data_max - data_min),
        mse=mse,
        max_abs_error=max_abs,
        data_min=data_min,
        data_max=data_max,
        model_bytes=int(model_bytes),
        raw_bytes=raw_bytes,
        compression_ratio=raw_bytes / model_bytes,
    )


def evaluate_tensor(field, volume: torch.Tensor, batch_size: int = 2**18) -> float:
    """PSNR of ``field`` against an in-memory ``[D, H, W]`` volume (data units), used after training."""
    shape = tuple(volume.shape)
    squared, count = 0.0, 0
    d = shape[0]
    step = max(1, 2**22 // (shape[1] * shape[2]))
    for z0 in range(0, d, step):
        z = slice(z0, min(z0 + step, d))
        points = voxel_coordinates(shape, z)
        prediction = query(field, points, batch_size).double()
        truth = volume[z].reshape(-1).double().cpu()
        squared += float((prediction.cpu() - truth).square().sum())
        count += truth.numel()
    return psnr_from_mse(squared / count, float(volume.max() - volume.min()))
