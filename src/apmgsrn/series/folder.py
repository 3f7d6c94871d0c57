"""The time-series brick-model folder: a long series on bricks, cut into groups of consecutive steps.

::

    MODEL_DIR/
      series.json                 format, steps (number, file, value range), groups, settings
      steps_000000_000010/        a brick-model folder (see brick_folder) whose bricks are time-series
        manifest.json             models of their box over steps 0..9 (brick_kind "series")
        brick_000_000_000.apmgsrn
      steps_000010_000020/
        ...

Every (brick, group) pair is one job; a group's folder is finished like any brick model, so a rerun trains only
the missing pairs. ``series.json`` is plain JSON checked entry by entry; group folder names follow one pattern
(no path separators, no way out of the folder).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.atomic import atomic_write_text
from apmgsrn.io.container import FORMAT, FORMAT_VERSION, sealed_manifest_text
from apmgsrn.io.description import (
    DescriptionError,
    SourceInfo,
    optional_str,
    read_manifest_file,
    require_dict,
    require_int,
    require_number,
)
from apmgsrn.series.options import MAX_STEPS

SERIES_BRICKS_KIND = "series-bricks"
SERIES_MANIFEST_NAME = "series.json"
_GROUP_NAME = re.compile(r"^steps_\d{6,7}_\d{6,7}$")


def group_folder_name(start: int, stop: int) -> str:
    """Folder of the steps ``start .. stop - 1`` inside a time-series brick model."""
    return f"steps_{start:06d}_{stop:06d}"


def series_manifest_path(directory: str | os.PathLike) -> Path:
    return Path(directory) / SERIES_MANIFEST_NAME


def is_series_brick_folder(path: str | os.PathLike) -> bool:
    """True if ``path`` is a folder holding a time-series brick manifest (not validated)."""
    return Path(path).is_dir() and series_manifest_path(path).is_file()


def new_series_manifest(labels, names, groups: list[range], settings: dict, source: SourceInfo) -> dict:
    """The manifest of a time-series brick model before any brick is trained.

    Args:
        labels: every step's number.
        names: every step's file (and time index).
        groups: the consecutive step ranges, covering the series in order.
        settings: everything that decides the models (a rerun must match it).
        source: where the data came from.
    """
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": SERIES_BRICKS_KIND,
        "complete": False,
        "settings": settings,
        "source": source.to_dict(),
        "steps": [{"label": label, "name": name} for label, name in zip(labels, names)],
        "groups": [{"start": g.start, "stop": g.stop, "folder": group_folder_name(g.start, g.stop)} for g in groups],
    }


def write_series_manifest(directory: str | os.PathLike, manifest: dict) -> None:
    """Write ``series.json`` atomically."""
    atomic_write_text(series_manifest_path(directory), sealed_manifest_text(manifest),
                      "time-series brick manifest", model_part=True)


def read_series_manifest(directory: str | os.PathLike) -> dict:
    """Read and check ``series.json`` (JSON only; nothing in it is executed).

    Raises:
        ApmgsrnError: missing, not ours, corrupt, inconsistent or from a newer format version.
    """
    path = series_manifest_path(directory)
    return read_manifest_file(path, SERIES_BRICKS_KIND, LIMITS.header_bytes, "time-series brick manifest", _check)


def _check(manifest: dict) -> None:
    if not isinstance(manifest.get("complete"), bool):
        raise DescriptionError("complete is not true or false")
    require_dict(manifest.get("settings", {}), "settings")
    SourceInfo.from_dict(manifest.get("source", {}))
    steps = manifest.get("steps")
    if not isinstance(steps, list) or not 1 <= len(steps) <= MAX_STEPS:
        raise DescriptionError("steps is not a list of steps")
    for index, step in enumerate(steps):
        step = require_dict(step, f"steps[{index}]")
        require_number(step.get("label"), f"steps[{index}].label")
        optional_str(step.get("name"), f"steps[{index}].name")
        for key in ("value_min", "value_max"):
            if key in step:
                require_number(step[key], f"steps[{index}].{key}")
    groups = manifest.get("groups")
    if not isinstance(groups, list) or not 1 <= len(groups) <= len(steps):
        raise DescriptionError("groups is not a list of step groups")
    expected_start = 0
    for index, group in enumerate(groups):
        group = require_dict(group, f"groups[{index}]")
        start = require_int(group.get("start"), f"groups[{index}].start", 0, len(steps))
        stop = require_int(group.get("stop"), f"groups[{index}].stop", 1, len(steps))
        folder = group.get("folder")
        if start != expected_start or stop <= start:
            raise DescriptionError(f"groups[{index}] does not continue the steps before it")
        if not isinstance(folder, str) or not _GROUP_NAME.match(folder) or folder != group_folder_name(start, stop):
            raise DescriptionError(f"groups[{index}] has an invalid folder")
        expected_start = stop
    if expected_start != len(steps):
        raise DescriptionError("groups do not cover every step")


def manifest_groups(manifest: dict) -> list[tuple[range, str]]:
    """``(steps, folder)`` of every group of a checked manifest, in order."""
    return [(range(g["start"], g["stop"]), g["folder"]) for g in manifest["groups"]]
