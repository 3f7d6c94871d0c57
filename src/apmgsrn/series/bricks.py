"""A long time series on bricks: one job per (brick, group of consecutive steps), resumable like bricks.

The series is cut into groups of ``group_steps`` consecutive steps; each group is a brick-model folder whose
bricks are time-series models of their box over the group's steps (format: :mod:`apmgsrn.series.folder`).
Every job of every group goes into one queue at once; each job reads only its box of its steps
(:class:`SeriesBricks`, the brick job kind of :mod:`apmgsrn.decomposition`). Running the same call again after a
crash trains only the (brick, group) pairs whose files are missing.

:mod:`apmgsrn.series` registers :func:`load_series_bricks` as the ``series-bricks`` loader of
:func:`apmgsrn.io.open_model`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from apmgsrn.decomposition.brick_model import brick_description, load_bricks
from apmgsrn.decomposition.brick_training import BrickJob, VolumeBricks
from apmgsrn.decomposition.bricked_field import BrickedField
from apmgsrn.decomposition.coordinator import (
    BrickProgress,
    BrickTrainingSummary,
    check_out_folder,
    open_brick_run,
    run_brick_jobs,
)
from apmgsrn.decomposition.executor import JobQueue
from apmgsrn.decomposition.planner import Brick, DecompositionConfig
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SeriesLayout, SeriesStepInfo, SourceInfo
from apmgsrn.io.brick_folder import brick_file_name
from apmgsrn.series.data import VolumeSeries, series_fingerprint
from apmgsrn.series.folder import (
    SERIES_BRICKS_KIND,
    group_folder_name,
    manifest_groups,
    new_series_manifest,
    read_series_manifest,
    series_manifest_path,
    write_series_manifest,
)
from apmgsrn.series.field import SeriesConfig, SeriesFieldConfig
from apmgsrn.series.file import PACKED_SERIES_KIND, SERIES_KIND, model_file_description
from apmgsrn.series.fit import SeriesOutput
from apmgsrn.series.packing import SeriesPacking
from apmgsrn.series.qat import budgeted
from apmgsrn.series.steps import StepwiseConfig, series_trainer
from apmgsrn.training.trainer import TrainConfig, as_json


@dataclass(frozen=True)
class SeriesBricks(VolumeBricks):
    """The brick job kind of a time series (:attr:`~apmgsrn.decomposition.brick_training.BrickJob.kind`): every
    brick a time-series model of its box over every step of its :class:`~apmgsrn.series.data.VolumeSeries`.

    Attributes:
        stepwise: train step by step (the job's field config one grid set per step); None: one joint model.
        packing: a stepwise series' packed file (None: float32).
    """

    stepwise: StepwiseConfig | None = None
    packing: SeriesPacking | None = None

    @property
    def file_kind(self) -> str:
        return SERIES_KIND if self.packing is None else PACKED_SERIES_KIND

    def settings(self) -> dict:
        if self.stepwise is None:  # absent for the runs before stepwise bricks
            return {}
        return {"stepwise": self.stepwise.settings(),
                "packing": None if self.packing is None else self.packing.settings()}

    def fingerprint(self, volume: VolumeSeries) -> dict:
        return series_fingerprint(volume)

    def read(self, volume: VolumeSeries, brick: Brick) -> np.ndarray:
        """The box of every step, ``[T, d, h, w]`` float32, one step's file open at a time."""
        z, y, x = brick.slices()
        return np.stack([volume.read(t, z, y, x) for t in range(len(volume))])

    def fit_options(self, job: BrickJob, region: np.ndarray, device: torch.device) -> dict:
        """The series' trainer and the end of its fit: each step's number, file and value range in the brick's
        box; stepwise, the steps' fine-tunes and the one towards the packing share one budget."""
        series = job.volume
        steps = [SeriesStepInfo(label, series.step_name(t), (float(region[t].min()), float(region[t].max())))
                 for t, label in enumerate(series.labels)]
        stepwise, packing, tune_packed, tune_decoder = budgeted(self.stepwise, self.packing, job.train_config,
                                                                region.shape[0], job.field_config, region.shape[1:],
                                                                device, show_progress=False)
        return {"train": series_trainer(stepwise, show_progress=False),
                "output": SeriesOutput(steps, packing, tune_packed, tune_decoder)}


def step_groups(steps: int, group_steps: int | None) -> list[range]:
    """Consecutive groups of at most ``group_steps`` steps covering ``0 .. steps-1`` (None: one group)."""
    size = steps if not group_steps else max(1, int(group_steps))
    return [range(start, min(start + size, steps)) for start in range(0, steps, size)]


def group_config(config: SeriesFieldConfig, steps: int) -> SeriesFieldConfig:
    """The series model of a group of ``steps`` steps: the run's, with at most as many basis grids as steps."""
    series = config.series
    return SeriesFieldConfig(config.field, replace(series, steps=steps, basis=min(series.basis, steps)))


@dataclass(frozen=True)
class SeriesBrickSummary:
    """What a time-series brick run did: one brick summary per group, and the whole model's figures."""

    out: Path
    groups: list[BrickTrainingSummary]
    complete: bool
    model_bytes: int
    seconds: float

    @property
    def failed(self) -> dict[str, str]:
        """``group/brick`` -> why it failed, over every group."""
        return {f"{g.out.name}/{name}": why for g in self.groups for name, why in g.failed.items()}


def train_series_bricks(
    series: VolumeSeries,
    decomposition: DecompositionConfig,
    config: SeriesFieldConfig,
    train_config: TrainConfig,
    out: Path,
    queue: JobQueue,
    group_steps: int | None = None,
    transform: str = "none",
    log_offset: float = 0.0,
    device: str = "auto",
    progress: BrickProgress | None = None,
    poll_seconds: float = 1.0,
    stepwise: StepwiseConfig | None = None,
    packing: SeriesPacking | None = None,
) -> SeriesBrickSummary:
    """Train (or finish training) a time-series brick model in the folder ``out``.

    Args:
        series: the steps; only their recipe travels to the jobs.
        decomposition: brick counts (x, y, z), ghost cells, blend.
        config: the model of every (brick, group): its series part is resized to each group's steps.
        train_config: how to train every job (brick ``b`` seeded ``seed + b``, as for bricks).
        out: the model folder (created; an existing one must come from the same settings).
        queue: where the jobs run.
        group_steps: steps per group (None: the whole series in one group).
        transform: value transform, fitted per job.
        log_offset: offset for ``log10``.
        device: device name resolved on each worker.
        progress: the display (None: none).
        poll_seconds: how often the display refreshes.
        stepwise: train every (brick, group) step by step from the group's own start step (``config`` then one
            grid set per step: :func:`~apmgsrn.series.steps.stepwise_config`); None: one joint model.
        packing: stepwise: pack every brick's file (None: float32).

    Raises:
        ApmgsrnError: the folder holds another model, or the bricks do not fit the steps.
    """
    started = time.perf_counter()
    out = Path(out)
    groups = step_groups(len(series), group_steps)
    settings = as_json({"steps": [series.step_name(t) for t in range(len(series))], "group_steps": group_steps,
                        "field": config.to_dict(), "bricks": list(decomposition.bricks),
                        "ghost_cells": decomposition.ghost_cells,
                        **({} if stepwise is None else {"stepwise": True})})
    source = SourceInfo(series.step_name(0), series.variable, series.describe())
    manifest = _prepare_folder(out, settings) or new_series_manifest(
        series.labels, [series.step_name(t) for t in range(len(series))], groups, settings, source)
    manifest["complete"] = False
    write_series_manifest(out, manifest)
    runs = []
    for group in groups:
        folder = out / group_folder_name(group.start, group.stop)
        folder.mkdir(exist_ok=True)
        runs.append(open_brick_run(series.subseries(group), decomposition, group_config(config, len(group)),
                                   train_config, folder, transform, log_offset, device, queue.threads_per_job, None,
                                   SeriesBricks(stepwise, packing)))
    summaries = run_brick_jobs(runs, queue, progress or BrickProgress(enabled=False), poll_seconds, started)
    complete = all(s.complete for s in summaries)
    if complete:
        _record_step_ranges(manifest, runs)
    manifest["complete"] = complete
    write_series_manifest(out, manifest)
    model_bytes = series_manifest_path(out).stat().st_size + sum(s.model_bytes for s in summaries)
    return SeriesBrickSummary(out, summaries, complete, model_bytes, time.perf_counter() - started)


def _prepare_folder(out: Path, settings: dict) -> dict | None:
    """Create the model folder, or check that an existing one belongs to the same run."""
    check_out_folder(out)
    if out.is_dir() and series_manifest_path(out).exists():
        manifest = read_series_manifest(out)
        if manifest.get("settings") != settings:
            differs = sorted(k for k in set(settings) | set(manifest["settings"])
                             if settings.get(k) != manifest["settings"].get(k))
            raise ApmgsrnError(f"{out}: holds a time-series brick model made with other settings ({', '.join(differs)} "
                               "differ); rerun with the same options to finish it, or pass another out=", arguments=("out",))
        return manifest
    if out.is_dir() and any(out.iterdir()):
        raise ApmgsrnError(f"{out}: folder is not empty and holds no brick model; pass a new or empty out=",
                           arguments=("out",))
    out.mkdir(exist_ok=True)
    return None


def _record_step_ranges(manifest: dict, runs) -> None:
    """Each step's value range over every brick, from the steps the bricks' files record."""
    for (group, _), run in zip(manifest_groups(manifest), runs):
        for brick in run.plan.bricks:
            steps = model_file_description(run.out / brick_file_name(brick.name)).get("steps", [])
            for local, step in enumerate(steps):
                entry = manifest["steps"][group.start + local]
                entry["value_min"] = min(entry.get("value_min", math.inf), float(step["value_min"]))
                entry["value_max"] = max(entry.get("value_max", -math.inf), float(step["value_max"]))


class SeriesBrickField(nn.Module):
    """Every step of a time-series brick model: per group of steps, one time-series network per brick.

    :meth:`step_field` gives a step as a :class:`~apmgsrn.decomposition.bricked_field.BrickedField` of that
    step's materialised brick networks, so it decodes and renders as fast as a single-step brick model.

    Attributes:
        groups: per group, its steps, brick plan, networks and blend flag.
        bricks: the first group's networks (what ``info`` describes).
        value_min, value_max: over every step, data units.
        transform: the value transform of the networks.
    """

    def __init__(self, groups: list[tuple[range, object, list, bool]]):
        super().__init__()
        self.groups = [(steps, plan, blend) for steps, plan, _, blend in groups]
        self.networks = nn.ModuleList(nn.ModuleList(fields) for _, _, fields, _ in groups)
        self.bricks = self.networks[0]
        every = [f for fields in self.networks for f in fields]
        self.value_min = float(min(f.value_min for f in every))
        self.value_max = float(max(f.value_max for f in every))
        self.transform = every[0].transform

    @property
    def steps(self) -> int:
        return self.groups[-1][0].stop

    def step_field(self, step: int) -> BrickedField:
        """Step ``step`` as a brick model of materialised single-step networks.

        Raises:
            IndexError: ``step`` outside the series.
        """
        for (steps, plan, blend), fields in zip(self.groups, self.networks):
            if step in steps:
                local = step - steps.start
                device = next(fields[0].parameters()).device
                return BrickedField(plan, [f.step_field(local) for f in fields], blend=blend).to(device).eval()
        raise IndexError(f"step {step} is outside the series of {self.steps} steps")

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        raise ValueError("a time-series brick model is evaluated one step at a time: use step_field(step)")

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())


def load_series_bricks(path: Path, device: torch.device):
    """Load a time-series brick-model folder.

    Returns:
        The :class:`SeriesBrickField` and its description (kind ``series-bricks``, with ``bricks`` of the first
        group and ``series`` over every step).

    Raises:
        ApmgsrnError: an unfinished model, a group folder missing or holding another model.
    """
    directory = Path(path)
    manifest = read_series_manifest(directory)
    if not manifest["complete"]:
        raise ApmgsrnError(f"{directory}: time-series brick model is unfinished; run the same brick training "
                           "again to finish it")
    groups, loaded = [], []
    for steps, folder in manifest_groups(manifest):
        bricks = load_bricks(directory / folder, device)
        if bricks.kind not in (SERIES_KIND, PACKED_SERIES_KIND) or any(f.steps != len(steps) for f in bricks.fields):
            raise ApmgsrnError(f"{directory / folder}: does not hold the steps {steps.start}..{steps.stop - 1} of "
                               "this series; re-train the model")
        groups.append((steps, bricks.plan, bricks.fields, bricks.manifest["blend"]))
        loaded.append(bricks)
    field = SeriesBrickField(groups).to(device).eval()
    first = loaded[0].fields[0].config.series
    steps_in_all = len(manifest["steps"])
    if first.placement == "per_step":  # trained stepwise: every step its own grids and placement
        config = SeriesConfig(steps_in_all, steps_in_all, "keyframes", placement="per_step")
    else:
        config = SeriesConfig(steps_in_all, first.basis, first.coefficients, first.residual)
    steps = tuple(SeriesStepInfo(s["label"], s.get("name") or "", (s.get("value_min", field.value_min),
                                                                      s.get("value_max", field.value_max)))
                  for s in manifest["steps"])
    description = brick_description(loaded[0], field.parameter_count(), SeriesLayout(config, steps))
    description = replace(description, kind=SERIES_BRICKS_KIND, value_range=(field.value_min, field.value_max),
                          file_bytes=series_manifest_path(directory).stat().st_size + sum(b.file_bytes for b in loaded),
                          source=SourceInfo.from_dict(manifest.get("source", {})))
    return field, description

