"""Safe listing and opening of the files the viewer may show: only what lies under the served PATH.

The page names files by their path relative to the root, and every name that comes back from the page is
checked again here (the page is not trusted: anyone who reaches the socket can send any name). A name is
refused when it is absolute, holds a ``..`` component, or resolves (symbolic links followed) to a place
outside the root, and when it is not one of the entries the listing itself would show.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from apmgsrn.data import SUPPORTED_SUFFIXES
from apmgsrn.errors import ApmgsrnError
from apmgsrn.sources import is_model_path

MODEL = "model"
VOLUME = "volume"
PRESET = "preset"

# Suffixes of colour-map presets; volumes use the readers' own list, models are told by the render source.
PRESET_SUFFIXES = (".json",)


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


def _volume_suffixes() -> tuple[str, ...]:
    return tuple(suffix for group in SUPPORTED_SUFFIXES.values() for suffix in group)


def _is_within(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


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
            ApmgsrnError: the path does not exist.
        """
        given = Path(path).expanduser()
        if not given.exists():
            raise ApmgsrnError(f"{given}: no such file or folder; give a model, a volume or a folder of them")
        self.config = config
        self._volume_suffixes = _volume_suffixes()
        resolved = given.resolve()
        self.single: str | None = None
        if resolved.is_dir() and self._kind_of_directory(resolved) is None:
            self.root = resolved
        else:
            self.root = resolved.parent
            self.single = resolved.name
            if self._kind(resolved) not in (MODEL, VOLUME):
                raise ApmgsrnError(
                    f"{given}: neither a model file nor a volume this reader knows; give a model (.apmgsrn), "
                    "a volume or a folder of them"
                )

    # ------------------------------------------------------------------ classification
    def _kind_of_directory(self, path: Path) -> str | None:
        if path.suffix.lower() == ".zarr":
            return VOLUME
        if is_model_path(path):  # a brick model
            return MODEL
        return None

    def _kind(self, path: Path) -> str | None:
        """What an existing path is to the viewer (None: not shown)."""
        if path.is_dir():
            return self._kind_of_directory(path)
        suffix = path.suffix.lower()
        if suffix in PRESET_SUFFIXES:
            return PRESET
        if suffix in self._volume_suffixes:
            return VOLUME
        # A .apmgsrn file, or a model saved under another name: its header is read, never executed.
        return MODEL if is_model_path(path) else None

    # ------------------------------------------------------------------ listing
    def entries(self) -> list[CatalogEntry]:
        """Every model, volume and preset under the root, sorted by name.

        Returns:
            The entries (for a single-file root: that file alone).
        """
        if self.single is not None:
            path = self.root / self.single
            return [CatalogEntry(self.single, self._kind(path) or MODEL, _size(path))]
        found: list[CatalogEntry] = []
        self._walk(self.root, 0, found)
        return sorted(found, key=lambda entry: entry.name)

    def _walk(self, folder: Path, depth: int, found: list[CatalogEntry]) -> None:
        try:
            children = sorted(folder.iterdir(), key=lambda p: p.name)
        except OSError:
            return  # an unreadable folder is simply not listed
        for child in children:
            if len(found) >= self.config.max_entries:
                return
            if child.name.startswith("."):
                continue
            # Symbolic links are followed only while they stay under the root.
            if not _is_within(child.resolve(), self.root):
                continue
            kind = self._kind(child)
            if kind is not None:
                found.append(CatalogEntry(child.relative_to(self.root).as_posix(), kind, _size(child)))
            elif child.is_dir() and depth + 1 < self.config.max_depth:
                self._walk(child, depth + 1, found)

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
        candidate = (self.root / relative).resolve()
        if not _is_within(candidate, self.root):
            raise ApmgsrnError(f"refused {name!r}: it leads outside {self.root}")
        if not candidate.exists():
            raise ApmgsrnError(f"{name}: no such file under {self.root}; refresh the list")
        if any(part.startswith(".") for part in relative.parts):
            raise ApmgsrnError(f"refused {name!r}: hidden files are not served")
        if len(relative.parts) > self.config.max_depth:
            raise ApmgsrnError(f"refused {name!r}: deeper than the listing goes")
        kind = self._kind(candidate)
        if kind not in kinds:
            raise ApmgsrnError(f"refused {name!r}: not a {' or '.join(kinds)} file")
        return candidate

    def kind_of(self, name: str) -> str:
        """Kind of a listed entry (``model``, ``volume`` or ``preset``); checks the name like :meth:`resolve`."""
        return self._kind(self.resolve(name)) or ""


def _size(path: Path) -> int:
    try:
        return path.stat().st_size if path.is_file() else 0
    except OSError:
        return 0
