"""Trilinear interpolation of a sparse volume: values at a few voxels, zero everywhere else.

The voxel convention is the ground truth's (:func:`apmgsrn.ops.trilinear.sample_volume`): voxel ``i`` of an
axis of ``n`` sits at ``-1 + 2 i / (n - 1)``, points outside the box are clamped to it. A lookup is a binary
search of each corner's flat index in the sorted stored indices, so memory grows with the stored voxels,
not with the volume. Every input is defined (the contract of :mod:`apmgsrn.ops`): a point however far, ``±inf``
included, samples the border; a point with a NaN coordinate samples NaN.
"""

from __future__ import annotations

import torch

from apmgsrn.ops.contract import nan_where_nan


def sample_sparse_volume(
    indices: torch.Tensor, values: torch.Tensor, shape: tuple[int, int, int], points: torch.Tensor,
    snap: float = 1e-4,
) -> torch.Tensor:
    """Interpolate a sparse ``(D, H, W)`` volume at points, corner-aligned and trilinear.

    Args:
        indices: ``[K]`` int64 flat voxel indices ``(z * H + y) * W + x``, strictly increasing.
        values: ``[K]`` float values at those voxels (every other voxel is 0).
        shape: ``(D, H, W)``.
        points: ``[N, 3]`` coordinates ``(x, y, z)`` in ``[-1, 1]^3``.
        snap: a point closer than this to a voxel (in voxel units) is taken to be on it: float32 coordinates
            of a voxel (``-1 + 2 i / (n - 1)``) map back to ``i`` only up to rounding, and a voxel must get
            exactly its own value, not a blend with its neighbour's of weight 1e-7.

    Returns:
        ``[N]`` interpolated values in ``values``' dtype (exactly ``values[k]`` at voxel ``indices[k]``; NaN at
        a point with a NaN coordinate).
    """
    n = points.shape[0]
    out = torch.zeros(n, dtype=values.dtype, device=points.device)
    if indices.numel() == 0 or n == 0:
        return nan_where_nan(points, out)
    sizes = (shape[2], shape[1], shape[0])  # x, y, z
    lower, upper, fraction = [], [], []
    for axis, size in enumerate(sizes):
        if size == 1:
            # One voxel along this axis: every point is on it.
            zero = torch.zeros(n, dtype=torch.int64, device=points.device)
            lower.append(zero)
            upper.append(zero)
            fraction.append(torch.zeros(n, dtype=torch.float32, device=points.device))
            continue
        coordinate = points[:, axis].float()
        # clamped in float, NaN included (it goes to -1; the point's value is NaN below)
        coordinate = torch.where(coordinate >= -1, coordinate.clamp(max=1), -1.0)
        u = ((coordinate + 1) * 0.5) * (size - 1)  # [N] in voxel units
        nearest = torch.round(u)
        u = torch.where((u - nearest).abs() < snap, nearest, u)
        low = torch.floor(u).clamp(0, size - 2)
        lower.append(low.to(torch.int64))
        upper.append(low.to(torch.int64) + 1)
        fraction.append(u - low)
    width, height = sizes[0], sizes[1]
    for corner in range(8):
        bits = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1)  # x, y, z
        x, y, z = (upper[a] if bits[a] else lower[a] for a in range(3))
        weight = torch.ones(n, dtype=torch.float32, device=points.device)
        for a in range(3):
            weight = weight * (fraction[a] if bits[a] else 1 - fraction[a])
        flat = (z * height + y) * width + x  # [N]
        position = torch.searchsorted(indices, flat).clamp(max=indices.numel() - 1)
        found = indices[position] == flat
        # A zero weight contributes nothing even where its corner is a stored voxel (keeps voxels exact).
        contribution = torch.where(found & (weight > 0), values[position] * weight.to(values.dtype), 0)
        out += contribution
    return nan_where_nan(points, out)
