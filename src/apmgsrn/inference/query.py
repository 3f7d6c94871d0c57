"""Evaluate a field at many points in bounded-memory batches."""

from __future__ import annotations

import torch

from apmgsrn.arguments import MAX_BATCH_SIZE, check_int
from apmgsrn.threads import inference_governor


@torch.no_grad()
def query(field, points: torch.Tensor, batch_size: int = 2**18) -> torch.Tensor:
    """Values of ``field`` at ``points`` ``[N, 3]`` -> ``[N]``, ``batch_size`` points per forward pass.

    Points are moved to the field's device batch by batch; the result is on the points' device.

    Raises:
        InvalidArgument: ``batch_size`` is not an integer from 1 to :data:`~apmgsrn.arguments.MAX_BATCH_SIZE`.
    """
    check_int("batch_size", batch_size, 1, MAX_BATCH_SIZE)
    device = _device_of(field)
    out = torch.empty(points.shape[0], dtype=torch.float32, device=points.device)
    governor = inference_governor(device.type)  # CPU threads by timing the batches (apmgsrn.threads)
    with governor:
        for start in range(0, points.shape[0], batch_size):
            chunk = points[start : start + batch_size].to(device, non_blocking=True)
            out[start : start + chunk.shape[0]] = field(chunk).view(-1).to(out.device)
            governor.tick(chunk.shape[0])
    return out


def _device_of(field) -> torch.device:
    for p in field.parameters():
        return p.device
    return torch.device("cpu")
