"""The files the viewer may show: what lies under the served PATH, listed once, and nothing else.

The listing is made when the viewer starts and is the only thing the page can open: a name that comes
back from the page (anyone who reaches the socket can send any name) must be one of the listed entries,
and is checked again on the way to the file: refused when it is absolute, holds a ``..`` component, is
hidden, or now resolves (symbolic links followed) outside the root, to something that is not a regular
file or a model/Zarr folder, or to another kind of file than was listed.

A volume is listed, and opened, only if :mod:`apmgsrn.data.opener` accepts it with the served folder as
root: the file and every file its container reaches (a Zarr store's chunks, an HDF5 or NetCDF-4 file's
external storage; links to other files are refused) must be regular files inside the folder. The same check
runs when the page asks for the entry and when the reader opens it (``open_volume(..., root=)``).

Any file may lie in the folder: a symbolic-link loop, a named pipe, a file that cannot be read, a name
that is not UTF-8, a hostile header. The listing never fails on one of them: it lists what it can and
records the rest in :attr:`Catalog.skipped` with the reason, for the page and the terminal to show.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from apmgsrn.data import SUPPORTED_SUFFIXES
from apmgsrn.data.readers import check_volume_path
from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.paraview import PRESET_SUFFIXES
from apmgsrn.sources import is_model_path

MODEL = "model"
VOLUME = "volume"
PRESET = "preset"


@dataclass(frozen=True)
class CatalogConfig:
    """How far the listing looks below the root."""

    max_depth: int = 3  # folder levels below the root that are searched
    max_entries: int = 1000  # entries listed at most (a huge tree is cut, not walked to the end)


@dataclass(frozen=True)
class CatalogEntry:
    """One file the viewer can open.

    Attributes:
        name: path relative to the root, ``/``-separated (what the page shows and sends back).
        kind: ``"model"``, ``"volume"`` or ``"preset"``.
        size_bytes: file size (0 for a folder: a brick model or a Zarr store).
    """

    name: str
    kind: str
    size_bytes: int


@dataclass(frozen=True)
class SkippedFile:
    """A file under the root that is not listed, and why (shown to the user, never opened)."""

    name: str
    reason: str


class _Skip(Exception):
    """A file the listing leaves out; the message says why."""


def _volume_suffixes() -> tuple[str, ...]:
    return tuple(suffix for group in SUPPORTED_SUFFIXES.values() for suffix in group)


def _is_within(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


def _sendable(name: str) -> bool:
    """Whether the page can show a name and send it back unchanged (UTF-8 text, no control characters)."""
    try:
        name.encode("utf-8")  # a name of undecodable bytes holds lone surrogates here
    except UnicodeEncodeError:
        return False
    return "\\" not in name and all(ch.isprintable() for ch in name)


class Catalog:
    """The models, volumes and ParaView presets under a root the viewer was started on.

    ``PATH`` may be a folder (everything in it, a few levels deep), a model file, a brick model folder or
    a volume file (then that one entry only).
    """

    def __init__(self, path: str | os.PathLike, config: CatalogConfig = CatalogConfig()) -> None:
        """Args:
        path: the folder or file given to ``apmgsrn view``.
        config: listing limits.

        Raises:
            ApmgsrnError: the path does not exist, or is a file the viewer cannot show.
        """
        given = Path(path).expanduser()
        if not given.exists():
            raise ApmgsrnError(f"{given}: no such file or folder; give a model, a volume or a folder of them")
        self.config = config
        self._volume_suffixes = _volume_suffixes()
        resolved = given.resolve()
        self.single: str | None = None
        self.skipped: list[SkippedFile] = []
        self.truncated = False  # more entries than max_entries were found
        if resolved.is_dir() and self._kind_of_directory(resolved) is None:
            self.root = resolved
            self._entries: dict[str, CatalogEntry] = {}
            self._walk(self.root, 0, {self.root})
        else:
            self.root = resolved.parent
            self.single = resolved.name
            try:
                kind = self._classify(resolved)
            except _Skip as exc:
                raise ApmgsrnError(f"{given}: {exc}; give a model, a volume or a folder of them") from None
            if kind not in (MODEL, VOLUME):
                raise ApmgsrnError(
                    f"{given}: neither a model file nor a volume this reader knows; give a model (.apmgsrn), "
                    "a volume or a folder of them"
                )
            self._entries = {self.single: CatalogEntry(self.single, kind, _size(resolved))}

    # ------------------------------------------------------------------ classification
    def _kind_of_directory(self, path: Path) -> str | None:
        if path.suffix.lower() == ".zarr":
            return VOLUME
        if is_model_path(path):  # a brick model
            return MODEL
        return None

    def _classify(self, path: Path) -> str | None:
        """What a resolved path is to the viewer: a kind, None (a plain folder or a foreign file).

        Raises:
            _Skip: a file the viewer will not touch (not a regular file or folder, unreadable).
        """
        try:
            mode = path.stat().st_mode
        except OSError as exc:
            raise _Skip(f"cannot be read ({exc.strerror})") from None
        if stat.S_ISDIR(mode):
            kind = self._kind_of_directory(path)
            if kind == VOLUME:
                self._check_volume(path)
            return kind
        if not stat.S_ISREG(mode):  # a named pipe or a device would block or never end when read
            raise _Skip("not a regular file")
        suffix = path.suffix.lower()
        if suffix in PRESET_SUFFIXES:
            return PRESET
        if suffix in self._volume_suffixes:
            self._check_volume(path)
            return VOLUME
        # A .apmgsrn file, or a model saved under another name: its header is read, never executed.
        return MODEL if is_model_path(path) else None

    def _check_volume(self, path: Path) -> None:
        """The opener's checks of a volume under the served folder (no data is read).

        Raises:
            _Skip: the volume, or a file it reaches, is not a regular file inside the root.
        """
        try:
            check_volume_path(path, self.root)
        except ApmgsrnError as exc:
            reason = str(exc)
            raise _Skip(reason.removeprefix(f"{path}: ")) from None

    # ------------------------------------------------------------------ listing
    def entries(self) -> list[CatalogEntry]:
        """Every model, volume and preset listed under the root, sorted by name.

        Returns:
            The entries (for a single-file root: that file alone).
        """
        return sorted(self._entries.values(), key=lambda entry: entry.name)

    def _walk(self, folder: Path, depth: int, visited: set[Path]) -> None:
        """List ``folder`` (a path under the root); ``visited``: the resolved folders walked so far."""
        try:
            children = sorted(folder.iterdir(), key=lambda p: p.name)
        except OSError as exc:
            self._skip(folder, f"folder cannot be read ({exc.strerror})")
            return
        for child in children:
            if len(self._entries) >= self.config.max_entries:
                if not self.truncated:
                    self.truncated = True
                    note = f"the listing stops at {self.config.max_entries} entries; serve a smaller folder"
                    self.skipped.append(SkippedFile(child.relative_to(self.root).as_posix(), note))
                return
            if child.name.startswith("."):
                continue  # hidden: never listed, never mentioned
            try:
                self._visit(child, depth, visited)
            except _Skip as exc:
                self._skip(child, str(exc))
            except Exception as exc:  # noqa: BLE001 - one hostile file must not stop the listing
                self._skip(child, f"cannot be read ({type(exc).__name__})")

    def _visit(self, child: Path, depth: int, visited: set[Path]) -> None:
        if not _sendable(child.name):
            raise _Skip("name is not printable UTF-8 text; rename it")
        try:
            target = child.resolve(strict=True)
        except (OSError, RuntimeError):  # RuntimeError: a symbolic-link loop (Python < 3.13)
            raise _Skip("broken symbolic link or link loop") from None
        if not _is_within(target, self.root):
            raise _Skip("symbolic link to a place outside the served folder")
        kind = self._classify(target)
        name = child.relative_to(self.root).as_posix()
        if kind is not None:
            self._entries[name] = CatalogEntry(name, kind, _size(target))
        elif target.is_dir() and depth + 1 < self.config.max_depth and target not in visited:
            visited.add(target)  # a folder reached twice (through a link inside the root) is listed once
            self._walk(child, depth + 1, visited)

    def _skip(self, path: Path, reason: str) -> None:
        name = path.relative_to(self.root).as_posix()
        self.skipped.append(SkippedFile(name if _sendable(name) else ascii(name), reason))

    # ------------------------------------------------------------------ opening
    def resolve(self, name: str, kinds: tuple[str, ...] = (MODEL, VOLUME, PRESET)) -> Path:
        """The file behind an entry name sent by the page, after every safety check.

        Args:
            name: relative ``/``-separated path, as listed by :meth:`entries`.
            kinds: which kinds of entry are acceptable here.

        Returns:
            The resolved path (inside the root).

        Raises:
            ApmgsrnError: the name leaves the root, is not listed, or is of another kind.
        """
        if not isinstance(name, str) or not name or "\x00" in name or "\\" in name:
            raise ApmgsrnError(f"refused {name!r}: not a file name from the list")
        relative = PurePosixPath(name)
        if relative.is_absolute() or ".." in relative.parts or name.startswith("~"):
            raise ApmgsrnError(f"refused {name!r}: only files under {self.root} can be opened")
        if self.single is not None and name != self.single:
            raise ApmgsrnError(f"refused {name!r}: this viewer serves {self.single} only")
        if any(part.startswith(".") for part in relative.parts):
            raise ApmgsrnError(f"refused {name!r}: hidden files are not served")
        if len(relative.parts) > self.config.max_depth:
            raise ApmgsrnError(f"refused {name!r}: deeper than the listing goes")
        entry = self._entries.get(name)
        if entry is None:
            raise ApmgsrnError(f"refused {name!r}: not a file this viewer lists")
        if entry.kind not in kinds:
            raise ApmgsrnError(f"refused {name!r}: not a {' or '.join(kinds)} file")
        # The file may have changed since it was listed: every check again, on what is there now.
        try:
            candidate = (self.root / relative).resolve(strict=True)
        except (OSError, RuntimeError):
            raise ApmgsrnError(f"{name}: no longer there (or now a broken link) under {self.root}") from None
        if not _is_within(candidate, self.root):
            raise ApmgsrnError(f"refused {name!r}: it leads outside {self.root}")
        try:
            kind = self._classify(candidate)
        except _Skip as exc:
            raise ApmgsrnError(f"refused {name!r}: {exc}") from None
        if kind != entry.kind:
            raise ApmgsrnError(f"refused {name!r}: it is no longer the {entry.kind} that was listed")
        return candidate


def _size(path: Path) -> int:
    try:
        return path.stat().st_size if path.is_file() else 0
    except OSError:
        return 0
