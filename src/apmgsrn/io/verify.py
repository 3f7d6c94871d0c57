"""Check a model file, a training checkpoint or a model folder without evaluating it.

Every file is read as its loader reads it: the container's header and description checksum, every tensor's
checksum, then (for a model kind with a registered loader) the description parsed and the network built, never
evaluated. A brick folder adds its manifest, each brick against its manifest entry (brick, box, run and
checksum, :func:`~apmgsrn.io.brick_folder.check_brick_file`), and the folder as a whole as it opens (brick grid,
finished or not). A time-series brick folder is checked through each of its step groups' brick folders, then as
a whole. Kinds are told by the loader registry, so the caller imports the packages that register theirs
(:func:`apmgsrn.verify` imports them all).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

from apmgsrn.errors import ApmgsrnError, ApmgsrnNote
from apmgsrn.io.brick_folder import (
    brick_kind,
    check_brick_file,
    is_brick_folder,
    manifest_path,
    read_manifest,
)
from apmgsrn.io.container import CHECKSUMS_VERSION, verify_file
from apmgsrn.io.registry import file_loader, model_kind, open_model


@dataclass(frozen=True)
class FileCheck:
    """What checking one file (or a folder as a whole) found.

    Attributes:
        path: the file or folder.
        problem: one line naming it and what is wrong; None when it is good.
        what: what it is, for the report (``"field"``, ``"brick manifest"``, ...).
        unchecked: it was written before checksums, so damage to it cannot be detected.
    """

    path: Path
    problem: str | None = None
    what: str = ""
    unchecked: bool = False

    @property
    def ok(self) -> bool:
        return self.problem is None

    def line(self) -> str:
        """One line for a report: ``PATH: ok (...)`` or the problem."""
        if self.problem is not None:
            return self.problem if self.problem.startswith(str(self.path)) else f"{self.path}: {self.problem}"
        remark = "; written before checksums, damage cannot be detected" if self.unchecked else ""
        return f"{self.path}: ok ({self.what}{remark})"


def verify_model(path: str | os.PathLike) -> list[FileCheck]:
    """Check a model file, checkpoint or model folder; nothing is evaluated.

    Returns:
        One check per file (a folder: its manifest and every brick, then the folder as a whole, which is
        checked only when every file is good). Problems are reported, not raised.
    """
    path = Path(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ApmgsrnNote)  # the report says which files have no checksums
        if path.is_dir():
            return _check_folder(path)
        return [_check_file(path)[0]]


def _check_file(path: Path):
    """(check, description or None) of one container file: checksums, then its loader when its kind has one."""
    try:
        header = verify_file(path)
        unchecked = header.checksums is None
        try:
            load = file_loader(header.kind)
        except ApmgsrnError:  # a checkpoint (or another kind without a loader): its checksums are all there is
            return FileCheck(path, what=f"{header.kind or 'unknown kind'}, checksums only", unchecked=unchecked), None
        _, description = load(path, "cpu")
    except ApmgsrnError as exc:
        return FileCheck(path, str(exc)), None
    return FileCheck(path, what=header.kind, unchecked=unchecked), description


def _check_folder(folder: Path) -> list[FileCheck]:
    """A brick folder, or a folder of brick folders (a time series' step groups), then the folder as a whole."""
    if is_brick_folder(folder):
        checks = _check_brick_folder(folder)
    elif model_kind(folder) is not None:
        checks = [c for sub in sorted(folder.iterdir()) if is_brick_folder(sub) for c in _check_brick_folder(sub)]
    else:
        return [FileCheck(folder, f"{folder}: not a model folder (no manifest that reads)")]
    if all(c.ok for c in checks):
        checks.append(_check_whole(folder))
    return checks


def _check_brick_folder(folder: Path) -> list[FileCheck]:
    """The manifest, then every brick file against its entry."""
    try:
        manifest = read_manifest(folder)
    except ApmgsrnError as exc:
        return [FileCheck(manifest_path(folder), str(exc))]
    checks = [FileCheck(manifest_path(folder), what="brick manifest",
                        unchecked=manifest["format_version"] < CHECKSUMS_VERSION)]
    kind = brick_kind(manifest)
    for entry in manifest["bricks"]:
        path = folder / entry["file"]
        if path.is_symlink() or not path.is_file():
            checks.append(FileCheck(path, f"{path}: brick model file of {entry['name']} is missing"))
            continue
        check, description = _check_file(path)
        if check.ok and check.what != kind:
            check = FileCheck(path, f"{path}: is a {check.what} file, not a brick of kind {kind}")
        elif check.ok:
            try:
                check_brick_file(path, entry, description.volume_shape, description.training)
            except ApmgsrnError as exc:
                check = FileCheck(path, str(exc))
        checks.append(check)
    return checks


def _check_whole(folder: Path) -> FileCheck:
    """The folder opened as its loader opens it (networks built, nothing evaluated)."""
    try:
        description = open_model(folder).description
    except ApmgsrnError as exc:
        return FileCheck(folder, str(exc))
    return FileCheck(folder, what=f"{description.kind} model, opens")
