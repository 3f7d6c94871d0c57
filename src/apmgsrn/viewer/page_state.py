"""The page's shared state (trame's), kept in step with the session from whatever thread reports a change.

The session calls back from its worker thread; trame's state belongs to its asyncio loop. Every update
is therefore handed to the loop with ``call_soon_threadsafe`` (or applied at once on the loop itself).
Frames travel as data URLs: JPEG while a view is still being refined (small and fast over an SSH tunnel),
PNG once it is complete; the overlay travels as line segments the page draws as SVG.

The state is the server's: every page of one viewer shows the same view, and a page may change only
the controls of :meth:`PageState.accepts`, each to a value the server offers (a listed file, an offered
colour map) or would take (a size in range); everything else it sends is dropped before another page
or the session sees it (see :mod:`apmgsrn.viewer.guard`).
"""

from __future__ import annotations

import asyncio
import base64
import math

import torch

from apmgsrn.sources import RenderSource
from apmgsrn.viewer.catalog import CatalogEntry, SkippedFile
from apmgsrn.viewer.files import encode_image
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import PAGE, editor_points
from apmgsrn.viewer.worker import Frame


class PageState:
    """Writes the session's frames, messages and sources into the page's state."""

    def __init__(self, state, session: ViewerSession, device: torch.device) -> None:
        """Args:
        state: trame's shared state.
        session: the viewer session (its callbacks should be this object's ``on_frame``/``on_message``).
        device: the render device (shown in the statistics).
        """
        self.state = state
        self.session = session
        self.device = device
        self.loop: asyncio.AbstractEventLoop | None = None  # set once the server runs
        self._shown_generation = -1
        self._listed: frozenset[str] = frozenset()
        self._rules = {
            "source_name": lambda name: name is None or (isinstance(name, str) and name in self._listed),
            "colormap": lambda key: isinstance(key, str) and key in self.session.colormaps.keys(),
            "value_range": _is_range,
            "samples_per_ray": lambda value: _is_whole(value, PAGE.samples_per_ray),
            "batch_size": lambda value: _is_whole(value, PAGE.batch_size),
            "image_size": lambda value: _is_whole(value, PAGE.image_size),
            "overlay": lambda value: isinstance(value, bool),
            "time_step": lambda value: _is_whole(value, (0, self._shown_steps() - 1)),
            "time_playing": lambda value: isinstance(value, bool),
            # The messages are the server's; a page may only close them.
            "error_message": lambda text: text == "",
            "saved_message": lambda text: text == "",
        }

    def _shown_steps(self) -> int:
        """Time steps of the shown source (1 for anything but a time-series model)."""
        source = self.session.source
        return 1 if source is None else source.steps

    def accepts(self, key: str, value: object) -> bool:
        """Whether a page may set state ``key`` to ``value`` (see the module notes)."""
        rule = self._rules.get(key)
        return rule is not None and bool(rule(value))

    def initialize(
        self, viewable: list[CatalogEntry], skipped: list[SkippedFile], title: str, upload_limit: int
    ) -> None:
        """The state the page starts with.

        Args:
            viewable: the models and volumes the picker offers (the only names a page may pick).
            skipped: files under PATH that are not listed, and why.
            title: the page's title.
            upload_limit: bytes an uploaded preset may have.
        """
        settings = self.session.settings
        self._listed = frozenset(e.name for e in viewable)
        self.state.client_only("upload_error")  # the page's own note on a file it did not send
        self.state.update(
            {
                "entries": [{"title": f"{e.name}  ({e.kind})", "value": e.name} for e in viewable],
                "skipped_files": [f"{s.name}: {s.reason}" for s in skipped[:200]],
                "skipped_count": len(skipped),
                "upload_error": "",
                "source_name": None,
                "source_description": "no model or volume opened",
                "colormaps": self.session.colormap_keys(),
                "colormap": settings.colormap,
                "opacity_points": editor_points(settings.opacity),
                "histogram": [],
                "data_min": 0.0,
                "data_max": 1.0,
                "value_step": 0.01,
                "value_range": [0.0, 1.0],
                "samples_per_ray": settings.samples_per_ray,
                "batch_size": settings.batch_size,
                "batch_sizes": list(PAGE.batch_sizes),
                "image_size": settings.image_width,
                "image_sizes": list(PAGE.image_sizes),
                "overlay": False,
                "overlay_available": False,
                "frame_src": "",
                "frame_generation": -1,
                "frame_stride": 0,
                "frame_width": settings.image_width,
                "frame_height": settings.image_height,
                "overlay_lines": [],
                "stats_text": "",
                "error_message": "",
                "status_message": "",
                "saved_message": "",
                "upload_limit": upload_limit,
                "time_steps": 1,
                "time_step": 0,
                "time_playing": False,
                "time_label": "",
                "trame__title": title,
            }
        )

    def push(self, updates: dict) -> None:
        """Apply state updates on the loop (safe from any thread)."""

        def apply() -> None:
            with self.state:
                self.state.update(updates)

        if self.loop is None:
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is self.loop:
            apply()
        else:
            self.loop.call_soon_threadsafe(apply)

    def on_frame(self, frame: Frame) -> None:
        """Session callback: show a frame."""
        # The page gets the plain image and draws the overlay as SVG, crisp at any display size.
        data = base64.b64encode(encode_image(frame.plain, lossless=frame.done)).decode("ascii")
        kind = "png" if frame.done else "jpeg"
        updates = {
            "frame_src": f"data:image/{kind};base64,{data}",
            "frame_generation": frame.generation,
            "frame_stride": frame.stride,
            "frame_width": frame.camera.width,
            "frame_height": frame.camera.height,
            # SVG units: pixel c spans [c, c + 1], so a pixel-index coordinate moves by half a pixel.
            "overlay_lines": [
                [round(x0 + 0.5, 2), round(y0 + 0.5, 2), round(x1 + 0.5, 2), round(y1 + 0.5, 2),
                 "#{:02x}{:02x}{:02x}".format(*color)]
                for x0, y0, x1, y1, color in frame.lines
            ],
            "stats_text": self._statistics_text(frame),
        }
        if frame.done:
            updates["status_message"] = ""

        def apply() -> None:
            # Frames arrive in order from the one worker; this guard keeps it so if that ever changes.
            if frame.generation < self._shown_generation:
                return
            self._shown_generation = frame.generation
            with self.state:
                self.state.update(updates)

        if self.loop is not None:
            self.loop.call_soon_threadsafe(apply)

    def _statistics_text(self, frame: Frame) -> str:
        stats = self.session.statistics()
        last = f"{stats.last_frame_seconds:.2f} s" if stats.last_frame_seconds is not None else "-"
        fps = f"{stats.moving_fps:.1f}" if stats.moving_fps is not None else "-"
        return (
            f"last full frame {last}   this pass {stats.last_pass_seconds or 0:.2f} s\n"
            f"passes {frame.pass_index + 1}/{frame.pass_count} (stride {frame.stride})   "
            f"fps while moving {fps}\n"
            f"{frame.camera.width}x{frame.camera.height} px   field evaluations {stats.field_evaluations:,}\n"
            f"{stats.memory}   device {self.device}"
        )

    def on_message(self, kind: str, payload: object) -> None:
        """Session callback: an error, a status line, or a newly opened source."""
        if kind == "error":
            # The picker goes back to what is shown (a file that failed to open is not shown).
            current = self.session.source.name if self.session.source is not None else None
            self.push({"error_message": str(payload), "status_message": "", "source_name": current})
        elif kind == "status":
            self.push({"status_message": str(payload)})
        elif kind == "source" and isinstance(payload, RenderSource):
            self.push(self._source_state(payload))
        elif kind == "step" and isinstance(payload, RenderSource):
            self.push({**_time_state(payload), "source_description": f"{payload.name}: {payload.description}"})

    def _source_state(self, source: RenderSource) -> dict:
        low, high = self.session.settings.value_range
        return {
            "source_name": source.name,
            "source_description": f"{source.name}: {source.description}",
            "histogram": source.histogram,
            "data_min": low,
            "data_max": high,
            "value_step": (high - low) / 1000.0,
            "value_range": [low, high],
            "overlay_available": source.grid_boxes is not None or source.brick_boxes is not None,
            "error_message": "",
            "status_message": "rendering",
            **_time_state(source),
        }


def _time_state(source: RenderSource) -> dict:
    """The time slider's state: steps, the one shown and its number (one step: the slider hides)."""
    label = f"step {source.step} of {source.steps} (number {source.step_labels[source.step]:g})" \
        if source.series is not None else ""
    return {"time_steps": source.steps, "time_step": source.step, "time_label": label}


def _is_whole(value: object, limits: tuple[int, int]) -> bool:
    """A whole number (``5`` or ``5.0``, not ``True``) within ``limits``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return math.isfinite(value) and value == int(value) and limits[0] <= value <= limits[1]


def _is_range(value: object) -> bool:
    """Two finite numbers, the first below the second."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        return False
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in value):
        return False
    return value[0] < value[1]
