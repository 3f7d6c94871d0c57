"""The state of one viewer: what is shown, from where, with which settings; rendering is its worker's.

This module knows nothing of the web page (the trame app in ``app.py`` is a thin layer over it), so the
camera control and the scheduling are tested without a browser. The pieces: :class:`OrbitView` (the
camera), :mod:`settings` (settings and colour maps), :class:`RenderSource` (what is shown, opened by
:func:`apmgsrn.sources.open_source`) and :class:`RenderWorker` (the progressive render thread). Every
change that alters the image bumps the *generation* counter the worker renders against.
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import replace
from typing import Callable

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import Camera, TransferFunction, read_presets
from apmgsrn.sources import RenderSource, open_source
from apmgsrn.viewer.catalog import MODEL, VOLUME, Catalog
from apmgsrn.viewer.orbit import OrbitView
from apmgsrn.viewer.overlay import draw_boxes, overlay_lines
from apmgsrn.viewer.settings import (
    PAGE,
    ColormapLibrary,
    RenderSettings,
    ViewerConfig,
    editor_points,
    finite_number,
    linear_nodes,
    opacity_points,
    usable_range,
    whole_number,
)
from apmgsrn.viewer.worker import Frame, RenderRequest, RenderWorker, ViewerStatistics

FrameCallback = Callable[[Frame], None]
MessageCallback = Callable[[str, object], None]


class ViewerSession:
    """One viewer's state and its render worker.

    Every public method may be called from any thread; rendering happens in the worker's thread (or in
    the caller's through :meth:`step`, as tests do). Callbacks run in the worker's thread:
    ``on_frame(frame)`` for every image, ``on_message(kind, payload)`` with kind ``"source"`` (a
    :class:`RenderSource` was opened), ``"step"`` (another step of a time-series model is shown), ``"status"``
    (a line of text) or ``"error"`` (a message).
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
        self.colormaps = ColormapLibrary()
        self._lock = threading.RLock()
        self._generation = 0
        self._view = OrbitView()
        self._settings = RenderSettings.initial(config)
        self._transfer_function: TransferFunction | None = None
        self._source: RenderSource | None = None
        self._last_motion = -math.inf
        self.worker = RenderWorker(self, self._lock, self.device, config)

    # ------------------------------------------------------------------------------------ rendering
    def start(self) -> None:
        """Start the render thread (idempotent)."""
        self.worker.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the render thread after its current chunk of pixels."""
        with self._lock:
            self._generation += 1  # abandon the pass in flight
        self.worker.stop(timeout)

    def step(self) -> bool:
        """Do the next piece of work in the caller's thread (see :meth:`RenderWorker.step`)."""
        return self.worker.step()

    def run_until_idle(self, timeout: float = 120.0) -> None:
        """Render in the caller's thread until the view is complete (for tests and scripts)."""
        self.worker.run_until_idle(timeout)

    def statistics(self) -> ViewerStatistics:
        """Frame times, passes, frames per second while moving, device memory."""
        return self.worker.statistics()

    @property
    def last_frame(self) -> Frame | None:
        return self.worker.last_frame

    # ------------------------------------------------------------------------------------ state access
    @property
    def generation(self) -> int:
        return self._generation

    @property
    def settings(self) -> RenderSettings:
        return self._settings

    @property
    def source(self) -> RenderSource | None:
        return self._source

    def colormap_keys(self) -> list[str]:
        """Names of the colour maps on offer, built-ins first."""
        return self.colormaps.keys()

    def extent(self) -> tuple[float, float, float]:
        """Half sizes of the volume's box (longest 1)."""
        source = self._source
        return source.extent if source is not None else (1.0, 1.0, 1.0)

    def camera(self) -> Camera:
        """The camera of the current view and image size."""
        with self._lock:
            return self._view.camera(self._settings.image_width, self._settings.image_height, self.extent())

    def transfer_function(self) -> TransferFunction:
        """The transfer function of the current settings, in data units."""
        with self._lock:
            if self._transfer_function is None:
                self._transfer_function = self.colormaps.transfer_function(self._settings)
            return self._transfer_function

    # ------------------------------------------------------------------------------------ camera
    def _changed(self, motion: bool = False) -> None:
        """Call with the lock held after anything that alters the image."""
        self._generation += 1
        if motion:
            self._last_motion = time.monotonic()
        self.worker.wake()

    def _move(self, change: Callable[[OrbitView], OrbitView], motion: bool = True) -> None:
        with self._lock:
            self._view = change(self._view)
            self._changed(motion=motion)

    def orbit(self, dx: float, dy: float) -> None:
        """Turn the view by a drag of ``(dx, dy)`` viewport fractions."""
        dx, dy = finite_number(dx), finite_number(dy)
        self._move(lambda view: view.orbited(dx, dy))

    def pan(self, dx: float, dy: float) -> None:
        """Slide the view by a drag of ``(dx, dy)`` viewport fractions."""
        dx, dy = finite_number(dx), finite_number(dy)
        with self._lock:
            size = (self._settings.image_width, self._settings.image_height)
            self._move(lambda view: view.panned(dx, dy, *size, self.extent()))

    def zoom(self, steps: float) -> None:
        """Zoom out (positive) or in (negative) by wheel steps."""
        steps = max(-20.0, min(20.0, finite_number(steps)))
        self._move(lambda view: view.zoomed(steps))

    def reset_view(self) -> None:
        """Back to the starting camera."""
        self._move(lambda view: OrbitView(), motion=False)

    def end_interaction(self) -> None:
        """The pointer was released: refine at once instead of waiting for ``rest_seconds``."""
        with self._lock:
            self._last_motion = -math.inf
            self.worker.wake()

    def is_moving(self, now: float | None = None) -> bool:
        """Whether a camera event came less than ``rest_seconds`` ago."""
        now = time.monotonic() if now is None else now
        return now - self._last_motion < self.config.rest_seconds

    def wait_seconds(self) -> float | None:
        """How long the worker may sleep: until the view rests, or None (until woken)."""
        if self.is_moving():
            return max(0.01, self._last_motion + self.config.rest_seconds - time.monotonic())
        return None

    # ------------------------------------------------------------------------------------ settings
    def _update_settings(self, moving: bool = False, **changes) -> None:
        with self._lock:
            settings = replace(self._settings, **changes)
            transfer_function = self.colormaps.transfer_function(settings)  # validate before applying
            self._settings = settings
            self._transfer_function = transfer_function
            self._changed(motion=moving)

    def set_colormap(self, key: str, use_preset_opacity: bool = True) -> list[list[float]]:
        """Use another colour map; a preset that carries its own opacity replaces the opacity nodes
        (unless ``use_preset_opacity`` is False), midpoints and sharpness included.

        Returns:
            The opacity nodes now in use as the editor shows them, ``[[position, opacity], ...]``.

        Raises:
            ApmgsrnError: unknown key.
        """
        choice = self.colormaps.choice(key)
        with self._lock:
            changes: dict = {"colormap": key}
            if use_preset_opacity and choice.opacity:
                changes["opacity"] = choice.opacity
            self._update_settings(**changes)
            return editor_points(self._settings.opacity)

    def set_opacity(self, points, moving: bool = False) -> list[list[float]]:
        """Use other opacity nodes ``[(position, opacity), ...]`` on [0, 1] (position: fraction of the value
        range), joined by straight lines; ``moving``: an edit in progress (coarse images until it rests).

        Returns:
            The nodes in use (sorted, clamped to [0, 1]), ``[[position, opacity], ...]``.

        Raises:
            ApmgsrnError: not a list of number pairs.
        """
        nodes = linear_nodes(opacity_points(points))
        self._update_settings(moving=moving, opacity=nodes)
        return editor_points(nodes)

    def set_value_range(self, low: float, high: float) -> None:
        """Stretch the transfer function over ``[low, high]`` (data units, ``low < high``)."""
        low, high = finite_number(low), finite_number(high)
        if not high > low:
            raise ApmgsrnError(f"value range {low:g}..{high:g} is empty; the minimum must be below the maximum")
        self._update_settings(value_range=(float(low), float(high)))

    def set_samples_per_ray(self, count: int) -> None:
        """Samples across the box's longest side (1..4096)."""
        self._update_settings(samples_per_ray=whole_number(count, *PAGE.samples_per_ray, "samples per ray"))

    def set_batch_size(self, count: int) -> None:
        """Points per forward pass (16..2^24)."""
        self._update_settings(batch_size=whole_number(count, *PAGE.batch_size, "batch size"))

    def set_image_size(self, width: int, height: int) -> None:
        """Rendered image size in pixels (16..2048 each)."""
        width = whole_number(width, *PAGE.image_size, "image width")
        height = whole_number(height, *PAGE.image_size, "image height")
        self._update_settings(image_width=width, image_height=height)

    def set_overlay(self, enabled: bool) -> None:
        """Draw the feature-grid boxes (and brick borders) over the image; redraws the last image."""
        with self._lock:
            self._settings = replace(self._settings, overlay=bool(enabled))
        self.worker.submit("overlay", self.worker.redraw)

    def add_presets(self, path: str | os.PathLike, label: str) -> list[str]:
        """Offer every preset of a ParaView ``.json`` or ``.xml`` file (see :meth:`ColormapLibrary.add_presets`).

        Raises:
            ApmgsrnError: not a readable preset file, or too many colour maps.
        """
        return self.colormaps.add_presets(read_presets(path), label)

    # ------------------------------------------------------------------------------------ sources
    def request_open(self, name: str) -> None:
        """Open a catalog entry in the worker (the page stays responsive); errors come as messages.

        Raises:
            ApmgsrnError: the name is refused by the catalog (checked at once, in the caller's thread).
        """
        self._resolve(name)
        self.worker.submit("open", lambda: self._open_reporting(name))

    def _open_reporting(self, name: str) -> None:
        self.message("status", f"opening {name}")
        try:
            self.open_now(name)
        except ApmgsrnError as exc:
            self.message("error", str(exc))
        except Exception as exc:  # noqa: BLE001 - a broken file must not stop the server
            self.message("error", f"{name}: cannot be opened ({type(exc).__name__}: {exc})")

    def _resolve(self, name: str):
        if self.catalog is None:
            raise ApmgsrnError("this viewer has no files to open")
        return self.catalog.resolve(name, kinds=(MODEL, VOLUME))

    def open_now(self, name: str) -> RenderSource:
        """Open a catalog entry in the caller's thread and show it.

        Raises:
            ApmgsrnError: refused name or unreadable file.
        """
        path = self._resolve(name)
        # The reader applies the opener's rules with the served folder as root: every file the volume
        # reaches (chunks, external storage) must lie inside it.
        options = replace(self.config.source, volume={**self.config.source.volume, "root": self.catalog.root})
        source = open_source(path, self.device, options, name=name)
        self.set_source(source)
        return source

    def set_source(self, source: RenderSource) -> None:
        """Show a source: value range and view reset, renderer rebuilt (bounds of a model sampled now)."""
        with self._lock:
            settings = replace(self._settings, value_range=usable_range(source.value_range))
            transfer_function = self.colormaps.transfer_function(settings)
        renderer = source.renderer(transfer_function, settings.renderer_config(self.config))
        self.message("status", f"{source.name}: preparing empty-space skipping")
        renderer.ensure_bounds()  # seconds for a model on a CPU: once per source, not per frame
        with self._lock:
            self._source = source
            self._settings = settings
            self._transfer_function = transfer_function
            self._view = OrbitView()
            self.worker.adopt(source, renderer)
            self._changed()
        self.message("source", source)

    def swap_source(self, current: RenderSource, source: RenderSource, renderer) -> bool:
        """Show ``source`` (another step of the shown time-series model) with its prepared renderer, keeping the
        view and settings. Returns False, changing nothing, when ``current`` is no longer what is shown."""
        with self._lock:
            if self._source is not current:
                return False
            self._source = source
            self.worker.adopt(source, renderer)
            self._changed()
        self.message("step", source)
        return True

    # ------------------------------------------------------------------------------------ for the worker
    def render_request(self) -> RenderRequest | None:
        """With the lock held: what the current generation shows (None before a source is open)."""
        if self._source is None:
            return None
        return RenderRequest(
            self._generation, self._source, self._settings, self.transfer_function(), self.camera(), self.is_moving()
        )

    def overlay(self, raw: np.ndarray, camera: Camera) -> tuple[np.ndarray, list]:
        """The frame with the overlay drawn in, and the overlay's segments (or ``raw`` and none)."""
        source = self._source
        if not self._settings.overlay or source is None:
            return raw, []
        if source.grid_boxes is None and source.brick_boxes is None:
            return raw, []
        extent = self.extent()
        image = draw_boxes(raw, camera, source.grid_boxes, source.brick_boxes, extent=extent)
        return image, overlay_lines(camera, source.grid_boxes, source.brick_boxes, extent=extent)

    def deliver(self, frame: Frame) -> None:
        if self.on_frame is not None:
            self.on_frame(frame)

    def message(self, kind: str, payload: object) -> None:
        if self.on_message is not None:
            self.on_message(kind, payload)
