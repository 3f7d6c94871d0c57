"""Fitting a time series: ``apmgsrn train`` on several steps, one model file for all of them.

Two ways to train (docs/time_series.md measures both):

- **stepwise** (the default): a model on the step with the most detail, then every other step's own grids
  fine-tuned from its neighbour's, placement and decoder shared (:mod:`apmgsrn.training.series_steps`),
  stored packed (grids quantised, one step size per grid and channel for the whole series, coded as what
  changes from one step to the next);
- **joint**: one shared model of every step, trained on all of them at once (a basis of grids mixed per
  step, :mod:`apmgsrn.models.series_field`).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from apmgsrn.data.fingerprint import series_fingerprint
from apmgsrn.data.series import VolumeSeries
from apmgsrn.io import SeriesStepInfo, SourceInfo
from apmgsrn.io.container import PACKED_SERIES_KIND, SERIES_KIND
from apmgsrn.models.series_field import SeriesFieldConfig
from apmgsrn.training.callbacks import TrainingProgress
from apmgsrn.training.fit import FitResult, check_output, fit, prepare_values
from apmgsrn.training.series_packing import SeriesPacking
from apmgsrn.training.series_qat import budgeted
from apmgsrn.training.series_steps import StepwiseConfig, series_trainer
from apmgsrn.training.trainer import TrainConfig


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
            per step for ``stepwise``: :func:`~apmgsrn.training.series_steps.stepwise_config`).
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
            them (:meth:`~apmgsrn.training.series_steps.StepwiseConfig.budget_scale`).
        plan: the run's plan (:meth:`apmgsrn.planning.Plan.record`), kept in the training summary.

    Returns:
        The result; its evaluation is a :class:`~apmgsrn.inference.evaluate.SeriesEvaluation`.
    """
    if field_config.series.steps != len(series):
        raise ValueError(f"the model has {field_config.series.steps} steps, the series {len(series)}")
    check_output(out, resume, SERIES_KIND if packing is None else PACKED_SERIES_KIND)  # before reading the series
    data = series.to_numpy()  # [T, D, H, W] float32, data units
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
               callbacks=[display], steps=steps, packing=packing, train=series_trainer(stepwise, progress),
               tune_packed=tune_packed, tune_decoder=tune_decoder, summary_extra={"plan": plan} if plan else None)
