"""The viewer's render worker: one thread that renders the current view coarse to fine and hands out frames.

Scheduling. Every change that alters the image bumps the session's *generation* counter. The worker
renders the current generation with the progressive schedule of :mod:`apmgsrn.rendering.progressive`
(strides 8, 4, 2, 1; after each pass a full image interpolated from the pixels rendered so far, the last
pass exact). A pass is rendered in chunks of pixels; between chunks and once more before a frame is
handed out, the worker compares its generation with the current one and drops the work when they
differ: a stale pass never reaches the page after a newer camera. While the view moves (a camera event
less than ``rest_seconds`` ago) only the passes that fit in ``interactive_seconds`` are rendered (at least
the coarsest), so dragging gives a steady stream of coarse images; once the view rests, the worker
refines the same generation to the full image. Other work (opening a file, redrawing the overlay) is
submitted as tasks and runs in the same thread before the next pass.
"""

from __future__ import annotations

import collections
import os
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable, Protocol

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import Camera, ProgressiveRender, TransferFunction, VolumeRenderer, as_uint8
from apmgsrn.sources import RenderSource
from apmgsrn.viewer.settings import RenderSettings, ViewerConfig


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


@dataclass(frozen=True)
class RenderRequest:
    """What the current generation shows."""

    generation: int
    source: RenderSource
    settings: RenderSettings
    transfer_function: TransferFunction
    camera: Camera
    moving: bool


class RenderHost(Protocol):
    """The session the worker renders for; called with the shared lock held unless noted."""

    generation: int
    source: RenderSource | None

    def is_moving(self) -> bool: ...
    def wait_seconds(self) -> float | None: ...
    def render_request(self) -> RenderRequest | None: ...
    def overlay(self, raw: np.ndarray, camera: Camera) -> tuple[np.ndarray, list]: ...
    def deliver(self, frame: Frame) -> None: ...  # without the lock
    def message(self, kind: str, payload: object) -> None: ...  # without the lock


@dataclass
class _Progress:
    generation: int
    render: ProgressiveRender
    render_seconds: float = 0.0  # time spent rendering this generation's passes so far
    field_evaluations: int = 0


class RenderWorker:
    """Renders a host's current view pass by pass, in a thread of its own or through :meth:`step`."""

    def __init__(self, host: RenderHost, lock: threading.RLock, device: torch.device, config: ViewerConfig) -> None:
        """Args:
        host: the session it renders for.
        lock: the host's lock (guards the host's state and this worker's).
        device: where to render.
        config: scheduling settings.
        """
        self.host = host
        self.device = device
        self.config = config
        self.renderer: VolumeRenderer | None = None
        self._renderer_source: RenderSource | None = None  # the source ``renderer`` draws
        self.last_frame: Frame | None = None
        self._lock = lock
        self._wake = threading.Condition(lock)
        self._tasks: dict[str, Callable[[], None]] = {}
        self._progress: _Progress | None = None
        self._failed_generation: int | None = None
        self._seconds_per_ray: float | None = None
        self._moving_frames: collections.deque[float] = collections.deque(maxlen=64)
        self._last_frame_seconds: float | None = None
        self._last_pass_seconds: float | None = None
        self._stop = False
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------------------------ thread
    def start(self) -> None:
        """Start the render thread (idempotent)."""
        with self._lock:
            if self._thread is not None:
                return
            self._stop = False
            self._thread = threading.Thread(target=self._run, name="apmgsrn-viewer-render", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the thread after its current chunk of pixels (the caller bumps the generation first)."""
        with self._wake:
            self._stop = True
            self._wake.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout)
        self._thread = None

    def wake(self) -> None:
        """Call with the lock held after the host changed something."""
        self._wake.notify_all()

    def submit(self, key: str, task: Callable[[], None]) -> None:
        """Run a task in the worker's thread before the next pass; a newer task of the same key replaces it."""
        with self._wake:
            self._tasks[key] = task
            self._wake.notify_all()

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._stop and not self._has_work():
                    self._wake.wait(timeout=self.host.wait_seconds())
                if self._stop:
                    return
            try:
                self.step()
            except ApmgsrnError as exc:
                self.host.message("error", str(exc))
            except Exception as exc:  # noqa: BLE001 - the server must survive a failing render
                self.host.message("error", f"rendering failed: {type(exc).__name__}: {exc}")
                with self._lock:
                    self._progress = None
                    self.renderer = None  # rebuilt for the next generation
                    # Wait for the next change instead of retrying the same failing render in a loop.
                    self._failed_generation = self.host.generation

    # ------------------------------------------------------------------------------------ scheduling
    def _has_work(self) -> bool:
        if self._tasks:
            return True
        host = self.host
        if host.source is None or self._failed_generation == host.generation:
            return False
        progress = self._progress
        if progress is None or progress.generation != host.generation:
            return True
        if progress.render.done:
            return False
        return not host.is_moving() or self._fits_budget(progress)

    def _fits_budget(self, progress: _Progress) -> bool:
        """While moving: whether the next pass still fits the interactive time budget."""
        if progress.render.next_pass == 0:
            return True
        if self._seconds_per_ray is None:
            return False
        rays = progress.render.next_pixels.numel()
        return progress.render_seconds + rays * self._seconds_per_ray <= self.config.interactive_seconds

    def idle(self) -> bool:
        """True when nothing is left to do (the current view is complete, nothing pending)."""
        with self._lock:
            return not self._has_work() and not self.host.is_moving()

    def step(self) -> bool:
        """Do the next piece of work: a task, or one pass of the current view.

        Returns:
            True if it did something.
        """
        with self._lock:
            task = self._tasks.pop(next(iter(self._tasks))) if self._tasks else None
        if task is not None:
            task()
            return True
        return self._render_next_pass()

    def run_until_idle(self, timeout: float = 120.0) -> None:
        """Work in the caller's thread until the view is complete (for tests and scripts).

        Raises:
            TimeoutError: still busy after ``timeout`` seconds.
        """
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if not self.step():
                if self.idle():
                    return
                time.sleep(0.01)
        raise TimeoutError("viewer still busy")

    # ------------------------------------------------------------------------------------ rendering
    def adopt(self, source: RenderSource, renderer: VolumeRenderer) -> None:
        """With the lock held: render a newly opened source with a prepared renderer; forget the old view."""
        self.renderer = renderer
        self._renderer_source = source
        self._progress = None
        self.last_frame = None
        self._failed_generation = None

    def _prepare(self) -> tuple[_Progress, bool] | None:
        """With the lock held: the progress of the current generation, and whether the view moves."""
        request = self.host.render_request()
        if request is None:
            return None
        if self._progress is None or self._progress.generation != request.generation:
            renderer = self._renderer_for(request)
            render = ProgressiveRender(renderer, request.camera, self.config.strides)
            self._progress = _Progress(request.generation, render)
        progress = self._progress
        if progress.render.done or (request.moving and not self._fits_budget(progress)):
            return None
        return progress, request.moving

    def _renderer_for(self, request: RenderRequest) -> VolumeRenderer:
        """The renderer of a request: the one in use, with other settings or transfer function if need be."""
        config = request.settings.renderer_config(self.config)
        renderer = self.renderer
        if renderer is None or self._renderer_source is not request.source:
            renderer = request.source.renderer(request.transfer_function, config)
        elif renderer.config != config:
            renderer = renderer.reconfigured(config)  # keeps the bounds (a model's are slow to sample)
        if renderer.transfer_function is not request.transfer_function:
            renderer.set_transfer_function(request.transfer_function)
        self.renderer, self._renderer_source = renderer, request.source
        return renderer

    def _render_next_pass(self) -> bool:
        with self._lock:
            prepared = self._prepare()
        if prepared is None:
            return False
        progress, moving = prepared
        generation = progress.generation
        pixels = progress.render.next_pixels
        pass_start = time.monotonic()
        for start in range(0, pixels.numel(), self.config.chunk_pixels):
            if self.host.generation != generation:
                return True  # a newer view exists: drop this pass
            chunk = pixels[start : start + self.config.chunk_pixels]
            chunk_start = time.monotonic()
            progress.field_evaluations += progress.render.render_pixels(chunk).field_evaluations
            per_ray = (time.monotonic() - chunk_start) / max(1, chunk.numel())
            # Smoothed cost per ray: the budget test of the next interactive pass uses it.
            previous = self._seconds_per_ray
            self._seconds_per_ray = per_ray if previous is None else 0.7 * previous + 0.3 * per_ray
        now = time.monotonic()
        result = progress.render.finish_pass()
        raw = as_uint8(result.image)
        camera = progress.render.camera
        with self._lock:
            if self.host.generation != generation:
                return True  # stale: never shown
            progress.render_seconds += now - pass_start
            image, lines = self.host.overlay(raw, camera)
            frame = Frame(
                generation, image, raw, lines, camera, result.stride, result.pass_index,
                len(progress.render.passes), moving, progress.render_seconds,
            )
            self.last_frame = frame
            self._last_pass_seconds = now - pass_start
            if frame.done:
                self._last_frame_seconds = frame.elapsed
            if moving:
                self._moving_frames.append(now)
        self.host.deliver(frame)
        return True

    def redraw(self) -> None:
        """Hand out the last frame again with the overlay as it is now (no re-render)."""
        with self._lock:
            frame = self.last_frame
            if frame is None or frame.generation != self.host.generation:
                return
            image, lines = self.host.overlay(frame.plain, frame.camera)
            frame = self.last_frame = replace(frame, image=image, lines=lines)
        self.host.deliver(frame)

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
            passes_done=progress.render.next_pass if progress else 0,
            pass_count=len(self.config.strides),
            moving_fps=fps,
            memory=device_memory(self.device),
            field_evaluations=progress.field_evaluations if progress else 0,
        )


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
