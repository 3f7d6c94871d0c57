"""What the viewer shows: a model file, a brick model or a raw volume, opened as a field with its extras.

A :class:`ViewSource` carries what the page needs beside the field itself: the value range, the volume's
shape (for the box proportions), a value histogram (drawn under the opacity editor) and, for APMGSRN
models, the boxes of the learned feature grids and the brick borders (the overlay).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.render import ValueBounds, VolumeField

# Corner k of a box has x from bit 0, y from bit 1 and z from bit 2 (the order of ``grid_boxes``).
CORNER_BITS = tuple(((k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1) for k in range(8))


@dataclass(frozen=True)
class SourceConfig:
    """Limits and sampling of opened sources."""

    max_volume_voxels: int = 1 << 27  # raw volumes are held in memory: refuse larger ones (512 MiB float32)
    histogram_bins: int = 64
    histogram_lattice: int = 40  # a model's histogram samples it on this many points per axis


@dataclass
class ViewSource:
    """An opened model or volume.

    Attributes:
        name: the catalog name it was opened by.
        kind: ``"model"``, ``"brick model"`` or ``"volume"``.
        field: ``[N, 3] -> [N, 1]`` callable on the device (points in [-1, 1]^3).
        value_range: ``(min, max)`` of the data, data units.
        volume_shape: ``(D, H, W)``.
        bounds: exact macro-cell bounds for a raw volume; None for a model (sampled by the renderer).
        grid_boxes: ``[M, 8, 3]`` corners of the learned feature grids, field coordinates, or None.
        brick_boxes: ``[B, 8, 3]`` corners of the bricks' routing regions, or None.
        histogram: ``[bins]`` log(1 + count) over ``value_range``, normalised so the largest is 1.
        description: one line for the page.
    """

    name: str
    kind: str
    field: Callable[[torch.Tensor], torch.Tensor]
    value_range: tuple[float, float]
    volume_shape: tuple[int, int, int]
    bounds: ValueBounds | None
    grid_boxes: torch.Tensor | None
    brick_boxes: torch.Tensor | None
    histogram: list[float]
    description: str


def open_source(
    name: str,
    path: Path,
    kind: str,
    device: torch.device,
    config: SourceConfig = SourceConfig(),
    macro_cells: int = 16,
) -> ViewSource:
    """Open a catalog entry for viewing.

    Args:
        name: the entry's catalog name.
        path: its resolved path.
        kind: ``"model"`` or ``"volume"`` (from the catalog).
        device: where to evaluate.
        config: limits and histogram settings.
        macro_cells: macro cells per axis for a volume's exact bounds.

    Returns:
        The source.

    Raises:
        ApmgsrnError: the file cannot be read as that kind, or the volume is too large.
    """
    if kind == "model":
        return _open_model(name, path, device, config)
    if kind == "volume":
        return _open_volume(name, path, device, config, macro_cells)
    raise ApmgsrnError(f"{name}: a {kind} cannot be rendered; pick a model or a volume")


def _open_model(name: str, path: Path, device: torch.device, config: SourceConfig) -> ViewSource:
    import apmgsrn

    loaded = apmgsrn.load(path, device=device)
    model, description = loaded.field, loaded.description
    value_range = description.value_range
    shape = description.volume_shape
    grid_boxes, brick_boxes = None, None
    if description.bricks is not None:
        bricks = model.bricks
        kind = "brick model"
        counts = description.bricks.counts  # (I, J, K) along x, y, z
        brick_boxes = routing_boxes(counts)
        per_brick = []
        for index, brick_field in enumerate(bricks):
            local = _grid_boxes_of(brick_field)
            if local is not None:
                # The brick maps global p to local = p * scale + offset (see BrickedField); invert it.
                scale = model.brick_scales[index].detach().cpu()
                offset = model.brick_offsets[index].detach().cpu()
                per_brick.append((local - offset) / scale)
        grid_boxes = torch.cat(per_brick) if per_brick else None
        text = f"brick model, {len(bricks)} bricks ({counts[0]}x{counts[1]}x{counts[2]})"
    else:
        kind = "model"
        grid_boxes = _grid_boxes_of(model)
        grids = f", {grid_boxes.shape[0]} feature grids" if grid_boxes is not None else ""
        text = f"{description.model} model{grids}"
    text += f", volume {shape[2]}x{shape[1]}x{shape[0]}"
    histogram = _field_histogram(model, value_range, device, config)
    return ViewSource(name, kind, model, value_range, shape, None, grid_boxes, brick_boxes, histogram, text)


def _grid_boxes_of(field) -> torch.Tensor | None:
    """Corners ``[M, 8, 3]`` of a single field's placed grids (None for a baseline without them)."""
    with torch.no_grad():
        boxes = field.encoder.grid_boxes()
    return None if boxes is None else boxes.detach().float().cpu()


def _open_volume(
    name: str, path: Path, device: torch.device, config: SourceConfig, macro_cells: int
) -> ViewSource:
    from apmgsrn.data import check_finite, open_volume

    volume = open_volume(path)
    voxels = 1
    for n in volume.shape:
        voxels *= int(n)
    if voxels > config.max_volume_voxels:
        raise ApmgsrnError(
            f"{name}: {voxels:,} voxels is more than the viewer holds in memory ({config.max_volume_voxels:,}); "
            "train a model of it and view the model"
        )
    check_finite(volume)
    field = VolumeField(volume.to_numpy(), device=device)
    value_range = (field.value_min, field.value_max)
    bounds = ValueBounds.from_volume(field.volume, macro_cells)
    histogram = _histogram(field.volume.reshape(-1), value_range, config.histogram_bins)
    shape = field.volume_shape
    description = f"volume {shape[2]}x{shape[1]}x{shape[0]} (reference: trilinear voxels)"
    return ViewSource(name, "volume", field, value_range, shape, bounds, None, None, histogram, description)


def routing_boxes(counts: tuple[int, int, int]) -> torch.Tensor:
    """Corners of the regions a brick model routes to each brick: the box cut evenly, ``[B, 8, 3]``.

    Args:
        counts: bricks ``(I, J, K)`` along ``(x, y, z)``.

    Returns:
        Corners in field coordinates, bricks in flat-index order ``i + I j + I J k``.
    """
    boxes = []
    for k in range(counts[2]):
        for j in range(counts[1]):
            for i in range(counts[0]):
                low = [-1.0 + 2.0 * p / c for p, c in zip((i, j, k), counts)]
                high = [-1.0 + 2.0 * (p + 1) / c for p, c in zip((i, j, k), counts)]
                boxes.append([[(low, high)[bit][axis] for axis, bit in enumerate(bits)] for bits in CORNER_BITS])
    return torch.tensor(boxes, dtype=torch.float32)


def _field_histogram(model, value_range, device, config: SourceConfig) -> list[float]:
    n = config.histogram_lattice
    axis = torch.linspace(-1.0, 1.0, n, device=device)
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)  # [n^3, 3]
    with torch.inference_mode():
        values = model(points).reshape(-1).float()
    return _histogram(values, value_range, config.histogram_bins)


def _histogram(values: torch.Tensor, value_range: tuple[float, float], bins: int) -> list[float]:
    lo, hi = value_range
    if not hi > lo:
        hi = lo + 1.0
    if values.numel() > 1 << 24:  # a large volume: every k-th voxel tells the same distribution
        values = values[:: values.numel() // (1 << 24) + 1]
    counts = torch.histc(values.float().clamp(lo, hi), bins=bins, min=lo, max=hi).cpu()
    # Log scale: scientific volumes are mostly background, whose bin would flatten every other one.
    heights = torch.log1p(counts)
    top = float(heights.max()) if heights.numel() else 0.0
    return [round(float(h) / top, 4) if top > 0 else 0.0 for h in heights]
