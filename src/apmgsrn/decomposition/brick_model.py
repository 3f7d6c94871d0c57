"""The brick model on disk: a folder holding ``manifest.json`` and one ordinary model file per brick.

::

    MODEL_DIR/
      manifest.json                  format, brick grid, ghost cells, blend, settings, per-brick figures
      brick_000_000_000.apmgsrn      a single-field model file (safetensors + JSON) per brick
      brick_001_000_000.apmgsrn
      brick_001_000_000.apmgsrn.ckpt training checkpoint of a brick in progress (removed when it is done)

The manifest is plain JSON and every brick file is a checked safetensors file, so loading never runs
code from the folder. The manifest is written atomically at the start of training (``complete: false``)
and again at the end; each brick file is written atomically by the job that trained it, so a crash at
any moment leaves only whole files, and the next run trains the bricks whose files are missing.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import torch

from apmgsrn.decomposition.planner import Brick, BrickPlan, DecompositionConfig, plan_bricks
from apmgsrn.errors import ApmgsrnError

MANIFEST_NAME = "manifest.json"
BRICK_SUFFIX = ".apmgsrn"
MAX_MANIFEST_BYTES = 64 * 1024 * 1024
#: Brick grids beyond this many bricks are refused when loading (a hostile manifest could ask for
#: billions of modules).
MAX_BRICKS = 1_000_000
_BRICK_FILE = re.compile(r"^brick_\d{3,7}_\d{3,7}_\d{3,7}\.apmgsrn$")


def brick_file_name(brick: Brick) -> str:
    """File name of a brick's model inside the model folder."""
    return brick.name + BRICK_SUFFIX


def manifest_path(directory: Path) -> Path:
    return Path(directory) / MANIFEST_NAME


def is_brick_model_directory(path) -> bool:
    """True if ``path`` is a folder with a brick-model manifest (complete or not)."""
    try:
        read_manifest(Path(path))
        return True
    except ApmgsrnError:
        return False


def write_manifest(directory: Path, manifest: dict) -> None:
    """Write ``manifest.json`` atomically (temp file + rename)."""
    from apmgsrn.training.checkpoint import atomic_write

    text = json.dumps(manifest, indent=1, allow_nan=True)
    atomic_write(manifest_path(directory), lambda temp: Path(temp).write_text(text, encoding="utf-8"))


def new_manifest(plan: BrickPlan, settings: dict, source: dict) -> dict:
    """The manifest of a brick model before any brick is trained."""
    from apmgsrn.training.checkpoint import FORMAT, FORMAT_VERSION

    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": "bricks",
        "complete": False,
        "volume_shape": list(plan.volume_shape),
        "grid": list(plan.counts),
        "ghost_cells": plan.config.ghost_cells,
        "blend": plan.config.blend,
        "settings": settings,
        "source": source,
        "value_range": None,
        "bricks": [
            {"index": b.index, "name": b.name, "file": brick_file_name(b), "position": list(b.position),
             "start": list(b.start), "stop": list(b.stop)}
            for b in plan.bricks
        ],
    }


def _positive_ints(value, count: int, minimum: int) -> bool:
    return (
        isinstance(value, list)
        and len(value) == count
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= minimum for v in value)
    )


def read_manifest(directory: Path) -> dict:
    """Read and check a brick model folder's manifest (JSON only; nothing in it is executed).

    Args:
        directory: the model folder.

    Returns:
        The manifest as a dict, its structure checked.

    Raises:
        ApmgsrnError: no manifest, not ours, corrupt, inconsistent or from a newer format version.
    """
    from apmgsrn.training.checkpoint import FORMAT, FORMAT_VERSION

    directory = Path(directory)
    path = manifest_path(directory)
    if not directory.is_dir():
        raise ApmgsrnError(f"{directory}: no such brick model folder")
    if not path.is_file():
        raise ApmgsrnError(
            f"{directory}: folder has no {MANIFEST_NAME}, so it is not a brick model; pass a model file or a "
            "folder written by 'apmgsrn train --bricks'"
        )
    not_ours = f"{path}: not an apmgsrn brick model manifest (corrupt or another format); re-train the model"
    try:
        if path.stat().st_size > MAX_MANIFEST_BYTES:
            raise ApmgsrnError(not_ours)
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        raise ApmgsrnError(not_ours) from None
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or manifest.get("kind") != "bricks":
        raise ApmgsrnError(not_ours)
    version = manifest.get("format_version")
    if not isinstance(version, int):
        raise ApmgsrnError(not_ours)
    if version > FORMAT_VERSION:
        raise ApmgsrnError(
            f"{path}: written by a newer apmgsrn (model format {version}, this one reads up to {FORMAT_VERSION}); "
            "upgrade apmgsrn to load it"
        )
    grid = manifest.get("grid")
    ghost = manifest.get("ghost_cells")
    if not (
        _positive_ints(manifest.get("volume_shape"), 3, 2)
        and _positive_ints(grid, 3, 1)
        and isinstance(ghost, int) and not isinstance(ghost, bool) and ghost >= 0
        and isinstance(manifest.get("blend"), bool)
        and isinstance(manifest.get("complete"), bool)
        and isinstance(manifest.get("bricks"), list)
    ):
        raise ApmgsrnError(not_ours)
    if grid[0] * grid[1] * grid[2] > MAX_BRICKS or len(manifest["bricks"]) != grid[0] * grid[1] * grid[2]:
        raise ApmgsrnError(f"{path}: brick list does not match the {grid[0]}x{grid[1]}x{grid[2]} grid; re-train the model")
    for entry in manifest["bricks"]:
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str) or not _BRICK_FILE.match(entry["file"]):
            # File names are checked against one pattern: no path separators, no way out of the folder.
            raise ApmgsrnError(f"{path}: invalid brick entry {str(entry)[:80]!r}; re-train the model")
    return manifest


def read_manifest_header(directory: Path) -> dict:
    """The manifest in the form :func:`apmgsrn.training.checkpoint.load_model` dispatches on."""
    manifest = read_manifest(directory)
    return {"kind": "bricks", "description": manifest, "version": manifest["format_version"]}


def plan_from_manifest(manifest: dict) -> BrickPlan:
    """The brick plan a manifest describes (recomputed, then checked against the stored boxes)."""
    config = DecompositionConfig(tuple(manifest["grid"]), manifest["ghost_cells"], manifest["blend"])
    return plan_bricks(tuple(manifest["volume_shape"]), config)


def missing_bricks(directory: Path, plan: BrickPlan) -> list[Brick]:
    """Bricks without a readable model file in ``directory``."""
    from apmgsrn.training.checkpoint import read_header

    missing = []
    for brick in plan.bricks:
        path = Path(directory) / brick_file_name(brick)
        try:
            if path.is_symlink() or read_header(path)["kind"] != "field":
                missing.append(brick)
        except ApmgsrnError:
            missing.append(brick)
    return missing


def brick_summary_from_file(path: Path) -> dict:
    """Per-brick figures stored in a brick's model file (for bricks trained by an earlier run)."""
    from apmgsrn.training.checkpoint import read_header

    description = read_header(path)["description"]
    training = description.get("training", {}) if isinstance(description, dict) else {}
    return {
        "psnr": training.get("psnr"),
        "seconds": training.get("seconds"),
        "iterations": training.get("iterations"),
        "stopped_early": training.get("stopped_early"),
        "value_min": description.get("value_min"),
        "value_max": description.get("value_max"),
        "bytes": path.stat().st_size,
        "device": training.get("device"),
    }


def load_brick_model(path: Path, description: dict, device: torch.device):
    """Load a brick model folder as a :class:`~apmgsrn.decomposition.bricked_field.BrickedField`.

    Args:
        path: the model folder.
        description: its manifest, as :func:`read_manifest` returned it.
        device: where to put the networks.

    Returns:
        The routed model, ``[N, 3] -> [N, 1]`` in data units, with ``file_bytes`` of the whole folder.

    Raises:
        ApmgsrnError: an unfinished model, a missing or foreign brick file, or boxes that disagree with
            the grid.
    """
    from apmgsrn.decomposition.bricked_field import BrickedField
    from apmgsrn.models.field import NeuralField
    from apmgsrn.training.checkpoint import load_model

    directory = Path(path)
    if not directory.is_dir():
        # A single file that claims to be a brick model: only folders with a checked manifest are.
        raise ApmgsrnError(f"{directory}: not an apmgsrn model file (a brick model is a folder); re-train the model")
    manifest = read_manifest(directory)
    plan = plan_from_manifest(manifest)
    if not manifest["complete"]:
        missing = [b.name for b in missing_bricks(directory, plan)]
        listed = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise ApmgsrnError(
            f"{directory}: brick model is unfinished ({len(missing)} of {len(plan)} bricks missing: {listed or 'none'}); "
            "run the same 'apmgsrn train --bricks' command again to finish it"
        )
    fields = []
    total_bytes = manifest_path(directory).stat().st_size
    for brick, entry in zip(plan.bricks, manifest["bricks"]):
        if (
            entry.get("file") != brick_file_name(brick)
            or entry.get("start") != list(brick.start)
            or entry.get("stop") != list(brick.stop)
        ):
            raise ApmgsrnError(
                f"{manifest_path(directory)}: entry of {brick.name} disagrees with the brick grid; re-train the model"
            )
        brick_path = directory / entry["file"]
        if brick_path.is_symlink() or not brick_path.is_file():
            raise ApmgsrnError(
                f"{brick_path}: brick model file is missing; run the 'apmgsrn train --bricks' command again to "
                "re-train it"
            )
        field = load_model(brick_path, device=device)
        trained_as = (getattr(field, "training_summary", None) or {}).get("brick") or {}
        if (
            not isinstance(field, NeuralField)
            or tuple(field.volume_shape) != brick.shape
            or trained_as.get("name") != brick.name
        ):
            raise ApmgsrnError(f"{brick_path}: not the model of {brick.name}; re-train the model")
        fields.append(field)
        total_bytes += brick_path.stat().st_size
    model = BrickedField(plan, fields, blend=manifest["blend"]).to(device).eval()
    model.file_bytes = total_bytes
    model.source = manifest.get("source") if isinstance(manifest.get("source"), dict) else {}
    model.brick_summaries = [
        {**{k: v for k, v in entry.items() if k not in ("file",)}} for entry in manifest["bricks"]
    ]
    training = manifest.get("training")
    model.training_summary = training if isinstance(training, dict) else {}
    model.settings = manifest.get("settings") if isinstance(manifest.get("settings"), dict) else {}
    return model
