"""Fitting a time series: ``apmgsrn train`` on several steps, one model file for all of them.

Two ways to train (docs/time_series.md measures both):

- **stepwise** (the default): a model on the step with the most detail, then every other step's own grids
  fine-tuned from its neighbour's, placement and decoder shared (:mod:`apmgsrn.series.steps`),
  stored packed (grids quantised, one step size per grid and channel for the whole series, coded as what
  changes from one step to the next);
- **joint**: one shared model of every step, trained on all of them at once (a basis of grids mixed per
  step, :mod:`apmgsrn.series.field`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SeriesStepInfo, SourceInfo
from apmgsrn.io.container import PACKED_SERIES_KIND, SERIES_KIND
from apmgsrn.series.data import VolumeSeries, series_fingerprint
from apmgsrn.series.evaluate import SeriesEvaluation, evaluate_series
from apmgsrn.series.field import SeriesFieldConfig
from apmgsrn.series.file import save_series
from apmgsrn.series.packing import (
    PackedSeries,
    SeriesPacking,
    series_overhead,
    series_packing_report,
    write_packed_series,
)
from apmgsrn.series.qat import budgeted
from apmgsrn.series.steps import StepwiseConfig, series_trainer
from apmgsrn.training.callbacks import TrainingProgress
from apmgsrn.training.fit import FitResult, PreparedValues, TrainedField, check_output, fit, prepare_values
from apmgsrn.recipes import SERIES
from apmgsrn.training.trainer import TrainConfig, TrainingInterrupted


def series_budget(iterations: int, steps: int) -> int:
    """Iterations of a time series of ``steps`` steps, given those of one volume.

    Consecutive steps share most of what they hold, and every iteration trains the shared grids and decoder
    on several steps at once, so the series needs far less than one budget per step.
    """
    return max(1, round(iterations * min(float(steps), SERIES.joint_budget_steps)))


@dataclass(frozen=True)
class SeriesOutput:
    """How :func:`~apmgsrn.training.fit.fit` ends for a time series (its ``output``; the interface of
    :class:`~apmgsrn.training.fit.FieldOutput`): pack the field (with the fine-tunes towards the packing), measure
    every step and write a ``series`` or ``packed-series`` file.

    Attributes:
        steps: each step's number, name and value range, saved in the file.
        packing: how to pack the grids (a ``packed-series`` file; None: the series file of its config's storage
            dtype).
        tune_packed: with ``packing.qat_iterations``: fine-tunes the field towards its first packing
            (:func:`~apmgsrn.series.qat.fine_tune_rounded`'s signature, less ``show_progress``).
        tune_decoder: with ``packing.decoder_iterations``: fine-tunes its decoder to the coded grids
            (:func:`~apmgsrn.series.decoder.fine_tune_decoder`'s signature, less ``show_progress``).
        source: where the data came from, as the file will say (a size target allows for its description:
            :func:`~apmgsrn.series.packing.series_overhead`; None: a placeholder of usual length).
    """

    steps: Sequence[SeriesStepInfo]
    packing: SeriesPacking | None = None
    tune_packed: Callable[..., tuple[int, float]] | None = None
    tune_decoder: Callable[..., tuple[int, float]] | None = None
    source: SourceInfo | None = None

    @property
    def kind(self) -> str:
        return SERIES_KIND if self.packing is None else PACKED_SERIES_KIND

    def finish(self, trained: TrainedField, prepared: PreparedValues, truth: np.ndarray, train_config: TrainConfig,
               checkpoint: Path, psnr_voxels: int | None) -> tuple[SeriesEvaluation, dict, Callable[..., object]]:
        """Pack (or round) the trained series, measure every step; the summary's first entries (each step's
        PSNR and largest error) and what writes the file.

        Raises:
            TrainingInterrupted: Ctrl-C in the packing, with the training's checkpoint to resume from.
        """
        packing, steps = self.packing, list(self.steps)
        if packing is None:
            trained.field.round_to_storage()  # measure what the file will give back
            evaluation = evaluate_series(trained.field.step_field, truth, max_voxels=psnr_voxels)

            def write(out, field, source, summary):
                return save_series(out, field, source, summary, steps)
        else:
            before = evaluate_series(trained.field.step_field, truth, max_voxels=psnr_voxels)
            # The packing search and the fine-tune towards it are part of making the model: they count in its
            # training time (the evaluations, as for one volume, do not).
            started = time.perf_counter()
            try:
                overhead = series_overhead(trained.field, self.source, trained.summary, steps)
                packed = packing.pack(trained.field, overhead)
                if packing.qat_iterations and self.tune_packed is None:
                    raise ValueError("packing.qat_iterations needs tune_packed")
                if packing.decoder_iterations and self.tune_decoder is None:
                    raise ValueError("packing.decoder_iterations needs tune_decoder")

                def tune(to: PackedSeries, iterations: int) -> None:  # towards the packing's steps
                    ran, _ = self.tune_packed(trained.field, prepared.values, to, train_config, iterations)
                    trained.state.iteration += ran

                packed, tuned = packing.fine_tune(trained.field, packed, tune)

                def decoder(iterations: int) -> int:  # to the grids as coded
                    return self.tune_decoder(trained.field, prepared.values, train_config, iterations)[0]

                packed, decoder_tuned = packing.tune_decoder(trained.field, packed, decoder)
                trained.state.iteration += decoder_tuned
            except KeyboardInterrupt:  # the checkpoint holds the training: a resume packs again
                if not checkpoint.exists():
                    raise
                raise TrainingInterrupted(trained.state.iteration, checkpoint) from None
            trained.state.elapsed += time.perf_counter() - started
            trained.field.load_state_dict(packed.state)  # measure what the file will give back
            evaluation = evaluate_series(trained.field.step_field, truth, max_voxels=psnr_voxels)
            report = series_packing_report(trained.field, packed.bit_width, before, evaluation, packing.target_bytes,
                                           tuned, len(packed.restored), decoder_tuned)

            def write(out, field, source, summary):
                return write_packed_series(out, field, packed, source, summary, steps, report)
        first = {"steps": [{"psnr": e.psnr, "max_abs_error": e.max_abs_error} for e in evaluation.steps]}
        return evaluation, first, write


def fit_series(
    series: VolumeSeries,
    field_config: SeriesFieldConfig,
    train_config: TrainConfig,
    out: Path,
    device: torch.device,
    transform: str = "none",
    log_offset: float = 0.0,
    resume: bool = False,
    progress: bool = True,
    stepwise: StepwiseConfig | None = None,
    packing: SeriesPacking | None = None,
    plan: dict | None = None,
) -> FitResult:
    """Train one time-series model on every step of a series and save it to ``out``.

    The steps are read one at a time into one ``[T, D, H, W]`` array; the value transform and scaling are
    fitted on all of them, so every step shares the decoder's output range.

    Args:
        series: the data.
        field_config: the model to build; its series config must have ``len(series)`` steps (one basis slice
            per step for ``stepwise``: :func:`~apmgsrn.series.steps.stepwise_config`).
        train_config: how to train: the whole series (joint; the batch is split over ``steps_per_iteration``
            steps), or the start step's model (stepwise).
        out: model file to write (atomically).
        device: training device.
        transform: value transform (``none``, ``log10``, ``zscore``).
        log_offset: offset for ``log10``.
        resume: continue from ``out.ckpt`` if it exists.
        progress: show training progress (see :mod:`apmgsrn.progress`).
        stepwise: train step by step (None: one joint model of all steps).
        packing: how to pack the grids (a ``packed-series`` file); None: a float series file. Its
            quantisation-aware fine-tune after stepwise training shares the steps' budget and is shortened with
            them (:meth:`~apmgsrn.series.steps.StepwiseConfig.budget_scale`).
        plan: the run's plan (:meth:`apmgsrn.planning.Plan.record`), kept in the training summary.

    Returns:
        The result; its evaluation is a :class:`~apmgsrn.series.evaluate.SeriesEvaluation`.
    """
    if field_config.series.steps != len(series):
        raise ValueError(f"the model has {field_config.series.steps} steps, the series {len(series)}")
    check_output(out, resume, SERIES_KIND if packing is None else PACKED_SERIES_KIND)  # before reading the series
    data = series.to_numpy()  # [T, D, H, W] float32, data units
    for t in range(len(series)):  # name the step whose values are not finite
        finite = int(np.count_nonzero(np.isfinite(data[t])))
        if finite < data[t].size:
            raise ApmgsrnError(f"{series.step_name(t)}: step {t} has {data[t].size - finite} of {data[t].size} "
                               "voxels NaN or Inf; pass fill_nonfinite=VALUE to replace them (e.g. "
                               "fill_nonfinite=0)", arguments=("fill_nonfinite",))
    prepared = prepare_values(data, transform, log_offset, series.describe(), device)
    source = SourceInfo(series.step_name(0), series.variable, series.describe())
    steps = [SeriesStepInfo(label, series.step_name(t), (float(data[t].min()), float(data[t].max())))
             for t, label in enumerate(series.labels)]
    # A resume must continue on the same steps: each file's real path and a hash of a sample of its values.
    fingerprint = {"data": series_fingerprint(series), "field": field_config.to_dict(),
                   "transform": asdict(prepared.transform)}
    # Stepwise, the steps' fine-tunes and the one towards the packing share one budget.
    stepwise, packing, tune_packed, tune_decoder = budgeted(stepwise, packing, train_config, len(series),
                                                            field_config, data.shape[1:], device, progress)
    display = TrainingProgress("train" if stepwise is None else "start step", enabled=progress)
    return fit(prepared, data, field_config, train_config, out, source, fingerprint, resume=resume,
               callbacks=[display], train=series_trainer(stepwise, progress),
               output=SeriesOutput(steps, packing, tune_packed, tune_decoder, source),
               summary_extra={"plan": plan} if plan else None)
