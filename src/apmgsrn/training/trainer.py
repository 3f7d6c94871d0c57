"""The training loop of docs/method.md §4: two optimisers, delayed and early-stopped grid motion,
a learning rate that follows the iteration budget, atomic checkpoints and exact resume."""

from __future__ import annotations

import copy
import json
import math
import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

from apmgsrn.arguments import MAX_BATCH_SIZE, MAX_ITERATIONS, check_choice, check_int, check_number, check_optional_int
from apmgsrn.choices import DECODER_PRECISIONS, DENSITY_NORMALIZATIONS, LR_SCHEDULES
from apmgsrn.device import inference_dtype
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.io.container import load_tensors, read_header, save_tensors
from apmgsrn.io.description import DescriptionError
from apmgsrn.models.encoders.base import Encoder
from apmgsrn.models.field import NeuralField
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.recipes import VOLUME
from apmgsrn.threads import ThreadGovernor, thread_candidates
from apmgsrn.training.checkpoint import (
    CHECKPOINT_KIND,
    TrainingState,
    check_tensors,
    optimizer_layout,
    state_from_json,
)
from apmgsrn.training.losses import feature_density_loss
from apmgsrn.training.optimizer import CpuAdam
from apmgsrn.training.points import ErrorGuide, draw_batch, spatially_ordered

#: What can move the grid placements (:attr:`TrainConfig.placement_loss`).
PLACEMENT_LOSSES = ("density", "reconstruction")

#: Whether a model's step gives the same numbers on every thread count the governor may choose, by
#: (field kind, parameter shapes, volume dims, batch size, thread counts): see Trainer._thread_invariant.
_THREAD_PROBES: dict[tuple, bool] = {}


@dataclass(frozen=True)
class TrainConfig:
    """How to train (docs/method.md §4; defaults are the paper's unless noted).

    Attributes:
        iterations: total iterations.
        batch_size: random points per iteration.
        lr: Adam learning rate of the grids and decoder.
        placement_lr: Adam learning rate of the grid placements.
        betas: Adam betas of both optimisers.
        density_start: iterations before the density step starts (delayed start); None: 5 % of the
            budget (paper: 500 of 50,000). Measured at 2,000 iterations, grids that move early and stop
            at half the budget leave the features time to settle: +1 to +2 dB over the paper's window.
        density_window: moving-average window of the density loss for early freezing.
        density_tolerance: relative fall below which the grid placements freeze (0.01 %).
        freeze_fraction: the grid placements freeze at this fraction of the budget at the latest (paper: 0.8).
        density_power: ``P`` of the flat-top Gaussian.
        density_normalization: ``"batch"`` (paper: ``rho / sum_X rho``) or ``"mass"`` (ours: share of the
            grids' total feature mass, so mass that leaves the domain counts; see
            :func:`~apmgsrn.training.losses.feature_density_loss`).
        lr_schedule: ``"cosine"`` (ours: constant while the grids move, then a half-cosine to
            ``final_lr_fraction`` over the remaining budget), ``"constant"``, or ``"plateau"`` (paper: x0.1
            when ``L_rec`` stops falling by 0.01 % over 500 iterations, after the grids froze).
            ``"steps"``: x0.33 at 40, 60 and 80 % of the budget (the NGP/fVSRN reference code).
        final_lr_fraction: learning rate at the end of the cosine schedule, relative to ``lr``.
        seed: seeds initialisation and point sampling.
        checkpoint_every: iterations between atomic training checkpoints.
        history_every: iterations between recorded loss-curve points; None: about 500 points in all.
        stop_after_lr_cuts: with ``lr_schedule="plateau"``, end training once the plateau scheduler has cut
            the learning rate this many times (paper, per brick: 3); None: run the whole budget.
        decoder_precision: dtype of the decoder's hidden matrix products in the reconstruction step
            (weights, gradients, optimiser and the output layer stay float32). ``"float32"`` by default;
            ``"auto"``: bfloat16 on CPUs that multiply it natively (AVX512-BF16 or AMX), float32 elsewhere.
            bfloat16 trains 1.5x faster on such a CPU but costs PSNR where the model is accurate: 0.09 dB on
            neghip (38 dB), 0.75 dB on a viscous-finger step (58 dB), small preset, 2,000 iterations
            (docs/benchmarks.md). Evaluation always runs in float32.
        voxel_fraction: share of every batch drawn at voxel positions with the voxels' own values as
            targets (:func:`~apmgsrn.training.points.draw_batch`); the rest are uniform points with trilinear
            targets. 0 (docs/method.md §4, and what older checkpoints ran with): uniform points only. The model
            kinds' own defaults are in :func:`apmgsrn.models.registry.training_defaults`.
        steps_per_iteration: a time series only: the batch is split evenly over this many steps (every step is
            visited once per round of ``T / steps_per_iteration`` iterations).
        anchored_grids: the first this many adaptive grids keep the placement they started with (the density
            loss moves the others). With the default initialisation they cover the whole domain, so no
            region is ever left without features: a point no grid covers decodes to the bottom of the value
            range. 0 (docs/method.md §3, and what older checkpoints ran with): every grid moves. Small models
            sized for a byte target anchor one (:func:`apmgsrn.training.sizing.anchored_grids_for`).
        placement_loss: what moves the grid placements. ``"density"`` (docs/method.md §4): the feature-density
            loss, between ``density_start`` and the freeze. ``"reconstruction"``: the reconstruction error
            itself, from the first iteration until the freeze, at ``placement_lr`` scaled by the network's
            schedule; no density loss. It follows structures that moved (a time series' step fine-tuned from
            its neighbour's grids, :mod:`apmgsrn.series.steps`) and costs about 1.4 times the
            iteration time on CPU (the fused kernel gives the placement's gradient; elsewhere the reference
            multi-grid path runs, about 2.4 times).
        error_sampling: share of the voxel points (``voxel_fraction``) drawn in proportion to the model's
            absolute error at the voxels, measured ``error_measurements`` times in the run
            (:class:`~apmgsrn.training.points.ErrorGuide`); the rest of them uniformly. 0 (and what older
            checkpoints ran with): uniformly; nothing changes without voxel points. A single volume (or a
            series' step) only. The model kinds' own defaults are in
            :func:`apmgsrn.models.registry.training_defaults`; docs/models.md has the measurements. A
            checkpoint keeps the last measurement, so a resumed run draws what the uninterrupted one would.
        error_measurements: how many times a run with ``error_sampling`` measures the error, evenly spaced (the
            first before its first iteration; ``VOLUME.error_measurements`` by default).
        error_parts: each measurement after the first re-measures one of this many interleaved parts of the
            voxels in turn, the others keeping their last errors (:class:`~apmgsrn.training.points.ErrorGuide`):
            this many times cheaper. 1 (and what older checkpoints ran with): every voxel every time.
    """

    iterations: int = 2000
    batch_size: int = 32768
    lr: float = 0.01
    placement_lr: float = 0.001
    betas: tuple[float, float] = (0.9, 0.99)
    density_start: int | None = None
    density_window: int = 1000
    density_tolerance: float = 1e-4
    freeze_fraction: float = 0.5
    density_power: int = 10
    density_normalization: str = "mass"
    lr_schedule: str = "cosine"
    final_lr_fraction: float = 0.01
    seed: int = 0
    checkpoint_every: int = 250
    history_every: int | None = None
    stop_after_lr_cuts: int | None = None
    decoder_precision: str = "float32"
    steps_per_iteration: int = 4
    voxel_fraction: float = 0.0
    anchored_grids: int = 0
    placement_loss: str = "density"
    error_sampling: float = 0.0
    error_measurements: int = VOLUME.error_measurements
    error_parts: int = 1

    def __post_init__(self) -> None:
        """Refuse every value the loop cannot run with (:class:`~apmgsrn.errors.InvalidArgument`)."""
        check_int("iterations", self.iterations, 1, MAX_ITERATIONS)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH_SIZE)
        check_number("lr", self.lr, 0.0)  # 0 is allowed: a frozen network (or grid maps) is a valid experiment
        check_number("placement_lr", self.placement_lr, 0.0)
        if not isinstance(self.betas, (tuple, list)) or len(self.betas) != 2:
            raise InvalidArgument(f"betas={self.betas!r}: must be two numbers in [0, 1)", arguments=("betas",))
        object.__setattr__(self, "betas", tuple(check_number("betas", b, 0.0, 1.0, high_open=True)
                                                for b in self.betas))
        if self.history_every is None:
            object.__setattr__(self, "history_every", max(10, self.iterations // 500))
        if self.density_start is None:
            object.__setattr__(self, "density_start", max(1, round(0.05 * self.iterations)))
        check_int("steps_per_iteration", self.steps_per_iteration, 1)
        check_int("density_start", self.density_start, 0, MAX_ITERATIONS)
        check_int("density_window", self.density_window, 1)
        check_number("density_tolerance", self.density_tolerance, 0.0, 1.0)
        check_number("freeze_fraction", self.freeze_fraction, 0.0, 1.0)
        check_int("density_power", self.density_power, 1, 64)
        check_choice("density_normalization", self.density_normalization, DENSITY_NORMALIZATIONS)
        check_choice("lr_schedule", self.lr_schedule, LR_SCHEDULES)
        check_number("final_lr_fraction", self.final_lr_fraction, 0.0, 1.0)
        check_int("seed", self.seed, 0, 2**63 - 1)
        check_int("checkpoint_every", self.checkpoint_every, 1, MAX_ITERATIONS)
        check_int("anchored_grids", self.anchored_grids, 0)
        check_choice("placement_loss", self.placement_loss, PLACEMENT_LOSSES)
        check_int("history_every", self.history_every, 1)
        check_optional_int("stop_after_lr_cuts", self.stop_after_lr_cuts, 1)
        check_choice("decoder_precision", self.decoder_precision, DECODER_PRECISIONS)
        object.__setattr__(self, "voxel_fraction", check_number("voxel_fraction", self.voxel_fraction, 0.0, 1.0))
        object.__setattr__(self, "error_sampling", check_number("error_sampling", self.error_sampling, 0.0, 1.0))
        check_int("error_measurements", self.error_measurements, 1)
        check_int("error_parts", self.error_parts, 1)

    @property
    def error_guided(self) -> bool:
        """Whether some voxel points are drawn where the model is wrong (:attr:`error_sampling` of voxel points)."""
        return self.error_sampling > 0 and self.voxel_fraction > 0


#: Names older versions stored for today's :class:`TrainConfig` fields.
RENAMED = {"transform_lr": "placement_lr"}
#: :class:`TrainConfig` fields added since, with the value the versions without them ran with.
ADDED = {"voxel_fraction": 0.0, "anchored_grids": 0, "placement_loss": "density", "error_sampling": 0.0,
         "error_measurements": 20, "error_parts": 1}


def current_names(stored: dict) -> dict:
    """A stored training config with the names and fields this version uses, so that brick folders and
    checkpoints written before the grid maps were called placements, or before a field existed, still match
    their runs."""
    if not isinstance(stored, dict):
        return stored
    return {**ADDED, **{RENAMED.get(key, key): value for key, value in stored.items()}}


def default_budget(device: torch.device) -> tuple[int, int]:
    """(iterations, batch size) sized for the device: minutes on a 2-core CPU, the paper's on a GPU."""
    if device.type == "cuda":
        return VOLUME.gpu_iterations, VOLUME.gpu_batch_size
    return VOLUME.cpu_iterations, VOLUME.cpu_batch_size


class TrainingInterrupted(Exception):
    """Raised after Ctrl-C once the checkpoint is safely written."""

    def __init__(self, iteration: int, checkpoint: Path):
        super().__init__(f"interrupted at iteration {iteration}; checkpoint saved to {checkpoint}")
        self.iteration = iteration
        self.checkpoint = checkpoint


class StepLosses(NamedTuple):
    """Losses of one iteration, detached 0-d tensors on the training device (reading one syncs a GPU)."""

    reconstruction: torch.Tensor
    density: torch.Tensor | None  # None once the grids stopped moving (or before they start)


class TrainingCallback:
    """Hooks of the training loop; subclass and override what you need (each does nothing by default).

    The loop calls :meth:`on_start` before the first iteration (after a resume: at the resumed one),
    :meth:`after_step` after every iteration, and :meth:`on_end` when the loop stops for any reason.
    """

    def on_start(self, trainer: Trainer) -> None:
        """Training is about to start at ``trainer.state.iteration``."""

    def after_step(self, trainer: Trainer, iteration: int, losses: StepLosses) -> None:
        """Iteration ``iteration`` (counted from 1) is done: the parameters are updated."""

    def on_end(self, trainer: Trainer) -> None:
        """The loop stopped: budget spent, early stop, Ctrl-C or an error."""


class _GovernThreads(TrainingCallback):
    """Runs the loop under the trainer's :class:`~apmgsrn.threads.ThreadGovernor`, one unit per step."""

    def on_start(self, trainer: Trainer) -> None:
        trainer.thread_governor.__enter__()

    def after_step(self, trainer: Trainer, iteration: int, losses: StepLosses) -> None:
        trainer.thread_governor.tick()

    def on_end(self, trainer: Trainer) -> None:
        trainer.thread_governor.__exit__(None, None, None)


class Trainer:
    """Fits a :class:`NeuralField` to a volume (or a series field to a series) of values scaled to ``[0, 1]``.

    Args:
        field: the model (its ``fit_min``/``fit_max`` give the scaling to data units).
        volume: ``[D, H, W]`` fitted values scaled to ``[0, 1]``, on the training device; ``[T, D, H, W]``
            for a :class:`~apmgsrn.series.field.SeriesField` (one volume per step).
        config: how to train.
        checkpoint_path: where periodic training checkpoints go (None: no checkpoints).
        fingerprint: description of the run that a resumed checkpoint must match.
        callbacks: called around every iteration (progress display, grid recording, ...).
        warm: the field is trained already (a series step fine-tuned from its neighbour): the encoder does not
            start from the data (:meth:`~apmgsrn.models.encoders.base.Encoder.initialize_from_volume`).
    """

    def __init__(
        self,
        field: NeuralField,
        volume: torch.Tensor,
        config: TrainConfig,
        checkpoint_path: Path | None = None,
        fingerprint: dict | None = None,
        callbacks: Sequence[TrainingCallback] = (),
        warm: bool = False,
    ):
        if config.error_guided and volume.dim() != 3:
            raise InvalidArgument("error_sampling guides the points of a single volume, not of a joint series model",
                                  arguments=("error_sampling",))
        self.field = field
        self.volume = volume
        self.config = config
        self.device = volume.device
        self.checkpoint_path = Path(checkpoint_path) if checkpoint_path else None
        self.fingerprint = fingerprint or {}
        self.callbacks = tuple(callbacks)
        encoder = field.encoder
        placement_params = list(encoder.placement_parameters())
        grids = placement_params[0].shape[0] if placement_params else 0
        if config.anchored_grids > grids:
            raise InvalidArgument(f"anchored_grids={config.anchored_grids}: the model has {grids} grids that move",
                                  arguments=("anchored_grids",))
        self._placement_params = placement_params
        placement_ids = {id(p) for p in placement_params}
        network_params = [p for p in field.parameters() if id(p) not in placement_ids]
        # One fused kernel per parameter group on a GPU, where a step is bound by kernel launches; the CPU keeps
        # Adam's single-tensor steps, whose numbers the reference models pin, made by CpuAdam's kernel in fewer
        # passes.
        fused = self.device.type == "cuda"
        adam = torch.optim.Adam if fused else CpuAdam
        self.network_optimizer = adam(
            _learning_rate_groups(encoder, network_params), lr=config.lr, betas=config.betas, fused=fused
        )
        self.placement_optimizer = (
            adam(placement_params, lr=config.placement_lr, betas=config.betas, fused=fused)
            if placement_params
            else None
        )
        self.hidden_dtype = inference_dtype(config.decoder_precision, self.device)  # same rule as inference
        #: Whether a reconstruction step runs the encoder's fused training kernel where it has one (False:
        #: autograd through its ops and the decoder's matrix products, the same numbers to float rounding).
        self.fused_step = True
        # Batches sorted by position where the encoder's tables outgrow the CPU's caches (a GPU gains nothing
        # for the launches a sort costs).
        self.order_batches = self.device.type == "cpu" and encoder.prefers_ordered_batches()
        # CPU threads chosen by timing the steps, where that cannot change the numbers (exact resume).
        self.thread_governor = ThreadGovernor(enabled=self.device.type == "cpu" and self._thread_invariant())
        self.callbacks = (_GovernThreads(), *self.callbacks)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.state = TrainingState()
        self._pending_density: list[torch.Tensor] = []
        #: A series: each step's recent reconstruction loss ``[T]`` (for progress; NaN until it is drawn).
        self.step_losses = torch.full((volume.shape[0],), math.nan, device=self.device) if volume.dim() == 4 else None
        self.error_guide = ErrorGuide(volume, config.error_parts) if config.error_guided else None
        if self.placement_optimizer is None:
            self.state.frozen_at = 0
        # Encoders that start from the data (hybrid: adaptive grids on the volume's detail) do it here, the
        # one place every training path (single file, bricks) goes through; a resumed run then loads its
        # checkpoint over it.
        if not warm:
            encoder.initialize_from_volume(volume)

    def _thread_invariant(self) -> bool:
        """Whether a step gives the same numbers on any thread count up to the current one: a batch that
        ATen reduces serially, float32 decoder products (MKL's are the same on 1 and 2 threads for these
        shapes; oneDNN's bfloat16 ones are not known to be), and an encoder that says so."""
        return (
            # ATen sums at most 32768 elements on one thread (its grain size); a larger batch is summed in
            # per-thread parts, so its loss, and the density target built from it, would follow the thread count.
            self.config.batch_size <= 32768
            and self.hidden_dtype is None
            and self.config.placement_loss == "density"  # placement gradients: not shown to be
            and self.field.encoder.thread_invariant(torch.get_num_threads())
            and self._same_numbers_on_every_thread_count()
        )

    def _same_numbers_on_every_thread_count(self) -> bool:
        """Checked, not assumed: one reconstruction step's prediction and gradients on a copy of the field,
        on each thread count the governor may choose, compared bit for bit. Matrix-product libraries split
        their work by thread count on some CPUs (seen on a 16-core machine with another PyTorch build, where
        the rule above held here). Measured once per model shape, batch and thread count in a process."""
        threads = torch.get_num_threads()
        counts = thread_candidates(threads)
        if len(counts) == 1:
            return True
        key = (type(self.field).__name__, tuple((n, tuple(p.shape)) for n, p in self.field.named_parameters()),
               self.volume.dim(), self.config.batch_size, counts)
        if key not in _THREAD_PROBES:
            field = copy.deepcopy(self.field)
            points = torch.rand(self.config.batch_size, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
            steps = (torch.zeros(1, dtype=torch.long),) if self.volume.dim() == 4 else ()
            results = []
            try:
                for count in counts:
                    torch.set_num_threads(count)
                    field.zero_grad(set_to_none=True)
                    prediction = field.normalized(points, *steps, detach_placement=True)
                    prediction.square().mean().backward()
                    results.append([prediction.detach()] + [p.grad for p in field.parameters() if p.grad is not None])
            finally:
                torch.set_num_threads(threads)
            _THREAD_PROBES[key] = all(
                len(other) == len(results[0]) and all(torch.equal(a, b) for a, b in zip(other, results[0]))
                for other in results[1:]
            )
        return _THREAD_PROBES[key]

    # ----------------------------------------------------------------------------- schedule
    def learning_rate(self, iteration: int) -> float:
        """Network learning rate at ``iteration`` (see :class:`TrainConfig`)."""
        cfg = self.config
        if cfg.lr_schedule == "constant":
            return cfg.lr
        if cfg.lr_schedule == "plateau":
            return cfg.lr * self.state.lr_scale
        if cfg.lr_schedule == "steps":
            # NGP/fVSRN reference code: x0.33 at 40, 60 and 80 % of the budget.
            cuts = sum(iteration >= int(f * cfg.iterations) for f in (0.4, 0.6, 0.8))
            return cfg.lr * 0.33**cuts
        # cosine: hold the rate while the grids may still move, then anneal over what is left.
        hold = self._freeze_deadline() if self.placement_optimizer is not None else 0
        if self.state.frozen_at is not None:
            hold = min(hold, self.state.frozen_at)
        hold = min(hold, int(cfg.iterations * 0.5))
        if iteration < hold:
            return cfg.lr
        progress = (iteration - hold) / max(cfg.iterations - hold, 1)
        floor = cfg.final_lr_fraction
        return cfg.lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))

    def _freeze_deadline(self) -> int:
        return int(self.config.iterations * self.config.freeze_fraction)

    # ----------------------------------------------------------------------------- one step
    def step(self) -> StepLosses:
        """One iteration: reconstruction step, then (while the grids move) the density step.

        Returns:
            The losses in fitted ``[0, 1]`` units; they stay on the device so that a GPU step never
            waits for the host.
        """
        cfg, st = self.config, self.state
        for group in self.network_optimizer.param_groups:
            group["lr"] = self.learning_rate(st.iteration) * group.get("lr_multiplier", 1.0)
        # Step 1: L_rec moves grids and decoder only (transform-detached coordinates), or the placement too.
        tracking = cfg.placement_loss == "reconstruction" and st.frozen_at is None
        if self.volume.dim() == 3:
            guide = self.error_guide
            every = max(1, cfg.iterations // cfg.error_measurements)
            if guide is not None and (guide.cumulative is None or st.iteration % every == 0):
                # float32, the fused kernel where it runs
                guide.measure(self.field.normalized, self.generator, st.iteration // every)
            points, target = draw_batch(self.volume, cfg.batch_size, cfg.voxel_fraction, self.generator,  # [B, 3], [B]
                                        guide, cfg.error_sampling)
            if self.order_batches:
                points, target = spatially_ordered(points, target)
            # One fused pass gives the prediction and the gradients (the features', and the decoder's when it
            # learns), where the encoder has such a kernel.
            fusable = self.fused_step and not tracking and self.hidden_dtype is None
            fused = self.field.fused_mse_step(points, target) if fusable else None
            prediction = fused if fused is not None else self.field.normalized(
                points, detach_placement=not tracking, hidden_dtype=self.hidden_dtype)
        else:
            fused = None
            # A series: the batch is cut into groups of equal size, each at one step.
            steps = self.batch_steps(st.iteration)  # [G]
            points, target = self._draw_series_batch(steps)
            prediction = self.field.normalized(points, steps, detach_placement=not tracking,
                                               hidden_dtype=self.hidden_dtype)
        prediction = prediction.view(-1)  # [B]
        error = (prediction - target).square()  # [B]
        reconstruction = error.mean()
        if self.step_losses is not None:
            # Running per-step loss (stays on the device; the progress display reads it now and then).
            group_losses = error.detach().view(len(steps), -1).mean(1)  # [G]
            previous = self.step_losses[steps]
            self.step_losses[steps] = torch.where(previous.isnan(), group_losses,  # the newest weighs 0.3
                                                  torch.lerp(previous, group_losses, 0.3))
        if fused is None:
            self.network_optimizer.zero_grad(set_to_none=True)
            if tracking:
                self.placement_optimizer.zero_grad(set_to_none=True)
            reconstruction.backward()
        self.network_optimizer.step()
        if tracking:
            self._placement_step(cfg.placement_lr * self.learning_rate(st.iteration) / max(cfg.lr, 1e-30))

        # Step 2: L_density moves the transforms only, between the delayed start and the freeze.
        density_value = None
        if cfg.placement_loss == "density" and st.frozen_at is None and st.iteration >= cfg.density_start:
            density = self.field.encoder.feature_density(points, cfg.density_power)  # [B]
            mean_density = (
                self.field.encoder.mean_feature_density(cfg.density_power)
                if cfg.density_normalization == "mass"
                else None
            )
            density_loss = feature_density_loss(density, error.detach(), mean_density)
            self.placement_optimizer.zero_grad(set_to_none=True)
            density_loss.backward()
            self._placement_step(cfg.placement_lr)
            density_value = density_loss.detach()
        return StepLosses(reconstruction.detach(), density_value)

    def _placement_step(self, lr: float) -> None:
        """Move the grid placements by their gradients at ``lr`` (the anchored grids stay)."""
        if self.config.anchored_grids:  # no gradient ever reaches them, so Adam never moves them
            for p in self._placement_params:
                if p.grad is not None:
                    p.grad[: self.config.anchored_grids] = 0
        for group in self.placement_optimizer.param_groups:
            group["lr"] = lr
        self.placement_optimizer.step()

    def _draw_series_batch(self, steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``[G n, 3]`` and targets of a series batch: group ``g`` of ``n`` points at step ``steps[g]``."""
        cfg = self.config
        per_group = cfg.batch_size // len(steps)
        if cfg.voxel_fraction == 0:  # one draw for the whole batch, as before the option existed
            points = torch.rand(cfg.batch_size, 3, generator=self.generator, device=self.device) * 2 - 1
            points = points[: len(steps) * per_group]
            groups = points.view(len(steps), -1, 3)  # [G, n, 3]
            target = torch.cat([sample_volume(self.volume[s], group) for s, group in zip(steps.tolist(), groups)])
            return points, target
        drawn = [draw_batch(self.volume[s], per_group, cfg.voxel_fraction, self.generator) for s in steps.tolist()]
        return torch.cat([p for p, _ in drawn]), torch.cat([t for _, t in drawn])

    def batch_steps(self, iteration: int) -> torch.Tensor:
        """Steps of a series that iteration ``iteration`` trains on: ``steps_per_iteration`` indices ``[G]``.

        The steps are visited in rounds: each round is a random order of every step (seeded by the seed and
        the round), cut into consecutive groups, so every step gets the same share of the budget. It is a
        function of the iteration alone, so a resumed run draws exactly what the interrupted one would have.
        """
        total = self.volume.shape[0]
        count = min(self.config.steps_per_iteration, total)
        first = iteration * count
        chosen = []
        for position in range(first, first + count):
            round_, index = divmod(position, total)
            if not chosen or index == 0:
                order = torch.randperm(total, generator=torch.Generator().manual_seed(self.config.seed * 7919 + round_))
            chosen.append(int(order[index]))
        return torch.tensor(chosen, device=self.device)

    def _update_freeze(self, density: torch.Tensor | None) -> None:
        """Early stop of grid motion: freeze once the windowed mean fails to fall by the tolerance.

        Density losses are gathered on the device and read back every 100 density steps (one sync).
        """
        cfg, st = self.config, self.state
        if st.frozen_at is not None:
            return
        if density is not None:
            self._pending_density.append(density)
            st.density_steps += 1
            w = cfg.density_window
            if st.density_steps % 100 == 0:
                self._flush_density()
                if len(st.density_losses) >= 2 * w:
                    recent = sum(st.density_losses[-w:]) / w
                    before = sum(st.density_losses[-2 * w : -w]) / w
                    if not recent < before * (1 - cfg.density_tolerance):
                        st.frozen_at = st.iteration + 1
        if st.iteration + 1 >= self._freeze_deadline():
            st.frozen_at = st.iteration + 1
        if st.frozen_at is not None:
            self._pending_density.clear()
            for p in self.field.encoder.placement_parameters():
                p.requires_grad_(False)

    def _flush_density(self) -> None:
        """Move device-side density losses to the state (kept to the last two windows)."""
        st = self.state
        if self._pending_density:
            st.density_losses.extend(torch.stack(self._pending_density).tolist())
            self._pending_density.clear()
        st.density_losses = st.density_losses[-2 * self.config.density_window :]

    def _update_plateau(self, reconstruction: float) -> None:
        """Paper schedule: x0.1 when ``L_rec`` has not fallen by 0.01 % for 500 iterations (grids frozen)."""
        cfg, st = self.config, self.state
        if cfg.lr_schedule != "plateau" or st.frozen_at is None:
            return
        if reconstruction < st.plateau_best * (1 - cfg.density_tolerance):
            st.plateau_best, st.plateau_since = reconstruction, st.iteration
        elif st.iteration - st.plateau_since >= 500:
            st.lr_scale *= 0.1
            st.plateau_best, st.plateau_since = reconstruction, st.iteration

    def stopped_early(self) -> bool:
        """True once the plateau scheduler made ``stop_after_lr_cuts`` cuts (each cut is x0.1)."""
        cuts = self.config.stop_after_lr_cuts
        # lr_scale is exactly 0.1 ** cuts; the half-step margin absorbs its rounding.
        return cuts is not None and self.state.lr_scale < 10.0 ** (0.5 - cuts)

    # ----------------------------------------------------------------------------- loop
    def run(self) -> TrainingState:
        """Train from ``state.iteration`` (0, or where :meth:`load_checkpoint` left it) to the budget.

        Raises:
            TrainingInterrupted: on Ctrl-C, after saving a checkpoint.
        """
        cfg, st = self.config, self.state
        self.field.train()
        start = time.perf_counter() - st.elapsed
        stop = _StopRequest() if self.checkpoint_path is not None else None
        for callback in self.callbacks:
            callback.on_start(self)
        try:
            while st.iteration < cfg.iterations and not self.stopped_early():
                if stop is not None and stop.requested:
                    # Ctrl-C lands between iterations, so the checkpoint is an exact state to resume.
                    self.save_checkpoint(self.checkpoint_path)
                    raise TrainingInterrupted(st.iteration, self.checkpoint_path)
                losses = self.step()
                self._update_freeze(losses.density)
                if st.iteration % cfg.history_every == 0:
                    loss = float(losses.reconstruction)  # one host sync per recorded point
                    if not math.isfinite(loss):
                        raise ApmgsrnError(
                            f"training diverged at iteration {st.iteration} (loss {loss}); "
                            "lower lr= or check the data", arguments=("lr",),
                        )
                    self._update_plateau(loss)
                    st.history["iteration"].append(st.iteration)
                    st.history["reconstruction"].append(loss)
                    st.history["density"].append(float(losses.density) if losses.density is not None else float("nan"))
                    group = self.network_optimizer.param_groups[0]
                    st.history["lr"].append(group["lr"] / group.get("lr_multiplier", 1.0))  # the step's base rate
                st.iteration += 1
                st.elapsed = time.perf_counter() - start
                for callback in self.callbacks:
                    callback.after_step(self, st.iteration, losses)
                if self.checkpoint_path and st.iteration % cfg.checkpoint_every == 0 and st.iteration < cfg.iterations:
                    self.save_checkpoint(self.checkpoint_path)
        finally:
            if stop is not None:
                stop.restore()
            for callback in self.callbacks:
                callback.on_end(self)
        self.field.eval()
        return st

    def grid_status(self) -> str:
        st = self.state
        if st.frozen_at is not None:
            return f"frozen@{st.frozen_at}"
        return "moving" if st.iteration >= self.config.density_start else "waiting"

    # ----------------------------------------------------------------------------- checkpoints
    def save_checkpoint(self, path: Path) -> None:
        """Write model, optimiser moments and RNG state atomically (safetensors + JSON, no pickle)."""
        self._flush_density()
        tensors = {f"model.{k}": v for k, v in self.field.state_dict().items()}
        optimizers = {"network": self.network_optimizer, "placement": self.placement_optimizer}
        groups = {}
        for name, optimizer in optimizers.items():
            if optimizer is None:
                continue
            state = optimizer.state_dict()
            groups[name] = state["param_groups"]
            for index, entry in state["state"].items():
                for key, value in entry.items():
                    tensors[f"optim.{name}.{index}.{key}"] = torch.as_tensor(value)
        tensors["generator"] = self.generator.get_state()
        if self.error_guide is not None and self.error_guide.cumulative is not None:
            tensors["error_guide"] = self.error_guide.cumulative  # the last measurement: a resume draws as before
            if self.config.error_parts > 1:  # and the errors the next part's measurement is merged into
                tensors["error_guide_errors"] = self.error_guide.errors
        description = {
            "fingerprint": self.fingerprint,
            "config": asdict(self.config),
            "state": asdict(self.state),
            "param_groups": groups,  # informative: a resume takes the groups from its own config
        }
        save_tensors(path, tensors, CHECKPOINT_KIND, description, what="training checkpoint")

    def load_checkpoint(self, path: Path) -> None:
        """Restore a checkpoint written by :meth:`save_checkpoint` for the same run.

        Everything is checked before anything is loaded: the run's fingerprint (data and model) and
        config, the loop state field by field, and every tensor's name, shape and dtype.

        Raises:
            ApmgsrnError: not a checkpoint, another run's, or damaged (one line naming the file).
        """
        header = read_header(path)
        if header.kind != CHECKPOINT_KIND:
            raise ApmgsrnError(f"{path}: not a training checkpoint; remove it or pass another out=", arguments=("out",))
        description = header.description
        if description.get("fingerprint") != as_json(self.fingerprint) or current_names(
            description.get("config")
        ) != as_json(asdict(self.config)):
            raise ApmgsrnError(
                f"{path}: checkpoint was made with other data or settings; rerun with the same data file and "
                "options, or delete it to start over"
            )
        optimizers = {"network": self.network_optimizer, "placement": self.placement_optimizer}
        try:
            state = state_from_json(description.get("state"), self.config.iterations)
            # Adam has moments once it stepped: the network from the first iteration, the grid maps from
            # the first density step.
            stepped = {"network": state.iteration > 0, "placement": state.density_steps > 0}
            expected = {f"model.{k}": (tuple(v.shape), v.dtype) for k, v in self.field.state_dict().items()}
            expected["generator"] = (tuple(self.generator.get_state().shape), torch.uint8)
            if self.error_guide is not None and state.iteration > 0:  # measured before the first iteration
                expected["error_guide"] = ((self.error_guide.block_count,), torch.float64)
                if self.config.error_parts > 1:
                    expected["error_guide_errors"] = ((self.error_guide.block_count,), torch.float64)
            for name, optimizer in optimizers.items():
                if optimizer is not None:
                    expected |= optimizer_layout(name, optimizer, stepped[name])
            tensors = {_current_tensor_name(k): v for k, v in load_tensors(path).items()}
            check_tensors(tensors, expected)
            if "error_guide" in expected:
                errors = tensors.get("error_guide_errors")
                self.error_guide.restore(tensors["error_guide"].to(self.device),
                                         None if errors is None else errors.to(self.device))
        except DescriptionError as exc:
            raise ApmgsrnError(f"{path}: training checkpoint is damaged ({exc}); delete it to start over") from None
        self.field.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        for name, optimizer in optimizers.items():
            if optimizer is None:
                continue
            moments: dict = {}
            prefix = f"optim.{name}."
            for key, value in tensors.items():
                if key.startswith(prefix):
                    index, entry = key[len(prefix) :].split(".", 1)
                    moments.setdefault(int(index), {})[entry] = value.to(self.device) if entry != "step" else value
            optimizer.load_state_dict({"state": moments, "param_groups": optimizer.state_dict()["param_groups"]})
        self.generator.set_state(tensors["generator"])
        self.state = state
        if self.state.frozen_at is not None:
            for p in self.field.encoder.placement_parameters():
                p.requires_grad_(False)


def _learning_rate_groups(encoder: Encoder, parameters: list[nn.Parameter]) -> list:
    """Optimiser parameter groups, one per learning-rate multiplier the encoder asks for.

    Args:
        encoder: the field's encoder (:meth:`Encoder.learning_rate_multipliers`).
        parameters: the parameters the network optimiser updates.

    Returns:
        The plain parameter list when the encoder asks for no multiplier, else groups whose
        ``lr_multiplier`` scales the scheduled rate in every step.
    """
    multiplier_of = encoder.learning_rate_multipliers()
    if not multiplier_of:
        return parameters
    groups: dict[float, list] = {}
    for p in parameters:
        groups.setdefault(float(multiplier_of.get(p, 1.0)), []).append(p)
    return [{"params": params, "lr_multiplier": multiplier} for multiplier, params in groups.items()]


def _current_tensor_name(name: str) -> str:
    """``optim.transform.*`` (older checkpoints) read as ``optim.placement.*``."""
    return "optim.placement." + name[len("optim.transform."):] if name.startswith("optim.transform.") else name


class _StopRequest:
    """Turns Ctrl-C (SIGINT) into a flag the loop reads between iterations (main thread only)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def restore(self) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def as_json(value):
    """The value as it reads back from JSON (tuples become lists): what a saved description compares to."""
    return json.loads(json.dumps(value))
