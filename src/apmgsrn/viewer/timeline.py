"""The time axis of a time-series model in the viewer: show a step, and play the steps in a loop.

A step is shown by materialising its features once (:meth:`apmgsrn.sources.RenderSource.at_step`) and
preparing its renderer (empty-space bounds sampled for that step) in the worker's thread; the camera,
transfer function and settings stay. Playing advances one step each time the shown step's image is complete
and at least ``interval`` seconds have passed, so every step is seen whole however slow the device.
"""

from __future__ import annotations

import time

from apmgsrn.errors import ApmgsrnError
from apmgsrn.sources import RenderSource
from apmgsrn.viewer.session import ViewerSession
from apmgsrn.viewer.settings import whole_number


class Timeline:
    """Steps of the session's time-series source.

    Args:
        session: the viewer session.
        interval: least seconds between two steps while playing.
    """

    def __init__(self, session: ViewerSession, interval: float = 0.5) -> None:
        self.session = session
        self.interval = float(interval)
        self.playing = False
        self._last_advance = -float("inf")

    def _series_source(self) -> RenderSource:
        source = self.session.source
        if source is None or source.series is None:
            raise ApmgsrnError("the shown model has no time steps; open a time-series model")
        return source

    def request_step(self, step: int) -> None:
        """Show step ``step`` (prepared in the worker; errors come as the session's messages).

        Raises:
            ApmgsrnError: nothing with time steps is shown, or ``step`` is outside the series.
        """
        source = self._series_source()
        step = whole_number(step, 0, source.steps - 1, "time step")
        self.session.worker.submit("step", lambda: self._show_reporting(step))

    def _show_reporting(self, step: int) -> None:
        try:
            self.show_step(step)
        except ApmgsrnError as exc:
            self.session.message("error", str(exc))

    def show_step(self, step: int) -> RenderSource | None:
        """Show step ``step`` now, in the caller's thread (the worker's, or a test's).

        Returns:
            The source shown, or None when another source was opened meanwhile.
        """
        current = self._series_source()
        if step == current.step:
            return current
        source = current.at_step(step)
        settings = self.session.settings
        renderer = source.renderer(self.session.transfer_function(), settings.renderer_config(self.session.config))
        renderer.ensure_bounds()  # this step's empty space: another step's would hide what moved
        return source if self.session.swap_source(current, source, renderer) else None

    def next_step(self, now: float | None = None) -> int | None:
        """While playing: the step to show next once the shown one is rendered whole, else None.

        Args:
            now: the time (``time.monotonic()``), for tests.
        """
        source = self.session.source
        if not self.playing or source is None or source.series is None:
            return None
        now = time.monotonic() if now is None else now
        frame = self.session.last_frame
        complete = frame is not None and frame.done and frame.generation == self.session.generation
        if not complete or now - self._last_advance < self.interval:
            return None
        self._last_advance = now
        return (source.step + 1) % source.steps
