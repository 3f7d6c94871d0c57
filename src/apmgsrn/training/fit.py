"""The fitting pipeline: prepare the values, build the field, train it, measure it, save it.

Every fit goes through here: ``apmgsrn train`` (:func:`fit_volume`;
:func:`~apmgsrn.series.fit.fit_series` for a time series, one model for every step), each brick of a
brick model (:mod:`apmgsrn.decomposition.brick_training`) and the replay behind the grid animation
(:func:`train_prepared` with a callback). The steps take an array and plain metadata, not a volume
object, so data that is not one volume (a time series) can be prepared its own way and fitted the same: it
brings its own field class (:func:`register_field_class`), trainer (``train=``) and end of the fit (``output=``,
a :class:`FieldOutput`'s interface), and this module knows nothing of it.

1. :func:`prepare_values`: finite check, value transform, scaling to ``[0, 1]``, onto the device.
2. :func:`train_prepared`: build the field from its config and seed, train it (resuming from a
   checkpoint when one is there) with callbacks; a constant volume needs no training.
3. :func:`fit`: the above, then the PSNR and largest error against the truth, the training summary and
   the model file (atomic), and the checkpoint removed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np
import torch

from apmgsrn.data import Volume
from apmgsrn.data.fingerprint import volume_fingerprint
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.evaluate import Evaluation, evaluate
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.io.container import check_replaceable
from apmgsrn.io.field_file import FIELD_KIND
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig
from apmgsrn.models.value_transform import ValueTransform, fit_value_transform
from apmgsrn.training.callbacks import TrainingProgress
from apmgsrn.training.checkpoint import checkpoint_path_for
from apmgsrn.training.timing import resumed_budget, size_for_minutes
from apmgsrn.training.trainer import TrainConfig, Trainer, TrainingCallback, TrainingState

#: Field classes of model configs other than :class:`FieldConfig` (config type -> class built with the same
#: arguments as :class:`NeuralField`); the time-series package registers its own (:func:`register_field_class`).
_FIELD_CLASSES: dict[type, type] = {}


def register_field_class(config_type: type, field_class: type) -> None:
    """Make :func:`build_field` (and so :func:`train_prepared`) build ``field_class`` for configs of
    ``config_type``."""
    _FIELD_CLASSES[config_type] = field_class


@dataclass(frozen=True)
class PreparedValues:
    """Values ready for training, and what maps the network's output back to data units.

    Attributes:
        values: ``[D, H, W]`` (a series: ``[T, D, H, W]``) float32 in ``[0, 1]`` (fitted units scaled by their
            range), on the device.
        transform: the value transform, fitted on the data.
        fit_min, fit_max: value range in fitted units (after the transform).
        value_min, value_max: value range in data units.
    """

    values: torch.Tensor
    transform: ValueTransform
    fit_min: float
    fit_max: float
    value_min: float
    value_max: float

    @property
    def constant(self) -> bool:
        """Every value is the same: the output scaling alone reproduces it exactly."""
        return not self.fit_max - self.fit_min > 0


def prepare_values(
    data: np.ndarray, transform: str, log_offset: float, where: str, device: torch.device
) -> PreparedValues:
    """Check, transform and scale values for training (``data`` itself is left as it is).

    Args:
        data: ``[D, H, W]`` float32 values in data units (``[T, D, H, W]`` for a series: one transform and
            one scaling for every step).
        transform: value transform kind (``none``, ``log10``, ``zscore``), fitted on ``data``.
        log_offset: offset for ``log10``.
        where: the data's file (and region), for error messages.
        device: training device.

    Raises:
        ApmgsrnError: NaN or Inf values, or a transform the values do not allow.
    """
    finite = int(np.count_nonzero(np.isfinite(data)))
    if finite < data.size:
        raise ApmgsrnError(
            f"{where}: {data.size - finite} of {data.size} voxels are NaN or Inf; "
            "pass fill_nonfinite=VALUE to replace them (e.g. fill_nonfinite=0)", arguments=("fill_nonfinite",),
        )
    value_min, value_max = float(data.min()), float(data.max())
    value_transform = fit_value_transform(transform, [data], value_min, log_offset, where)
    fitted = value_transform.apply(data)
    fit_min, fit_max = float(fitted.min()), float(fitted.max())
    span = fit_max - fit_min
    # In place where the transform already made a copy: one extra volume-sized array at most.
    scaled = np.array(fitted, dtype=np.float32) if fitted is data else np.ascontiguousarray(fitted, np.float32)
    scaled -= np.float32(fit_min)
    # A constant volume has no range: fit zeros, and the output scaling returns the constant exactly.
    scaled /= np.float32(span if span > 0 else 1.0)
    values = torch.from_numpy(scaled).to(device)  # [D, H, W] (or [T, D, H, W]) in [0, 1]
    return PreparedValues(values, value_transform, fit_min, fit_max, value_min, value_max)


def check_output(out: Path, resume: bool, kind: str = FIELD_KIND) -> None:
    """Refuse, before any work, an output whose folder is missing, a file there that is not an older model
    of ``kind`` (``field`` or ``series``), or a leftover checkpoint that ``resume`` does not take.

    Raises:
        ApmgsrnError: the folder does not exist, ``out`` is a file a model may not replace, or an
            interrupted run's checkpoint is there.
    """
    out = Path(out)
    check_replaceable(out, kind)
    if not out.absolute().parent.is_dir():
        raise ApmgsrnError(f"{out}: output folder {out.parent} does not exist; create it or pass another out=",
                           arguments=("out",))
    checkpoint = checkpoint_path_for(out)
    if checkpoint.exists() and not resume:
        raise ApmgsrnError(
            f"{checkpoint}: an interrupted run left this checkpoint; pass resume=True to continue it, "
            "or delete it to start over", arguments=("resume",),
        )


@dataclass(frozen=True)
class TrainedField:
    """A field after :func:`train_prepared`.

    Attributes:
        field: the trained field, in eval mode.
        state: the trainer's final state (iterations, time, history); a fresh one for a constant volume.
        resumed_from: iteration the run resumed at from a checkpoint (0: fresh).
        summary: entries the training adds to the model file's training summary (a stepwise series: its
            start step and every step's iterations).
    """

    field: NeuralField
    state: TrainingState
    resumed_from: int
    summary: dict = dataclass_field(default_factory=dict)


def build_field(prepared: PreparedValues, field_config: FieldConfig, volume_shape: tuple[int, int, int],
                seed: int) -> NeuralField:
    """A fresh field of ``field_config`` (of the class registered for its type, :func:`register_field_class`; a
    series config: a series field) with the value scaling of ``prepared``, initialised from ``seed``, on the
    values' device."""
    field_class = _FIELD_CLASSES.get(type(field_config), NeuralField)
    return field_class(
        field_config,
        fit_min=prepared.fit_min,
        fit_max=prepared.fit_max,
        value_min=prepared.value_min,
        value_max=prepared.value_max,
        transform=prepared.transform,
        volume_shape=volume_shape,
        generator=torch.Generator().manual_seed(seed),
    ).to(prepared.values.device)


def train_prepared(
    prepared: PreparedValues,
    field_config: FieldConfig,
    train_config: TrainConfig,
    volume_shape: tuple[int, int, int],
    checkpoint: Path | None = None,
    fingerprint: dict | None = None,
    callbacks: Sequence[TrainingCallback] = (),
) -> TrainedField:
    """Build a field (initialised from ``train_config.seed``) and train it on prepared values.

    Args:
        prepared: the values and their scaling (``[T, D, H, W]`` values for a series).
        field_config: the model to build: a :class:`FieldConfig`, or another registered config (a series').
        train_config: how to train.
        volume_shape: ``(D, H, W)`` of the data (of every step of a series), saved with the field.
        checkpoint: periodic training checkpoints go here; one already there is resumed (None: none).
        fingerprint: what a resumed checkpoint must match (data and model).
        callbacks: called around every iteration.
    """
    field = build_field(prepared, field_config, volume_shape, train_config.seed)
    if prepared.constant:
        # Empty space (a constant brick) is exact without training: the output scaling returns the
        # constant whatever the network says.
        return TrainedField(field.eval(), TrainingState(), 0)
    trainer = Trainer(field, prepared.values, train_config, checkpoint, fingerprint, callbacks)
    if checkpoint is not None and Path(checkpoint).exists():
        trainer.load_checkpoint(checkpoint)
    resumed_from = trainer.state.iteration
    return TrainedField(field, trainer.run(), resumed_from)


@dataclass(frozen=True)
class FitResult:
    """What :func:`fit` made.

    Attributes:
        field: the trained field.
        model_path: its model file.
        model_bytes: the file's size.
        seconds: training time (a resumed run counts its earlier part too; a packed series' packing search and
            quantisation-aware fine-tune too).
        iterations: iterations run (fewer than the budget after an early stop; 0 for a constant volume).
        frozen_at: iteration where the grids stopped moving.
        stopped_early: training ended before the budget (early stop, or a constant volume).
        resumed_from: iteration the run resumed at (0: fresh).
        evaluation: PSNR and largest error against the truth, data units (what the fit's output measures: per
            step and overall for a series).
        training: what the training function added to the file's summary (:attr:`TrainedField.summary`).
    """

    field: NeuralField
    model_path: Path
    model_bytes: int
    seconds: float
    iterations: int
    frozen_at: int | None
    stopped_early: bool
    resumed_from: int
    evaluation: Evaluation
    training: dict = dataclass_field(default_factory=dict)

    def packed_summary(self, batch_size: int, device) -> dict:
        """The training summary a packed file of this fit keeps: no loss history and no plan (a packed file's
        bytes are the point of packing)."""
        return {"iterations": self.iterations, "batch_size": batch_size, "seconds": round(self.seconds, 3),
                "frozen_at": self.frozen_at, "stopped_early": self.stopped_early, "device": str(device)}

    @property
    def psnr(self) -> float:
        return self.evaluation.psnr

    @property
    def max_abs_error(self) -> float:
        return self.evaluation.max_abs_error


@dataclass(frozen=True)
class FieldOutput:
    """How :func:`fit` ends for one volume: the field rounded to what its file stores, measured against the
    truth, saved as a ``field`` file. Data of another kind brings its own object with this interface (a time
    series: :class:`apmgsrn.series.fit.SeriesOutput`, which packs and measures every step)."""

    #: The kind of file written (what ``out`` may replace: :func:`check_output`).
    kind: str = FIELD_KIND

    def finish(self, trained: TrainedField, prepared: PreparedValues, truth: np.ndarray, train_config: TrainConfig,
               checkpoint: Path, psnr_voxels: int | None) -> tuple[Evaluation, dict, Callable[..., object]]:
        """Make the trained field what the file gives back and measure it.

        Returns:
            The evaluation, entries the training summary starts with, and what writes the file
            (``write(out, field, source, summary)``).
        """
        trained.field.round_to_storage()  # measure what the file will give back
        return evaluate(trained.field, truth, max_voxels=psnr_voxels), {}, save_field


def fit(
    prepared: PreparedValues,
    truth: np.ndarray,
    field_config: FieldConfig,
    train_config: TrainConfig,
    out: Path,
    source: SourceInfo,
    fingerprint: dict,
    resume: bool = False,
    callbacks: Sequence[TrainingCallback] = (),
    psnr_voxels: int | None = None,
    summary_extra: dict | None = None,
    train: Callable[..., TrainedField] = train_prepared,
    output: FieldOutput | None = None,
) -> FitResult:
    """Train a field on prepared values, measure it against the truth and save it to ``out``.

    Checkpoints go to ``out.ckpt`` on the way and are removed once the model file is written.

    Args:
        prepared: the values and their scaling (:func:`prepare_values`).
        truth: ``[D, H, W]`` the same values in data units, for the final PSNR and largest error;
            ``[T, D, H, W]`` for a series.
        field_config: the model to build (a series' config for a series).
        train_config: how to train.
        out: model file to write (atomically).
        source: description of the data, saved in the file.
        fingerprint: what a resumed checkpoint must match.
        resume: continue from ``out.ckpt`` if it exists (else a leftover checkpoint is refused).
        callbacks: called around every iteration (e.g. :class:`~apmgsrn.training.callbacks.TrainingProgress`).
        psnr_voxels: measure on a regular subset of about this many voxels (None: every voxel).
        summary_extra: more entries of the training summary (e.g. the brick's box).
        train: trains the field (:func:`train_prepared`'s signature; a series trained step by step passes
            :func:`~apmgsrn.series.steps.train_stepwise`).
        output: how the fit ends: what it measures and the file it writes (None: :class:`FieldOutput`, one
            volume's ``field`` file; a series: :class:`apmgsrn.series.fit.SeriesOutput`).

    Raises:
        TrainingInterrupted: Ctrl-C in training (or in what ``output`` does after it, a series' packing), with a
            checkpoint to resume from.
    """
    out = Path(out)
    output = FieldOutput() if output is None else output
    check_output(out, resume, output.kind)
    checkpoint = checkpoint_path_for(out)
    trained = train(prepared, field_config, train_config, tuple(truth.shape[-3:]), checkpoint, fingerprint, callbacks)
    evaluation, first_entries, write = output.finish(trained, prepared, truth, train_config, checkpoint, psnr_voxels)
    summary_extra = {**first_entries, **(summary_extra or {})}
    state = trained.state
    summary = {
        "iterations": state.iteration,
        "batch_size": train_config.batch_size,
        "seconds": round(state.elapsed, 3),
        "frozen_at": state.frozen_at,
        "stopped_early": state.iteration < train_config.iterations,
        "final_reconstruction_loss": state.history["reconstruction"][-1] if state.history["reconstruction"] else None,
        "final_density_loss": _last_finite(state.history["density"]),
        "psnr": evaluation.psnr,
        "max_abs_error": evaluation.max_abs_error,
        "device": str(prepared.values.device),
        "config": asdict(train_config),
        "history": state.history,
        **summary_extra,
        **trained.summary,
    }
    write(out, trained.field, source, summary)
    if checkpoint.exists():
        checkpoint.unlink()
    return FitResult(
        field=trained.field,
        model_path=out,
        model_bytes=out.stat().st_size,
        seconds=state.elapsed,
        iterations=state.iteration,
        frozen_at=state.frozen_at,
        stopped_early=summary["stopped_early"],
        resumed_from=trained.resumed_from,
        evaluation=evaluation,
        training=trained.summary,
    )


def fit_volume(
    volume: Volume,
    field_config: FieldConfig,
    train_config: TrainConfig,
    out: Path,
    device: torch.device,
    transform: str = "none",
    log_offset: float = 0.0,
    resume: bool = False,
    progress: bool = True,
    plan: dict | None = None,
    minutes: float | None = None,
) -> FitResult:
    """Train a model on a whole volume and save it to ``out`` (the ``train`` command).

    Args:
        volume: the data.
        field_config: the model to build.
        train_config: how to train.
        out: model file to write (atomically).
        device: training device.
        transform: value transform (``none``, ``log10``, ``zscore``).
        log_offset: offset for ``log10``.
        resume: continue from ``out.ckpt`` if it exists.
        progress: show training progress (see :mod:`apmgsrn.progress`).
        plan: the run's plan (:meth:`apmgsrn.planning.Plan.record`), kept in the training summary.
        minutes: a time budget: the iterations are sized to this machine first (:func:`timed_config`).
    """
    check_output(out, resume)  # before reading what may be a large volume
    data = volume.to_numpy()  # [D, H, W] float32, data units
    prepared = prepare_values(data, transform, log_offset, str(volume.path), device)
    extra = {"plan": plan} if plan else {}
    if minutes is not None:
        train_config, budget = timed_config(prepared, field_config, train_config, tuple(volume.shape), minutes,
                                            checkpoint_path_for(out) if resume else None,
                                            print if progress else None)
        extra.update(time_budget=budget)
    source = SourceInfo.of_volume(volume)
    # A resume must continue on the same data: the file's real path (any link to it will do) and a hash of a
    # sample of its values, not its name.
    fingerprint = {"data": volume_fingerprint(volume), "field": field_config.to_dict(),
                   "transform": asdict(prepared.transform)}
    return fit(prepared, data, field_config, train_config, out, source, fingerprint, resume=resume,
               callbacks=[TrainingProgress(enabled=progress)], summary_extra=extra or None)


def timed_config(prepared: PreparedValues, field_config, train_config: TrainConfig,
                 volume_shape: tuple[int, int, int], minutes: float, checkpoint: Path | None = None,
                 log: Callable[[str], None] | None = None) -> tuple[TrainConfig, dict]:
    """``train_config`` sized to ``minutes`` on this machine (:func:`~apmgsrn.training.timing.size_for_minutes`,
    on a throwaway field of the run's model), or, resuming from ``checkpoint``, to what the interrupted run chose;
    and what the file's summary records of it."""
    if checkpoint is not None and checkpoint.exists():
        sized = resumed_budget(checkpoint, train_config)
        return sized, {"minutes": minutes, "iterations": sized.iterations, "resumed": True}
    probe = build_field(prepared, field_config, volume_shape, train_config.seed)
    sized, budget = size_for_minutes(probe, prepared.values, train_config, minutes)
    if log is not None:
        log(budget.line())
    return sized, budget.to_dict()


def _last_finite(values: list[float]) -> float | None:
    for value in reversed(values):
        if value == value:  # not NaN
            return value
    return None
