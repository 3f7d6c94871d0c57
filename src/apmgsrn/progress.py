"""Progress of long work, shown where the user is looking.

- a terminal: a tqdm bar on stderr (redrawn in place);
- a Jupyter notebook: ``tqdm.auto``'s widget;
- anything else (a Slurm log, a pipe, CI): one plain line every ~10 seconds and one at the end, so a log
  read while the job runs tells how far it got and how long it has left.

:class:`Progress` is a context manager taking a total and a unit; training, evaluation, decoding and brick
runs all use it. ``APMGSRN_PROGRESS_SECONDS`` sets the interval of the plain lines (default 10).
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import TextIO

from tqdm import tqdm as terminal_tqdm

#: Environment variable: seconds between progress lines when stderr is not a terminal.
INTERVAL_VARIABLE = "APMGSRN_PROGRESS_SECONDS"
MODES = ("terminal", "notebook", "lines", "off")


def progress_mode(stream: TextIO) -> str:
    """How to show progress on ``stream``: ``"notebook"`` inside a Jupyter kernel, ``"terminal"`` when
    the stream is a terminal, else ``"lines"``.

    Args:
        stream: where the progress goes (usually ``sys.stderr``).

    Returns:
        One of :data:`MODES` (never ``"off"``).
    """
    if _in_jupyter_kernel():
        return "notebook"
    try:
        return "terminal" if stream.isatty() else "lines"
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return "lines"


def _in_jupyter_kernel() -> bool:
    # Only look if IPython is already loaded: importing it here would cost every command half a second.
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None and hasattr(ipython, "get_ipython") else None
    return shell is not None and "IPKernelApp" in getattr(shell, "config", {})


def interval_seconds() -> float:
    """Seconds between plain progress lines (``APMGSRN_PROGRESS_SECONDS``, default 10)."""
    try:
        value = float(os.environ.get(INTERVAL_VARIABLE, ""))
    except ValueError:
        value = math.nan
    return value if value >= 0 and math.isfinite(value) else 10.0


class Progress:
    """Progress of ``total`` units of work.

    Use as a context manager; the final line (plain-line mode) is written only when the block ends
    without an exception, so an error message stays the last line the user sees.

    Args:
        total: units of work in all.
        unit: name of a unit (``"it"``, ``"voxel"``, ``"brick"``).
        description: what is being done (``"train"``, ``"eval"``).
        initial: units already done (a resumed run).
        enabled: False shows nothing.
        stream: where to write (default: stderr, so that ``--json`` output on stdout stays clean).
        mode: one of :data:`MODES`; None: :func:`progress_mode` of the stream.
    """

    def __init__(
        self,
        total: int,
        unit: str = "it",
        description: str = "",
        initial: int = 0,
        enabled: bool = True,
        stream: TextIO | None = None,
        mode: str | None = None,
    ):
        self.stream = stream if stream is not None else sys.stderr
        self.mode = "off" if not enabled else (mode or progress_mode(self.stream))
        if self.mode not in MODES:
            raise ValueError(f"progress mode must be one of {MODES}")
        self.total = int(total)
        self.unit = unit
        self.description = description
        self.initial = self.count = int(initial)
        self.fields: dict[str, str] = {}
        self.interval = interval_seconds()
        self._started = time.monotonic()
        self._next_line = self._started + self.interval
        self._bar = None
        if self.mode in ("terminal", "notebook"):
            # Big counts (voxels) read better as 1.2M than 1200000.
            options = dict(total=self.total, initial=self.initial, unit=unit, desc=description or None,
                           unit_scale=self.total >= 100_000, leave=True)
            if self.mode == "notebook":
                from tqdm.auto import tqdm as notebook_tqdm  # picks the widget inside Jupyter

                self._bar = notebook_tqdm(**options)
            else:
                self._bar = terminal_tqdm(file=self.stream, dynamic_ncols=True, **options)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        self.close(completed=exc_type is None)

    def update(self, count: int = 1) -> None:
        """Count ``count`` more units done (cheap: call it every iteration)."""
        self.count += count
        if self._bar is not None:
            self._bar.update(count)
        elif self.mode == "lines" and time.monotonic() >= self._next_line:
            self._line()

    def set_fields(self, **fields: str) -> None:
        """Figures shown beside the count (e.g. ``loss="1.2e-04"``), until they are set again."""
        self.fields = dict(fields)
        if self._bar is not None:
            self._bar.set_postfix(fields, refresh=False)

    def write(self, line: str) -> None:
        """Write a line of its own (above the bar on a terminal)."""
        if self.mode == "off":
            return
        if self._bar is not None:
            self._bar.write(line, file=self.stream if self.mode == "terminal" else None)
        else:
            print(line, file=self.stream, flush=True)

    def close(self, completed: bool = True) -> None:
        """End the display; in plain-line mode write the last line if the work completed."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.mode == "lines" and completed:
            self._line()
        self.mode = "off"

    def line(self) -> str:
        """The plain progress line: count, figures, rate and time left."""
        elapsed = time.monotonic() - self._started
        parts = [f"{self.description} " if self.description else ""]
        percent = f" ({100 * self.count / self.total:.0f}%)" if self.total > 0 else ""
        parts[0] += f"{_number(self.count)}/{_number(self.total)} {self.unit}{percent}"
        parts += [f"{name} {value}" for name, value in self.fields.items()]
        done_now = self.count - self.initial
        rate = done_now / elapsed if elapsed > 0 else 0.0
        if rate > 0:
            parts.append(f"{_number(rate)} {self.unit}/s")
        timing = f"{_duration(elapsed)} elapsed"
        if rate > 0 and self.count < self.total:
            timing += f", {_duration((self.total - self.count) / rate)} left"
        parts.append(timing)
        return " | ".join(parts)

    def _line(self) -> None:
        print(self.line(), file=self.stream, flush=True)
        self._next_line = time.monotonic() + self.interval


def _number(value: float) -> str:
    """``950``, ``12.5``, ``48.2k``, ``1.2M``: short, with SI prefixes from ten thousand on."""
    for prefix, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(value) >= max(scale, 1e4):
            scaled = value / scale
            return f"{scaled:.1f}{prefix}" if abs(scaled) < 100 else f"{scaled:.0f}{prefix}"
    if value == int(value):
        return str(int(value))
    return f"{value:.1f}" if abs(value) >= 10 else f"{value:.2f}"


def _duration(seconds: float) -> str:
    """``0:42``, ``12:05``, ``3:02:11``."""
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"
