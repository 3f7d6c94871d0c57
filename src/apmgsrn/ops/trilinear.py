"""Trilinear sampling of a dense volume at points in [-1, 1]^3 (the ground truth of docs/method.md §1)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from apmgsrn.ops.contract import nan_where_nan


def sample_volume(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Trilinearly interpolate a volume at points, corner-aligned.

    Voxel ``i`` of an axis with ``n`` voxels sits at ``-1 + 2 i / (n - 1)``; points outside the box (however
    far, ``±inf`` included) are clamped to its border (ground truth never uses zero padding); a point with a
    NaN coordinate samples NaN (the contract of :mod:`apmgsrn.ops`).

    Args:
        volume: ``[D, H, W]`` values, C order (z, y, x), x fastest.
        points: ``[N, 3]`` coordinates ``(x, y, z)`` in ``[-1, 1]^3``.

    Returns:
        ``[N]`` interpolated values, in the volume's dtype.
    """
    if _fused(volume, points):
        from apmgsrn.ops.trilinear_cpu import sample_volume_cpu

        return sample_volume_cpu(volume, points.to(volume.dtype).contiguous())
    return sample_volume_reference(volume, points)


def sample_volume_reference(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """:func:`sample_volume` by ``F.grid_sample`` (any device and dtype, differentiable)."""
    n = points.shape[0]
    grid = points.to(volume.dtype).view(1, n, 1, 1, 3)  # [1, N, 1, 1, 3]
    out = F.grid_sample(
        volume[None, None], grid, mode="bilinear", padding_mode="border", align_corners=True
    )  # [1, 1, N, 1, 1]
    return nan_where_nan(points, out.view(n))


def _fused(volume: torch.Tensor, points: torch.Tensor) -> bool:
    """Whether the CPU kernel (:mod:`apmgsrn.ops.trilinear_cpu`, bit for bit the reference) can sample."""
    if volume.device.type != "cpu" or points.device.type != "cpu" or volume.dtype != torch.float32:
        return False
    if not volume.is_contiguous() or volume.dim() != 3 or points.dim() != 2 or points.shape[-1] != 3:
        return False
    if torch.is_grad_enabled() and (volume.requires_grad or points.requires_grad):
        return False
    from apmgsrn.ops.trilinear_cpu import LIBRARY

    return LIBRARY.available()


def voxel_coordinates(
    shape: tuple[int, int, int],
    z: slice | None = None,
    stride: int = 1,
    box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] | None = None,
) -> torch.Tensor:
    """Coordinates in ``[-1, 1]^3`` of every voxel of a ``(D, H, W)`` volume (or of z-slab ``z``), or of
    every ``stride``-th voxel along each axis.

    Args:
        shape: ``(D, H, W)`` voxels.
        z: a z-slab (default: all of z).
        stride: every ``stride``-th voxel along each axis.
        box: ``((x0, x1), (y0, y1), (z0, z1))``: the lattice spans this box instead of ``[-1, 1]^3`` (a
            decoded region), first and last voxel on its faces.

    Returns:
        ``[n, 3]`` points ``(x, y, z)``, C order (x fastest), matching
        ``volume[z][::stride, ::stride, ::stride].reshape(-1)``.
    """
    d, h, w = shape
    box = box or ((-1.0, 1.0),) * 3
    zs = torch.arange(d)[z if z is not None else slice(None)][::stride]
    axes = [axis_coordinates(zs, d, *box[2]), axis_coordinates(torch.arange(h)[::stride], h, *box[1]),
            axis_coordinates(torch.arange(w)[::stride], w, *box[0])]
    gz, gy, gx = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)


def axis_coordinates(index: torch.Tensor, n: int, low: float = -1.0, high: float = 1.0) -> torch.Tensor:
    """Corner-aligned coordinates (float32, on ``index``'s device) of voxels ``index`` of an axis of ``n``
    voxels whose first and last voxel sit at ``low`` and ``high``."""
    if n == 1:  # one voxel: the middle of the span
        return torch.full((len(index),), 0.5 * (low + high), device=index.device)
    if (low, high) == (-1.0, 1.0):
        return index.to(torch.float32) * (2.0 / (n - 1)) - 1.0
    # float64 on the way: a region's bounds are not multiples of the step, and float32 would round each
    # point twice.
    return (low + index.to(torch.float64) * ((high - low) / (n - 1))).to(torch.float32)
