"""Train one brick where the job runs: read only its box from disk, fit it, save its model atomically.

This is the function a worker executes. It receives a small, picklable :class:`BrickJob` (the volume
travels as its recipe, never its contents: a worker reopens the file and reads one region) and returns a
small :class:`BrickResult`; the trained network goes straight to the brick's model file.
"""

from __future__ import annotations

import math
import os
import resource
import socket
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.decomposition.planner import Brick
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.models.registry import FieldConfig
from apmgsrn.training.checkpoint import checkpoint_path_for
from apmgsrn.training.trainer import TrainConfig

#: Paper (SPEC section 6): a brick is done after the plateau scheduler's third learning-rate cut.
BRICK_LR_CUTS = 3


@dataclass(frozen=True)
class BrickJob:
    """Everything a worker needs to train one brick.

    Attributes:
        volume: the :class:`apmgsrn.data.Volume` (pickles as a recipe; the file must be readable on the
            worker under the same path), or a :class:`VolumeRecipe` for readers that do not pickle.
        brick: which box to read and fit.
        field_config: the model to build for the brick.
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


@dataclass(frozen=True)
class BrickResult:
    """What a finished (or refused) brick job reports back.

    Attributes:
        name: the brick's name.
        index: its flat index.
        ok: True when the model file was written.
        message: why not, for a refused brick (a problem with the data, not worth retrying).
        psnr: PSNR over the brick's box (its own value range), dB.
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
        from apmgsrn.data import open_volume

        return open_volume(self.path, variable=self.variable, time=self.time, shape=self.shape_xyz,
                           dtype=self.dtype, fill_nonfinite=self.fill_nonfinite)


def shippable_volume(volume):
    """The volume itself if it pickles (readers pickle as their recipe), else a :class:`VolumeRecipe`.

    Args:
        volume: a :class:`apmgsrn.data.Volume`.

    Returns:
        Something a :class:`BrickJob` can carry to another process.
    """
    import pickle

    try:
        pickle.dumps(volume)
        return volume
    except Exception:  # noqa: BLE001 - any pickling failure: reopen by path instead
        from apmgsrn.data.readers import SUPPORTED_SUFFIXES

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
        from distributed import Worker, get_worker

        from apmgsrn.decomposition.executor import BRICK_RESOURCE

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


#: Bytes of mapped rows per slab when a brick is read from a memory-mapped (raw, .npy) volume.
MAPPED_SLAB_BYTES = 16 << 20


def read_brick(volume, brick: Brick) -> np.ndarray:
    """Read one brick's box, keeping the process's resident set near the brick's own size.

    Pages a memory map touches count in the resident set (what a Dask nanny holds against the memory
    limit) until the map is closed, and the pages of a box cover whole rows of the volume, several times
    the box's own bytes. So a memory-mapped volume is read in z-slabs, closing the map after each; other
    readers read the box at once. The file handle is closed at the end either way.

    Args:
        volume: the :class:`apmgsrn.data.Volume`.
        brick: the box to read.

    Returns:
        float32 ``[d, h, w]``.
    """
    from apmgsrn.data.memory_map import MemoryMappedVolume

    z, y, x = brick.slices()
    if not isinstance(volume, MemoryMappedVolume):
        region = volume.read(z, y, x)
        volume.close()
        return region
    depth, height, width = brick.shape
    region = np.empty((depth, height, width), dtype=np.float32)
    row_bytes = height * volume.shape[2] * volume.dtype.itemsize  # one z-slice of the box's rows
    step = max(1, MAPPED_SLAB_BYTES // row_bytes)
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
    from apmgsrn.device import keep_large_allocations_cached, resolve_device

    brick = job.brick
    worker = f"{socket.gethostname()}:{os.getpid()}"
    threads = torch.get_num_threads()
    try:
        device = resolve_device(job.device)
        if device.type == "cpu":
            torch.set_num_threads(_job_threads(job))
            keep_large_allocations_cached()
        elif device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        volume = job.volume.open() if isinstance(job.volume, VolumeRecipe) else job.volume
        region = read_brick(volume, brick)  # [d, h, w] float32: this brick only
        return _fit_region(job, region, device, worker, volume.path)
    except ApmgsrnError as exc:
        return BrickResult(brick.name, brick.index, ok=False, message=str(exc), worker=worker)
    finally:
        # Thread workers share the process-wide setting: leave it as it was.
        torch.set_num_threads(threads)


def _fit_region(job: BrickJob, region: np.ndarray, device: torch.device, worker: str, path) -> BrickResult:
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.value_transform import fit_value_transform
    from apmgsrn.training.trainer import Trainer

    brick = job.brick
    where = f"{path} ({brick.name}, voxels z {brick.start[0]}:{brick.stop[0]} " \
            f"y {brick.start[1]}:{brick.stop[1]} x {brick.start[2]}:{brick.stop[2]})"
    if not np.isfinite(region).all():
        raise ApmgsrnError(
            f"{where}: holds NaN or Inf voxels; pass --fill-nonfinite VALUE to replace them (e.g. --fill-nonfinite 0)"
        )
    value_min, value_max = float(region.min()), float(region.max())
    value_transform = fit_value_transform(job.transform, [region], value_min, job.log_offset, where)
    fitted = value_transform.apply(region)
    fit_min, fit_max = float(fitted.min()), float(fitted.max())
    span = fit_max - fit_min
    # In place where the transform already made a copy: one extra brick-sized array at most.
    scaled = fitted if fitted is not region else fitted.copy()
    scaled -= np.float32(fit_min)
    scaled /= np.float32(span if span > 0 else 1.0)
    values = torch.from_numpy(scaled).to(device)  # [d, h, w] in [0, 1]
    del fitted, scaled

    config = job.train_config
    field = NeuralField(
        job.field_config,
        fit_min=fit_min,
        fit_max=fit_max,
        value_min=value_min,
        value_max=value_max,
        transform=value_transform,
        volume_shape=brick.shape,
        generator=torch.Generator().manual_seed(config.seed),
    ).to(device)
    checkpoint = checkpoint_path_for(Path(job.model_path))
    resumed_from = 0
    if span > 0:
        fingerprint = {"brick": brick.name, "box": [list(brick.start), list(brick.stop)],
                       "source": job.source.to_dict(), "field": job.field_config.to_dict()}
        trainer = Trainer(field, values, config, checkpoint, fingerprint, progress=False)
        if checkpoint.exists():
            trainer.load_checkpoint(checkpoint)
            resumed_from = trainer.state.iteration
        state = trainer.run(resume=False)
        iterations, seconds, frozen_at = state.iteration, state.elapsed, state.frozen_at
        stopped_early = state.iteration < config.iterations
        history = state.history
    else:
        # A constant brick (empty space) is exact without training: the output scaling returns the
        # constant whatever the network says.
        iterations, seconds, frozen_at, stopped_early, history = 0, 0.0, None, True, {}
    del values
    psnr = _brick_psnr(field, region, device, job.psnr_voxels)
    training = {
        "iterations": iterations,
        "batch_size": config.batch_size,
        "seconds": round(seconds, 3),
        "frozen_at": frozen_at,
        "stopped_early": stopped_early,
        "psnr": psnr,
        "device": str(device),
        "config": _config_dict(config),
        "history": history,
        "brick": {"name": brick.name, "index": brick.index, "position": list(brick.position),
                  "start": list(brick.start), "stop": list(brick.stop)},
    }
    save_field(job.model_path, field, job.source, training)
    if checkpoint.exists():
        checkpoint.unlink()
    peak_device = int(torch.cuda.max_memory_allocated(device)) if device.type == "cuda" else 0
    return BrickResult(
        name=brick.name,
        index=brick.index,
        ok=True,
        psnr=psnr,
        seconds=seconds,
        iterations=iterations,
        stopped_early=stopped_early,
        value_min=value_min,
        value_max=value_max,
        model_bytes=Path(job.model_path).stat().st_size,
        peak_rss_bytes=peak_rss_bytes(),
        peak_device_bytes=peak_device,
        worker=worker,
        device=str(device),
        resumed_from=resumed_from,
    )


def _brick_psnr(field, region: np.ndarray, device: torch.device, max_voxels: int | None) -> float:
    """PSNR over the brick (its own value range), on every voxel or on a strided subset."""
    from apmgsrn.inference.evaluate import evaluate_tensor, psnr_from_mse
    from apmgsrn.inference.query import query
    from apmgsrn.ops.trilinear import voxel_coordinates

    if not max_voxels or region.size <= max_voxels:
        return evaluate_tensor(field, torch.from_numpy(region).to(device))
    stride = max(1, math.ceil((region.size / max_voxels) ** (1 / 3)))
    truth = torch.from_numpy(np.ascontiguousarray(region[::stride, ::stride, ::stride])).reshape(-1).double()
    prediction = query(field, voxel_coordinates(region.shape, stride=stride)).double().cpu()
    mse = float((prediction - truth).square().mean())
    return psnr_from_mse(mse, float(region.max() - region.min()))


def _config_dict(config: TrainConfig) -> dict:
    from dataclasses import asdict

    return asdict(config)


def brick_train_config(config: TrainConfig, brick: Brick) -> TrainConfig:
    """The run's training config for one brick: its own seed (run seed + brick index), so every brick
    is reproducible on its own and a rerun after a crash retrains it to the same model."""
    return replace(config, seed=config.seed + brick.index)
