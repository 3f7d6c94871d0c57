"""The one gate between a path and a volume reader: which files a reader may open, and how much an array
may claim.

Every volume reader (NetCDF, HDF5, Zarr, raw, npy, VTK XML), the ``.pvd`` collections of a series and the
viewer's catalogue pass their paths through here, so a file is judged by the same rules wherever it is read:

- **Regular files only.** A named pipe blocks its reader forever, a character device such as ``/dev/zero``
  never ends, a socket or block device is not a volume: each is refused before a reader opens it. What is
  opened here is opened with ``O_NONBLOCK`` and checked again on the open descriptor, so a file swapped for
  a pipe between the check and the open is refused rather than waited on.
- **Links resolved, boundaries kept.** Symbolic links are followed to the real file; where a root folder is
  given (the viewer's served folder), the real path must lie inside it. A Zarr store is the root of its own
  files: a chunk that links out of the store is refused.
- **A container's other files follow the same rules**: every file of a Zarr store (walked before anything
  is read) and an HDF5 or NetCDF-4 file's external storage (see :mod:`apmgsrn.data.hdf5`).
- **The declared size is checked before any read.** A volume that fits in the memory budget (half the
  memory available now) may be sparse; a larger one is read lazily, brick by brick, and must then really be
  stored: its declared bytes may exceed what the file stores by at most zlib's expansion bound
  (:func:`check_declared_array`). A file of a few kilobytes declaring an 8192^3 array is refused at once
  instead of being read (or filled) for hours.

Every refusal is one :class:`~apmgsrn.errors.ApmgsrnError` line naming the file and the problem.
"""

from __future__ import annotations

import fcntl
import math
import os
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError


#: Names of Zarr metadata files (format 3 and 2).
ZARR_METADATA_NAMES = frozenset({"zarr.json", ".zarray", ".zgroup", ".zattrs", ".zmetadata"})

_KINDS = (
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder"),
)


def memory_budget() -> int:
    """Bytes an input may take in memory: half of what is available now (Linux ``/proc/meminfo``), else half
    the physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024 // 2
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


def _not_regular(mode: int) -> str:
    """What a file of ``mode`` is, for a refusal: "a named pipe, not a regular file; ..."."""
    kind = next((name for test, name in _KINDS if test(mode)), "something else")
    return f"{kind}, not a regular file; only regular files are read"


def _refusal(path: Path, container: Path | None, role: str, state: str) -> ApmgsrnError:
    """One line naming the file (and the container that reaches it) and what is wrong with it."""
    if container is None:
        return ApmgsrnError(f"{path}: {state}")
    return ApmgsrnError(f"{container}: {role} {path} is {state}")


def _inside(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


def real_path(path: str | os.PathLike, root: str | os.PathLike | None = None, container: Path | None = None,
              role: str = "its file") -> Path:
    """The real path of an input (links followed), checked to lie inside ``root``.

    Args:
        path: the path as given.
        root: the folder it must stay in (None: anywhere).
        container: the file or store that reaches ``path`` (for messages), or None.
        role: what ``path`` is to the container ("its file", "its entry", ...), for messages.

    Returns:
        The resolved path.

    Raises:
        ApmgsrnError: a missing file, a broken link or link loop, or a real path outside ``root``.
    """
    path = Path(path)
    try:
        real = path.resolve(strict=True)
    except FileNotFoundError:
        raise _refusal(path, container, role, "missing (or a broken link); check the path") from None
    except (OSError, RuntimeError) as exc:  # RuntimeError: a link loop (Python < 3.13)
        raise _refusal(path, container, role, f"not resolvable ({exc}); a link loop?") from None
    if root is not None:
        boundary = Path(root).resolve()
        if not _inside(real, boundary):
            # The link's target is not named: the viewer shows refusals to whoever reaches its page.
            raise _refusal(path, container, role, f"outside {boundary} (links followed); only files inside it are read")
    return real


def check_regular(path: str | os.PathLike, root: str | os.PathLike | None = None, container: Path | None = None,
                  role: str = "its file") -> os.stat_result:
    """Check that an input is a regular file (links followed) inside ``root``, without opening it.

    Args:
        path, root, container, role: as for :func:`real_path`.

    Returns:
        The file's ``stat`` (its size is what a reader can find there).

    Raises:
        ApmgsrnError: as :func:`real_path`, or the path is a pipe, a device, a socket or a folder.
    """
    real = real_path(path, root, container, role)
    try:
        status = real.stat()
    except OSError as exc:
        raise _refusal(Path(path), container, role, f"unreadable ({exc.strerror})") from None
    if not stat.S_ISREG(status.st_mode):
        raise _refusal(Path(path), container, role, _not_regular(status.st_mode))
    return status


def open_regular(path: str | os.PathLike, root: str | os.PathLike | None = None, max_bytes: int | None = None,
                 container: Path | None = None, role: str = "its file") -> BinaryIO:
    """Open an input for reading: a regular file inside ``root``, checked on the open descriptor.

    The file is opened with ``O_NONBLOCK`` (opening a named pipe then returns at once instead of waiting for
    a writer) and ``fstat`` must say regular file before anything is read; blocking reads are restored after.

    Args:
        path, root, container, role: as for :func:`real_path`.
        max_bytes: refuse a larger file (None: any size).

    Returns:
        A binary file object at offset 0.

    Raises:
        ApmgsrnError: as :func:`check_regular`, or the file is larger than ``max_bytes``.
    """
    real = real_path(path, root, container, role)
    try:
        descriptor = os.open(real, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise _refusal(Path(path), container, role, f"unreadable ({exc.strerror})") from None
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise _refusal(Path(path), container, role, _not_regular(status.st_mode))
        if max_bytes is not None and status.st_size > max_bytes:
            raise _refusal(Path(path), container, role,
                           f"{status.st_size:,} bytes, more than such a file may hold ({max_bytes:,}); is it damaged?")
        flags = fcntl.fcntl(descriptor, fcntl.F_GETFL)
        fcntl.fcntl(descriptor, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


def read_regular(path: str | os.PathLike, max_bytes: int, root: str | os.PathLike | None = None) -> bytes:
    """The whole content of a small regular input file (a ``.pvd`` collection, a header).

    Raises:
        ApmgsrnError: as :func:`open_regular`.
    """
    with open_regular(path, root, max_bytes) as handle:
        return handle.read(max_bytes + 1)[:max_bytes]


@dataclass(frozen=True)
class StoreFiles:
    """What a walk of a Zarr store found.

    Attributes:
        total_bytes: bytes of all its files together (what the store can really hold).
        largest_bytes: the largest data (non-metadata) file.
        largest: that file, or None for a store without data files.
    """

    total_bytes: int
    largest_bytes: int
    largest: Path | None


def walk_store(store: str | os.PathLike, root: str | os.PathLike | None = None) -> StoreFiles:
    """Check every entry of a Zarr store before zarr reads any: regular files (links followed, staying inside
    the store) or plain folders, metadata files of at most :attr:`~apmgsrn.limits.Limits.zarr_metadata_bytes`.

    Args:
        store: the store folder.
        root: the folder the store must lie in (None: anywhere).

    Returns:
        The sizes found (:class:`StoreFiles`).

    Raises:
        ApmgsrnError: an entry that is a pipe, device or socket, a link out of the store, to a folder, broken
            or looping, an unreadable folder, or an oversized metadata file.
    """
    store = Path(store)
    real_store = real_path(store, root)
    total, largest_bytes, largest = 0, 0, None

    def refuse_unreadable(error: OSError) -> None:
        raise ApmgsrnError(f"{store}: its folder {error.filename} cannot be read ({error.strerror})")

    for folder, folders, files in os.walk(real_store, onerror=refuse_unreadable, followlinks=False):
        for name in (*folders, *files):
            entry = Path(folder, name)
            shown = store / entry.relative_to(real_store)
            mode = os.lstat(entry).st_mode
            if stat.S_ISDIR(mode):
                continue  # a plain folder: walked in turn
            if stat.S_ISLNK(mode):
                mode = real_path(shown, real_store, container=store).stat().st_mode
                if stat.S_ISDIR(mode):
                    raise _refusal(shown, store, "its entry", "a link to a folder; a store's folders must be its own")
            if not stat.S_ISREG(mode):
                raise _refusal(shown, store, "its file", _not_regular(mode))
            size = entry.stat().st_size
            total += size
            if name in ZARR_METADATA_NAMES:
                if size > LIMITS.zarr_metadata_bytes:
                    raise ApmgsrnError(f"{store}: its metadata file {shown} is {size:,} bytes (at most "
                                       f"{LIMITS.zarr_metadata_bytes:,}); the store is damaged")
            elif size > largest_bytes:
                largest_bytes, largest = size, shown
    return StoreFiles(total, largest_bytes, largest)


def declared_bytes(shape: Iterable[int], dtype: np.dtype | None) -> int:
    """Bytes an array of ``shape`` and ``dtype`` declares (8 a value for a non-numeric type)."""
    itemsize = np.dtype(dtype).itemsize if dtype is not None else 8
    return math.prod(int(n) for n in shape) * max(itemsize, 1)


def check_declared_array(path: Path, name: str | None, shape: tuple[int, ...], dtype: np.dtype | None,
                         stored_bytes: int) -> None:
    """Refuse an array that declares more than the file can hold, before any of it is read.

    An array whose float32 copy fits in :func:`memory_budget` passes (it may be sparse: fill values of
    missing chunks). A larger one is read lazily and must be stored: its declared bytes may be at most
    :attr:`~apmgsrn.limits.Limits.expansion` times the bytes the file stores for it (plus
    :attr:`~apmgsrn.limits.Limits.declared_slack`).

    Args:
        path: the file, for messages.
        name: the array's name in the file (None for a single-array file).
        shape: the array's shape as read (3-D, or the selected step's).
        dtype: its stored type.
        stored_bytes: bytes the file really stores for it (chunks present, file size).

    Raises:
        ApmgsrnError: the array is larger than the budget and than its stored bytes can expand to.
    """
    voxels = math.prod(int(n) for n in shape)
    if voxels * 4 <= memory_budget():
        return
    claimed = declared_bytes(shape, dtype)
    if claimed <= LIMITS.expansion * stored_bytes + LIMITS.declared_slack:
        return
    label = f"array {name!r}" if name else "the array"
    extent = "x".join(str(n) for n in reversed(shape))
    raise ApmgsrnError(
        f"{path}: {label} declares {extent} (x*y*z) {dtype} values ({claimed / 2**30:,.1f} GiB), more than half "
        f"the free memory, but only {stored_bytes:,} bytes of it are stored; it is damaged or not a real volume"
    )
