"""The web page (trame + Vuetify), a thin layer over :class:`apmgsrn.viewer.session.ViewerSession`.

Threads. trame runs an asyncio loop; the page's events (triggers and state changes) arrive on it and
only change the session, which is cheap. Rendering, opening files and image encoding happen in the
session's worker thread; each finished pass is encoded there and handed to the loop with
``call_soon_threadsafe``, so the loop never waits for the field.

Frames travel as data URLs in the shared state: JPEG while a view is still being refined (small and
fast over an SSH tunnel), PNG once it is complete.
"""

from __future__ import annotations

import asyncio
import base64
import io
import re
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.render import save_transfer_function
from apmgsrn.viewer.catalog import MODEL, PRESET, VOLUME, Catalog
from apmgsrn.viewer.session import Frame, ViewerConfig, ViewerSession
from apmgsrn.viewer.sources import ViewSource
from apmgsrn.viewer.webpage import VIEWER_SCRIPT, VIEWER_STYLE

IMAGE_SIZES = (128, 192, 256, 384, 512, 768, 1024)
BATCH_SIZES = tuple(1 << k for k in range(12, 23))  # 4096 .. 4194304 points per forward pass


@dataclass(frozen=True)
class ViewerAppConfig:
    """How the page is served."""

    host: str = "127.0.0.1"
    port: int = 8080
    save_directory: Path = Path("apmgsrn-view")  # server-side copies of saved frames and transfer functions
    max_upload_bytes: int = 1 << 20  # ParaView presets are a few kB; anything near this is not one
    title: str = "apmgsrn viewer"
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


def encode_image(image: np.ndarray, lossless: bool) -> bytes:
    """PNG (lossless) or JPEG bytes of an ``[H, W, 3]`` uint8 image.

    Args:
        image: the frame.
        lossless: PNG when True, else JPEG at quality 85.

    Returns:
        The encoded file's bytes.
    """
    from PIL import Image

    buffer = io.BytesIO()
    picture = Image.fromarray(np.ascontiguousarray(image))
    if lossless:
        picture.save(buffer, format="PNG", compress_level=3)
    else:
        picture.save(buffer, format="JPEG", quality=85)
    return buffer.getvalue()


def _safe_stem(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("._") or "view"


class ViewerApp:
    """The trame server of one viewer."""

    def __init__(
        self, catalog: Catalog, device: torch.device | str = "cpu", config: ViewerAppConfig = ViewerAppConfig()
    ):
        """Args:
        catalog: what may be listed and opened.
        device: where to render.
        config: serving settings.
        """
        from trame.app import get_server

        self.catalog = catalog
        self.config = config
        self.device = torch.device(device)
        self.server = get_server(f"apmgsrn-viewer-{id(self)}", client_type="vue3")
        self.state = self.server.state
        self.controller = self.server.controller
        self.session = ViewerSession(
            catalog, self.device, config.viewer, on_frame=self._on_frame, on_message=self._on_message
        )
        self._loop: asyncio.AbstractEventLoop | None = None
        self._shown_generation = -1
        self._upload_directory = Path(tempfile.mkdtemp(prefix="apmgsrn-view-uploads-"))
        self._uploads = 0
        self._initial_state()
        self._register_handlers()
        self._build_page()

    # ------------------------------------------------------------------------------------ state
    def _initial_state(self) -> None:
        entries = self.catalog.entries()
        for entry in entries:
            # Presets are a few kB: a huge .json beside the data is something else and is not read.
            if entry.kind == PRESET and entry.size_bytes <= self.config.max_upload_bytes:
                try:
                    self.session.add_presets(self.catalog.resolve(entry.name, (PRESET,)), entry.name)
                except ApmgsrnError:
                    continue  # a JSON file that is no preset is simply not offered
        viewable = [e for e in entries if e.kind in (MODEL, VOLUME)]
        settings = self.session.settings
        self.state.update(
            {
                "entries": [{"title": f"{e.name}  ({e.kind})", "value": e.name} for e in viewable],
                "source_name": None,
                "source_description": "no model or volume opened",
                "colormaps": self.session.colormap_keys(),
                "colormap": settings.colormap,
                "opacity_points": [list(p) for p in settings.opacity],
                "histogram": [],
                "data_min": 0.0,
                "data_max": 1.0,
                "value_step": 0.01,
                "value_range": [0.0, 1.0],
                "samples_per_ray": settings.samples_per_ray,
                "batch_size": settings.batch_size,
                "batch_sizes": list(BATCH_SIZES),
                "image_size": settings.image_width,
                "image_sizes": list(IMAGE_SIZES),
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
                "upload_limit": self.config.max_upload_bytes,
                "trame__title": self.config.title,
            }
        )
        self._first_entry = viewable[0].name if viewable else None

    def _push(self, updates: dict) -> None:
        """Apply state updates on the loop (safe from any thread)."""

        def apply() -> None:
            with self.state:
                self.state.update(updates)

        if self._loop is None:
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is self._loop:
            apply()
        else:
            self._loop.call_soon_threadsafe(apply)

    # ------------------------------------------------------------------------------------ session callbacks
    def _on_frame(self, frame: Frame) -> None:
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

        if self._loop is not None:
            self._loop.call_soon_threadsafe(apply)

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

    def _on_message(self, kind: str, payload: object) -> None:
        if kind == "error":
            # The picker goes back to what is shown (a file that failed to open is not shown).
            current = self.session.source.name if self.session.source is not None else None
            self._push({"error_message": str(payload), "status_message": "", "source_name": current})
        elif kind == "status":
            self._push({"status_message": str(payload)})
        elif kind == "source" and isinstance(payload, ViewSource):
            self._push(self._source_state(payload))

    def _source_state(self, source: ViewSource) -> dict:
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
        }

    # ------------------------------------------------------------------------------------ page events
    def _register_handlers(self) -> None:
        state, controller = self.state, self.controller

        @controller.trigger("viewer_camera")
        def camera(orbit_x=0.0, orbit_y=0.0, pan_x=0.0, pan_y=0.0, zoom=0.0, end=False, reset=False):
            self._guard(self._camera, orbit_x, orbit_y, pan_x, pan_y, zoom, end, reset)

        @controller.trigger("viewer_opacity")
        def opacity(points, interactive=False):
            def apply():
                clean = self.session.set_opacity(points, moving=bool(interactive))
                if not interactive:
                    self.session.end_interaction()
                state.opacity_points = [list(p) for p in clean]

            self._guard(apply)

        @controller.trigger("viewer_open")
        def open_entry(name):
            """Open by name (the page's picker uses the state; scripts and tests may call this)."""
            self._guard(self._open, name)

        @controller.trigger("viewer_save_frame")
        def save_frame():
            return self._guard(self._save_frame)

        @controller.trigger("viewer_save_transfer_function")
        def save_tf():
            return self._guard(self._save_transfer_function)

        @controller.trigger("viewer_upload_preset")
        def upload(name, text):
            self._guard(self._upload_preset, name, text)

        @controller.trigger("viewer_reset_view")
        def reset_view():
            self._guard(self.session.reset_view)

        @state.change("source_name")
        def source_changed(source_name, **_):
            current = self.session.source.name if self.session.source else None
            if source_name and source_name != current:
                self._guard(self._open, source_name)

        @state.change("colormap")
        def colormap_changed(colormap, **_):
            if colormap and colormap != self.session.settings.colormap:
                def apply():
                    points = self.session.set_colormap(colormap)
                    state.opacity_points = [list(p) for p in points]

                self._guard(apply)

        @state.change("value_range")
        def range_changed(value_range, **_):
            if isinstance(value_range, (list, tuple)) and len(value_range) == 2:
                if tuple(float(v) for v in value_range) != self.session.settings.value_range:
                    self._guard(self.session.set_value_range, value_range[0], value_range[1])

        @state.change("samples_per_ray")
        def spp_changed(samples_per_ray, **_):
            if samples_per_ray is not None and int(samples_per_ray) != self.session.settings.samples_per_ray:
                self._guard(self.session.set_samples_per_ray, samples_per_ray)

        @state.change("batch_size")
        def batch_changed(batch_size, **_):
            if batch_size is not None and int(batch_size) != self.session.settings.batch_size:
                self._guard(self.session.set_batch_size, batch_size)

        @state.change("image_size")
        def size_changed(image_size, **_):
            if image_size is not None and int(image_size) != self.session.settings.image_width:
                self._guard(self.session.set_image_size, image_size, image_size)

        @state.change("overlay")
        def overlay_changed(overlay, **_):
            if bool(overlay) != self.session.settings.overlay:
                self._guard(self.session.set_overlay, bool(overlay))

        controller.on_server_ready.add(self._on_ready)

    def _guard(self, function, *args):
        """Run a page request; a user error becomes the page's error line, never a dead server."""
        try:
            return function(*args)
        except ApmgsrnError as exc:
            self.state.error_message = str(exc)
        except Exception as exc:  # noqa: BLE001 - report, keep serving
            self.state.error_message = f"{type(exc).__name__}: {exc}"
        return None

    def _camera(self, orbit_x, orbit_y, pan_x, pan_y, zoom, end, reset=False) -> None:
        if reset:  # first: the page drops motion queued before a reset, motion after it comes along
            self.session.reset_view()
        if orbit_x or orbit_y:
            self.session.orbit(orbit_x, orbit_y)
        if pan_x or pan_y:
            self.session.pan(pan_x, pan_y)
        if zoom:
            self.session.zoom(zoom)
        if end:
            self.session.end_interaction()

    def _open(self, name: str) -> None:
        self.state.error_message = ""
        try:
            self.session.request_open(name)
        except ApmgsrnError:
            # Put the picker back on what is shown, then report.
            self.state.source_name = self.session.source.name if self.session.source else None
            raise
        self.state.status_message = f"opening {name}"

    def _save_frame(self) -> dict:
        frame = self.session.last_frame
        if frame is None:
            raise ApmgsrnError("no image yet: open a model or a volume first")
        source = self.session.source
        stem = _safe_stem(Path(source.name).stem if source else "view")
        name = f"{stem}_{time.strftime('%Y%m%d-%H%M%S')}_{frame.generation}.png"
        data = encode_image(frame.image, lossless=True)
        path = self._write(name, data)
        self.state.saved_message = f"saved {path}" + ("" if frame.done else " (still refining: a coarse pass)")
        return {"name": name, "data": base64.b64encode(data).decode("ascii"), "path": str(path)}

    def _save_transfer_function(self) -> dict:
        transfer_function = self.session.transfer_function()
        source = self.session.source
        stem = _safe_stem(Path(source.name).stem if source else "view")
        name = f"{stem}_transfer_function_{time.strftime('%Y%m%d-%H%M%S')}.json"
        directory = self._save_directory()
        path = save_transfer_function(transfer_function, directory / name, name=f"apmgsrn {stem}")
        self.state.saved_message = f"saved {path}"
        return {"name": name, "data": base64.b64encode(path.read_bytes()).decode("ascii"), "path": str(path)}

    def _save_directory(self) -> Path:
        directory = Path(self.config.save_directory)
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ApmgsrnError(
                f"{directory}: cannot create the save folder ({exc.strerror}); pass another --save-dir"
            ) from None
        return directory

    def _write(self, name: str, data: bytes) -> Path:
        path = self._save_directory() / name
        temporary = path.with_name(f".{path.name}.tmp")
        temporary.write_bytes(data)
        temporary.replace(path)  # atomic: a reader never sees half a PNG
        return path

    def _upload_preset(self, name, text) -> None:
        if not isinstance(name, str) or not isinstance(text, str):
            raise ApmgsrnError("upload refused: expected a file name and its text")
        if len(text.encode("utf-8")) > self.config.max_upload_bytes:
            raise ApmgsrnError(
                f"{name}: larger than the upload limit of {self.config.max_upload_bytes:,} bytes; not a preset"
            )
        if not name.lower().endswith(".json"):
            raise ApmgsrnError(f"{name}: upload a ParaView colour-map preset (.json)")
        self._uploads += 1
        # Written under our own name in our own folder: the uploaded name is a label only.
        path = self._upload_directory / f"upload_{self._uploads}.json"
        path.write_text(text, encoding="utf-8")
        keys = self.session.add_presets(path, f"uploaded {_safe_stem(name)}")  # JSON parsing only
        self.state.colormaps = self.session.colormap_keys()
        self.state.colormap = keys[0]
        self.state.error_message = ""
        self.state.saved_message = f"added {len(keys)} colour map(s) from {name}"

    def _on_ready(self, **_) -> None:
        self._loop = asyncio.get_event_loop()
        self.session.start()
        if self._first_entry is not None:
            self.state.source_name = self._first_entry
            self.state.flush()

    # ------------------------------------------------------------------------------------ layout
    def _build_page(self) -> None:
        from trame.ui.vuetify3 import VAppLayout
        from trame.widgets import client, html
        from trame_client.widgets.core import HtmlElement
        from trame.widgets import vuetify3 as v

        with VAppLayout(self.server, full_height=True) as layout:
            client.Style(VIEWER_STYLE)
            client.Script(VIEWER_SCRIPT)
            with v.VAppBar(density="compact", elevation=1):
                html.Div(self.config.title, classes="text-h6 ml-4 mr-6", id="apm-title")
                html.Div("{{ source_description }}", classes="text-body-2 text-medium-emphasis", id="apm-source")
                v.VSpacer()
                v.VSwitch(
                    v_model=("overlay", False),
                    label="grids & bricks",
                    disabled=("!overlay_available",),
                    hide_details=True,
                    density="compact",
                    color="primary",
                    classes="mr-4 flex-grow-0",
                    id="apm-overlay-switch",
                )
                v.VBtn("reset view", click="window.apmgsrnViewer.resetView()", variant="text", id="apm-reset")
                v.VBtn("save PNG", click="window.apmgsrnViewer.saveFrame()", variant="text", id="apm-save-frame")
                v.VBtn(
                    "save TF (.json)",
                    click="window.apmgsrnViewer.saveTransferFunction()",
                    variant="text",
                    id="apm-save-tf",
                )
            with v.VNavigationDrawer(permanent=True, width=340, location="left"):
                with html.Div(classes="pa-3"):
                    html.Div("data", classes="apm-section")
                    v.VSelect(
                        v_model=("source_name", None),
                        items=("entries", []),
                        label="model or volume",
                        density="compact",
                        hide_details=True,
                        id="apm-source-select",
                    )
                    html.Div("colour map", classes="apm-section")
                    with html.Div(classes="d-flex align-center"):
                        v.VSelect(
                            v_model=("colormap", self.session.settings.colormap),
                            items=("colormaps", []),
                            density="compact",
                            hide_details=True,
                            id="apm-colormap-select",
                        )
                        v.VBtn(
                            "upload",
                            click="window.apmgsrnViewer.chooseUpload()",
                            variant="text",
                            size="small",
                            id="apm-upload-button",
                        )
                        html.Input(type="file", accept=".json,application/json", id="apm-upload", style="display:none")
                    html.Div("opacity", classes="apm-section")
                    html.Div(id="apm-tf-editor")
                    html.Div(
                        "click: add point · drag: move · double-click or right-click: delete",
                        classes="text-caption text-medium-emphasis",
                    )
                    html.Div("value range", classes="apm-section")
                    v.VRangeSlider(
                        v_model=("value_range", [0.0, 1.0]),
                        min=("data_min",),
                        max=("data_max",),
                        step=("value_step",),
                        hide_details=True,
                        density="compact",
                        id="apm-range",
                    )
                    html.Div(
                        "{{ Number(value_range[0]).toPrecision(4) }} … {{ Number(value_range[1]).toPrecision(4) }}",
                        classes="text-caption",
                    )
                    html.Div("sampling", classes="apm-section")
                    v.VSlider(
                        v_model=("samples_per_ray", self.session.settings.samples_per_ray),
                        min=8,
                        max=512,
                        step=8,
                        label="samples / ray",
                        thumb_label=True,
                        hide_details=True,
                        density="compact",
                        id="apm-spp",
                    )
                    v.VSelect(
                        v_model=("batch_size", self.session.settings.batch_size),
                        items=("batch_sizes", []),
                        label="batch size (points per pass)",
                        density="compact",
                        hide_details=True,
                        classes="mt-2",
                        id="apm-batch",
                    )
                    v.VSelect(
                        v_model=("image_size", self.session.settings.image_width),
                        items=("image_sizes", []),
                        label="image size (pixels)",
                        density="compact",
                        hide_details=True,
                        classes="mt-2",
                        id="apm-image-size",
                    )
                    html.Div("statistics", classes="apm-section")
                    html.Pre("{{ stats_text }}", classes="text-caption", style="white-space: pre-wrap", id="apm-stats")
            with v.VMain(), html.Div(id="apm-viewport"):
                with html.Div(id="apm-messages"):
                    v.VAlert(
                        "{{ error_message }}",
                        v_if="error_message",
                        type="error",
                        density="compact",
                        closable=True,
                        click_close="error_message = ''",
                        id="apm-error",
                        classes="mb-1",
                    )
                    v.VAlert(
                        "{{ saved_message }}",
                        v_if="saved_message",
                        type="success",
                        density="compact",
                        closable=True,
                        click_close="saved_message = ''",
                        id="apm-saved",
                    )
                html.Img(
                    src=("frame_src",),
                    v_show="frame_src",
                    id="apm-frame",
                    draggable="false",
                    raw_attrs=[':data-generation="frame_generation"', ':data-stride="frame_stride"'],
                )
                with html.Svg(
                    id="apm-overlay-svg",
                    v_show="frame_src && overlay_lines.length",
                    raw_attrs=[
                        ':viewBox="`0 0 ${frame_width} ${frame_height}`"',
                        'preserveAspectRatio="xMidYMid meet"',
                    ],
                ):
                    HtmlElement(
                        "line",
                        v_for="(line, index) in overlay_lines",
                        key="index",
                        raw_attrs=[
                            ':x1="line[0]"', ':y1="line[1]"', ':x2="line[2]"', ':y2="line[3]"', ':stroke="line[4]"',
                            'stroke-width="1.5"', 'vector-effect="non-scaling-stroke"',
                        ],
                    )
                html.Div(
                    "{{ status_message || 'left drag: orbit · shift/middle drag: pan · wheel: zoom' }}",
                    id="apm-overlay-text",
                )
        self.layout = layout

    # ------------------------------------------------------------------------------------ serving
    def serve(self) -> None:
        """Serve until interrupted (blocking)."""
        # trame reads sys.argv for its own options: hide ours from it.
        saved_argv = sys.argv
        sys.argv = [saved_argv[0]]
        try:
            self.server.start(
                port=self.config.port,
                host=self.config.host,
                open_browser=False,
                show_connection_info=False,
                timeout=0,  # never stop on its own when the last page closes
                disable_logging=True,
            )
        finally:
            sys.argv = saved_argv
            self.session.stop()
