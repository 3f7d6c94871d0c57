"""``bench quality``: train every (volume, model, size, seed) and tabulate PSNR, real size and time.

Results go to ``OUT/quality.csv`` one row per finished run, so an interrupted or extended benchmark (more
volumes, seeds or models) only runs what is missing. ``OUT/quality.md`` holds the tables in the form of the
paper's Table 1 and ``OUT/quality.png`` the chart; both are rebuilt from every row in the CSV.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from apmgsrn.arguments import MAX_BATCH_SIZE, check_choice, check_int, check_number
from apmgsrn.atomic import atomic_write_text
from apmgsrn.bench.charts import quality_chart
from apmgsrn.bench.datasets import DataSpec, open_spec
from apmgsrn.bench.results import QualityRow, append_row, read_rows, write_rows
from apmgsrn.bench.tables import quality_tables
from apmgsrn.choices import LR_SCHEDULES, MODEL_KINDS, SIZE_PRESETS, VALUE_TRANSFORMS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.registry import preset_config, stored_bytes, training_defaults
from apmgsrn.training.fit import fit_volume
from apmgsrn.training.trainer import TrainConfig


@dataclass(frozen=True)
class QualityPlan:
    """What ``bench quality`` runs.

    Attributes:
        datasets: the volumes.
        models: model names (keys of :data:`apmgsrn.models.registry.ENCODERS`).
        sizes: size presets.
        seeds: seeds ``0 .. seeds - 1`` per combination.
        iterations, batch_size: training budget of every run.
        lr_schedule: one schedule for every model, or None for each model's default.
        voxel_fraction: one share of voxel points for every model, or None for each model's default.
        transform, log_offset: value transform applied to every volume.
    """

    datasets: tuple[DataSpec, ...]
    models: tuple[str, ...] = MODEL_KINDS
    sizes: tuple[str, ...] = ("small", "medium")
    seeds: int = 1
    iterations: int = 2000
    batch_size: int = 32768
    lr_schedule: str | None = None
    voxel_fraction: float | None = None
    transform: str = "none"
    log_offset: float = 0.0

    def __post_init__(self) -> None:
        for model in self.models:
            check_choice("models", model, MODEL_KINDS)
        for size in self.sizes:
            check_choice("sizes", size, SIZE_PRESETS)
        check_int("seeds", self.seeds, 1)
        check_int("iterations", self.iterations, 1)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_SIZE)
        if self.lr_schedule is not None:
            check_choice("lr_schedule", self.lr_schedule, LR_SCHEDULES)
        if self.voxel_fraction is not None:
            check_number("voxel_fraction", self.voxel_fraction, 0.0, 1.0)
        check_choice("transform", self.transform, VALUE_TRANSFORMS)
        check_number("log_offset", self.log_offset)


def quality_paths(out: Path) -> dict[str, Path]:
    """Files of a quality benchmark in folder ``out``."""
    return {
        "csv": out / "quality.csv",
        "markdown": out / "quality.md",
        "chart": out / "quality.png",
        "models": out / "models",
    }


def run_quality(
    plan: QualityPlan,
    out: Path,
    device: torch.device,
    log: Callable[[str], None] = print,
) -> list[QualityRow]:
    """Train what ``plan`` asks that ``out/quality.csv`` does not hold yet; then rebuild table and chart.

    Args:
        plan: the combinations and budget.
        out: results folder (created if missing; its parent must exist).
        device: training device.
        log: receives one line per run.

    Returns:
        Every row of the CSV (earlier runs included).
    """
    paths = prepare_folder(out)
    rows = read_rows(paths["csv"], QualityRow)
    if rows:
        write_rows(paths["csv"], rows, QualityRow)  # a file of an older version gets today's columns first
    done = {row.key() for row in rows}
    cases = [
        (spec, model, size, seed)
        for spec in plan.datasets
        for model in plan.models
        for size in plan.sizes
        for seed in range(plan.seeds)
    ]
    for number, (spec, model, size, seed) in enumerate(cases, 1):
        train_config = TrainConfig(
            iterations=plan.iterations, batch_size=plan.batch_size, seed=seed,
            checkpoint_every=max(250, plan.iterations // 4),
            **training_defaults(model, lr_schedule=plan.lr_schedule, voxel_fraction=plan.voxel_fraction),
        )
        schedule = train_config.lr_schedule
        key = (spec.label, model, size, seed, plan.iterations, plan.batch_size, schedule, train_config.voxel_fraction,
               train_config.error_sampling)
        if key in done:
            continue
        volume = open_spec(spec)
        voxels = f"_v{train_config.voxel_fraction:g}" if train_config.voxel_fraction else ""
        if train_config.voxel_fraction and train_config.error_sampling:
            voxels += f"_e{train_config.error_sampling:g}"
        model_file = paths["models"] / f"{spec.stem}_{model}_{size}_s{seed}_i{plan.iterations}{voxels}.apmgsrn"
        result = fit_volume(
            volume, preset_config(model, size), train_config, model_file, device,
            transform=plan.transform, log_offset=plan.log_offset, resume=True,
        )
        parameters = result.field.parameter_count()
        row = QualityRow(
            dataset=spec.label,
            shape="x".join(str(n) for n in reversed(volume.shape)),
            model=model,
            size=size,
            seed=seed,
            iterations=result.iterations,
            batch_size=plan.batch_size,
            lr_schedule=schedule,
            parameters=parameters,
            parameter_bytes=stored_bytes(result.field.config),
            file_bytes=result.model_bytes,
            data_dtype=str(volume.dtype),
            data_bytes=volume.stored_bytes,
            compression_ratio=volume.stored_bytes / result.model_bytes,
            compression_ratio_float32=volume.raw_bytes / result.model_bytes,
            psnr=result.psnr,
            train_seconds=result.seconds,
            ms_per_iteration=1000 * result.seconds / max(result.iterations, 1),
            device=str(device),
            model_file=str(model_file),
            voxel_fraction=train_config.voxel_fraction,
            max_abs_error=result.evaluation.max_abs_error,
            error_sampling=train_config.error_sampling,
        )
        append_row(paths["csv"], row)
        rows.append(row)
        done.add(key)
        log(
            f"[{number}/{len(cases)}] {spec.label} {model} {size} seed {seed}: {row.psnr:.2f} dB, "
            f"{parameters:,} parameters, {row.file_bytes / 1024:.0f} KB, {row.train_seconds:.1f} s"
        )
    write_quality_report(rows, out)
    return rows


def prepare_folder(out: Path) -> dict[str, Path]:
    """Create the results folder and its ``models`` subfolder.

    Raises:
        ApmgsrnError: the parent folder does not exist or ``out`` is a file.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ApmgsrnError(f"{out}: is a file; out= needs a folder for the results", arguments=("out",))
    if not out.absolute().parent.is_dir():
        raise ApmgsrnError(f"{out}: parent folder {out.parent} does not exist; create it or pass another out=",
                           arguments=("out",))
    paths = quality_paths(out)
    paths["models"].mkdir(parents=True, exist_ok=True)
    return paths


def write_quality_report(rows: list[QualityRow], out: Path) -> None:
    """Write ``quality.md`` (tables) and ``quality.png`` (chart) into ``out`` from ``rows``."""
    if not rows:
        return
    paths = quality_paths(Path(out))
    atomic_write_text(paths["markdown"], quality_tables(rows), "results table")
    quality_chart(rows, paths["chart"])
