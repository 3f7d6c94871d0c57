"""What gets rendered: a model file, a brick-model folder or a volume file, opened as a field with its extras.

One opener for ``apmgsrn render`` and the viewer. A :class:`RenderSource` carries what a render needs beside
the field: the value range (the default transfer-function range), the volume's shape (the box's
proportions) and, for a raw volume, the voxels themselves (exact empty-space bounds); for the viewer also
the boxes of the learned feature grids and the brick borders (the overlay) and a value histogram.

It sits above ``render`` (which knows fields only), ``data`` (volume files) and the model files: opening a
model is one function, :func:`_load_model`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from apmgsrn.api import load
from apmgsrn.data import check_finite, open_volume
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import model_kind
from apmgsrn.rendering import (
    Field,
    RendererConfig,
    TransferFunction,
    VolumeField,
    VolumeRenderer,
    extent_from_shape,
)

MODEL_SUFFIXES = (".apmgsrn",)  # a file named so is read as a model (and refused as one if it is not)

# Corner k of a box has x from bit 0, y from bit 1 and z from bit 2 (the order of ``grid_boxes``).
CORNER_BITS = tuple(((k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1) for k in range(8))


@dataclass(frozen=True)
class SourceOptions:
    """How sources are opened.

    Attributes:
        volume: keyword arguments of :func:`apmgsrn.data.open_volume` for a volume file (variable, time,
            shape, dtype, fill_nonfinite).
        max_volume_voxels: refuse a raw volume larger than this (it is held in memory); None: no limit.
        histogram_bins: bins of the value histogram (0: none).
        histogram_lattice: a model's histogram samples it on this many points per axis.
        step: the step of a time-series model to show first (None: step 0).
    """

    volume: dict = field(default_factory=dict)
    max_volume_voxels: int | None = None
    histogram_bins: int = 0
    histogram_lattice: int = 40
    step: int | None = None


@dataclass(frozen=True)
class RenderSource:
    """An opened model or volume.

    Attributes:
        name: what it was opened as (a path, or the viewer's catalog name).
        kind: ``"model"``, ``"brick model"`` or ``"volume"``.
        field: ``[N, 3] -> [N, 1]`` callable on ``device`` (points in [-1, 1]^3); a
            :class:`~apmgsrn.rendering.VolumeField` for a volume.
        value_range: ``(min, max)`` of the data, data units.
        volume_shape: ``(D, H, W)``.
        device: where the field evaluates.
        description: one line for people.
        grid_boxes: ``[M, 8, 3]`` corners of the learned feature grids, field coordinates, or None.
        brick_boxes: ``[B, 8, 3]`` corners of the bricks' routing regions, or None.
        histogram: ``[bins]`` log(1 + count) over ``value_range``, the largest 1; empty unless asked for.
        series: the :class:`~apmgsrn.series.field.SeriesField` of a time-series model, else None;
            ``field`` is then its step ``step``, materialised (see :meth:`at_step`).
        step: the step shown of a time-series model.
        step_labels: the number of every step of a time-series model (empty otherwise).
    """

    name: str
    kind: str
    field: Field
    value_range: tuple[float, float]
    volume_shape: tuple[int, int, int]
    device: torch.device
    description: str
    grid_boxes: torch.Tensor | None = None
    brick_boxes: torch.Tensor | None = None
    histogram: list[float] = field(default_factory=list)
    series: torch.nn.Module | None = None
    step: int = 0
    step_labels: tuple[float, ...] = ()

    @property
    def steps(self) -> int:
        """Time steps of a time-series model (1 for anything else)."""
        return len(self.step_labels) if self.series is not None else 1

    def at_step(self, step: int) -> RenderSource:
        """This time-series model at another step: that step's features materialised once, so rendering it
        costs what a single-step model costs. The value range stays the whole series' (colours compare).

        Raises:
            ApmgsrnError: not a time-series model, or ``step`` outside it.
        """
        if self.series is None:
            raise ApmgsrnError(f"{self.name}: holds one volume; only time-series models have steps")
        if not 0 <= int(step) < self.steps:
            raise ApmgsrnError(f"{self.name}: step {step} is outside the series of {self.steps} steps (0..{self.steps - 1})")
        step = int(step)
        field = self.series.step_field(step)
        # A series whose steps place their grids themselves shows the step's own grids.
        grid_boxes = _grid_boxes_of(field) if self.grid_boxes is not None else None
        return replace(self, field=field, step=step, grid_boxes=grid_boxes,
                       description=_step_text(self.description, step, self.step_labels))

    @property
    def extent(self) -> tuple[float, float, float]:
        """Half sizes of the box with the volume's proportions (longest 1)."""
        return extent_from_shape(self.volume_shape)

    def renderer(
        self,
        transfer_function: TransferFunction,
        config: RendererConfig = RendererConfig(),
        extent: tuple[float, float, float] | None = None,
    ) -> VolumeRenderer:
        """A renderer of this source: a raw volume gets exact bounds, a model's are sampled on first use.

        Args:
            transfer_function: colour and opacity maps in data units.
            config: sampling, batching and skipping settings.
            extent: half sizes of the drawn box (default :attr:`extent`).

        Returns:
            The renderer, on :attr:`device`.
        """
        extent = self.extent if extent is None else extent
        if isinstance(self.field, VolumeField):
            return VolumeRenderer.for_volume(self.field, transfer_function, config, extent=extent)
        return VolumeRenderer(self.field, transfer_function, config, extent=extent, device=self.device)


def is_model_path(path: str | Path) -> bool:
    """Whether a path is a model (file or brick-model folder) rather than a volume.

    Args:
        path: an existing file or folder.

    Returns:
        True for a ``.apmgsrn`` file and for anything whose header (or manifest) says it is a model.
    """
    path = Path(path)
    if path.suffix.lower() == ".zarr":
        return False
    return (path.is_file() and path.suffix.lower() in MODEL_SUFFIXES) or model_kind(path) is not None


def open_source(
    path: str | Path, device: torch.device | str = "cpu", options: SourceOptions = SourceOptions(), name: str = ""
) -> RenderSource:
    """Open a model file, a brick-model folder or a volume file for rendering.

    Args:
        path: the file or folder.
        device: where to evaluate.
        options: how to read a volume, limits, histogram.
        name: what to call it (default: the path as given).

    Returns:
        The source.

    Raises:
        ApmgsrnError: missing path, unreadable file, NaN/Inf voxels, or a volume over the limit.
    """
    name = name or str(path)
    if not Path(path).exists():
        raise ApmgsrnError(f"{path}: no such file; give a model file or a volume file")
    device = torch.device(device)
    if is_model_path(path):
        source = _load_model(Path(path), name, device, options.step)
    else:
        source = _open_volume(Path(path), name, device, options)
    if options.histogram_bins > 0:
        source = replace(source, histogram=_source_histogram(source, options))
    return source


def _load_model(path: Path, name: str, device: torch.device, step: int | None = None) -> RenderSource:
    """The one place a model file is opened for rendering: the network and its file's description (a
    time-series model at step ``step``, 0 by default)."""
    model = load(path, device=device)
    field, description = model.field, model.description
    shape = description.volume_shape
    if description.series is not None:
        labels = tuple(step.label for step in description.series.steps)
        bricks = description.bricks
        if bricks is None:
            parts, grid_boxes, brick_boxes = f"{description.config.encoder.grids} feature grids", _grid_boxes_of(field), None
        else:
            counts = bricks.counts
            parts, grid_boxes, brick_boxes = f"{counts[0]}x{counts[1]}x{counts[2]} bricks", None, routing_boxes(counts)
        text = (f"time-series {description.model} {'brick ' if bricks else ''}model, {len(labels)} steps, {parts}, "
                f"volume {shape[2]}x{shape[1]}x{shape[0]}")
        source = RenderSource(name, "brick model" if bricks else "model", field, description.value_range, shape,
                              device, text, grid_boxes, brick_boxes, series=field, step_labels=labels)
        return source.at_step(step or 0)
    if step is not None:
        raise ApmgsrnError(f"{path}: holds one volume; time= picks a step of a time-series model only",
                           arguments=("time",))
    if description.bricks is not None:
        counts = description.bricks.counts  # (I, J, K) along x, y, z
        per_brick = []
        for index, brick_field in enumerate(field.bricks):
            local = _grid_boxes_of(brick_field)
            if local is not None:
                # The brick maps global p to local = p * scale + offset (see BrickedField); invert it.
                scale = field.brick_scales[index].detach().cpu()
                offset = field.brick_offsets[index].detach().cpu()
                per_brick.append((local - offset) / scale)
        grid_boxes = torch.cat(per_brick) if per_brick else None
        text = f"brick model, {len(field.bricks)} bricks ({counts[0]}x{counts[1]}x{counts[2]})"
        kind, brick_boxes = "brick model", routing_boxes(counts)
    else:
        grid_boxes = _grid_boxes_of(field)
        grids = f", {grid_boxes.shape[0]} feature grids" if grid_boxes is not None else ""
        text = f"{description.model} model{grids}"
        kind, brick_boxes = "model", None
    text += f", volume {shape[2]}x{shape[1]}x{shape[0]}"
    if description.packing is not None:
        bound = description.packing.max_error
        text += ", packed" + (f", |error| <= {bound:.4g} at every voxel" if bound is not None else "")
    return RenderSource(name, kind, field, description.value_range, shape, device, text, grid_boxes, brick_boxes)


def _step_text(description: str, step: int, labels: tuple[float, ...]) -> str:
    """A time-series source's description with the step shown."""
    base = description.split("; step ")[0]
    return f"{base}; step {step} of {len(labels)} (number {labels[step]:g})"


def _grid_boxes_of(field: torch.nn.Module) -> torch.Tensor | None:
    """Corners ``[M, 8, 3]`` of a single field's placed grids (None for a baseline without them)."""
    with torch.no_grad():
        boxes = field.encoder.grid_boxes()
    return None if boxes is None else boxes.detach().float().cpu()


def _open_volume(path: Path, name: str, device: torch.device, options: SourceOptions) -> RenderSource:
    volume = open_volume(path, **options.volume)
    voxels = 1
    for n in volume.shape:
        voxels *= int(n)
    if options.max_volume_voxels is not None and voxels > options.max_volume_voxels:
        raise ApmgsrnError(
            f"{name}: {voxels:,} voxels is more than the viewer holds in memory ({options.max_volume_voxels:,}); "
            "train a model of it and view the model"
        )
    check_finite(volume)
    volume_field = VolumeField(volume.to_numpy(), device=device)
    value_range = (volume_field.value_min, volume_field.value_max)
    shape = volume_field.volume_shape
    description = f"volume {shape[2]}x{shape[1]}x{shape[0]} (reference: trilinear voxels)"
    return RenderSource(name, "volume", volume_field, value_range, shape, device, description)


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


def _source_histogram(source: RenderSource, options: SourceOptions) -> list[float]:
    """Value histogram: every voxel of a volume, a lattice of ``histogram_lattice^3`` points of a model."""
    if isinstance(source.field, VolumeField):
        values = source.field.volume.reshape(-1)
    else:
        n = options.histogram_lattice
        axis = torch.linspace(-1.0, 1.0, n, device=source.device)
        z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
        points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)  # [n^3, 3]
        with torch.inference_mode():
            values = source.field(points).reshape(-1).float()
    return _histogram(values, source.value_range, options.histogram_bins)


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
