"""The web page (trame + Vuetify), a thin layer over :class:`apmgsrn.viewer.session.ViewerSession`.

Threads. trame runs an asyncio loop; the page's events (triggers and state changes) arrive on it and
only change the session, which is cheap. Rendering, opening files and image encoding happen in the
session's worker thread; :class:`PageState` hands each result to the loop, so the loop never waits for
the field. The layout is :func:`build_page`'s, saved files :class:`SaveFolder`'s, and what the server
takes from the network :class:`ConnectionGuard`'s.
"""

from __future__ import annotations

import asyncio
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.viewer.catalog import MODEL, PRESET, VOLUME, Catalog, SkippedFile
from apmgsrn.viewer.files import SaveFolder, safe_stem, uploaded_presets
from apmgsrn.viewer.guard import ConnectionGuard, GuardConfig, is_loopback_name, new_secret
from apmgsrn.viewer.layout import build_page
from apmgsrn.viewer.page_state import PageState
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import ViewerConfig
from apmgsrn.viewer.timeline import Timeline


@dataclass(frozen=True)
class ViewerAppConfig:
    """How the page is served."""

    host: str = "127.0.0.1"
    port: int = 8080
    save_directory: Path = Path("apmgsrn-view")  # server-side copies of saved frames and transfer functions
    max_upload_bytes: int = 1 << 20  # ParaView presets are a few kB; anything near this is not one
    message_margin_bytes: int = 64 * 1024  # a message's framing beside an upload (file name, RPC name, headers)
    title: str = "apmgsrn viewer"
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


class ViewerApp:
    """The trame server of one viewer: page events to the session, the session's results to the page."""

    def __init__(
        self, catalog: Catalog, device: torch.device | str = "cpu", config: ViewerAppConfig = ViewerAppConfig()
    ):
        """Args:
        catalog: what may be listed and opened.
        device: where to render.
        config: serving settings.
        """
        from trame.app import get_server  # the optional [viewer] extra

        self.catalog = catalog
        self.config = config
        self.device = torch.device(device)
        message_bytes = config.max_upload_bytes + config.message_margin_bytes
        # ws_max_msg_size: aiohttp's limit on one websocket frame (the guard caps the whole message).
        self.server = get_server(f"apmgsrn-viewer-{id(self)}", client_type="vue3", ws_max_msg_size=message_bytes)
        self.state = self.server.state
        self.controller = self.server.controller
        self.session = ViewerSession(catalog, self.device, config.viewer)
        self.page = PageState(self.state, self.session, self.device)
        self.session.on_frame = self.page.on_frame
        self.session.on_message = self.page.on_message
        self.timeline = Timeline(self.session)
        self.guard = ConnectionGuard(
            new_secret(),
            GuardConfig(message_bytes=message_bytes, loopback_only=is_loopback_name(config.host)),
            self.page.accepts,
        )
        self.controller.on_server_bind.add(self.guard.install)
        self.saves = SaveFolder(config.save_directory)
        self.skipped: list[SkippedFile] = list(catalog.skipped)
        self._first_entry = self._offer_entries()
        self._register_handlers()
        self.layout = build_page(self.server, config.title, self.session.settings)

    def _offer_entries(self) -> str | None:
        """Presets of the catalog become colour maps; models and volumes the picker's entries. Returns the first.

        A preset file that cannot be read is left out and added to :attr:`skipped`.
        """
        entries = self.catalog.entries()
        for entry in entries:
            if entry.kind != PRESET:
                continue
            # Presets are a few kB: a huge .json beside the data is something else and is not read.
            if entry.size_bytes > self.config.max_upload_bytes:
                self.skipped.append(SkippedFile(entry.name, f"larger than {self.config.max_upload_bytes:,} bytes"))
                continue
            try:
                path = self.catalog.resolve(entry.name, (PRESET,))
                self.session.add_presets(path, entry.name)
            except ApmgsrnError as exc:  # the message starts with the file's path: the listing names it
                self.skipped.append(SkippedFile(entry.name, str(exc).split(": ", 1)[-1]))
        viewable = [e for e in entries if e.kind in (MODEL, VOLUME)]
        self.page.initialize(viewable, self.skipped, self.config.title, self.config.max_upload_bytes)
        return viewable[0].name if viewable else None

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
                state.opacity_points = clean

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
                    state.opacity_points = self.session.set_colormap(colormap)

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

        @state.change("time_step")
        def time_step_changed(time_step, **_):
            source = self.session.source
            if source is not None and source.series is not None and time_step is not None \
                    and int(time_step) != source.step:
                self._guard(self.timeline.request_step, time_step)

        @state.change("time_playing")
        def playing_changed(time_playing, **_):
            self.timeline.playing = bool(time_playing)

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
        saved = self.saves.save_frame(frame, self.session.source)
        self.state.saved_message = f"saved {saved['path']}" + ("" if frame.done else " (still refining: a coarse pass)")
        return saved

    def _save_transfer_function(self) -> dict:
        saved = self.saves.save_transfer_function(self.session.transfer_function(), self.session.source)
        self.state.saved_message = f"saved {saved['path']}"
        return saved

    def _upload_preset(self, name, text) -> None:
        presets = uploaded_presets(name, text, self.config.max_upload_bytes)  # JSON/XML parsing, in memory
        keys = self.session.colormaps.add_presets(presets, f"uploaded {safe_stem(name)}")
        self.state.colormaps = self.session.colormap_keys()
        self.state.colormap = keys[0]
        self.state.error_message = ""
        self.state.saved_message = f"added {len(keys)} colour map(s) from {name}"

    async def _play(self) -> None:
        """While playing, move to the next step whenever the shown one is rendered whole."""
        while True:
            await asyncio.sleep(0.1)
            step = self.timeline.next_step()
            if step is not None:
                self._guard(self.timeline.request_step, step)

    def _on_ready(self, **_) -> None:
        self.page.loop = asyncio.get_event_loop()
        self._player = self.page.loop.create_task(self._play())
        self.session.start()
        if self._first_entry is not None:
            self.state.source_name = self._first_entry
            self.state.flush()

    # ------------------------------------------------------------------------------------ serving
    def serve(self) -> None:
        """Serve until interrupted (blocking)."""
        # trame reads its options from sys.argv or $TRAME_ARGS: hide both, so host, port and secret are
        # this app's alone (a TRAME_ARGS meant for another app must not rebind the viewer to 0.0.0.0).
        saved_argv, saved_trame_args = sys.argv, os.environ.pop("TRAME_ARGS", None)
        sys.argv = [saved_argv[0]]
        self.server.cli.set_defaults(authKey=self.guard.secret)
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
            if saved_trame_args is not None:
                os.environ["TRAME_ARGS"] = saved_trame_args
            self.session.stop()
