"""Where a training batch looks at the volume: uniform points with trilinear targets, voxels, or a mix.

SPEC section 4 draws points uniformly in the domain and takes the trilinearly interpolated volume there as
the target. The data, though, are the voxels, and PSNR, maximum error, decoded volumes and compression
ratios are all measured on them. :func:`draw_batch` can give a fraction of each batch at voxel positions
(their exact values, no interpolation): the network then fits the samples it is judged on, while the
uniform rest keeps it close to the trilinear interpolant between them, which is what renders ray-march.
docs/models.md ("Voxel points") has the measurements behind the model defaults.
"""

from __future__ import annotations

import torch

from apmgsrn.ops.trilinear import axis_coordinates, sample_volume


def voxel_count(batch: int, fraction: float) -> int:
    """Points of a batch of ``batch`` that sit on voxels when a ``fraction`` of it should."""
    return min(batch, round(batch * fraction))


def draw_batch(
    volume: torch.Tensor, count: int, voxel_fraction: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Training points ``[count, 3]`` in ``[-1, 1]^3`` and their targets ``[count]``.

    Args:
        volume: ``[D, H, W]`` values (corner-aligned: voxel ``i`` of ``n`` at ``-1 + 2 i / (n - 1)``).
        count: points to draw.
        voxel_fraction: share of the points drawn at voxel positions (uniformly over the voxels, with the
            voxel's value as target); the others are uniform in the domain with trilinear targets. 0 draws
            exactly what SPEC section 4 (and every version before this option) draws.
        generator: the trainer's generator (same seed, same batches).
    """
    on_voxels = voxel_count(count, voxel_fraction)
    uniform = torch.rand(count - on_voxels, 3, generator=generator, device=volume.device) * 2 - 1
    if on_voxels == 0:
        return uniform, sample_volume(volume, uniform)
    d, h, w = volume.shape
    index = torch.randint(0, d * h * w, (on_voxels,), generator=generator, device=volume.device)
    z, y, x = index // (h * w), index // w % h, index % w
    voxels = torch.stack([axis_coordinates(x, w), axis_coordinates(y, h), axis_coordinates(z, d)], dim=1)
    points = torch.cat([voxels, uniform])
    targets = torch.cat([volume.reshape(-1)[index], sample_volume(volume, uniform)])
    return points, targets


def spatially_ordered(
    points: torch.Tensor, targets: torch.Tensor, cells: int = 64
) -> tuple[torch.Tensor, torch.Tensor]:
    """The batch's points ``[B, 3]`` and targets ``[B]`` reordered by the cell of a ``cells^3`` lattice they fall
    in (z, then y, then x; a stable sort, so the same batch always gives the same order).

    Neighbouring points then read neighbouring rows of large feature tables, which saves cache misses in
    the encoder's forward and backward. The loss is a mean over the batch, so only the order of its sums
    changes.
    """
    cell = ((points.clamp(-1, 1) + 1) * (0.5 * (cells - 1))).round().long()  # [B, 3] (x, y, z)
    key = (cell[:, 2] * cells + cell[:, 1]) * cells + cell[:, 0]  # [B]
    order = torch.argsort(key, stable=True)
    return points[order], targets[order]
