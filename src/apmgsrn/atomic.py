"""Atomic file output: every file the product writes appears whole under its final name, or not at all.

A writer gets a temporary path in the target's own folder (so the final rename is atomic on every POSIX
filesystem), writes there, and the temporary file is renamed onto the target only after the write and an
``fsync`` succeed. Any failure, a full disk included, removes the temporary file, leaves an existing target
untouched and becomes one :class:`~apmgsrn.errors.ApmgsrnError` naming the file. The temporary name keeps
the target's suffix, so writers that choose a format by suffix (Pillow, matplotlib, imageio) work unchanged.

Every write passes one gate first (:func:`check_output_target`): the target is never an existing path that is
not a regular file (a device such as ``/dev/null``, a named pipe, a socket: renaming onto one would replace it
with a file), and never a file inside a model folder (a brick folder's manifest and bricks), which only that
model's own writers (``model_part=True``) may write.

A leaf like :mod:`apmgsrn.errors` (no torch, no numpy): model files, volumes, images, plots and benchmark
tables all write through it.
"""

from __future__ import annotations

import errno
import os
import re
import stat
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError

#: Files whose presence makes a folder a model folder (a brick model, a time-series brick model), told from
#: other files of that name by the format they declare near their start.
MODEL_MANIFEST_NAMES = ("manifest.json", "series.json")
_MANIFEST_FORMAT = re.compile(rb'"format"\s*:\s*"apmgsrn"')

_SPECIAL_KINDS = (
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISSOCK, "a socket"),
)


def special_kind(path: str | os.PathLike) -> str | None:
    """What ``path`` is when it exists and is neither a regular file nor a folder (``"a named pipe"``, ``"a
    character device"``, ...; links followed), else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None  # absent (or a dangling link: the rename replaces the link itself)
    return next((name for test, name in _SPECIAL_KINDS if test(mode)), None)


def model_folder_of(path: str | os.PathLike) -> Path | None:
    """The model folder ``path`` lies in: its folder when that folder holds an apmgsrn manifest
    (:data:`MODEL_MANIFEST_NAMES`, a regular file declaring ``"format": "apmgsrn"``), else None."""
    folder = Path(os.path.realpath(Path(path).parent if str(Path(path).parent) else "."))
    for name in MODEL_MANIFEST_NAMES:
        if _is_apmgsrn_manifest(folder / name):
            return folder
    return None


def _is_apmgsrn_manifest(path: Path) -> bool:
    try:
        handle = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # never blocks, even on a pipe
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(handle).st_mode):
            return False
        return _MANIFEST_FORMAT.search(os.read(handle, LIMITS.manifest_head_bytes)) is not None
    except OSError:
        return False
    finally:
        os.close(handle)


def check_output_target(path: str | os.PathLike, what: str = "output", *, model_part: bool = False,
                        option: str | None = None) -> Path:
    """The one check of what an output would replace: nothing but a regular file, nothing inside a model.

    Args:
        path: the file (or folder) to write.
        what: what it is, for messages (``"plot"``, ``"ONNX model"``...).
        model_part: the writer writes a part of the model folder ``path`` lies in (its manifest, a brick, a
            brick's checkpoint); every other writer is refused there.
        option: the option that named ``path`` (``--out``), for the advice.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ApmgsrnError: ``path`` is an existing device, named pipe or socket (links followed), or lies in a
            model folder.
    """
    path = Path(path)
    advice = f"choose another {option}" if option else "choose another path"
    kind = special_kind(path)
    if kind is not None:
        raise ApmgsrnError(f"{path}: is {kind}, not a regular file; the {what} is only written as a regular file, "
                           f"which would replace it: {advice}")
    if not model_part:
        folder = model_folder_of(path)
        if folder is not None:
            raise ApmgsrnError(f"{path}: lies in the model folder {folder}; the {what} would replace or join the "
                               f"files of that model: {advice} outside it")
    return path


def check_suffix(path: str | os.PathLike, suffixes: Iterable[str], what: str = "output",
                 option: str | None = None) -> Path:
    """Refuse an output whose suffix is not one of ``suffixes`` (the format it names), case-insensitively.

    Raises:
        ApmgsrnError: one line naming the suffixes (and ``option``, where the name came from an option).
    """
    path = Path(path)
    suffixes = tuple(suffixes)
    if path.suffix.lower() not in suffixes:
        where = f" {option}" if option else " path"
        raise ApmgsrnError(f"{path}: the {what} must be named {' or '.join(f'*{s}' for s in suffixes)} (its "
                           f"format); choose another{where}")
    return path


def check_output_path(path: str | os.PathLike, what: str = "output", *, model_part: bool = False) -> Path:
    """Check that ``path`` can be written as a file before any work is spent producing it.

    Args:
        path: the file to write.
        what: what the file is, for messages (``"model file"``, ``"image"``...).
        model_part: as :func:`check_output_target`.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ApmgsrnError: the path is a folder, a device, pipe or socket, or lies in a model folder; its folder
            does not exist, or the folder is not writable.
    """
    path = check_output_target(path, what, model_part=model_part)
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


def atomic_write(path: str | os.PathLike, write: Callable[[str], object], what: str = "output", *,
                 model_part: bool = False) -> Path:
    """Call ``write(temp_path)``, then rename the temporary file onto ``path``.

    Args:
        path: final file name.
        write: writes the whole file to the path it is given.
        what: what the file is, for messages.
        model_part: the file is a part of the model folder it lies in, written by that model's writer
            (:func:`check_output_target`).

    Returns:
        ``path``.

    Raises:
        ApmgsrnError: the target is refused by :func:`check_output_path`, the folder is missing or read-only, or
            writing failed (full disk, ...); the temporary file is removed and an existing ``path`` is left as
            it was.
    """
    path = check_output_path(path, what, model_part=model_part)
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
        check_output_target(path, what, model_part=model_part)  # again: the write may have taken hours
        os.replace(temp, path)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot write the {what} ({describe_os_error(exc)})") from None
    finally:
        if os.path.exists(temp):
            os.unlink(temp)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, what: str = "output", *, model_part: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    return atomic_write(path, lambda temp: Path(temp).write_text(text, encoding="utf-8"), what, model_part=model_part)
