"""Quantisation-aware fine-tune of a stepwise series: every step's feature grids (or tables) trained towards the
integers the packed file stores them as.

Packing a series rounds every step's grids to steps shared by all steps (:mod:`apmgsrn.series.packing`);
where the file must hold 30 steps in five single-step files that rounding costs most of what separates the
steps from their own models (the 30 viscous-finger steps: 0.8 dB at 7.25 bits). Here each step, once the
packing's steps are known, gets a short fine-tune in which the forward pass sees its grids rounded to those
steps and the gradient moves the float values beneath (straight-through), the decoder and placement kept.
Its voxel points are drawn where the rounded step is wrong, as a step's fine-tune draws them: with uniform
draws the same fine-tune lost 1.1 dB instead of gaining. The field then holds the float values; packing it on
the same steps stores what was trained (:meth:`~apmgsrn.series.packing.SeriesPacking.repack`).

The steps are independent here, so a CPU process with several threads fine-tunes as many steps at once, one
thread each (:func:`qat_lanes`): on two threads the 30 viscous-finger steps take 46-47 s instead of 58-61, and
every step ends as it does on one thread.

``train --qat-iterations N`` runs it at the end of a series' training, ``pack SERIES DATA --qat-iterations N`` on
a float series file (from the training settings the file recorded). A single field's fine-tune
(:func:`~apmgsrn.training.packing.quantization_aware_fine_tune`) quantises every parameter of one network on
random points; here only a step's own grids are rounded and the trainer's guided voxel draws pick the points.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import partial

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.io.quantization import group_ids
from apmgsrn.series.field import SeriesField
from apmgsrn.progress import Progress
from apmgsrn.recipes import PACKING, PackingRecipe
from apmgsrn.threads import work_threads
from apmgsrn.series.decoder import fine_tune_decoder
from apmgsrn.series.packing import SHARED_STEP_TENSORS, PackedSeries, SeriesPacking, packed_group
from apmgsrn.series.steps import (
    StepwiseConfig,
    load_step,
    shortened_measurements,
    step_shares,
    step_voxel_fraction,
    step_worker,
    store_step,
)
from apmgsrn.training.trainer import TrainConfig, Trainer, TrainingCallback, current_names


class RoundedForward(TrainingCallback):
    """Straight-through rounding of some parameters: the model computes with ``step * round(x / step)``,
    and every update the optimiser makes to those rounded values is applied to the float values ``x`` kept
    here. At the end the parameters hold the float values again."""

    def __init__(self, parameters: list[torch.Tensor], steps: list[torch.Tensor]):
        self.parameters, self.steps = parameters, steps
        self.floats = [p.detach().clone() for p in parameters]

    def on_start(self, trainer: Trainer) -> None:
        self._round()

    @torch.no_grad()
    def after_step(self, trainer: Trainer, iteration: int, losses) -> None:
        for parameter, value, step in zip(self.parameters, self.floats, self.steps):
            value += parameter - torch.round(value / step) * step  # the update made to the rounded value
        self._round()

    @torch.no_grad()
    def on_end(self, trainer: Trainer) -> None:
        for parameter, value in zip(self.parameters, self.floats):
            parameter.copy_(value)

    @torch.no_grad()
    def _round(self) -> None:
        for parameter, value, step in zip(self.parameters, self.floats, self.steps):
            parameter.copy_(torch.round(value / step) * step)


def element_steps(series: SeriesField, packed: PackedSeries) -> dict[str, torch.Tensor]:
    """The step of every element of one step's slice of each per-step feature tensor the packing quantised
    (attribute name of the encoder -> a tensor of the slice's shape)."""
    out = {}
    for name in series.encoder.step_features:
        full = f"encoder.{name}"
        if full not in SHARED_STEP_TENSORS or full not in packed.steps:
            continue
        tensor = getattr(series.encoder, name)
        slice_numel = tensor[0].numel()
        size = packed_group(packed, full, tuple(tensor.shape))
        steps = packed.steps[full].astype(np.float32)
        out[name] = torch.from_numpy(steps[:slice_numel // size][group_ids(slice_numel, size)]).reshape(
            tensor.shape[1:])
    return out


def fine_tune_rounded(series: SeriesField, values: torch.Tensor, packed: PackedSeries, config: TrainConfig,
                      iterations: int, show_progress: bool = True, measurements: int = PACKING.qat_measurements,
                      recipe: PackingRecipe = PACKING) -> tuple[int, float]:
    """Every step's features fine-tuned towards the steps ``packed`` rounds them to (module docstring); the
    series field is changed in place.

    Args:
        series: the trained series field (its decoder and placement are kept).
        values: ``[T, D, H, W]`` the training values.
        packed: the field packed once (its :attr:`~apmgsrn.series.packing.PackedSeries.steps`).
        config: the start model's training (the fine-tune takes its learning rate times the recipe's
            ``qat_lr_share``, the steps' batch share on a CPU, its voxel share, guided at ``qat_guided_share``).
        iterations: each step's iterations.
        show_progress: one line of progress over the steps.
        measurements: times each step's fine-tune measures where it is wrong (fewer where a long series shortened
            it: :func:`~apmgsrn.series.steps.shortened_measurements`).
        recipe: the fine-tune's learning-rate share, guided share and measured parts.

    Returns:
        (iterations run over all steps, seconds).
    """
    began = time.perf_counter()
    steps = element_steps(series, packed)
    if not steps or iterations < 1:
        return 0, 0.0
    device = values.device
    batch_share, _, _ = step_shares(series.config.field.model, device)
    tune = replace(config, iterations=iterations, lr=config.lr * recipe.qat_lr_share, density_start=iterations + 1,
                   history_every=None, stop_after_lr_cuts=None, error_sampling=recipe.qat_guided_share,
                   error_measurements=measurements, error_parts=recipe.qat_error_parts,
                   batch_size=max(1, round(config.batch_size * batch_share)),
                   voxel_fraction=step_voxel_fraction(config.voxel_fraction))
    series.requires_grad_(False)
    step_sizes = [steps[name].to(device) for name in steps]
    lanes = qat_lanes(series.steps, device)
    workers = [step_worker(series).requires_grad_(False) for _ in range(lanes)]
    shown_lock, stop = threading.Lock(), threading.Event()

    def lane(index: int) -> None:
        """Steps ``index``, ``index + lanes``, ... on ``workers[index]``."""
        worker = workers[index]
        if lanes > 1:
            torch.set_num_threads(1)  # this thread's: one core per lane
        parameters = [getattr(worker.encoder, name).requires_grad_(True) for name in steps]
        for t in range(index, series.steps, lanes):
            if stop.is_set():
                return
            load_step(worker, series, t)
            rounded = RoundedForward(parameters, step_sizes)
            Trainer(worker, values[t], tune, None, {}, [rounded], warm=True).run()
            store_step(worker, series, t)
            with shown_lock:
                shown.update(1)

    threads = torch.get_num_threads()
    with Progress(series.steps, unit="step", description="quantisation-aware", enabled=show_progress) as shown:
        if lanes == 1:
            lane(0)
        else:
            with ThreadPoolExecutor(lanes) as pool:
                running = [pool.submit(lane, index) for index in range(lanes)]
                try:
                    for future in running:
                        future.result()
                except BaseException:  # Ctrl-C: the lanes stop after the step they are on
                    stop.set()
                    raise
                finally:
                    torch.set_num_threads(threads)  # torch keeps the last count set as every new thread's
    series.requires_grad_(True)
    return iterations * series.steps, time.perf_counter() - began


def qat_lanes(steps: int, device: torch.device) -> int:
    """How many steps are fine-tuned at once, each on one CPU thread: as many as the process has threads (at
    most one per step) on a CPU, one on a GPU. The steps' fine-tunes are independent of each other, and one
    thread per step keeps the cores busier than all threads on one step's small batch; every step gives what
    it gives on one thread, whatever the process's thread count."""
    return min(work_threads(), steps) if device.type == "cpu" else 1


def budgeted(stepwise: StepwiseConfig | None, packing: SeriesPacking | None, config: TrainConfig, steps: int,
             field_config, volume_shape: tuple[int, int, int], device: torch.device, show_progress: bool = True
             ) -> tuple[StepwiseConfig | None, SeriesPacking | None, Callable[..., tuple[int, float]],
                        Callable[..., tuple[int, float]]]:
    """What ``fit`` trains a model of ``field_config`` on ``steps`` steps with. A series trained stepwise: its
    steps' fine-tunes and the quantisation-aware one after them under one budget
    (:meth:`~apmgsrn.series.steps.StepwiseConfig.budget_scale`): the stepwise config that counts the
    packing's fine-tune, the packing with that fine-tune shortened with the steps', and the fine-tune (``fit``'s
    ``tune_packed``) measuring as often per iteration as an unshortened one. Anything else (no ``stepwise``: a
    joint series, one volume): as given, with the fine-tune as it is. Last, the decoder's fine-tune to the coded
    grids (``fit``'s ``tune_decoder``, :func:`~apmgsrn.series.decoder.fine_tune_decoder`), outside the
    budget: 300 iterations take about 10 s, the steps' fine-tunes shortened by as many points lost more than it
    gains (docs/time_series.md).

    A series whose packing target holds every step coded alone at its bit width
    (:meth:`~apmgsrn.series.packing.SeriesPacking.holds_every_step_alone`: a few steps; eight of the small
    hybrid's within five files at 10 bits) is trained unpulled (``step_sparsity`` 0) unless a pull was asked for.
    The pull only saves bytes, which such a series does not lack, and over the long fine-tunes of steps that change
    much it held them far from their data: on three steps 40 apart (t010, t050, t090) t010 fine-tuned from t050
    for its 9,321 iterations reached 70.62 dB pulled at 0.01 and 74.26 unpulled (its own model 72.90;
    docs/time_series.md)."""
    recipe = PACKING if packing is None else packing.recipe
    measurements = recipe.qat_measurements
    if (stepwise is not None and packing is not None and stepwise.step_sparsity is None
            and packing.holds_every_step_alone(field_config.fitted_to(volume_shape), steps)):
        stepwise = replace(stepwise, step_sparsity=0.0)
    if stepwise is not None and packing is not None and packing.qat_iterations:
        stepwise = replace(stepwise, qat_iterations=packing.qat_iterations)
        shares = step_shares(field_config.field.model, device)
        packing = replace(packing, qat_iterations=stepwise.shortened_qat(config, steps - 1, *shares))
        measurements = shortened_measurements(measurements, stepwise.budget_scale(config, steps - 1, *shares))
    return (stepwise, packing,
            partial(fine_tune_rounded, show_progress=show_progress, measurements=measurements, recipe=recipe),
            partial(fine_tune_decoder, show_progress=show_progress))


def stored_train_config(training: dict, where: str, purpose: str = "a quantisation-aware fine-tune") -> TrainConfig:
    """The training settings a model file recorded (its summary's ``config``), as a :class:`TrainConfig`, for
    ``purpose`` (what the message names should they be missing).

    Raises:
        ApmgsrnError: missing, or not settings the loop can run with (a damaged or hostile file).
    """
    stored = training.get("config") if isinstance(training, dict) else None
    if not isinstance(stored, dict):
        raise ApmgsrnError(f"{where}: the file does not record its training settings, which {purpose} starts from "
                           "(a packed file keeps none: pack the float series file it was packed from)")
    known = {key: value for key, value in current_names(stored).items() if key in TrainConfig.__dataclass_fields__}
    try:
        return TrainConfig(**known)
    except (InvalidArgument, TypeError, ValueError) as exc:
        raise ApmgsrnError(f"{where}: its recorded training settings are damaged ({exc})") from None
