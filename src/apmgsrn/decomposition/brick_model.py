"""Open a brick-model folder (format: :mod:`apmgsrn.io.brick_folder`) as one routed field.

Importing this module registers the ``bricks`` loader with :func:`apmgsrn.io.open_model`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from apmgsrn.decomposition.bricked_field import BrickedField
from apmgsrn.decomposition.planner import Brick, BrickPlan, DecompositionConfig, plan_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import BrickLayout, ModelDescription, SeriesLayout, SourceInfo, file_loader, register_loader
from apmgsrn.io.brick_folder import (
    BRICKS_KIND,
    brick_file_name,
    brick_file_ready,
    brick_kind,
    brick_layout,
    check_brick_file,
    manifest_path,
    read_manifest,
)
from apmgsrn.io.field_file import FIELD_KIND


def plan_from_manifest(manifest: dict) -> BrickPlan:
    """The brick plan a manifest describes (recomputed from the grid; the stored boxes are checked by the
    loader)."""
    config = DecompositionConfig(tuple(manifest["grid"]), manifest["ghost_cells"], manifest["blend"])
    return plan_bricks(tuple(manifest["volume_shape"]), config)


def missing_bricks(directory: Path, plan: BrickPlan, kind: str = FIELD_KIND) -> list[Brick]:
    """Bricks without a readable model file (of ``kind``: ``field``, or a time series' kind) in
    ``directory``."""
    return [b for b in plan.bricks if not brick_file_ready(Path(directory) / brick_file_name(b.name), kind)]


def load_brick_model(path: Path, device: torch.device) -> tuple[BrickedField, ModelDescription]:
    """Load a brick model folder as a :class:`~apmgsrn.decomposition.bricked_field.BrickedField`.

    Args:
        path: the model folder.
        device: where to put the networks.

    Returns:
        The routed field ``[N, 3] -> [N, 1]`` in data units, and its description.

    Raises:
        ApmgsrnError: an unfinished model, a missing or foreign brick file, or boxes that disagree with
            the grid.
    """
    bricks = load_bricks(Path(path), device)
    if bricks.kind != FIELD_KIND:
        raise ApmgsrnError(f"{path}: is one step group of a time-series brick model; open the folder above it")
    model = BrickedField(bricks.plan, bricks.fields, blend=bricks.manifest["blend"]).to(device).eval()
    return model, brick_description(bricks, model.parameter_count())


@dataclass(frozen=True)
class LoadedBricks:
    """The networks of a brick-model folder, checked against its manifest.

    Attributes:
        directory: the folder.
        manifest: its checked manifest.
        plan: the brick grid.
        layout: the typed brick entries.
        fields: one network per brick in flat-index order (series fields for a time series).
        kind: the kind of every brick file (``field``, or a time series' kind).
        file_bytes: bytes of the manifest and every brick file.
        config: the spatial field config of the bricks (as their files describe it).
    """

    directory: Path
    manifest: dict
    plan: BrickPlan
    layout: BrickLayout
    fields: list
    kind: str
    file_bytes: int
    config: object = None


def load_bricks(directory: Path, device: torch.device) -> LoadedBricks:
    """Load and check every brick network of a finished brick-model folder.

    Raises:
        ApmgsrnError: an unfinished model, a missing, damaged or foreign brick file (another brick's, another
            run's, or other bytes than the manifest recorded), or boxes that disagree with the grid.
    """
    manifest = read_manifest(directory)
    try:
        plan = plan_from_manifest(manifest)
    except (ApmgsrnError, ValueError) as exc:
        raise ApmgsrnError(f"{manifest_path(directory)}: brick grid does not fit the volume ({exc}); "
                           "re-train the model") from None
    kind = brick_kind(manifest)
    if not manifest["complete"]:
        missing = [b.name for b in missing_bricks(directory, plan, kind)]
        if missing:
            listed = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
            state = f"{len(missing)} of {len(plan)} bricks missing: {listed}"
        else:
            state = "every brick file is there, but the run ended before it finished the manifest"
        raise ApmgsrnError(
            f"{directory}: brick model is unfinished ({state}); run the same brick training again to finish it"
        )
    layout = brick_layout(manifest)
    load = file_loader(kind)  # every brick file is of the manifest's kind (registered by its package)
    fields, config = [], None
    total_bytes = manifest_path(directory).stat().st_size
    for brick, entry, record in zip(plan.bricks, layout.entries, manifest["bricks"]):
        if entry.name != brick.name or entry.start != brick.start or entry.stop != brick.stop:
            raise ApmgsrnError(
                f"{manifest_path(directory)}: entry of {brick.name} disagrees with the brick grid; re-train the model"
            )
        brick_path = directory / entry.file
        if brick_path.is_symlink() or not brick_path.is_file():
            raise ApmgsrnError(
                f"{brick_path}: brick model file is missing; run the same brick training again to re-train it"
            )
        field, description = load(brick_path, device)
        check_brick_file(brick_path, record, description.volume_shape, description.training)
        fields.append(field)
        config = description.config if config is None else config
        total_bytes += description.file_bytes
    return LoadedBricks(directory, manifest, plan, layout, fields, kind, total_bytes, config)


def brick_description(bricks: LoadedBricks, parameters: int, series: SeriesLayout | None = None) -> ModelDescription:
    """The description of loaded bricks (their manifest's figures; ``series`` for a time series)."""
    manifest, fields = bricks.manifest, bricks.fields
    value_range = manifest.get("value_range") or [min(f.value_min for f in fields), max(f.value_max for f in fields)]
    if not all(math.isfinite(v) for v in value_range):
        raise ApmgsrnError(f"{manifest_path(bricks.directory)}: value range is not finite; re-train the model")
    return ModelDescription(
        kind=BRICKS_KIND,
        config=bricks.config,
        volume_shape=tuple(manifest["volume_shape"]),
        value_range=(float(value_range[0]), float(value_range[1])),
        transform=fields[0].transform.kind,
        source=SourceInfo.from_dict(manifest.get("source", {})),
        training=manifest.get("training") or {},
        parameters=parameters,
        file_bytes=bricks.file_bytes,
        format_version=manifest["format_version"],
        bricks=bricks.layout,
        series=series,
    )


register_loader(BRICKS_KIND, load_brick_model)
