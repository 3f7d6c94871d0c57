"""Evaluate a field on every voxel of a volume, one z-slab at a time (the one slab loop of the package).

A slab's points, predictions and ground truth are what lives in memory, so whole-volume passes (eval,
decode, the PSNR after training, benchmarks) work on volumes larger than memory.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from apmgsrn.inference.query import query
from apmgsrn.ops.trilinear import voxel_coordinates
from apmgsrn.recipes import RUNTIME


def z_slabs(shape: tuple[int, int, int], slab_voxels: int = RUNTIME.slab_voxels, stride: int = 1) -> Iterator[slice]:
    """Consecutive z-ranges covering ``0..D-1``, each with about ``slab_voxels`` evaluated voxels.

    Args:
        shape: ``(D, H, W)``.
        slab_voxels: evaluated voxels per slab (at least one z-slice of them).
        stride: every ``stride``-th voxel along each axis is evaluated; every slab then starts at a
            multiple of ``stride``, so ``volume[z][::s, ::s, ::s]`` of the slabs tile ``volume[::s, ::s, ::s]``.

    Returns:
        Iterator of z slices, in order.
    """
    d, h, w = shape
    plane = len(range(0, h, stride)) * len(range(0, w, stride))  # evaluated voxels per evaluated z-slice
    step = max(1, slab_voxels // plane) * stride
    for start in range(0, d, step):
        yield slice(start, min(start + step, d))


def field_slabs(
    field,
    shape: tuple[int, int, int],
    slab_voxels: int = RUNTIME.slab_voxels,
    stride: int = 1,
    batch_size: int = RUNTIME.query_batch,
    box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] | None = None,
) -> Iterator[tuple[slice, torch.Tensor]]:
    """The field's values on the corner-aligned voxel lattice of ``shape``, slab by slab.

    Args:
        field: module ``[N, 3] -> [N, 1]`` in data units (points in ``[-1, 1]^3``).
        shape: ``(D, H, W)`` of the lattice.
        slab_voxels: evaluated voxels per slab.
        stride: evaluate every ``stride``-th voxel along each axis (see :func:`z_slabs`).
        batch_size: points per forward pass.
        box: ``((x0, x1), (y0, y1), (z0, z1))`` in ``[-1, 1]``: the lattice spans this box (a region) instead
            of the whole cube.

    Returns:
        Iterator of ``(z slice, float32 CPU tensor [dz, h, w])``, where the tensor holds the values at
        ``volume[z][::stride, ::stride, ::stride]``.
    """
    _, h, w = shape
    rows, columns = len(range(0, h, stride)), len(range(0, w, stride))
    for z in z_slabs(shape, slab_voxels, stride):
        points = voxel_coordinates(shape, z, stride=stride, box=box)  # [dz * rows * columns, 3]
        values = query(field, points, batch_size)  # [dz * rows * columns]
        yield z, values.view(-1, rows, columns)
