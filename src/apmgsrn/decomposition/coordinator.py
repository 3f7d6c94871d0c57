"""Train a brick model: plan the bricks, queue one job per missing brick, follow them, write the manifest.

The coordinator never reads voxels: it sends each job the volume's recipe and the brick's box, and the
job reads that box itself. Running the same call again after a crash or a kill trains only the bricks
whose model files are missing (a brick interrupted half-way resumes from its training checkpoint), and
since every brick is seeded with ``seed + brick index`` the finished model is the same.
"""

from __future__ import annotations

import math
import sys
import time
import uuid
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TextIO

from apmgsrn.decomposition.brick_model import missing_bricks
from apmgsrn.decomposition.brick_training import (
    BrickJob,
    BrickResult,
    VolumeBricks,
    brick_policy,
    brick_train_config,
    peak_rss_bytes,
    shippable_volume,
    train_brick,
)
from apmgsrn.decomposition.executor import JobQueue
from apmgsrn.decomposition.planner import BrickPlan, DecompositionConfig, plan_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo
from apmgsrn.io.brick_folder import (
    brick_file_name,
    brick_kind,
    brick_record,
    brick_summary_from_file,
    manifest_path,
    new_manifest,
    new_run_id,
    read_manifest,
    write_manifest,
)
from apmgsrn.io.field_file import FIELD_KIND
from apmgsrn.models.registry import FieldConfig
from apmgsrn.progress import Progress
from apmgsrn.training.trainer import TrainConfig, as_json, current_names


@dataclass(frozen=True)
class BrickTrainingSummary:
    """What a brick training run did.

    Attributes:
        out: the model folder.
        plan: the bricks.
        trained: results of the bricks trained by this run (in finishing order).
        reused: names of bricks an earlier run had finished.
        failed: brick name -> why it failed (after retries).
        seconds: wall time of this run.
        coordinator_peak_rss_bytes: resident-set high-water mark of the coordinating process.
        worker_peak_rss_bytes: per worker (``host:pid``), the highest resident-set mark its jobs reported.
        complete: every brick has a model file.
        model_bytes: bytes of the folder's model files (manifest included).
        value_range: ``(min, max)`` over the bricks, data units (None while incomplete).
    """

    out: Path
    plan: BrickPlan
    trained: list[BrickResult]
    reused: list[str]
    failed: dict[str, str]
    seconds: float
    coordinator_peak_rss_bytes: int
    worker_peak_rss_bytes: dict[str, int] = field(default_factory=dict)
    complete: bool = False
    model_bytes: int = 0
    value_range: tuple[float, float] | None = None


class BrickProgress:
    """Shows bricks done / running / failed, each finished brick's PSNR and time, and the total time.

    One line per finished or failed brick, plus the count of bricks done where the user is looking (a
    bar on a terminal or in a notebook, a periodic line in logs; see :mod:`apmgsrn.progress`).

    Args:
        stream: where to write (default stderr, so that ``--json`` output on stdout stays clean).
        enabled: False shows nothing.
    """

    def __init__(self, stream: TextIO | None = None, enabled: bool = True):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self._progress = Progress(0, enabled=False)
        self.total = 0
        self.done = 0
        self.failed = 0

    def start(self, plan: BrickPlan, to_train: int, where: str, groups: int = 1) -> None:
        """The opening line: the brick grid (of each of ``groups`` step groups of a series), how many (brick,
        group) jobs are to train and how many are done already."""
        self.total = to_train
        self._progress = Progress(to_train, unit="brick", description="bricks", stream=self.stream,
                                  enabled=self.enabled)
        i, j, k = plan.counts
        reused = len(plan) * groups - to_train
        per_group = f" in each of {groups} step groups" if groups > 1 else ""
        self._progress.write(
            f"bricks      {i}x{j}x{k} = {len(plan)}{per_group} (ghost cells {plan.config.ghost_cells}); "
            f"{to_train} to train, {reused} already done; {where}"
        )

    def finished(self, result: BrickResult) -> None:
        self.done += 1
        early = f", stopped early at {result.iterations}" if result.stopped_early and result.iterations else ""
        empty = ", constant: no training needed" if result.iterations == 0 else ""
        resumed = f", resumed at {result.resumed_from}" if result.resumed_from else ""
        self._progress.write(
            f"[{self.done + self.failed:>{len(str(self.total))}}/{self.total}] {result.name} done: "
            f"PSNR {result.psnr:.2f} dB, max error {result.max_abs_error:.4g}, {result.iterations} it, "
            f"{result.seconds:.1f} s{early}{empty}{resumed} ({result.worker})"
        )
        self._progress.update(1)

    def brick_failed(self, name: str, message: str) -> None:
        self.failed += 1
        self._progress.write(
            f"[{self.done + self.failed:>{len(str(self.total))}}/{self.total}] {name} FAILED: {message}"
        )
        self._progress.update(1)

    def tick(self, running: int) -> None:
        self._progress.set_fields(done=str(self.done), running=str(running), failed=str(self.failed))

    def close(self, summary: BrickTrainingSummary, label: str | None = None) -> None:
        """The closing line of one brick folder (``label``: which one, when several trained at once)."""
        self._progress.close()
        if not self.enabled:
            return
        where = f"{label}: " if label else ""
        finished = len(summary.plan) - len(summary.failed) - len(missing_names(summary))
        print(
            f"finished    {where}{finished} of {len(summary.plan)} "
            f"bricks ({len(summary.trained)} trained now, {len(summary.reused)} earlier), {len(summary.failed)} failed, "
            f"total {summary.seconds:.1f} s",
            file=self.stream, flush=True,
        )


def missing_names(summary: BrickTrainingSummary) -> list[str]:
    """Bricks neither finished nor failed (an interrupted run)."""
    finished = {r.name for r in summary.trained if r.ok} | set(summary.reused) | set(summary.failed)
    return [b.name for b in summary.plan.bricks if b.name not in finished]


def training_settings(volume, plan: BrickPlan, field_config: FieldConfig, train_config: TrainConfig,
                      transform: str, log_offset: float, kind: VolumeBricks | None = None) -> dict:
    """Everything that decides the bricks' models (``kind``: what the bricks are, its own settings first); a
    rerun must match it to reuse finished bricks."""
    steps = getattr(volume, "steps", None)  # a series: every step's file and time index
    return as_json({
        **(kind or VolumeBricks()).settings(),
        "volume": {"path": Path(str(volume.path)).name, "variable": volume.variable,
                   "time": getattr(volume, "time", None), "shape": list(volume.shape),
                   **({"steps": [s.name() for s in steps]} if steps is not None else {})},
        "grid": list(plan.counts),
        "ghost_cells": plan.config.ghost_cells,
        "field": field_config.to_dict(),
        "training": asdict(train_config),
        "transform": transform,
        "log_offset": log_offset,
    })


def stored_settings(manifest: dict) -> dict:
    """A manifest's settings as this version writes them: the field config read back through
    :class:`~apmgsrn.models.registry.FieldConfig`, the training config through
    :class:`~apmgsrn.training.trainer.TrainConfig` under the names renamed since, so run-time fields older
    versions stored (the kernel backend), old names and options added since (their defaults) do not make an
    unfinished folder look like another run's."""
    settings = dict(manifest.get("settings") or {})
    if "training" in settings:
        settings["training"] = current_names(settings["training"])
    try:
        field = settings.get("field")
        if isinstance(field, dict) and "series" in field:  # the bricks of a time series
            field = dict(field, field=as_json(FieldConfig.from_dict(field.get("field")).to_dict()))
        else:
            field = FieldConfig.from_dict(field).to_dict()
        settings["field"] = as_json(field)
        if isinstance(settings.get("training"), dict):  # options added since (steps_per_iteration): defaults
            settings["training"] = as_json(asdict(TrainConfig(**settings["training"])))
    except (TypeError, ValueError):
        pass  # not a config this version reads: the comparison reports it as differing
    return settings


def check_out_folder(out: Path) -> None:
    """A brick model's folder can go to ``out``: not a file, and its parent exists.

    Raises:
        ApmgsrnError: naming ``out=``.
    """
    if out.exists() and not out.is_dir():
        raise ApmgsrnError(f"{out}: exists and is a file; a brick model is a folder: pass another out=",
                           arguments=("out",))
    if not out.absolute().parent.is_dir():
        raise ApmgsrnError(f"{out}: output folder {out.parent} does not exist; create it or pass another out=",
                           arguments=("out",))


def _prepare_directory(out: Path, settings: dict, data: dict) -> dict | None:
    """Create the model folder, or check that an existing one belongs to the same run on the same data
    (``data``: :func:`~apmgsrn.data.fingerprint.volume_fingerprint`; folders written before it was recorded
    are finished without that check).

    Returns:
        The existing manifest, or None for a new folder.
    """
    check_out_folder(out)
    if out.is_dir():
        if manifest_path(out).exists():
            manifest = read_manifest(out)
            stored = stored_settings(manifest)
            if stored != settings:
                differs = sorted(k for k in set(settings) | set(stored) if settings.get(k) != stored.get(k))
                raise ApmgsrnError(
                    f"{out}: holds a brick model made with other settings ({', '.join(differs)} differ); "
                    "rerun with the same options to finish it, or pass another out=", arguments=("out",),
                )
            stored_data = manifest.get("data")
            if stored_data is not None and stored_data != data:
                differs = sorted(k for k in set(data) | set(stored_data) if data.get(k) != stored_data.get(k))
                raise ApmgsrnError(
                    f"{out}: holds a brick model of other data ({', '.join(differs)} differ); rerun on the same "
                    "data file to finish it, or pass another out=", arguments=("out",),
                )
            return manifest
        if any(out.iterdir()):
            raise ApmgsrnError(f"{out}: folder is not empty and holds no brick model; pass a new or empty folder "
                               "as out=", arguments=("out",))
        return None
    try:
        out.mkdir()
    except OSError as exc:
        raise ApmgsrnError(f"{out}: cannot create the model folder ({exc.strerror}); pass another out=",
                           arguments=("out",)) from None
    return None


def train_bricks(
    volume,
    decomposition: DecompositionConfig,
    field_config: FieldConfig,
    train_config: TrainConfig,
    out: Path,
    queue: JobQueue,
    transform: str = "none",
    log_offset: float = 0.0,
    device: str = "auto",
    progress: BrickProgress | None = None,
    poll_seconds: float = 1.0,
    psnr_voxels: int | None = None,
) -> BrickTrainingSummary:
    """Train (or finish training) a brick model in the folder ``out``.

    Args:
        volume: a :class:`apmgsrn.data.Volume`; only its recipe is sent to the jobs, each of which reads its
            own brick. File-backed volumes must be readable under the same path on every worker. (A time
            series on bricks: :func:`apmgsrn.series.bricks.train_series_bricks`.)
        decomposition: brick counts (x, y, z), ghost cells and the blend flag saved with the model.
        field_config: the model of every brick.
        train_config: how to train every brick, through :func:`~apmgsrn.decomposition.brick_training.brick_policy`
            (under ``lr_schedule="plateau"`` a brick ends after the third cut, the paper's per-brick early
            stop; the default budget-following ``cosine`` runs the whole budget); brick ``b`` uses seed
            ``seed + b``.
        out: the model folder (created; an existing one must come from the same settings).
        queue: where the jobs run (see :func:`apmgsrn.decomposition.executor.open_job_queue`).
        transform: value transform, fitted per brick.
        log_offset: offset for ``log10``.
        device: device name resolved on each worker.
        progress: the display (None: none).
        poll_seconds: how often the display refreshes the running count.
        psnr_voxels: measure each brick's PSNR on about this many voxels (None: all).

    Returns:
        The summary; ``failed`` names bricks that kept failing (the others are finished and saved).

    Raises:
        ApmgsrnError: the folder holds another model, or the bricks do not fit the volume.
    """
    started = time.perf_counter()
    run = open_brick_run(volume, decomposition, field_config, train_config, Path(out), transform, log_offset,
                         device, queue.threads_per_job, psnr_voxels)
    return run_brick_jobs([run], queue, progress or BrickProgress(enabled=False), poll_seconds, started)[0]


@dataclass
class BrickRun:
    """One brick-model folder being trained: its plan, manifest, and the jobs of its missing bricks."""

    out: Path
    plan: BrickPlan
    manifest: dict
    jobs: list[BrickJob]
    reused: list[str]


def open_brick_run(volume, decomposition: DecompositionConfig, field_config, train_config: TrainConfig, out: Path,
                   transform: str, log_offset: float, device: str, threads: int | None,
                   psnr_voxels: int | None, kind: VolumeBricks | None = None) -> BrickRun:
    """Plan the bricks, prepare the folder and its manifest, and make a job for every missing brick
    (``kind``: what the bricks are, :attr:`BrickJob.kind`; None: one volume's).

    Raises:
        ApmgsrnError: the folder holds another model, or the bricks do not fit the volume.
    """
    plan = plan_bricks(volume.shape, decomposition, str(volume.path))
    source = SourceInfo.of_volume(volume)
    train_config = brick_policy(train_config)
    job_kind = kind or VolumeBricks()
    settings = training_settings(volume, plan, field_config, train_config, transform, log_offset, job_kind)
    data = as_json(job_kind.fingerprint(volume))
    manifest = _prepare_directory(out, settings, data) or new_manifest(
        plan.volume_shape, plan.counts, plan.config.ghost_cells, decomposition.blend, plan.bricks, settings, source
    )
    manifest["data"] = data
    manifest["blend"] = decomposition.blend
    manifest["complete"] = False
    manifest.setdefault("run_id", new_run_id())  # a folder begun before runs had ids: this run names it
    if job_kind.file_kind != FIELD_KIND:
        manifest["brick_kind"] = job_kind.file_kind
    write_manifest(out, manifest)
    todo = missing_bricks(out, plan, brick_kind(manifest))
    todo_names = {b.name for b in todo}
    shipped = shippable_volume(volume)
    jobs = [
        BrickJob(
            volume=shipped,
            brick=brick,
            field_config=field_config,
            train_config=brick_train_config(train_config, brick),
            model_path=(out / brick_file_name(brick.name)).absolute(),
            transform=transform,
            log_offset=log_offset,
            device=device,
            threads=threads,
            source=source.crop(brick.start, brick.stop),  # the brick file describes its own voxels
            psnr_voxels=psnr_voxels,
            kind=kind,
            run=manifest["run_id"],
        )
        for brick in todo
    ]
    return BrickRun(out, plan, manifest, jobs, [b.name for b in plan.bricks if b.name not in todo_names])


def run_brick_jobs(runs: list[BrickRun], queue: JobQueue, progress: BrickProgress, poll_seconds: float,
                   started: float) -> list[BrickTrainingSummary]:
    """Queue the jobs of every run at once, follow them, then finish each run's manifest.

    Returns:
        One summary per run, in order.
    """
    first = runs[0]
    progress.start(first.plan, sum(len(r.jobs) for r in runs), queue.description, groups=len(runs))
    token = uuid.uuid4().hex[:8]
    futures = {}
    for number, run in enumerate(runs):
        for job in run.jobs:
            key = f"{job.brick.name}-{number}-{token}" if len(runs) > 1 else f"{job.brick.name}-{token}"
            futures[queue.submit(train_brick, job, key=key)] = (number, job.brick, _job_label(run, job, len(runs)))
    trained: list[list[BrickResult]] = [[] for _ in runs]
    failed: list[dict[str, str]] = [{} for _ in runs]
    pending = set(futures)
    try:
        while pending:
            for future in queue.wait(pending, poll_seconds):
                pending.discard(future)
                number, brick, label = futures[future]
                error = future.exception()
                if error is not None:
                    failed[number][brick.name] = _one_line(error)
                    progress.brick_failed(label, failed[number][brick.name])
                    continue
                result = future.result()
                if result.ok:
                    trained[number].append(result)
                    progress.finished(result if len(runs) == 1 else replace(result, name=label))
                else:
                    failed[number][brick.name] = result.message
                    progress.brick_failed(label, result.message)
            progress.tick(queue.running())
    finally:
        for future in pending:  # interrupted: do not leave jobs running for nobody
            try:
                future.cancel()
            except Exception:  # noqa: BLE001 - cancelling is best effort
                pass
        summaries = [_finish(run.out, run.plan, run.manifest, trained[n], run.reused, failed[n], started, queue)
                     for n, run in enumerate(runs)]
        for summary in summaries:
            progress.close(summary, summary.out.name if len(summaries) > 1 else None)
    return summaries


def _job_label(run: BrickRun, job: BrickJob, runs: int) -> str:
    """A job's name in progress lines: the brick, and the run's folder when several run at once."""
    return job.brick.name if runs == 1 else f"{run.out.name}/{job.brick.name}"


def _one_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


def _finish(out: Path, plan: BrickPlan, manifest: dict, trained: list[BrickResult], reused: list[str],
            failed: dict[str, str], started: float, queue: JobQueue) -> BrickTrainingSummary:
    """Write the final manifest: per-brick figures, checksum and run, value range, and whether every brick is
    there."""
    by_name = {r.name: r for r in trained}
    missing = {b.name for b in missing_bricks(out, plan, brick_kind(manifest))}
    low, high = math.inf, -math.inf
    for entry, brick in zip(manifest["bricks"], plan.bricks):
        if brick.name in missing:
            for key in ("summary", "checksum", "run"):
                entry.pop(key, None)
            continue
        entry.update(brick_record(out / brick_file_name(brick.name)))
        result = by_name.get(brick.name)
        if result is not None:
            entry["summary"] = {"psnr": result.psnr, "seconds": round(result.seconds, 3),
                                "iterations": result.iterations, "stopped_early": result.stopped_early,
                                "value_min": result.value_min, "value_max": result.value_max,
                                "bytes": result.model_bytes, "device": result.device}
        else:
            entry["summary"] = brick_summary_from_file(out / brick_file_name(brick.name))
        low = min(low, float(entry["summary"]["value_min"]))
        high = max(high, float(entry["summary"]["value_max"]))
    complete = not missing
    seconds = time.perf_counter() - started
    workers: dict[str, int] = {}
    for result in trained:
        workers[result.worker] = max(workers.get(result.worker, 0), result.peak_rss_bytes)
    manifest["complete"] = complete
    manifest["value_range"] = [low, high] if complete else None
    manifest["training"] = {
        "last_run_seconds": round(seconds, 3),
        "last_run_trained": len(trained),
        "last_run_where": queue.description,
        "failed": failed,
    }
    write_manifest(out, manifest)
    model_bytes = manifest_path(out).stat().st_size + sum(
        (out / brick_file_name(b.name)).stat().st_size for b in plan.bricks if b.name not in missing
    )
    return BrickTrainingSummary(
        out=out,
        plan=plan,
        trained=trained,
        reused=reused,
        failed=failed,
        seconds=seconds,
        coordinator_peak_rss_bytes=peak_rss_bytes(),
        worker_peak_rss_bytes=workers,
        complete=complete,
        model_bytes=model_bytes,
        value_range=(low, high) if complete else None,
    )
