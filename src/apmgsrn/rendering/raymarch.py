"""The volume renderer: emission-absorption ray marching of any field through the volume's box (docs/method.md §7).

A render composes the stages of the other modules: rays are clipped to the box and, with empty-space
skipping, to the box around the macro cells the transfer function may show (``bounds``); their samples
are laid out a fixed step apart (``sampling``); the field is evaluated at the samples that are worth it;
the transfer table turns values into colour and opacity; and the samples are composited front to back
with opacity corrected for the step length (``compositing``).

Work is bounded by ``batch_size``: rays are taken in chunks, and each round advances every live ray of
a chunk by ``K`` samples with ``live rays * K <= batch_size``; the field sees only samples that are
inside the box, in front of the termination point and, with empty-space skipping, in a macro cell that
the opacity map does not make transparent. Skipped samples have opacity exactly 0, so skipping never
changes the image for exact bounds (the raw volume).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from apmgsrn.arguments import MAX_BATCH_SIZE, check_int, check_number
from apmgsrn.errors import InvalidArgument
from apmgsrn.rendering.bounds import Occupancy, ValueBounds
from apmgsrn.rendering.camera import Camera
from apmgsrn.rendering.compositing import FrontToBack, corrected_alpha
from apmgsrn.rendering.field import Field, VolumeField, evaluate_field, field_device
from apmgsrn.rendering.images import as_uint8
from apmgsrn.rendering.sampling import RaySamples, sample_offsets
from apmgsrn.rendering.transfer_function import TransferFunction, TransferTable
from apmgsrn.threads import inference_governor

#: Most samples per ray across the box (a 2^16-voxel axis), and macro cells per axis (their value bounds
#: take ``cells^3`` floats).
MAX_SAMPLES_PER_RAY, MAX_MACRO_CELLS = 1 << 16, 1024


@dataclass(frozen=True)
class RendererConfig:
    """What the renderer does; ``sampling`` and ``compositing`` explain the two step lengths."""

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
        check_int("samples_per_ray", self.samples_per_ray, 1, MAX_SAMPLES_PER_RAY)
        check_int("reference_samples", self.reference_samples, 1, MAX_SAMPLES_PER_RAY)
        check_int("batch_size", self.batch_size, 16, MAX_BATCH_SIZE)
        check_number("early_termination", self.early_termination, 0.0, 1.0, high_open=True)
        check_int("macro_cells", self.macro_cells, 1, MAX_MACRO_CELLS)
        check_int("samples_per_cell", self.samples_per_cell, 1, 64)
        check_int("seed", self.seed, 0, 2**63 - 1)
        check_int("table_size", self.table_size, 2, 1 << 20)
        if len(self.background) != 3:
            raise InvalidArgument(f"background={self.background!r}: must be three numbers in [0, 1]",
                                  arguments=("background",))
        for value in self.background:
            check_number("background", value, 0.0, 1.0)


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
        return as_uint8(self.image)


def default_batch_size(device: torch.device | str) -> int:
    """Points per field call suited to a device: 2^18 on a CPU, 2^20 on a GPU (fewer, larger rounds).

    Args:
        device: where the renderer runs.

    Returns:
        The batch size.
    """
    return 1 << 20 if torch.device(device).type == "cuda" else 1 << 18


class VolumeRenderer:
    """Renders a field ``[N, 3] -> [N, 1]`` with a transfer function from any camera.

    Holds the run state the config does not: the field, the baked transfer function, the value bounds
    and the resulting macro-cell :class:`~apmgsrn.rendering.bounds.Occupancy` (redone by
    :meth:`set_transfer_function`).
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
        self.device = torch.device(device) if device is not None else field_device(field)
        if len(extent) != 3 or min(extent) <= 0:
            raise ValueError(f"extent must be three positive half sizes, got {extent}")
        self.extent = tuple(float(e) for e in extent)
        self.bounds = bounds.to(self.device) if bounds is not None else None
        self.transfer_function = transfer_function
        self.table: TransferTable = transfer_function.table(config.table_size, self.device)
        self.occupancy: Occupancy | None = None
        self._classify()

    @classmethod
    def for_volume(
        cls,
        volume: torch.Tensor | np.ndarray | VolumeField,
        transfer_function: TransferFunction,
        config: RendererConfig = RendererConfig(),
        extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
        device: torch.device | str | None = None,
    ) -> "VolumeRenderer":
        """A renderer of the raw volume (the reference), with exact pooled bounds.

        Args:
            volume: ``[D, H, W]`` values, or a :class:`VolumeField` already holding them.
            transfer_function, config, extent: as for the constructor.
            device: where to keep the volume and march (default: the CPU, or the VolumeField's device).

        Returns:
            The renderer.
        """
        if isinstance(volume, VolumeField):
            field = volume
            device = field.device if device is None else device
        else:
            device = "cpu" if device is None else device
            field = VolumeField(volume, device=device)
        bounds = ValueBounds.from_volume(field.volume, config.macro_cells) if config.empty_space_skipping else None
        return cls(field, transfer_function, config, extent=extent, bounds=bounds, device=device)

    def reconfigured(self, config: RendererConfig) -> "VolumeRenderer":
        """The same field, transfer function, extent and device with other settings.

        Args:
            config: the new settings.

        Returns:
            A new renderer; it keeps the value bounds (often seconds of sampling for a model) when the
            macro cells and their sampling are unchanged.
        """
        cells = (config.macro_cells, config.samples_per_cell)
        bounds = self.bounds if cells == (self.config.macro_cells, self.config.samples_per_cell) else None
        return VolumeRenderer(self.field, self.transfer_function, config, self.extent, bounds, self.device)

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
        skipping = self.config.empty_space_skipping and self.bounds is not None
        self.occupancy = Occupancy(self.bounds, self.table) if skipping else None

    @property
    def visible_fraction(self) -> float | None:
        """Fraction of macro cells the current transfer function may show (None without skipping)."""
        return self.occupancy.visible_fraction if self.occupancy is not None else None

    # ------------------------------------------------------------------ rendering
    @property
    def step(self) -> float:
        """Step length between samples, world units."""
        return 2.0 * max(self.extent) / self.config.samples_per_ray

    @property
    def reference_step(self) -> float:
        """Slab thickness the transfer function's opacities refer to, world units."""
        return 2.0 * max(self.extent) / self.config.reference_samples

    def render(self, camera: Camera, alpha: bool = False) -> RenderResult:
        """Render a full image.

        Args:
            camera: the view and the image size.
            alpha: return RGBA ``[H, W, 4]``, colour not premultiplied, instead of RGB over the background.

        Returns:
            The image ``[H, W, 3]`` (or ``[H, W, 4]``; CPU, float32) and work counts.
        """
        pixels = torch.arange(camera.width * camera.height, device=self.device)
        colors, stats = self.render_pixels(camera, pixels, alpha)
        return RenderResult(colors.view(camera.height, camera.width, colors.shape[1]).cpu(), stats)

    def render_pixels(
        self, camera: Camera, pixels: torch.Tensor, alpha: bool = False
    ) -> tuple[torch.Tensor, RenderStatistics]:
        """Render some pixels of a camera's image.

        Args:
            camera: the view.
            pixels: ``[N]`` int64 linear pixel indices (``row * width + column``).
            alpha: RGBA (see :meth:`render_rays`).

        Returns:
            ``([N, 3] colours (``[N, 4]`` with alpha) on the renderer's device, work counts)``.
        """
        pixels = pixels.to(self.device)
        chunk = self.rays_per_chunk
        out = torch.empty((pixels.numel(), 4 if alpha else 3), dtype=torch.float32, device=self.device)
        stats = RenderStatistics()
        for start in range(0, pixels.numel(), chunk):
            ids = pixels[start : start + chunk]
            origins, directions = camera.rays(ids, self.device)
            colors, chunk_stats = self.render_rays(origins, directions, ids, alpha)
            out[start : start + chunk] = colors
            stats.add(chunk_stats)
        return out, stats

    @property
    def rays_per_chunk(self) -> int:
        """Rays marched together: a sixteenth of the batch, so each round advances them 16 samples or more."""
        return max(1, self.config.batch_size // 16)

    def render_rays(
        self, origins: torch.Tensor, directions: torch.Tensor, ray_ids: torch.Tensor | None = None,
        alpha: bool = False,
    ) -> tuple[torch.Tensor, RenderStatistics]:
        """Composite arbitrary rays (world space), in chunks of :attr:`rays_per_chunk`.

        Args:
            origins: ``[R, 3]`` ray origins.
            directions: ``[R, 3]`` unit directions.
            ray_ids: ``[R]`` int64 ids that seed the jitter (default ``0..R-1``).
            alpha: return ``[R, 4]`` RGBA: the accumulated colour divided by the ray's opacity (straight, not
                premultiplied; 0 where nothing was hit) and the opacity ``1 - T``; no background.

        Returns:
            ``([R, 3] colours, background included (or ``[R, 4]`` RGBA), work counts)``.
        """
        self.ensure_bounds()
        origins = origins.to(self.device, torch.float32)
        directions = directions.to(self.device, torch.float32)
        if ray_ids is None:
            ray_ids = torch.arange(origins.shape[0], device=self.device)
        ray_ids = ray_ids.to(self.device)
        chunk = self.rays_per_chunk
        out = torch.empty((origins.shape[0], 4 if alpha else 3), dtype=torch.float32, device=self.device)
        stats = RenderStatistics()
        background = torch.tensor(self.config.background, dtype=torch.float32, device=self.device)
        governor = inference_governor(self.device.type)  # CPU threads by timing the chunks (apmgsrn.threads)
        with torch.inference_mode(), governor:
            for start in range(0, origins.shape[0], chunk):
                end = start + chunk
                color, transmittance, chunk_stats = self._march(origins[start:end], directions[start:end],
                                                                ray_ids[start:end])
                if alpha:
                    opacity = 1.0 - transmittance
                    straight = torch.where(opacity[:, None] > 0, color / opacity.clamp(min=1e-12)[:, None], 0.0)
                    out[start:end] = torch.cat([straight.clamp(0.0, 1.0), opacity[:, None]], 1)
                else:
                    out[start:end] = color + transmittance[:, None] * background  # C + T * background
                stats.add(chunk_stats)
                governor.tick(chunk_stats.samples_in_box + chunk_stats.rays)
        return out, stats

    def _march(
        self, origins: torch.Tensor, directions: torch.Tensor, ray_ids: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, RenderStatistics]:
        """March a chunk of rays. Args: origins, directions ``[R, 3]``; ray_ids ``[R]``. Returns: the accumulated
        (premultiplied) colour ``[R, 3]``, the transmittance left ``[R]`` and the work counts."""
        config = self.config
        extent = torch.tensor(self.extent, dtype=torch.float32, device=self.device)
        offsets = sample_offsets(ray_ids, config.jitter, config.seed)
        samples = RaySamples.through_box(origins, directions, extent, self.step, offsets)
        occupancy = self.occupancy
        if occupancy is not None:
            box = None if occupancy.box is None else (occupancy.box[0] * extent, occupancy.box[1] * extent)
            samples = samples.within(origins, directions, box)
        stats = RenderStatistics(rays=origins.shape[0], samples_in_box=int(samples.count.sum()))
        compositor = FrontToBack(origins.shape[0], self.device, config.early_termination)
        # Rays in field coordinates ([-1, 1]^3), and in macro-cell units for the skipping test.
        field_origins = origins / extent
        field_directions = directions / extent
        if occupancy is not None:
            cell_origins, cell_directions = occupancy.cell_rays(field_origins, field_directions)
        active = (samples.first < samples.last).nonzero().squeeze(1)  # rays still marching
        cursor = samples.first.clone()  # next sample of each ray
        while active.numel() > 0:
            live = active.numel()
            k = max(1, min(64, config.batch_size // live))
            ray_cursor = cursor[active]
            index = ray_cursor[:, None] + torch.arange(k, device=self.device)  # [A, K] sample index along each ray
            t = samples.positions(active, index)  # [A, K]
            valid = index < samples.last[active, None]
            if occupancy is not None:
                valid &= occupancy.visible(cell_origins[active], cell_directions[active], t)
            exponent = samples.segment_lengths(active, index, t) * (1.0 / self.reference_step)  # [A, K]
            points = field_origins[active, None, :] + t[..., None] * field_directions[active, None, :]  # [A, K, 3]
            chosen = valid.view(-1).nonzero().squeeze(1)  # [S] samples that need the field
            selected = chosen.numel()
            if selected == 0:
                ray_t = compositor.add(active, torch.zeros((live, k), device=self.device), None)
            elif selected == live * k:  # every sample counts: no gathers
                colors, opacity = self.table.lookup(evaluate_field(self.field, points.view(-1, 3), config.batch_size))
                ray_t = compositor.add(active, corrected_alpha(opacity.view(live, k), exponent), colors)
            else:
                values = evaluate_field(self.field, points.view(-1, 3)[chosen], config.batch_size)
                colors, opacity = self.table.lookup(values)
                alpha = torch.zeros(live * k, device=self.device)
                alpha[chosen] = corrected_alpha(opacity, exponent.view(-1)[chosen])
                ray_t = compositor.add(active, alpha.view(live, k), colors, chosen)
            stats.field_evaluations += selected
            ray_cursor = ray_cursor + k
            cursor[active] = ray_cursor
            still = (ray_cursor < samples.last[active]) & (ray_t >= config.early_termination) & (ray_t > 0)
            active = active[still]
        return compositor.color, compositor.transmittance, stats
