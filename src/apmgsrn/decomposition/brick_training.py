"""Train one brick where the job runs: read only its box from disk, fit it, save its model atomically.

This is the function a worker executes. It receives a small, picklable :class:`BrickJob` (the volume
travels as its recipe, never its contents: a worker reopens the file and reads one region) and returns a
small :class:`BrickResult`; the trained network goes straight to the brick's model file.
"""

from __future__ import annotations

import os
import pickle
import resource
import socket
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.data import open_volume
from apmgsrn.data.fingerprint import volume_fingerprint
from apmgsrn.data.memory_map import MemoryMappedVolume
from apmgsrn.data.readers import SUPPORTED_SUFFIXES
from apmgsrn.decomposition.executor import BRICK_RESOURCE
from apmgsrn.decomposition.planner import Brick
from apmgsrn.device import resolve_device
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo
from apmgsrn.io.brick_folder import finished_brick_summary
from apmgsrn.io.field_file import FIELD_KIND
from apmgsrn.models.registry import FieldConfig
from apmgsrn.recipes import BRICKS
from apmgsrn.training.fit import fit, prepare_values
from apmgsrn.training.trainer import TrainConfig


class VolumeBricks:
    """The kind of a brick job of one volume: what the bricks' models are, how a brick's box is read and fitted,
    what a rerun must match. Data of another kind brings its own subclass, carried by :attr:`BrickJob.kind` (a
    time series: :class:`apmgsrn.series.bricks.SeriesBricks`, every brick a time-series model of its box over
    the steps); instances travel to the workers, so they must pickle (module-level classes, plain fields).
    """

    #: The kind of every brick's model file (the manifest's ``brick_kind``).
    file_kind: str = FIELD_KIND

    def settings(self) -> dict:
        """Entries the run's settings (:func:`~apmgsrn.decomposition.coordinator.training_settings`) start
        with: what else decides the bricks' models."""
        return {}

    def fingerprint(self, volume) -> dict:
        """What identifies the data (a rerun must continue on the same)."""
        return volume_fingerprint(volume)

    def read(self, volume, brick: Brick) -> np.ndarray:
        """The brick's box of ``volume``, float32 ``[d, h, w]`` (:func:`read_brick`)."""
        return read_brick(volume, brick)

    def fit_options(self, job: BrickJob, region: np.ndarray, device: torch.device) -> dict:
        """More keyword arguments of :func:`~apmgsrn.training.fit.fit` for this brick (``train=``, ``output=``)."""
        return {}


@dataclass(frozen=True)
class BrickJob:
    """Everything a worker needs to train one brick.

    Attributes:
        volume: the :class:`apmgsrn.data.Volume` (pickles as a recipe; the file must be readable on the
            worker under the same path), or a :class:`VolumeRecipe` for readers that do not pickle, or what
            ``kind`` reads (a :class:`~apmgsrn.series.data.VolumeSeries`: its steps' files, opened by the worker
            one at a time).
        brick: which box to read and fit.
        field_config: the model to build for the brick (a series config for the bricks of a series).
        train_config: how to train it (its ``seed`` is already the brick's own: run seed + brick index).
        model_path: the brick's model file (written atomically when done).
        transform: value transform kind (fitted on the brick's own values).
        log_offset: offset for ``log10``.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:I``, resolved on the worker.
        threads: torch CPU threads for this job; None: the CPU cores this process may use divided by the
            worker's task slots.
        source: description of the data, saved in the brick file.
        psnr_voxels: measure the brick's PSNR on a regular subset of about this many voxels (None: all
            of them); for very large bricks on slow devices, where the full pass would cost more than
            the training.
        kind: what the bricks are (None: a :class:`VolumeBricks`; a time series:
            :class:`apmgsrn.series.bricks.SeriesBricks`, which says how its steps train and pack).
        run: the id of the training run (its folder's manifest records it), saved in the brick file.
    """

    volume: object
    brick: Brick
    field_config: FieldConfig
    train_config: TrainConfig
    model_path: Path
    transform: str = "none"
    log_offset: float = 0.0
    device: str = "auto"
    threads: int | None = None
    source: SourceInfo = SourceInfo()
    psnr_voxels: int | None = None
    kind: VolumeBricks | None = None
    run: str | None = None

    @property
    def job_kind(self) -> VolumeBricks:
        return VolumeBricks() if self.kind is None else self.kind


@dataclass(frozen=True)
class BrickResult:
    """What a finished (or refused) brick job reports back.

    Attributes:
        name: the brick's name.
        index: its flat index.
        ok: True when the model file was written.
        message: why not, for a refused brick (a problem with the data, not worth retrying).
        psnr: PSNR over the brick's box (its own value range), dB.
        max_abs_error: largest absolute error over the brick's box (or the voxels its PSNR used), data units.
        seconds: training time.
        iterations: iterations run (fewer than the budget after an early stop).
        stopped_early: the plateau scheduler ended training before the budget.
        value_min, value_max: the brick's value range in data units.
        model_bytes: size of its model file.
        peak_rss_bytes: resident-set high-water mark of the process that ran the job.
        peak_device_bytes: CUDA peak allocation (0 on CPU).
        worker: ``host:pid`` of the process that ran the job.
        device: the device it trained on.
        resumed_from: iteration the job resumed at from the brick's training checkpoint (0: fresh).
    """

    name: str
    index: int
    ok: bool
    message: str = ""
    psnr: float = float("nan")
    max_abs_error: float = float("nan")
    seconds: float = 0.0
    iterations: int = 0
    stopped_early: bool = False
    value_min: float = float("nan")
    value_max: float = float("nan")
    model_bytes: int = 0
    peak_rss_bytes: int = 0
    peak_device_bytes: int = 0
    worker: str = ""
    device: str = ""
    resumed_from: int = 0


@dataclass(frozen=True)
class VolumeRecipe:
    """How to reopen a volume file on a worker, for volumes whose reader cannot be pickled.

    Attributes:
        path: absolute path of the file (the same on every worker).
        variable, time, fill_nonfinite: as given to :func:`apmgsrn.data.open_volume`.
        shape_xyz, dtype: raw files only (they have no header).
    """

    path: str
    variable: str | None = None
    time: int | None = None
    fill_nonfinite: float | None = None
    shape_xyz: tuple[int, int, int] | None = None
    dtype: str | None = None

    def open(self):
        return open_volume(self.path, variable=self.variable, time=self.time, shape=self.shape_xyz,
                           dtype=self.dtype, fill_nonfinite=self.fill_nonfinite)


def shippable_volume(volume):
    """The volume itself if it pickles (readers pickle as their recipe), else a :class:`VolumeRecipe`.

    Args:
        volume: a :class:`apmgsrn.data.Volume`.

    Returns:
        Something a :class:`BrickJob` can carry to another process.
    """
    try:
        pickle.dumps(volume)
        return volume
    except Exception:  # noqa: BLE001 - any pickling failure: reopen by path instead
        raw = Path(volume.path).suffix.lower() in SUPPORTED_SUFFIXES["raw"]
        return VolumeRecipe(
            path=str(Path(volume.path).absolute()),
            variable=None if raw else volume.variable,
            time=None if raw else volume.time,
            fill_nonfinite=volume.fill_nonfinite,
            shape_xyz=tuple(reversed(volume.shape)) if raw else None,
            dtype=str(volume.dtype) if raw else None,
        )


def peak_rss_bytes() -> int:
    """Resident-set high-water mark of this process (Linux reports KiB)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _job_threads(job: BrickJob) -> int:
    if job.threads:
        return job.threads
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    slots = 1
    try:
        from distributed import Worker, get_worker  # optional extra

        here = get_worker()  # raises outside a Dask worker
        if BRICK_RESOURCE in (here.state.total_resources or {}):
            # Workers started with --resources brick=N train N bricks at a time, whatever their threads.
            slots = max(1, int(here.state.total_resources[BRICK_RESOURCE]))
        else:
            # Every task slot of every worker in this process may train a brick at once (several workers
            # share a process in an in-process cluster).
            slots = max(1, sum(w.state.nthreads for w in list(Worker._instances) if w.status.name == "running"))
    except (ImportError, ValueError, AttributeError):
        pass
    return max(1, cores // slots)


def read_brick(volume, brick: Brick, slab_bytes: int = 16 << 20) -> np.ndarray:
    """Read one brick's box, keeping the process's resident set near the brick's own size.

    Pages a memory map touches count in the resident set (what a Dask nanny holds against the memory
    limit) until the map is closed, and the pages of a box cover whole rows of the volume, several times
    the box's own bytes. So a memory-mapped volume is read in z-slabs, closing the map after each; other
    readers read the box at once. The file handle is closed at the end either way.

    Args:
        volume: the :class:`apmgsrn.data.Volume`.
        brick: the box to read.
        slab_bytes: bytes of mapped rows per slab of a memory-mapped (raw, .npy) volume.

    Returns:
        float32 ``[d, h, w]``.
    """
    z, y, x = brick.slices()
    if not isinstance(volume, MemoryMappedVolume):
        region = volume.read(z, y, x)
        volume.close()
        return region
    depth, height, width = brick.shape
    region = np.empty((depth, height, width), dtype=np.float32)
    row_bytes = height * volume.shape[2] * volume.dtype.itemsize  # one z-slice of the box's rows
    step = max(1, slab_bytes // row_bytes)
    for start in range(z.start, z.stop, step):
        stop = min(z.stop, start + step)
        region[start - z.start : stop - z.start] = volume.read(slice(start, stop), y, x)
        volume.close()
    return region


def train_brick(job: BrickJob) -> BrickResult:
    """Read one brick's box, fit a field to it and save the field to ``job.model_path``.

    A problem with the data (NaN without a fill value, a transform the values forbid, an unreadable
    region) comes back as a result with ``ok=False`` and the message, since running it again elsewhere
    cannot help; anything else raises, so that the job queue retries it.

    Args:
        job: the brick and how to train it.

    Returns:
        The brick's figures.
    """
    brick = job.brick
    worker = f"{socket.gethostname()}:{os.getpid()}"
    threads = torch.get_num_threads()
    try:
        device = resolve_device(job.device)
        if device.type == "cpu":
            torch.set_num_threads(_job_threads(job))
        elif device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        done = finished_brick_summary(job.model_path, job.job_kind.file_kind, _box(job))
        if done is not None:  # this run's file of this brick is there: the job ran before (a lost result)
            return BrickResult(brick.name, brick.index, ok=True, psnr=done["psnr"],
                               max_abs_error=done["max_abs_error"], seconds=done["seconds"],
                               iterations=done["iterations"], stopped_early=bool(done["stopped_early"]),
                               value_min=done["value_min"], value_max=done["value_max"],
                               model_bytes=done["bytes"], peak_rss_bytes=peak_rss_bytes(), worker=worker,
                               device=str(done["device"] or ""))
        volume = job.volume.open() if isinstance(job.volume, VolumeRecipe) else job.volume
        region = job.job_kind.read(volume, brick)  # [d, h, w] ([T, d, h, w] for a series) float32: this brick only
        return _fit_region(job, region, device, worker, volume.path)
    except ApmgsrnError as exc:
        return BrickResult(brick.name, brick.index, ok=False, message=str(exc), worker=worker)
    finally:
        # Thread workers share the process-wide setting: leave it as it was.
        torch.set_num_threads(threads)


def _box(job: BrickJob) -> dict:
    """What a brick's file records of the brick it was trained as (and the run that trained it)."""
    brick = job.brick
    return {"name": brick.name, "index": brick.index, "position": list(brick.position),
            "start": list(brick.start), "stop": list(brick.stop), **({"run": job.run} if job.run else {})}


def _fit_region(job: BrickJob, region: np.ndarray, device: torch.device, worker: str, path) -> BrickResult:
    brick = job.brick
    where = f"{path} ({brick.name}, voxels z {brick.start[0]}:{brick.stop[0]} " \
            f"y {brick.start[1]}:{brick.stop[1]} x {brick.start[2]}:{brick.stop[2]})"
    prepared = prepare_values(region, job.transform, job.log_offset, where, device)
    box = _box(job)
    fingerprint = {"brick": brick.name, "box": [list(brick.start), list(brick.stop)],
                   "source": job.source.to_dict(), "field": job.field_config.to_dict()}
    # A brick always resumes its own checkpoint: the job may be a retry after a crash.
    result = fit(prepared, region, job.field_config, job.train_config, Path(job.model_path), job.source,
                 fingerprint, resume=True, psnr_voxels=job.psnr_voxels, summary_extra={"brick": box},
                 **job.job_kind.fit_options(job, region, device))
    peak_device = int(torch.cuda.max_memory_allocated(device)) if device.type == "cuda" else 0
    return BrickResult(
        name=brick.name,
        index=brick.index,
        ok=True,
        psnr=result.psnr,
        max_abs_error=result.max_abs_error,
        seconds=result.seconds,
        iterations=result.iterations,
        stopped_early=result.stopped_early,
        value_min=prepared.value_min,
        value_max=prepared.value_max,
        model_bytes=result.model_bytes,
        peak_rss_bytes=peak_rss_bytes(),
        peak_device_bytes=peak_device,
        worker=worker,
        device=str(device),
        resumed_from=result.resumed_from,
    )


def brick_policy(config: TrainConfig) -> TrainConfig:
    """How the bricks of a run train, given the run's config (the brick policy lives here, not in the CLI).

    Under the paper's ``plateau`` schedule a brick is done after the scheduler's third learning-rate cut
    (docs/method.md §6), which frees its worker for the next brick; every other schedule, the default
    budget-following ``cosine`` included, runs the whole budget.

    Args:
        config: the run's training config.

    Returns:
        The config every brick trains with (before its own seed, see :func:`brick_train_config`).
    """
    if config.lr_schedule == "plateau" and config.stop_after_lr_cuts is None:
        return replace(config, stop_after_lr_cuts=BRICKS.lr_cuts)
    return config


def brick_train_config(config: TrainConfig, brick: Brick) -> TrainConfig:
    """The run's training config for one brick: :func:`brick_policy`, and its own seed (run seed + brick
    index), so every brick is reproducible on its own and a rerun after a crash retrains it to the same
    model."""
    return replace(brick_policy(config), seed=config.seed + brick.index)
