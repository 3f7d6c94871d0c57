"""Atomic file output: every file the product writes appears whole under its final name, or not at all.

A writer gets a temporary path in the target's own folder (so the final rename is atomic on every POSIX
filesystem), writes there, and the temporary file is renamed onto the target only after the write and an
``fsync`` succeed. Any failure, a full disk included, removes the temporary file, leaves an existing target
untouched and becomes one :class:`~apmgsrn.errors.ApmgsrnError` naming the file. The temporary name keeps
the target's suffix, so writers that choose a format by suffix (Pillow, matplotlib, imageio) work unchanged.

A leaf like :mod:`apmgsrn.errors` (no torch, no numpy): model files, volumes, images, plots and benchmark
tables all write through it.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from apmgsrn.errors import ApmgsrnError


def check_output_path(path: str | os.PathLike, what: str = "output") -> Path:
    """Check that ``path`` can be written as a file before any work is spent producing it.

    Args:
        path: the file to write.
        what: what the file is, for messages (``"model file"``, ``"image"``...).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ApmgsrnError: the path is a folder, its folder does not exist, or the folder is not writable.
    """
    path = Path(path)
    if path.is_dir():
        raise ApmgsrnError(f"{path}: is a folder; give a file name for the {what}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ApmgsrnError(f"{path}: folder {folder} does not exist; create it or choose another {what} path")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ApmgsrnError(f"{path}: folder {folder} is not writable; choose another {what} path")
    return path


def describe_os_error(exc: OSError) -> str:
    """A short reason for a failed write (``no space left on the device``, ``permission denied``, ...)."""
    if exc.errno == errno.ENOSPC:
        return "no space left on the device"
    if exc.errno == errno.EDQUOT:
        return "disk quota exceeded"
    return (exc.strerror or str(exc)).lower()


def atomic_write(path: str | os.PathLike, write: Callable[[str], object], what: str = "output") -> Path:
    """Call ``write(temp_path)``, then rename the temporary file onto ``path``.

    Args:
        path: final file name.
        write: writes the whole file to the path it is given.
        what: what the file is, for messages.

    Returns:
        ``path``.

    Raises:
        ApmgsrnError: the folder is missing or read-only, or writing failed (full disk, ...); the temporary
            file is removed and an existing ``path`` is left as it was.
    """
    path = check_output_path(path, what)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        handle, temp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".partial{path.suffix}", dir=folder)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot write to {folder} ({describe_os_error(exc)})") from None
    os.close(handle)
    try:
        write(temp)
        with open(temp, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(temp, path)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot write the {what} ({describe_os_error(exc)})") from None
    finally:
        if os.path.exists(temp):
            os.unlink(temp)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, what: str = "output") -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    return atomic_write(path, lambda temp: Path(temp).write_text(text, encoding="utf-8"), what)
