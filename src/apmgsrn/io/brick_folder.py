"""The brick-model folder: ``manifest.json`` plus one single-field model file per brick.

::

    MODEL_DIR/
      manifest.json                  format, brick grid, ghost cells, blend, settings, per-brick figures
      brick_000_000_000.apmgsrn      a single-field model file (see field_file) per brick
      brick_001_000_000.apmgsrn
      brick_001_000_000.apmgsrn.ckpt training checkpoint of a brick in progress (removed when it is done)

The manifest is plain JSON checked field by field and sealed with a crc32c of its own content
(``manifest_checksum``: a change to it is refused as damage), and every brick file is a checked single-field
file, so loading never runs code from the folder. The manifest is written atomically at the start of training
(``complete: false``) and again at the end; each brick file is written atomically by the job that trained it,
so a crash at any moment leaves only whole files.

The manifest names its training run (``run_id``, made when the folder is created and kept by the reruns that
finish it) and records, for every finished brick, the crc32c of its file (``checksum``) and the run its file
says trained it (``run``), beside its box. Loading refuses a brick file that was trained as another brick or
box, by another run, or whose bytes are not the ones recorded (:func:`check_brick_file`). Manifests written
before these entries existed (format version 2 and older) still load, with a note.
"""

from __future__ import annotations

import os
import re
import uuid
from collections.abc import Iterable
from pathlib import Path

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.atomic import atomic_write_text
from apmgsrn.io.container import (
    CHECKSUMS_VERSION,
    FORMAT,
    FORMAT_VERSION,
    file_checksum,
    note_unchecked,
    read_header,
    sealed_manifest_text,
)
from apmgsrn.io.description import (
    BrickEntry,
    BrickLayout,
    DescriptionError,
    SourceInfo,
    read_manifest_file,
    require_dict,
    require_int,
    require_ints,
)
from apmgsrn.io.field_file import FIELD_KIND
from apmgsrn.io.packed import model_file_description

BRICKS_KIND = "bricks"
MANIFEST_NAME = "manifest.json"
BRICK_SUFFIX = ".apmgsrn"
_BRICK_NAME = re.compile(r"^brick_\d{3,7}_\d{3,7}_\d{3,7}$")
#: Kinds a brick's model file may be (a manifest's ``brick_kind``): a single field, and what other packages
#: register (the time-series package: its series kinds, :func:`register_brick_file_kind`).
BRICK_FILE_KINDS = [FIELD_KIND]
_CHECKSUM = re.compile(r"^[0-9a-f]{8}$")


def register_brick_file_kind(kind: str) -> None:
    """Let a manifest's ``brick_kind`` name ``kind`` (a model file kind with a loader in the registry)."""
    if kind not in BRICK_FILE_KINDS:
        BRICK_FILE_KINDS.append(kind)


def brick_file_name(name: str) -> str:
    """File name of a brick's model inside the model folder."""
    return name + BRICK_SUFFIX


def manifest_path(directory: str | os.PathLike) -> Path:
    return Path(directory) / MANIFEST_NAME


def is_brick_folder(path: str | os.PathLike) -> bool:
    """True if ``path`` is a folder holding a brick-model manifest (not validated)."""
    return Path(path).is_dir() and manifest_path(path).is_file()


def new_manifest(volume_shape: tuple[int, int, int], counts: tuple[int, int, int], ghost_cells: int, blend: bool,
                 bricks: Iterable, settings: dict, source: SourceInfo) -> dict:
    """The manifest of a brick model before any brick is trained.

    Args:
        volume_shape: ``(D, H, W)``.
        counts: bricks along x, y, z.
        ghost_cells: ghost cells of the plan.
        blend: blend neighbouring bricks at inference.
        bricks: the plan's bricks (objects with ``name``, ``index``, ``position``, ``start``, ``stop``).
        settings: everything that decides the bricks' models (a rerun must match it).
        source: where the data came from.
    """
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": BRICKS_KIND,
        "run_id": new_run_id(),
        "complete": False,
        "volume_shape": list(volume_shape),
        "grid": list(counts),
        "ghost_cells": ghost_cells,
        "blend": blend,
        "settings": settings,
        "source": source.to_dict(),
        "value_range": None,
        "bricks": [
            {"index": b.index, "name": b.name, "file": brick_file_name(b.name), "position": list(b.position),
             "start": list(b.start), "stop": list(b.stop)}
            for b in bricks
        ],
    }


def new_run_id() -> str:
    """A new training run's id (random: two runs never share one)."""
    return uuid.uuid4().hex


def write_manifest(directory: str | os.PathLike, manifest: dict) -> None:
    """Write ``manifest.json`` atomically, as this format version (an older folder finished by this version
    gets its run id and brick checksums from the writer)."""
    manifest["format_version"] = FORMAT_VERSION
    atomic_write_text(manifest_path(directory), sealed_manifest_text(manifest), "brick manifest", model_part=True)


def read_manifest(directory: str | os.PathLike) -> dict:
    """Read and check a brick model folder's manifest (JSON only; nothing in it is executed).

    Returns:
        The manifest as a dict, every field the product reads checked for type and range.

    Raises:
        ApmgsrnError: no manifest, not ours, corrupt, inconsistent or from a newer format version.
    """
    directory = Path(directory)
    path = manifest_path(directory)
    if not directory.is_dir():
        raise ApmgsrnError(f"{directory}: no such brick model folder")
    if not path.is_file():
        raise ApmgsrnError(
            f"{directory}: folder has no {MANIFEST_NAME}, so it is not a brick model; pass a model file or a "
            "folder written by a brick training run"
        )
    manifest = read_manifest_file(path, BRICKS_KIND, LIMITS.header_bytes, "brick model manifest", _check_manifest)
    if manifest["format_version"] < CHECKSUMS_VERSION:
        note_unchecked(path, f"brick manifest of format {manifest['format_version']}, written before brick "
                       "checksums and run ids: a changed, swapped or foreign brick cannot be detected")
    return manifest


def _check_manifest(manifest: dict) -> None:
    if manifest["format_version"] < 1:
        raise DescriptionError(f"format_version {manifest['format_version']} does not exist")
    volume_shape = require_ints(manifest.get("volume_shape"), "volume_shape", 3, 2, LIMITS.volume_axis)
    grid = require_ints(manifest.get("grid"), "grid", 3, 1, LIMITS.bricks)
    require_int(manifest.get("ghost_cells"), "ghost_cells", 0, LIMITS.volume_axis)
    for flag in ("blend", "complete"):
        if not isinstance(manifest.get(flag), bool):
            raise DescriptionError(f"{flag} is not true or false")
    if manifest.get("brick_kind", FIELD_KIND) not in BRICK_FILE_KINDS:
        raise DescriptionError("brick_kind is not a model kind")
    for key in ("settings", "training"):
        if manifest.get(key) is not None:
            require_dict(manifest[key], key)
    SourceInfo.from_dict(manifest.get("source", {})).check_shape(volume_shape)
    value_range = manifest.get("value_range")
    if value_range is not None and not (
        isinstance(value_range, list) and len(value_range) == 2
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value_range)
    ):
        raise DescriptionError("value_range is not two numbers")
    bricks = manifest.get("bricks")
    count = grid[0] * grid[1] * grid[2]
    if count > LIMITS.bricks or not isinstance(bricks, list) or len(bricks) != count:
        raise DescriptionError(f"brick list does not match the {grid[0]}x{grid[1]}x{grid[2]} grid")
    for index, entry in enumerate(bricks):
        _brick_entry(entry, index)
    if manifest["format_version"] >= CHECKSUMS_VERSION:
        _check_records(manifest)


def _check_records(manifest: dict) -> None:
    """A manifest of this format names its run, and a finished one records every brick's checksum and run."""
    if not isinstance(manifest.get("run_id"), str) or not manifest["run_id"]:
        raise DescriptionError("run_id is missing")
    for index, entry in enumerate(manifest["bricks"]):
        where = f"bricks[{index}]"
        if "checksum" not in entry and not manifest["complete"]:
            continue  # not finished yet
        if not isinstance(entry.get("checksum"), str) or not _CHECKSUM.match(entry["checksum"]):
            raise DescriptionError(f"{where} records no checksum")
        if "run" not in entry or not (entry["run"] is None or isinstance(entry["run"], str)):
            raise DescriptionError(f"{where} records no run")
        if entry["run"] is not None and entry["run"] != manifest["run_id"]:
            raise DescriptionError(f"{where} was trained by run {entry['run']}, not by the folder's run "
                                   f"{manifest['run_id']}")


def _brick_entry(entry, index: int) -> BrickEntry:
    where = f"bricks[{index}]"
    entry = require_dict(entry, where)
    name = entry.get("name")
    # Names and file names follow one pattern: no path separators, no way out of the folder.
    if not isinstance(name, str) or not _BRICK_NAME.match(name) or entry.get("file") != brick_file_name(name):
        raise DescriptionError(f"{where} has an invalid name or file")
    if require_int(entry.get("index"), f"{where}.index") != index:
        raise DescriptionError(f"{where}.index is not {index}")
    summary = entry.get("summary", {})
    return BrickEntry(
        name=name,
        index=index,
        position=require_ints(entry.get("position"), f"{where}.position", 3, 0, LIMITS.bricks),
        start=require_ints(entry.get("start"), f"{where}.start", 3, 0, LIMITS.volume_axis),
        stop=require_ints(entry.get("stop"), f"{where}.stop", 3, 1, LIMITS.volume_axis),
        file=entry["file"],
        summary=require_dict(summary, f"{where}.summary"),
    )


def brick_layout(manifest: dict) -> BrickLayout:
    """The typed brick grid of a manifest that :func:`read_manifest` accepted."""
    return BrickLayout(
        counts=tuple(manifest["grid"]),
        ghost_cells=manifest["ghost_cells"],
        blend=manifest["blend"],
        entries=tuple(_brick_entry(entry, i) for i, entry in enumerate(manifest["bricks"])),
    )


def brick_file_ready(path: str | os.PathLike, kind: str = FIELD_KIND) -> bool:
    """Whether a brick's model file exists as a readable model file of ``kind`` (``field``; ``series`` for the
    bricks of a time series); a symbolic link never is."""
    path = Path(path)
    try:
        return not path.is_symlink() and read_header(path).kind == kind
    except ApmgsrnError:
        return False


def finished_brick_summary(path: str | os.PathLike, kind: str, box: dict) -> dict | None:
    """The figures of the brick file at ``path`` when this run already wrote it as this brick (``box``: the
    name, start, stop and run a job records in its file), else None. A job that runs twice (Dask computes a
    result again when the worker holding it is lost) then returns them without training or writing again:
    a second write after the run has recorded the file's checksum would leave a file the manifest refuses."""
    if not box.get("run") or not brick_file_ready(path, kind):
        return None
    try:
        trained_as = _trained_as(model_file_description(path))
    except ApmgsrnError:
        return None
    if any(trained_as.get(key) != box[key] for key in ("name", "start", "stop", "run")):
        return None
    return brick_summary_from_file(path)


def brick_record(path: str | os.PathLike) -> dict:
    """What a manifest records of a finished brick file: its checksum and the run its file says trained it."""
    trained_as = _trained_as(model_file_description(path))
    return {"checksum": file_checksum(path), "run": trained_as.get("run")}


def check_brick_file(path: str | os.PathLike, entry: dict, volume_shape: tuple[int, ...], training: dict) -> None:
    """Refuse a loaded brick file that is not the one its manifest entry describes: trained as another brick
    or box (two bricks swapped), by another run, or with bytes other than those recorded.

    Args:
        path: the brick file.
        entry: its manifest entry (checked by :func:`read_manifest`).
        volume_shape: the shape its file describes.
        training: the training summary its file holds.

    Raises:
        ApmgsrnError: one line naming the brick.
    """
    name = entry["name"]
    trained_as = training.get("brick")
    shape = tuple(b - a for a, b in zip(entry["start"], entry["stop"]))
    if (
        tuple(volume_shape) != shape
        or not isinstance(trained_as, dict)
        or trained_as.get("name") != name
        or any(key in trained_as and trained_as[key] != entry[key] for key in ("index", "position", "start", "stop"))
    ):
        raise ApmgsrnError(f"{path}: not the model of {name} (trained for another brick or box); re-train the model")
    if "run" in entry and trained_as.get("run") != entry["run"]:
        raise ApmgsrnError(
            f"{path}: the model of {name} from another training run ({trained_as.get('run') or 'no run id'}, "
            f"not {entry['run'] or 'the run without an id'} that the manifest records); re-train the model"
        )
    if "checksum" in entry and file_checksum(path) != entry["checksum"]:
        raise ApmgsrnError(
            f"{path}: damaged: checksum of the brick file of {name} does not match the manifest's (the file was "
            "changed or replaced after the run); re-train the model"
        )


def _trained_as(description: dict) -> dict:
    """The brick a model file's description says it was trained as (empty if none)."""
    training = description.get("training")
    brick = training.get("brick") if isinstance(training, dict) else None
    return brick if isinstance(brick, dict) else {}


def brick_kind(manifest: dict) -> str:
    """The kind of every brick file of a checked manifest: ``field``, or ``series`` (``packed-series``) for a
    time series."""
    return manifest.get("brick_kind", FIELD_KIND)


def brick_summary_from_file(path: str | os.PathLike) -> dict:
    """Per-brick figures stored in a brick's model file (for bricks trained by an earlier run)."""
    description = model_file_description(path)
    training = description.get("training", {})
    training = training if isinstance(training, dict) else {}
    return {
        "psnr": training.get("psnr"),
        "max_abs_error": training.get("max_abs_error"),
        "seconds": training.get("seconds"),
        "iterations": training.get("iterations"),
        "stopped_early": training.get("stopped_early"),
        "value_min": description.get("value_min"),
        "value_max": description.get("value_max"),
        "bytes": Path(path).stat().st_size,
        "device": training.get("device"),
    }
