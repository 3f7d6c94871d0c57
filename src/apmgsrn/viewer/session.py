"""The state of one viewer: what is shown, from where, with which settings, and the progressive renders.

This module knows nothing of the web page (the trame app in ``app.py`` is a thin layer over it), so the
camera control and the scheduling are tested without a browser.

Scheduling. Every change that alters the image (camera, transfer function, sampling, image size, source)
bumps a *generation* counter. One worker thread renders the current generation coarse to fine: pass ``j``
renders the pixels on the lattice of stride ``strides[j]`` not rendered before (8, 4, 2, 1: 1/64, 3/64,
12/64, 48/64 of the pixels), and after each pass a full image is made by bilinear interpolation between
the lattice pixels rendered so far, so the last pass gives the exact render. A pass is rendered in
chunks of pixels; between chunks and once more before a frame is handed out, the worker compares its
generation with the current one and drops the work when they differ: a stale pass never reaches the
page after a newer camera. While the view moves (a camera event less than ``rest_seconds`` ago) only
the passes that fit in ``interactive_seconds`` are rendered (at least the coarsest), so dragging gives
a steady stream of coarse images; once the view rests, the worker refines the same generation to the
full image. The viewer schedules passes itself, with the renderer's public ``render_pixels``, rather
than iterating ``render_progressive``, because it must be able to abandon a pass half way.
"""

from __future__ import annotations

import collections
import math
import os
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.render import (
    BUILTIN_COLORMAPS,
    Camera,
    OpacityMap,
    RendererConfig,
    TransferFunction,
    VolumeRenderer,
    extent_from_shape,
    make_transfer_function,
    read_presets,
)
from apmgsrn.viewer.catalog import MODEL, VOLUME, Catalog
from apmgsrn.viewer.overlay import draw_boxes, overlay_lines
from apmgsrn.viewer.sources import SourceConfig, ViewSource, open_source

# Opacity the viewer starts with: the lowest fifth of the range (mostly background in scientific
# volumes) transparent, then a ramp, so the first image shows structure rather than a fog.
DEFAULT_VIEWER_OPACITY: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.2, 0.0), (1.0, 0.8))


@dataclass(frozen=True)
class ViewerConfig:
    """What the viewer starts with and how it schedules work."""

    image_width: int = 256
    image_height: int = 256
    samples_per_ray: int = 128
    batch_size: int = 1 << 16
    strides: tuple[int, ...] = (8, 4, 2, 1)
    interactive_seconds: float = 0.15  # time budget of one image while the view moves
    rest_seconds: float = 0.35  # the view rests this long after its last camera event
    chunk_pixels: int = 2048  # pixels rendered between two checks for a newer generation
    macro_cells: int = 16  # empty-space skipping cells per axis (coarse: bounds of a model are sampled)
    colormap: str = "Cool to Warm"
    opacity: tuple[tuple[float, float], ...] = DEFAULT_VIEWER_OPACITY
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    source: SourceConfig = field(default_factory=SourceConfig)

    def __post_init__(self) -> None:
        if not self.strides or self.strides[-1] != 1 or any(b >= a for a, b in zip(self.strides, self.strides[1:])):
            raise ValueError(f"strides must decrease strictly to 1, got {self.strides}")


# ---------------------------------------------------------------------------------------------- camera
@dataclass(frozen=True)
class OrbitView:
    """An orbiting camera as the user steers it: angles around the target, distance, pan.

    ``distance_scale`` multiplies the distance that fits the box in the view, so the same value suits any
    image size and volume proportions. Angles follow :meth:`apmgsrn.render.Camera.orbit`.
    """

    azimuth: float = 30.0
    elevation: float = 20.0
    distance_scale: float = 1.0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fov: float = 30.0

    # Degrees turned by a drag across the whole viewport.
    DEGREES_PER_VIEWPORT = 180.0
    MIN_DISTANCE_SCALE = 0.05
    MAX_DISTANCE_SCALE = 20.0

    def camera(self, width: int, height: int, extent: tuple[float, float, float]) -> Camera:
        """The camera of this view.

        Args:
            width, height: image size in pixels.
            extent: half sizes of the volume's box.

        Returns:
            The camera, looking at ``target``.
        """
        fitted = Camera.orbit(self.azimuth, self.elevation, None, self.fov, width, height, extent)
        distance = math.dist(fitted.position, fitted.target) * self.distance_scale
        around = Camera.orbit(self.azimuth, self.elevation, distance, self.fov, width, height, extent)
        position = tuple(p + t for p, t in zip(around.position, self.target))
        return Camera(position=position, target=self.target, up=around.up, fov=self.fov, width=width, height=height)

    def orbited(self, dx: float, dy: float) -> "OrbitView":
        """Turn the camera around the target by a drag.

        Args:
            dx, dy: drag as fractions of the viewport's width and height (right and down positive).

        Returns:
            The new view; the object follows the pointer, elevation stays within (-90, 90) degrees.
        """
        azimuth = (self.azimuth - self.DEGREES_PER_VIEWPORT * dx) % 360.0
        elevation = min(89.5, max(-89.5, self.elevation + self.DEGREES_PER_VIEWPORT * dy))
        return replace(self, azimuth=azimuth, elevation=elevation)

    def panned(self, dx: float, dy: float, width: int, height: int, extent: tuple[float, float, float]) -> "OrbitView":
        """Slide the target in the view plane so the object follows the pointer.

        Args:
            dx, dy: drag as fractions of the viewport (right and down positive).
            width, height: image size (for the aspect ratio).
            extent: the box's half sizes.

        Returns:
            The new view.
        """
        camera = self.camera(width, height, extent)
        _, right, up = camera.basis()
        distance = math.dist(camera.position, camera.target)
        visible_height = 2.0 * distance * math.tan(math.radians(self.fov) / 2.0)  # at the target's depth
        visible_width = visible_height * width / height
        shift = -dx * visible_width * right + dy * visible_height * up  # [3], world units
        target = tuple(float(t + s) for t, s in zip(self.target, shift))
        return replace(self, target=target)

    def zoomed(self, steps: float) -> "OrbitView":
        """Move closer (``steps < 0``) or away (``steps > 0``); one step is a factor of 1.1.

        Args:
            steps: wheel steps (a browser's ``deltaY / 100``).

        Returns:
            The new view, distance kept within sane limits.
        """
        scale = self.distance_scale * 1.1 ** max(-100.0, min(100.0, float(steps)))  # no float overflow
        return replace(self, distance_scale=min(self.MAX_DISTANCE_SCALE, max(self.MIN_DISTANCE_SCALE, scale)))


# ------------------------------------------------------------------------------------------ progressive
def lattice_passes(width: int, height: int, strides: tuple[int, ...]) -> list[torch.Tensor]:
    """Linear pixel indices of each coarse-to-fine pass (together: every pixel once).

    Args:
        width, height: image size.
        strides: decreasing lattice strides ending with 1.

    Returns:
        One ``[N_j]`` int64 tensor per stride: the lattice pixels of that stride no coarser pass has.
    """
    rows = torch.arange(height)[:, None]
    columns = torch.arange(width)[None, :]
    covered = torch.zeros((height, width), dtype=torch.bool)
    passes = []
    for stride in strides:
        lattice = (rows % stride == 0) & (columns % stride == 0)  # [H, W]
        new = lattice & ~covered
        passes.append(new.reshape(-1).nonzero().squeeze(1))
        covered |= new
    return passes


def _axis_weights(size: int, stride: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each pixel of an axis: lower and upper lattice index and the weight of the upper one."""
    count = (size - 1) // stride + 1  # lattice points on this axis
    position = torch.arange(size, dtype=torch.float32) / stride
    low = position.floor().to(torch.int64).clamp(max=count - 1)
    high = (low + 1).clamp(max=count - 1)
    weight = (position - low.to(torch.float32)).clamp(0.0, 1.0)
    weight = torch.where(high == low, torch.zeros_like(weight), weight)  # past the last lattice point: hold
    return low, high, weight


def upsample_lattice(image: torch.Tensor, stride: int) -> torch.Tensor:
    """Fill an image from its lattice pixels of a stride by bilinear interpolation.

    Args:
        image: ``[H, W, 3]`` whose pixels at rows and columns that are multiples of ``stride`` are known.
        stride: the lattice stride (1 returns the image itself).

    Returns:
        ``[H, W, 3]``, equal to ``image`` on the lattice.
    """
    if stride == 1:
        return image
    height, width = image.shape[:2]
    lattice = image[::stride, ::stride]  # [h, w, 3]
    r0, r1, rw = _axis_weights(height, stride)
    c0, c1, cw = _axis_weights(width, stride)
    top = lattice[r0]  # [H, w, 3]
    bottom = lattice[r1]
    rows = top + (bottom - top) * rw[:, None, None]
    left = rows[:, c0]  # [H, W, 3]
    right = rows[:, c1]
    return left + (right - left) * cw[None, :, None]


@dataclass(frozen=True)
class RenderSettings:
    """Everything except the camera and the source that decides the image."""

    colormap: str
    opacity: tuple[tuple[float, float], ...]
    value_range: tuple[float, float]
    samples_per_ray: int
    batch_size: int
    image_width: int
    image_height: int
    overlay: bool = False


@dataclass(frozen=True)
class ColormapChoice:
    """A colour map the page offers: a built-in name, or a preset of a ParaView JSON file."""

    key: str  # what the page shows and sends back
    spec: str  # a built-in name or a .json path
    preset_name: str | None = None
    opacity: tuple[tuple[float, float], ...] | None = None  # the preset's own opacity, on [0, 1]


@dataclass
class Frame:
    """An image handed to the page.

    Attributes:
        generation: the generation it shows (only the current one is ever handed out).
        image: ``[H, W, 3]`` uint8, overlay drawn when it is on (what a saved frame holds).
        plain: the same without the overlay.
        lines: the overlay as ``(column0, row0, column1, row1, rgb)`` segments (empty when off), for a
            page that draws them crisply over a scaled-up image.
        camera: the camera it was rendered with.
        stride: finest lattice rendered so far (1: exact).
        pass_index, pass_count: which pass of how many.
        moving: rendered while the view moved (interactive budget).
        elapsed: seconds spent rendering this generation's passes so far (waits excluded).
    """

    generation: int
    image: np.ndarray
    plain: np.ndarray
    lines: list
    camera: Camera
    stride: int
    pass_index: int
    pass_count: int
    moving: bool
    elapsed: float

    @property
    def done(self) -> bool:
        return self.stride == 1


@dataclass
class ViewerStatistics:
    """What the page shows about the work."""

    last_frame_seconds: float | None  # time of the last complete image (all passes)
    last_pass_seconds: float | None
    passes_done: int
    pass_count: int
    moving_fps: float | None  # images per second while the view moved (last two seconds)
    memory: str
    field_evaluations: int  # by the current generation so far


@dataclass
class _Progress:
    generation: int
    camera: Camera
    passes: list[torch.Tensor]
    buffer: torch.Tensor  # [H * W, 3] on the renderer's device
    next_pass: int = 0
    render_seconds: float = 0.0  # time spent rendering this generation's passes so far
    field_evaluations: int = 0


FrameCallback = Callable[[Frame], None]
MessageCallback = Callable[[str, object], None]


class ViewerSession:
    """One viewer's state and its render worker.

    Every public method may be called from any thread; rendering happens in the worker (or in the
    caller's thread through :meth:`step`, as tests do). Callbacks run in the worker's thread:
    ``on_frame(frame)`` for every image, ``on_message(kind, payload)`` with kind ``"source"`` (a
    :class:`ViewSource` was opened), ``"status"`` (a line of text) or ``"error"`` (a message).
    """

    def __init__(
        self,
        catalog: Catalog | None,
        device: torch.device | str = "cpu",
        config: ViewerConfig = ViewerConfig(),
        on_frame: FrameCallback | None = None,
        on_message: MessageCallback | None = None,
    ) -> None:
        """Args:
        catalog: the files that may be opened (None: only :meth:`set_source`).
        device: where to render.
        config: starting settings and scheduling.
        on_frame, on_message: callbacks, see the class notes.
        """
        self.catalog = catalog
        self.device = torch.device(device)
        self.config = config
        self.on_frame = on_frame
        self.on_message = on_message
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._generation = 0
        self._view = OrbitView()
        self._settings = RenderSettings(
            colormap=config.colormap,
            opacity=tuple(config.opacity),
            value_range=(0.0, 1.0),
            samples_per_ray=config.samples_per_ray,
            batch_size=config.batch_size,
            image_width=config.image_width,
            image_height=config.image_height,
        )
        self._colormaps: dict[str, ColormapChoice] = {name: ColormapChoice(name, name) for name in BUILTIN_COLORMAPS}
        self._transfer_function: TransferFunction | None = None
        self._source: ViewSource | None = None
        self._pending_open: str | None = None
        self._renderer: VolumeRenderer | None = None
        self._renderer_key: tuple | None = None
        self._renderer_transfer_function: TransferFunction | None = None
        self._progress: _Progress | None = None
        self._last_motion = -math.inf
        self._last_frame: Frame | None = None
        self._last_raw: np.ndarray | None = None
        self._republish = False
        self._seconds_per_ray: float | None = None
        self._moving_frames: collections.deque[float] = collections.deque(maxlen=64)
        self._last_frame_seconds: float | None = None
        self._last_pass_seconds: float | None = None
        self._stop = False
        self._thread: threading.Thread | None = None
        self._loading = False
        self._failed_generation: int | None = None

    # ------------------------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Start the render worker thread (idempotent)."""
        with self._lock:
            if self._thread is not None:
                return
            self._stop = False
            self._thread = threading.Thread(target=self._run, name="apmgsrn-viewer-render", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the worker after its current chunk of pixels."""
        with self._wake:
            self._stop = True
            self._generation += 1  # abandon the pass in flight
            self._wake.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout)
        self._thread = None

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._stop and not self._has_work():
                    self._wake.wait(timeout=self._wait_seconds())
                if self._stop:
                    return
            try:
                self.step()
            except ApmgsrnError as exc:
                self._message("error", str(exc))
            except Exception as exc:  # noqa: BLE001 - the server must survive a failing render
                self._message("error", f"rendering failed: {type(exc).__name__}: {exc}")
                with self._lock:
                    self._progress = None
                    self._renderer = None  # rebuilt for the next generation
                    # Wait for the next change instead of retrying the same failing render in a loop.
                    self._failed_generation = self._generation

    # ------------------------------------------------------------------------------------ state access
    @property
    def generation(self) -> int:
        return self._generation

    @property
    def view(self) -> OrbitView:
        return self._view

    @property
    def settings(self) -> RenderSettings:
        return self._settings

    @property
    def source(self) -> ViewSource | None:
        return self._source

    @property
    def last_frame(self) -> Frame | None:
        return self._last_frame

    @property
    def loading(self) -> bool:
        return self._loading or self._pending_open is not None

    def colormap_keys(self) -> list[str]:
        """Names of the colour maps on offer, built-ins first."""
        with self._lock:
            return list(self._colormaps)

    def extent(self) -> tuple[float, float, float]:
        """Half sizes of the volume's box (longest 1)."""
        source = self._source
        return extent_from_shape(source.volume_shape) if source is not None else (1.0, 1.0, 1.0)

    def camera(self) -> Camera:
        """The camera of the current view and image size."""
        with self._lock:
            return self._view.camera(self._settings.image_width, self._settings.image_height, self.extent())

    def transfer_function(self) -> TransferFunction:
        """The transfer function of the current settings, in data units."""
        with self._lock:
            if self._transfer_function is None:
                self._transfer_function = self._build_transfer_function(self._settings)
            return self._transfer_function

    # ------------------------------------------------------------------------------------ changes
    def _changed(self, motion: bool = False) -> None:
        """Call with the lock held after anything that alters the image."""
        self._generation += 1
        if motion:
            self._last_motion = time.monotonic()
        self._wake.notify_all()

    def orbit(self, dx: float, dy: float) -> None:
        """Turn the view by a drag of ``(dx, dy)`` viewport fractions."""
        with self._lock:
            self._view = self._view.orbited(_finite(dx), _finite(dy))
            self._changed(motion=True)

    def pan(self, dx: float, dy: float) -> None:
        """Slide the view by a drag of ``(dx, dy)`` viewport fractions."""
        with self._lock:
            s = self._settings
            self._view = self._view.panned(_finite(dx), _finite(dy), s.image_width, s.image_height, self.extent())
            self._changed(motion=True)

    def zoom(self, steps: float) -> None:
        """Zoom out (positive) or in (negative) by wheel steps."""
        with self._lock:
            self._view = self._view.zoomed(max(-20.0, min(20.0, _finite(steps))))
            self._changed(motion=True)

    def reset_view(self) -> None:
        """Back to the starting camera."""
        with self._lock:
            self._view = OrbitView()
            self._changed()

    def end_interaction(self) -> None:
        """The pointer was released: refine at once instead of waiting for ``rest_seconds``."""
        with self._lock:
            self._last_motion = -math.inf
            self._wake.notify_all()

    def is_moving(self, now: float | None = None) -> bool:
        """Whether a camera event came less than ``rest_seconds`` ago."""
        now = time.monotonic() if now is None else now
        return now - self._last_motion < self.config.rest_seconds

    def _update_settings(self, moving: bool = False, **changes) -> None:
        with self._lock:
            settings = replace(self._settings, **changes)
            transfer_function = self._build_transfer_function(settings)  # validate before applying
            self._settings = settings
            self._transfer_function = transfer_function
            self._changed(motion=moving)

    def set_colormap(self, key: str, use_preset_opacity: bool = True) -> tuple[tuple[float, float], ...]:
        """Use another colour map.

        Args:
            key: one of :meth:`colormap_keys`.
            use_preset_opacity: a preset that carries its own opacity replaces the opacity nodes.

        Returns:
            The opacity nodes now in use.

        Raises:
            ApmgsrnError: unknown key.
        """
        with self._lock:
            choice = self._colormaps.get(key)
            if choice is None:
                raise ApmgsrnError(f"unknown colour map {key!r}; pick one from the list")
            changes: dict = {"colormap": key}
            if use_preset_opacity and choice.opacity:
                changes["opacity"] = choice.opacity
            self._update_settings(**changes)
            return self._settings.opacity

    def set_opacity(self, points, moving: bool = False) -> tuple[tuple[float, float], ...]:
        """Use other opacity nodes.

        Args:
            points: ``[(position, opacity), ...]`` on [0, 1] (position: fraction of the value range);
                sorted by position here, at least one node.
            moving: an edit in progress (a point being dragged): render coarse images until it rests.

        Returns:
            The nodes in use (sorted, clamped to [0, 1]).

        Raises:
            ApmgsrnError: not a list of number pairs.
        """
        clean = _opacity_points(points)
        with self._lock:
            self._update_settings(moving=moving, opacity=clean)
            return clean

    def set_value_range(self, low: float, high: float) -> None:
        """Stretch the transfer function over ``[low, high]`` (data units, ``low < high``)."""
        low, high = _finite(low), _finite(high)
        if not high > low:
            raise ApmgsrnError(f"value range {low:g}..{high:g} is empty; the minimum must be below the maximum")
        self._update_settings(value_range=(float(low), float(high)))

    def set_samples_per_ray(self, count: int) -> None:
        """Samples across the box's longest side (1..4096)."""
        count = int(_finite(count))
        if not 1 <= count <= 4096:
            raise ApmgsrnError(f"samples per ray {count} is outside 1..4096")
        self._update_settings(samples_per_ray=count)

    def set_batch_size(self, count: int) -> None:
        """Points per forward pass (16..2^24)."""
        count = int(_finite(count))
        if not 16 <= count <= 1 << 24:
            raise ApmgsrnError(f"batch size {count} is outside 16..16777216")
        self._update_settings(batch_size=count)

    def set_image_size(self, width: int, height: int) -> None:
        """Rendered image size in pixels (16..2048 each)."""
        width, height = int(_finite(width)), int(_finite(height))
        if not (16 <= width <= 2048 and 16 <= height <= 2048):
            raise ApmgsrnError(f"image size {width}x{height} is outside 16..2048 pixels")
        self._update_settings(image_width=width, image_height=height)

    def set_overlay(self, enabled: bool) -> None:
        """Draw the feature-grid boxes (and brick borders) over the image; redraws the last image."""
        with self._lock:
            self._settings = replace(self._settings, overlay=bool(enabled))
            self._republish = True
            self._wake.notify_all()

    # ------------------------------------------------------------------------------------ colour maps
    def add_presets(self, path: str | os.PathLike, label: str) -> list[str]:
        """Offer every preset of a ParaView JSON file.

        Args:
            path: the file (already checked to be one the viewer may read).
            label: shown before each preset's name (e.g. the file's catalog name).

        Returns:
            The new colour-map keys.

        Raises:
            ApmgsrnError: the file is not a readable ParaView preset file.
        """
        keys = []
        for preset in read_presets(path):
            opacity = None
            if preset.opacity_map is not None:
                lo, hi = preset.color_map.span
                width = hi - lo if hi > lo else 1.0
                opacity = tuple(
                    (min(1.0, max(0.0, (x - lo) / width)), float(a)) for x, a, *_ in preset.opacity_map.points
                )
            key = f"{preset.name} ({label})"
            with self._lock:
                self._colormaps[key] = ColormapChoice(key, str(path), preset.name, opacity)
            keys.append(key)
        return keys

    def _build_transfer_function(self, settings: RenderSettings) -> TransferFunction:
        choice = self._colormaps.get(settings.colormap) or ColormapChoice(settings.colormap, settings.colormap)
        low, high = settings.value_range
        tf = make_transfer_function(choice.spec, (low, high), preset_name=choice.preset_name)
        # The range control always wins, also over a session export kept in its own data units.
        tf = tf.rescaled(low, high)
        return make_transfer_function_with_opacity(tf, settings.opacity)

    # ------------------------------------------------------------------------------------ sources
    def request_open(self, name: str) -> None:
        """Open a catalog entry in the worker (the page stays responsive); errors come as messages.

        Raises:
            ApmgsrnError: the name is refused by the catalog (checked at once, in the caller's thread).
        """
        if self.catalog is None:
            raise ApmgsrnError("this viewer has no files to open")
        self.catalog.resolve(name, kinds=(MODEL, VOLUME))
        with self._lock:
            self._pending_open = name
            self._wake.notify_all()

    def open_now(self, name: str) -> ViewSource:
        """Open a catalog entry in the caller's thread.

        Args:
            name: catalog name of a model or volume.

        Returns:
            The opened source (now shown).

        Raises:
            ApmgsrnError: refused name or unreadable file.
        """
        if self.catalog is None:
            raise ApmgsrnError("this viewer has no files to open")
        path = self.catalog.resolve(name, kinds=(MODEL, VOLUME))
        kind = self.catalog.kind_of(name)
        source = open_source(name, path, kind, self.device, self.config.source, self.config.macro_cells)
        self.set_source(source)
        return source

    def set_source(self, source: ViewSource) -> None:
        """Show a source: value range and view reset, renderer rebuilt (bounds of a model sampled now).

        Args:
            source: an opened model or volume.
        """
        with self._lock:
            settings = replace(self._settings, value_range=_usable_range(source.value_range))
            transfer_function = self._build_transfer_function(settings)
            config = self._renderer_config(settings)
        renderer = VolumeRenderer(
            source.field,
            transfer_function,
            config,
            extent=extent_from_shape(source.volume_shape),
            bounds=source.bounds,
            device=self.device,
        )
        self._message("status", f"{source.name}: preparing empty-space skipping")
        renderer.ensure_bounds()  # seconds for a model on a CPU: once per source, not per frame
        with self._lock:
            self._source = source
            self._settings = settings
            self._transfer_function = transfer_function
            self._renderer = renderer
            self._renderer_key = (settings.samples_per_ray, settings.batch_size)
            self._renderer_transfer_function = transfer_function
            self._view = OrbitView()
            self._progress = None
            self._last_frame = None
            self._last_raw = None
            self._changed()
        self._message("source", source)

    def _renderer_config(self, settings: RenderSettings) -> RendererConfig:
        return RendererConfig(
            samples_per_ray=settings.samples_per_ray,
            batch_size=settings.batch_size,
            macro_cells=self.config.macro_cells,
            background=self.config.background,
        )

    # ------------------------------------------------------------------------------------ statistics
    def statistics(self) -> ViewerStatistics:
        """Frame times, passes, frames per second while moving, device memory."""
        with self._lock:
            progress = self._progress
            frames = list(self._moving_frames)
        fps = None
        now = time.monotonic()
        recent = [t for t in frames if now - t < 2.0]
        if len(recent) >= 2 and recent[-1] > recent[0]:
            fps = (len(recent) - 1) / (recent[-1] - recent[0])
        return ViewerStatistics(
            last_frame_seconds=self._last_frame_seconds,
            last_pass_seconds=self._last_pass_seconds,
            passes_done=progress.next_pass if progress else 0,
            pass_count=len(self.config.strides),
            moving_fps=fps,
            memory=device_memory(self.device),
            field_evaluations=progress.field_evaluations if progress else 0,
        )

    # ------------------------------------------------------------------------------------ scheduling
    def _has_work(self) -> bool:
        if self._pending_open is not None or self._republish:
            return True
        if self._source is None or self._failed_generation == self._generation:
            return False
        progress = self._progress
        if progress is None or progress.generation != self._generation:
            return True
        if progress.next_pass >= len(progress.passes):
            return False
        return not self.is_moving() or self._fits_budget(progress)

    def _wait_seconds(self) -> float | None:
        if self.is_moving():
            return max(0.01, self._last_motion + self.config.rest_seconds - time.monotonic())
        return None

    def _fits_budget(self, progress: _Progress) -> bool:
        """While moving: whether the next pass still fits the interactive time budget."""
        if progress.next_pass == 0:
            return True
        if self._seconds_per_ray is None:
            return False
        rays = progress.passes[progress.next_pass].numel()
        return progress.render_seconds + rays * self._seconds_per_ray <= self.config.interactive_seconds

    def idle(self) -> bool:
        """True when nothing is left to do (the current view is complete, nothing pending)."""
        with self._lock:
            return not self._has_work() and not self.is_moving()

    def step(self) -> bool:
        """Do the next piece of work: open a pending source, redraw the overlay, or render one pass.

        Returns:
            True if it did something.
        """
        with self._lock:
            pending = self._pending_open
            self._pending_open = None
        if pending is not None:
            self._open_pending(pending)
            return True
        with self._lock:
            if self._republish:
                self._republish = False
                frame, raw = self._last_frame, self._last_raw
                if frame is not None and raw is not None and frame.generation == self._generation:
                    image, lines = self._with_overlay(raw, frame.camera)
                    frame = replace(frame, image=image, lines=lines)
                    self._last_frame = frame
                else:
                    frame = None
            else:
                frame = None
        if frame is not None:
            self._deliver(frame)
            return True
        return self._render_next_pass()

    def _open_pending(self, name: str) -> None:
        self._loading = True
        self._message("status", f"opening {name}")
        try:
            self.open_now(name)
        except ApmgsrnError as exc:
            self._message("error", str(exc))
        except Exception as exc:  # noqa: BLE001 - a broken file must not stop the server
            self._message("error", f"{name}: cannot be opened ({type(exc).__name__}: {exc})")
        finally:
            self._loading = False
        self._failed_generation: int | None = None

    def _prepare(self) -> tuple[_Progress, VolumeRenderer, bool] | None:
        """With the lock held: the progress of the current generation and the renderer to use."""
        if self._source is None:
            return None
        settings = self._settings
        if self._progress is None or self._progress.generation != self._generation:
            key = (settings.samples_per_ray, settings.batch_size)
            transfer_function = self._transfer_function or self._build_transfer_function(settings)
            self._transfer_function = transfer_function
            if self._renderer is None or key != self._renderer_key:
                old = self._renderer
                self._renderer = VolumeRenderer(
                    self._source.field,
                    transfer_function,
                    self._renderer_config(settings),
                    extent=self.extent(),
                    bounds=old.bounds if old is not None else self._source.bounds,
                    device=self.device,
                )
                self._renderer_key = key
                self._renderer_transfer_function = transfer_function
            elif transfer_function is not self._renderer_transfer_function:
                self._renderer.set_transfer_function(transfer_function)
                self._renderer_transfer_function = transfer_function
            width, height = settings.image_width, settings.image_height
            self._progress = _Progress(
                generation=self._generation,
                camera=self._view.camera(width, height, self.extent()),
                passes=lattice_passes(width, height, self.config.strides),
                buffer=torch.zeros((width * height, 3), dtype=torch.float32, device=self.device),
            )
        progress = self._progress
        if progress.next_pass >= len(progress.passes):
            return None
        moving = self.is_moving()
        if moving and not self._fits_budget(progress):
            return None
        return progress, self._renderer, moving

    def _render_next_pass(self) -> bool:
        with self._lock:
            prepared = self._prepare()
        if prepared is None:
            return False
        progress, renderer, moving = prepared
        generation = progress.generation
        pixels = progress.passes[progress.next_pass]
        pass_start = time.monotonic()
        for start in range(0, pixels.numel(), self.config.chunk_pixels):
            if self._generation != generation:
                return True  # a newer view exists: drop this pass
            chunk = pixels[start : start + self.config.chunk_pixels]
            chunk_start = time.monotonic()
            colors, work = renderer.render_pixels(progress.camera, chunk)
            progress.buffer[chunk.to(self.device)] = colors
            progress.field_evaluations += work.field_evaluations
            per_ray = (time.monotonic() - chunk_start) / max(1, chunk.numel())
            # Smoothed cost per ray: the budget test of the next interactive pass uses it.
            previous = self._seconds_per_ray
            self._seconds_per_ray = per_ray if previous is None else 0.7 * previous + 0.3 * per_ray
        now = time.monotonic()
        stride = self.config.strides[progress.next_pass]
        camera = progress.camera
        image = upsample_lattice(progress.buffer.view(camera.height, camera.width, 3), stride)
        raw = (image.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        with self._lock:
            if self._generation != generation:
                return True  # stale: never shown
            progress.next_pass += 1
            progress.render_seconds += now - pass_start
            image, lines = self._with_overlay(raw, camera)
            frame = Frame(
                generation=generation,
                image=image,
                plain=raw,
                lines=lines,
                camera=camera,
                stride=stride,
                pass_index=progress.next_pass - 1,
                pass_count=len(progress.passes),
                moving=moving,
                elapsed=progress.render_seconds,
            )
            self._last_frame = frame
            self._last_raw = raw
            self._last_pass_seconds = now - pass_start
            if frame.done:
                self._last_frame_seconds = frame.elapsed
            if moving:
                self._moving_frames.append(now)
        self._deliver(frame)
        return True

    def _with_overlay(self, raw: np.ndarray, camera: Camera) -> tuple[np.ndarray, list]:
        """The frame with the overlay drawn in, and the overlay's segments (or ``raw`` and none)."""
        source = self._source
        if not self._settings.overlay or source is None:
            return raw, []
        if source.grid_boxes is None and source.brick_boxes is None:
            return raw, []
        extent = self.extent()
        image = draw_boxes(raw, camera, source.grid_boxes, source.brick_boxes, extent=extent)
        return image, overlay_lines(camera, source.grid_boxes, source.brick_boxes, extent=extent)

    def _deliver(self, frame: Frame) -> None:
        if self.on_frame is not None:
            self.on_frame(frame)

    def _message(self, kind: str, payload: object) -> None:
        if self.on_message is not None:
            self.on_message(kind, payload)

    def run_until_idle(self, timeout: float = 120.0) -> None:
        """Render in the caller's thread until the view is complete (for tests and scripts).

        Args:
            timeout: give up after this many seconds.

        Raises:
            TimeoutError: still busy after ``timeout``.
        """
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if not self.step():
                with self._lock:
                    if not self._has_work() and not self.is_moving():
                        return
                time.sleep(0.01)
        raise TimeoutError("viewer still busy")


def make_transfer_function_with_opacity(
    tf: TransferFunction, opacity: tuple[tuple[float, float], ...]
) -> TransferFunction:
    """``tf`` with opacity nodes given on [0, 1] of its value range.

    Args:
        tf: a transfer function (its colour map's span is the value range).
        opacity: ``(position, alpha)`` pairs, positions on [0, 1].

    Returns:
        The transfer function with a linear opacity map through those nodes.
    """
    low, high = tf.value_range
    nodes = tuple((low + x * (high - low), a, 0.5, 0.0) for x, a in opacity)
    return tf.with_opacity(OpacityMap(nodes))


def _finite(value) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ApmgsrnError(f"expected a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ApmgsrnError(f"expected a finite number, got {value!r}")
    return number


def _opacity_points(points) -> tuple[tuple[float, float], ...]:
    if not isinstance(points, (list, tuple)) or not points or len(points) > 256:
        raise ApmgsrnError("opacity needs 1 to 256 points (position, opacity)")
    clean = []
    for point in points:
        if not isinstance(point, (list, tuple)) or len(point) != 2:
            raise ApmgsrnError(f"opacity point {point!r} is not a (position, opacity) pair")
        x, a = _finite(point[0]), _finite(point[1])
        clean.append((min(1.0, max(0.0, x)), min(1.0, max(0.0, a))))
    return tuple(sorted(clean, key=lambda p: p[0]))


def _usable_range(value_range: tuple[float, float]) -> tuple[float, float]:
    low, high = float(value_range[0]), float(value_range[1])
    return (low, high) if high > low else (low, low + 1.0)


def device_memory(device: torch.device) -> str:
    """A line about the memory in use on a device: CUDA allocator figures, or the process's resident set.

    Args:
        device: the render device.

    Returns:
        Text such as ``"CUDA 120.0 MiB (peak 300.0 MiB)"`` or ``"CPU process 850.3 MiB resident"``.
    """
    mib = 1024.0 * 1024.0
    if device.type == "cuda" and torch.cuda.is_available():
        used = torch.cuda.memory_allocated(device) / mib
        peak = torch.cuda.max_memory_allocated(device) / mib
        return f"CUDA {used:.1f} MiB (peak {peak:.1f} MiB)"
    try:
        with open("/proc/self/statm", encoding="ascii") as handle:
            resident_pages = int(handle.read().split()[1])
        return f"CPU process {resident_pages * os.sysconf('SC_PAGE_SIZE') / mib:.1f} MiB resident"
    except (OSError, ValueError, IndexError, AttributeError):
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        return f"CPU process peak {peak:.1f} MiB resident"

