"""Emission-absorption ray marching of any field through the volume's box (SPEC section 7).

Sampling. Rays are clipped to the box ``[-e, e]`` (``e`` the extent, longest half side 1). The step
length is fixed: ``step = longest box side / samples_per_ray``, so ``samples_per_ray`` samples cross the
box along its longest axis (a ray along the diagonal of a cube takes up to ``sqrt(3)`` times as many).
Sample ``i`` of a ray sits at ``t_near + (i + u) * step`` with ``u = 0.5``, or a per-pixel hashed offset
in ``[0, 1)`` when jitter is on (seeded, so a pixel always gets the same offset). Each sample stands for
the part of the ray closer to it than to its neighbours, clipped to the box, so the segment lengths
``dt_i`` add up to the chord exactly and a homogeneous medium obeys Beer-Lambert exactly.

Opacity correction. The transfer function's opacity ``a`` is the opacity of a slab one *reference step*
thick (``longest box side / reference_samples``); a sample of length ``dt`` gets
``alpha = 1 - (1 - a) ** (dt / reference_step)``, so images do not depend on ``samples_per_ray``.

Compositing is front to back: ``C += T * alpha * colour``, ``T *= 1 - alpha``, background added with the
final ``T``. A sample that finds ``T < early_termination`` contributes nothing and ends its ray.

Work is bounded by ``batch_size``: rays are taken in chunks, and each round advances every live ray of
a chunk by ``K`` samples with ``live rays * K <= batch_size``; the field sees only samples that are
inside the box, in front of the termination point and, with empty-space skipping, in a macro cell that
the opacity map does not make transparent (see ``empty_space``). Skipped samples have opacity exactly 0,
so skipping never changes the image for exact bounds (the raw volume).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from apmgsrn.render.camera import Camera
from apmgsrn.render.empty_space import ValueBounds, occupied_box
from apmgsrn.render.transfer_function import TransferFunction, TransferTable

Field = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class RendererConfig:
    """What the renderer does; see the module notes for the meaning of each step length."""

    samples_per_ray: int = 256  # samples across the box's longest side
    reference_samples: int = 256  # opacity is per step of (longest side / reference_samples)
    batch_size: int = 1 << 18  # most points per field call; bounds the working memory
    early_termination: float = 1e-3  # a ray stops once its transmittance falls below this (0: never)
    empty_space_skipping: bool = True
    macro_cells: int = 32  # macro cells per axis for empty-space skipping
    samples_per_cell: int = 4  # lattice steps per macro-cell edge when bounding a field by sampling
    jitter: bool = False  # per-pixel random start offset instead of the step's middle
    seed: int = 0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    table_size: int = 4096  # entries of the baked transfer function

    def __post_init__(self) -> None:
        if self.samples_per_ray < 1 or self.reference_samples < 1:
            raise ValueError("samples_per_ray and reference_samples must be positive")
        if self.batch_size < 16:
            raise ValueError("batch_size must be at least 16")
        if not 0.0 <= self.early_termination < 1.0:
            raise ValueError("early_termination must be in [0, 1)")


@dataclass
class RenderStatistics:
    """Work counts of one render."""

    rays: int = 0
    samples_in_box: int = 0  # what a renderer without skipping or early termination would evaluate
    field_evaluations: int = 0

    def add(self, other: "RenderStatistics") -> None:
        self.rays += other.rays
        self.samples_in_box += other.samples_in_box
        self.field_evaluations += other.field_evaluations


@dataclass
class RenderResult:
    """An image ``[H, W, 3]`` float32 on the CPU, sRGB in [0, 1], and the work it took."""

    image: torch.Tensor
    statistics: RenderStatistics

    def to_uint8(self) -> np.ndarray:
        """``[H, W, 3]`` uint8 copy of the image."""
        return to_uint8(self.image)


def default_batch_size(device: torch.device | str) -> int:
    """Points per field call suited to a device: 2^18 on a CPU, 2^20 on a GPU (fewer, larger rounds).

    Args:
        device: where the renderer runs.

    Returns:
        The batch size.
    """
    return 1 << 20 if torch.device(device).type == "cuda" else 1 << 18


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """Quantise an ``[H, W, 3]`` image in [0, 1] to uint8 (rounding to nearest)."""
    return (image.detach().clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


class VolumeRenderer:
    """Renders a field ``[N, 3] -> [N, 1]`` with a transfer function from any camera.

    Holds the run state the config does not: the field, the baked transfer function, the value bounds
    and the resulting macro-cell occupancy (redone by :meth:`set_transfer_function`).
    """

    def __init__(
        self,
        field: Field,
        transfer_function: TransferFunction,
        config: RendererConfig = RendererConfig(),
        extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
        bounds: ValueBounds | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        """Args:
        field: callable on ``[N, 3]`` points in [-1, 1]^3 returning ``[N, 1]`` (or ``[N]``) values.
        transfer_function: colour and opacity maps in data units.
        config: sampling, batching and skipping settings.
        extent: half sizes of the drawn box (x, y, z); see ``camera.extent_from_shape``.
        bounds: macro-cell value bounds; None with skipping on samples the field once, on first use.
        device: where to march; default the field's device (its ``device`` attribute or first parameter).
        """
        self.field = field
        self.config = config
        self.device = torch.device(device) if device is not None else _field_device(field)
        if len(extent) != 3 or min(extent) <= 0:
            raise ValueError(f"extent must be three positive half sizes, got {extent}")
        self.extent = tuple(float(e) for e in extent)
        self.bounds = bounds.to(self.device) if bounds is not None else None
        self.transfer_function = transfer_function
        self.table: TransferTable = transfer_function.table(config.table_size, self.device)
        self._occupancy: torch.Tensor | None = None
        self._occupied_box: tuple[torch.Tensor, torch.Tensor] | None = None
        self._classify()

    @classmethod
    def for_volume(
        cls,
        volume: torch.Tensor | np.ndarray,
        transfer_function: TransferFunction,
        config: RendererConfig = RendererConfig(),
        extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
        device: torch.device | str = "cpu",
    ) -> "VolumeRenderer":
        """A renderer of the raw volume (the reference), with exact pooled bounds.

        Args:
            volume: ``[D, H, W]`` values.
            transfer_function, config, extent: as for the constructor.
            device: where to keep the volume and march.

        Returns:
            The renderer.
        """
        from apmgsrn.render.volume_field import VolumeField

        field = VolumeField(volume, device=device)
        bounds = ValueBounds.from_volume(field.volume, config.macro_cells) if config.empty_space_skipping else None
        return cls(field, transfer_function, config, extent=extent, bounds=bounds, device=device)

    # ------------------------------------------------------------------ transfer function / skipping
    def set_transfer_function(self, transfer_function: TransferFunction) -> None:
        """Use another transfer function; re-bakes the table and re-classifies the macro cells."""
        self.transfer_function = transfer_function
        self.table = transfer_function.table(self.config.table_size, self.device)
        self._classify()

    def ensure_bounds(self) -> ValueBounds | None:
        """Compute the field's value bounds by sampling, once, if skipping is on and none were given."""
        if self.config.empty_space_skipping and self.bounds is None:
            with torch.inference_mode():
                self.bounds = ValueBounds.from_field(
                    self.field,
                    cells=self.config.macro_cells,
                    samples_per_cell=self.config.samples_per_cell,
                    batch_size=self.config.batch_size,
                    device=self.device,
                )
            self._classify()
        return self.bounds

    def _classify(self) -> None:
        if not self.config.empty_space_skipping or self.bounds is None:
            self._occupancy = None
            self._occupied_box = None
            return
        self._occupancy = self.bounds.occupancy(self.table)
        self._occupied_box = occupied_box(self._occupancy)

    @property
    def visible_fraction(self) -> float | None:
        """Fraction of macro cells the current transfer function may show (None without skipping)."""
        if self._occupancy is None:
            return None
        return float(self._occupancy.float().mean())

    # ------------------------------------------------------------------ rendering
    @property
    def step(self) -> float:
        """Step length between samples, world units."""
        return 2.0 * max(self.extent) / self.config.samples_per_ray

    @property
    def reference_step(self) -> float:
        """Slab thickness the transfer function's opacities refer to, world units."""
        return 2.0 * max(self.extent) / self.config.reference_samples

    def render(self, camera: Camera) -> RenderResult:
        """Render a full image.

        Args:
            camera: the view and the image size.

        Returns:
            The image ``[H, W, 3]`` (CPU, float32) and work counts.
        """
        pixels = torch.arange(camera.width * camera.height, device=self.device)
        colors, stats = self.render_pixels(camera, pixels)
        return RenderResult(colors.view(camera.height, camera.width, 3).cpu(), stats)

    def render_pixels(self, camera: Camera, pixels: torch.Tensor) -> tuple[torch.Tensor, RenderStatistics]:
        """Render some pixels of a camera's image.

        Args:
            camera: the view.
            pixels: ``[N]`` int64 linear pixel indices (``row * width + column``).

        Returns:
            ``([N, 3] colours on the renderer's device, work counts)``.
        """
        pixels = pixels.to(self.device)
        chunk = self.rays_per_chunk
        out = torch.empty((pixels.numel(), 3), dtype=torch.float32, device=self.device)
        stats = RenderStatistics()
        for start in range(0, pixels.numel(), chunk):
            ids = pixels[start : start + chunk]
            origins, directions = camera.rays(ids, self.device)
            colors, chunk_stats = self.render_rays(origins, directions, ids)
            out[start : start + chunk] = colors
            stats.add(chunk_stats)
        return out, stats

    def render_progressive(self, camera: Camera, strides: tuple[int, ...] = (8, 4, 2, 1)):
        """Coarse-to-fine rendering; see :func:`apmgsrn.render.progressive.render_progressive`.

        Args:
            camera: the view and image size.
            strides: lattice strides of the passes, decreasing to 1.

        Returns:
            An iterator of ``ProgressiveImage``, the last one the full image.
        """
        from apmgsrn.render.progressive import render_progressive

        return render_progressive(self, camera, strides)

    @property
    def rays_per_chunk(self) -> int:
        """Rays marched together: a sixteenth of the batch, so each round advances them 16 samples or more."""
        return max(1, self.config.batch_size // 16)

    def render_rays(
        self, origins: torch.Tensor, directions: torch.Tensor, ray_ids: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, RenderStatistics]:
        """Composite arbitrary rays (world space), in chunks of :attr:`rays_per_chunk`.

        Args:
            origins: ``[R, 3]`` ray origins.
            directions: ``[R, 3]`` unit directions.
            ray_ids: ``[R]`` int64 ids that seed the jitter (default ``0..R-1``).

        Returns:
            ``([R, 3] colours, background included, work counts)``.
        """
        self.ensure_bounds()
        origins = origins.to(self.device, torch.float32)
        directions = directions.to(self.device, torch.float32)
        if ray_ids is None:
            ray_ids = torch.arange(origins.shape[0], device=self.device)
        chunk = self.rays_per_chunk
        out = torch.empty((origins.shape[0], 3), dtype=torch.float32, device=self.device)
        stats = RenderStatistics()
        with torch.inference_mode():
            for start in range(0, origins.shape[0], chunk):
                end = start + chunk
                colors, chunk_stats = self._march(origins[start:end], directions[start:end], ray_ids[start:end])
                out[start:end] = colors
                stats.add(chunk_stats)
        return out, stats

    def _march(
        self, origins: torch.Tensor, directions: torch.Tensor, pixels: torch.Tensor
    ) -> tuple[torch.Tensor, RenderStatistics]:
        """March a chunk of rays. Args: origins, directions ``[R, 3]``; pixels ``[R]``. Returns: ``[R, 3]``."""
        config = self.config
        device = self.device
        rays = origins.shape[0]
        extent = torch.tensor(self.extent, dtype=torch.float32, device=device)
        step = self.step
        t_near, t_far = _intersect_box(origins, directions, -extent, extent)
        t_near = t_near.clamp(min=0.0)
        length = (t_far - t_near).clamp(min=0.0)  # [R]
        if config.jitter:
            offset = _pixel_jitter(pixels, config.seed)
        else:
            offset = torch.full((rays,), 0.5, device=device)
        count = torch.ceil(length / step - offset).clamp(min=0).to(torch.int64)  # samples of each ray
        first = torch.zeros_like(count)
        last = count.clone()
        occupancy_flat = None
        if self._occupancy is not None:
            occupancy_flat = self._occupancy.reshape(-1)
            if self._occupied_box is None:  # nothing visible at all
                last = first.clone()
            else:
                # Start and stop each ray at the box around the visible cells; one sample of slack either
                # side, and the per-sample cell test below decides the rest.
                low, high = (b * extent for b in self._occupied_box)
                t_in, t_out = _intersect_box(origins, directions, low, high)
                hits = t_out > t_in
                first_in = torch.floor((t_in - t_near) / step - offset).to(torch.int64) - 1
                last_in = torch.ceil((t_out - t_near) / step - offset).to(torch.int64) + 1
                first = torch.where(hits, first_in.clamp(min=0), count).clamp(max=count)
                last = torch.where(hits, torch.minimum(last_in, count), count).clamp(min=first)
        stats = RenderStatistics(rays=rays, samples_in_box=int(count.sum()))
        color = torch.zeros((rays, 3), dtype=torch.float32, device=device)
        transmittance = torch.ones(rays, dtype=torch.float32, device=device)

        # Rays in field coordinates ([-1, 1]^3) and in macro-cell coordinates ([0, G] per axis).
        field_origin = origins / extent
        field_direction = directions / extent
        cells_zyx = self.bounds.cells if self.bounds is not None else (1, 1, 1)
        cell_scale = 0.5 * torch.tensor(cells_zyx[::-1], dtype=torch.float32, device=device)  # (x, y, z)
        cell_origin = (field_origin + 1.0) * cell_scale
        cell_direction = field_direction * cell_scale
        cell_max = torch.tensor(cells_zyx[::-1], dtype=torch.float32, device=device) - 1.0
        cell_stride = torch.tensor([1, cells_zyx[2], cells_zyx[2] * cells_zyx[1]], device=device)

        # Ray ids still marching, and where each stands.
        active = (first < last).nonzero().squeeze(1)
        cursor = first
        eps = config.early_termination
        half_step = 0.5 * step
        while active.numel() > 0:
            live = active.numel()
            k = max(1, min(64, config.batch_size // live))
            steps = torch.arange(k, device=device)  # [K]
            ray_cursor = cursor[active]
            index = ray_cursor[:, None] + steps  # [A, K] sample index along each ray
            ray_near = t_near[active, None]
            t = ray_near + (index.to(torch.float32) + offset[active, None]) * step  # [A, K]
            valid = index < last[active, None]
            if occupancy_flat is not None:
                cell = cell_origin[active, None, :] + t[..., None] * cell_direction[active, None, :]  # [A, K, 3]
                cell = torch.minimum(cell.clamp_(min=0.0), cell_max).to(torch.int64)  # floor: all >= 0
                valid &= occupancy_flat[(cell * cell_stride).sum(dim=-1)]
            # Segment of the ray each sample stands for, clipped to the box (see the module notes).
            seg_low = torch.where(index == 0, ray_near, t - half_step)
            seg_high = torch.where(index == count[active, None] - 1, t_far[active, None], t + half_step)
            exponent = (seg_high - seg_low).clamp_(min=0.0) * (1.0 / self.reference_step)  # [A, K]
            points = field_origin[active, None, :] + t[..., None] * field_direction[active, None, :]  # [A, K, 3]
            chosen = valid.view(-1).nonzero().squeeze(1)  # [S] samples that need the field
            selected = chosen.numel()
            if selected == 0:
                alpha = torch.zeros((live, k), device=device)
                sample_rgb = None
            elif selected == live * k:  # every sample counts: no gathers
                values = self._evaluate(points.view(-1, 3))
                sample_rgb, opacity = self.table.lookup(values)
                alpha = (1.0 - torch.pow(1.0 - opacity.view(live, k), exponent))
            else:
                values = self._evaluate(points.view(-1, 3)[chosen])
                sample_rgb, opacity = self.table.lookup(values)
                alpha = torch.zeros(live * k, device=device)
                alpha[chosen] = 1.0 - torch.pow(1.0 - opacity, exponent.view(-1)[chosen])
                alpha = alpha.view(live, k)
            stats.field_evaluations += selected
            ray_t = transmittance[active]
            after = ray_t[:, None] * torch.cumprod(1.0 - alpha, dim=1)  # [A, K] T after each sample
            before = torch.cat([ray_t[:, None], after[:, :-1]], dim=1)  # [A, K] T before each sample
            keep = before >= eps  # early termination: later samples contribute nothing
            weight = before * alpha * keep  # [A, K]
            if sample_rgb is not None and selected == live * k:
                color[active] += (weight[..., None] * sample_rgb.view(live, k, 3)).sum(dim=1)
            elif sample_rgb is not None:
                color.index_add_(0, active[chosen // k], weight.view(-1)[chosen, None] * sample_rgb)
            # The ray's transmittance stops at its termination point (monotone: the smallest kept value).
            ray_t = torch.where(keep, after, torch.full_like(after, math.inf)).amin(dim=1)
            transmittance[active] = ray_t
            ray_cursor = ray_cursor + k
            cursor[active] = ray_cursor
            still = (ray_cursor < last[active]) & (ray_t >= eps) & (ray_t > 0)
            active = active[still]
        background = torch.tensor(config.background, dtype=torch.float32, device=device)
        return color + transmittance[:, None] * background, stats

    def _evaluate(self, points: torch.Tensor) -> torch.Tensor:
        """Field values at ``[S, 3]`` points in batches of at most ``batch_size``; returns ``[S]`` float32."""
        size = self.config.batch_size
        if points.shape[0] <= size:
            return self.field(points).reshape(-1).to(torch.float32)
        out = torch.empty(points.shape[0], dtype=torch.float32, device=points.device)
        for start in range(0, points.shape[0], size):
            out[start : start + size] = self.field(points[start : start + size]).reshape(-1)
        return out


def _intersect_box(
    origins: torch.Tensor, directions: torch.Tensor, low: torch.Tensor, high: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab-method ray/box intersection. Returns ``(t_enter [R], t_exit [R])``; a miss has exit < enter."""
    # Division by a zero component gives +-inf, which the min/max below handle (a parallel ray inside the
    # slab keeps (-inf, inf); outside it gets an empty interval).
    inverse = 1.0 / directions
    t0 = (low - origins) * inverse  # [R, 3]
    t1 = (high - origins) * inverse
    t_small = torch.minimum(t0, t1).nan_to_num(nan=-math.inf)
    t_large = torch.maximum(t0, t1).nan_to_num(nan=math.inf)
    return t_small.amax(dim=1), t_large.amin(dim=1)


def _pixel_jitter(pixels: torch.Tensor, seed: int) -> torch.Tensor:
    """A fixed pseudo-random offset in [0, 1) per pixel index (integer hash), independent of render order."""
    mask = 0xFFFFFFFF
    h = (pixels.to(torch.int64) * 0x27D4EB2D + (seed * 0x165667B1 + 0x3C6EF372)) & mask
    h = h ^ (h >> 15)
    h = (h * 0x2C1B3C6D) & mask
    h = h ^ (h >> 12)
    h = (h * 0x297A2D39) & mask
    h = h ^ (h >> 15)
    return (h >> 8).to(torch.float32) / float(1 << 24)  # 24 bits: exact in float32, never reaches 1


def _field_device(field: Field) -> torch.device:
    device = getattr(field, "device", None)
    if isinstance(device, (torch.device, str)):
        return torch.device(device)
    parameters = getattr(field, "parameters", None)
    if callable(parameters):
        for parameter in parameters():
            return parameter.device
    return torch.device("cpu")
