"""Warm-started steps: a time series trained one step after another, every step with its own feature grids.

The default way ``apmgsrn train`` fits a series (measured against one shared model of all steps in
docs/time_series.md):

1. **Start step.** The step with the most detail (largest mean gradient magnitude of its values,
   :func:`choose_start`) gets a single-step model trained on it alone, with the whole budget of one volume
   (more where the model kind's steps gain from it, :data:`START_ITERATION_SHARES`; its voxel points drawn
   uniformly, :data:`START_ERROR_SAMPLING`; then its own grids get a step's fine-tune from themselves, drawn
   where it is wrong, where the model kind trains so).
   Its grid placement is the one every step shares, so it is taken where the structures are richest (in a
   viscous-finger run, the last step, where the fingers have spread furthest).
2. **The other steps**, moving away from the start one neighbour at a time (:func:`step_order`), start from
   the neighbour's grids and fine-tune only their own feature grids at a lower learning rate (their voxel
   points drawn where they are wrong, as the model kind trains: ``error_sampling``, and half as many of their
   points between the voxels as the start model draws, :func:`step_voxel_fraction`), for a tenth of that
   budget, more for a step that differs much from its neighbour (:meth:`StepwiseConfig.step_config`; steps
   that differ little share their iterations evenly, :func:`step_factors`; a series too short to spend the
   budget of :meth:`StepwiseConfig.budget_scale` so shares the rest out among its steps, :func:`spend_spare`); the
   decoder stays the start model's, frozen (with ``step_sparsity`` the features are pulled back towards
   the neighbour's after every iteration, :class:`PullTowardsStart`, the default for a hybrid series; less on a
   fine-tune more than twice the base, :func:`step_pull`), and so
   does the placement, unless the fine-tuned step ends
   more than :data:`TRACK_DB` below the start model: then the step is fine-tuned again from its neighbour
   with the reconstruction error moving its grids' placement too (``placement_loss="reconstruction"``), and
   the better of the two is kept. Structures that travel across the domain are followed this way; every
   step stores its own placement (192 floats at the small size). A step whose neighbour's placement moved
   is fine-tuned with a moving placement first (the motion usually goes on), and with the placement kept
   only if that ends more than :data:`TRACK_DB` below.

The result is a :class:`~apmgsrn.models.series_field.SeriesField` with one basis slice per step (keyframe
weights, ``K = T``: the identity), so decoding, rendering and querying a step cost what a single-step model
costs. Consecutive steps' grids are close, which is what the packed series file's time predictor codes.

Resume: while the start model trains, its trainer checkpoints to ``MODEL.ckpt`` as for one volume; once it is
done, ``MODEL.ckpt`` becomes a *steps* checkpoint (kind ``series-steps``: the series field so far and the
steps done), rewritten atomically after every step. A kill loses at most the step in progress.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path

import torch

from apmgsrn.arguments import check_int, check_number
from apmgsrn.atomic import atomic_write
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.io.container import file_bytes, load_tensors, read_header
from apmgsrn.io.description import DescriptionError, require_int, require_number
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig
from apmgsrn.models.series_field import SeriesConfig, SeriesField, SeriesFieldConfig
from apmgsrn.ops.trilinear import voxel_coordinates
from apmgsrn.progress import Progress
from apmgsrn.training.checkpoint import CHECKPOINT_KIND, TrainingState, check_tensors, state_from_json
from apmgsrn.training.fit import PreparedValues, TrainedField, build_field, train_prepared
from apmgsrn.training.optimizer import pull_towards
from apmgsrn.training.points import draw_batch
from apmgsrn.training.series_packing import series_growth
from apmgsrn.training.trainer import TrainConfig, Trainer, TrainingCallback, TrainingInterrupted, as_json

STEPS_CHECKPOINT_KIND = "series-steps"
#: Start choices besides a step index.
STARTS = ("auto", "first", "last")
#: A step's fine-tune, as a share of the start model's iterations and learning rate (200 iterations at
#: lr 0.003 after 2,000 at 0.01: every viscous-finger step within 0.0-0.9 dB of its own model).
STEP_ITERATION_SHARE, STEP_LR_SHARE = 0.1, 0.3
#: The learning-rate share of a model kind's steps where it differs: the hybrid's steps at 0.3 ended 0.2-0.9 dB
#: below the same fine-tune at the start model's rate (30 viscous-finger steps, docs/time_series.md).
STEP_LR_SHARES = {"hybrid": 1.0}
#: The batch of a model kind's steps as a share of the start model's, where it differs; the step then runs
#: proportionally more iterations (the same points, times :data:`STEP_POINT_SHARES`). The hybrid's steps at half
#: the batch ended 0.03-0.54 dB higher in 16 % more time, the file 4 % smaller (30 viscous-finger steps, CPU;
#: docs/time_series.md); at 0.375 of it six steps fine-tuned from their neighbours ended 0.05 dB higher (mean)
#: than at half, in 3 % more time. CPU only, as is the quantisation-aware fine-tune's, which takes the same batch.
STEP_BATCH_SHARES = {"hybrid": 0.375}
#: The points (iterations times batch) a model kind's steps train on as a share of those of
#: :meth:`StepwiseConfig.step_config`'s iterations at the start model's batch, where it differs (with its
#: :data:`STEP_BATCH_SHARES`, CPU only). The hybrid's at 0.9 ended those six steps 0.04 dB lower (mean) than all
#: of them at half the batch, in 6 % less time, which the series needs to train within five times one step
#: once its packing is counted too (docs/time_series.md).
STEP_POINT_SHARES = {"hybrid": 0.9}
#: Share of the start model's voxel points drawn where it is wrong (:attr:`TrainConfig.error_sampling`; the steps'
#: fine-tunes keep the model kind's own). The start model's decoder is every step's: trained on where the start
#: step was wrong it fitted that step better and the others worse (a hybrid series of the 30 viscous-finger
#: steps, steps 0 and 5 about 1.4 dB lower, step 29 0.8 higher; docs/time_series.md). Where the kind draws
#: where it is wrong, the start step's own grids then get a step's fine-tune from themselves, drawn that way.
START_ERROR_SAMPLING = 0.0
#: The start model's iterations as a share of the configured ones (``--iterations``), for a model kind where it
#: differs (CPU only, as :data:`STEP_BATCH_SHARES`); its extra points are taken from the steps' budget at
#: :data:`START_POINT_COST` each (:meth:`StepwiseConfig.budget_scale`), so the series trains in the same time.
#: Its decoder is every step's, and the steps gain more from a finer one than from their own longer fine-tunes:
#: the hybrid's at 1.4 (2,800 iterations after 2,000), the steps' and their fine-tune towards the packing
#: shortened to 0.85 of their share, lifted steps 0 and 5 of the 30 viscous-finger steps by 0.1-0.5 dB and the
#: start step by 0.4-0.65, steps 15-25 0.3 lower to 0.03 higher, every step of three seeds above its own model
#: (one thread; before, two of the 21 seed-by-seed pairs were 0.03 and 0.22 dB below), in the same time. The
#: fewer passes over every voxel the start model's iterations make, the more it gains: upsampled to 128^3 (31
#: passes instead of 250) seed 0's steps went from -0.21..+0.40 dB against their own models to -0.03..+0.72, and
#: 19 of 21 seed-by-seed pairs are above (step 25 0.03 and 0.16 below on two of three seeds). At 0.6 or 0.8 of
#: the iterations, the steps lengthened instead, every step ended lower (0.2-0.9 dB at 128^3; docs/time_series.md).
START_ITERATION_SHARES = {"hybrid": 1.4}
#: What one of the start model's points costs in the steps' budget (:data:`STEPS_BUDGET_CAP`, in fine-tune
#: points): its decoder's weights get gradients, its placement and density steps run, and it has no fused
#: frozen-decoder pass. 800 more start iterations took 32-34 s where 30 fewer base iterations a step saved 16 s
#: (CPU, one thread); at 1.5, with the start model at 1.4, the 30 viscous-finger steps trained in 363.9 s, as
#: they did with the start model at 1.0 before (363.5 s; a step: 75.8 and 76.0 s); at 2.0 their steps ended
#: 0.1-0.25 dB lower for about 15 s less.
START_POINT_COST = 1.5
#: Default pull of a step's features towards its neighbour's (:attr:`StepwiseConfig.step_sparsity`) where a model
#: kind has one (elsewhere none). A hybrid series' tables take 2.59 MB at 10 bits unpulled, 1.91 MB pulled at
#: 0.02 and 1.35 MB at 8 bits (within five single-step files), 0.5-1.1 dB below the unpulled steps and 0.6-1.6
#: dB above the APMGSRN series (all at the full batch); at 0.05 they lose about 1.2 dB more for 25 % fewer
#: bytes (30 viscous-finger steps, docs/time_series.md). With quantisation steps that follow the output
#: (:func:`~apmgsrn.training.series_packing.sensitivity_steps`) 0.01 at 7 bits beats 0.02 at 8: -0.41 dB on the
#: start step, -0.01 to +0.36 on the others (mean +0.24), the file 9 % smaller (docs/time_series.md). Since the
#: steps draw voxel points where they are wrong they fit closer and packing costs more (0.01 at 7 bits: 1.1 dB);
#: with the bit width refined to the five-file target (:meth:`~apmgsrn.training.series_packing.SeriesPacking.pack`)
#: 0.02 lands at 7.6 bits and 0.01 at 7.2, and 0.02 ends higher on the first and last steps (+0.12, +0.33 dB),
#: -0.07 to +0.13 on the others, the same mean (7 steps, trained with a guide variant not kept). But on a series
#: whose structures travel (t050 shifted 4 voxels a step), where five files hold 10 bits either way, 0.02 lost
#: 0.8-1.0 dB on 9 of its 10 steps: the pull stays at 0.01 (docs/time_series.md). A fine-tune longer than twice
#: the base is pulled less (:func:`step_pull`), and a series whose packing target holds every step coded alone is
#: not pulled at all (:func:`~apmgsrn.training.series_qat.budgeted`).
STEP_SPARSITY_OF: dict[str, float] = {"hybrid": 0.01}
#: A step that differs from its neighbour by more than this many times the start model's RMS error gets
#: proportionally more iterations, up to ``STEP_ITERATION_CAP`` times the share above (the start model's whole
#: budget). Consecutive viscous-finger steps differ by 4-9 times the error (200 iterations enough); steps 40
#: apart by about 75 times, where 200 iterations left them 7 dB below their own models and 2,000 put them above.
STEP_CHANGE_SCALE, STEP_ITERATION_CAP = 8.0, 10.0
#: Steps whose change asks for less than this many times the base iterations (differ from their neighbour by
#: less than twice :data:`STEP_CHANGE_SCALE` times the start model's error: consecutive steps of a smooth run)
#: share their iterations evenly (:func:`step_factors`). At that scale how much a step changed does not say how
#: long its fine-tune must be: the 30 viscous-finger steps (1.0-1.75 times the base, the most to the steps
#: nearest the start, which have the most detail) spread evenly ended 0.16-0.22 dB higher on steps 0 and 5, far
#: from the start, which fit finest and were closest to their own models, 0.06-0.28 lower on steps 15-25, whose
#: margin was widest, and the start step the same (three seeds, one thread; on two threads every step of three
#: seeds then above its own model; docs/time_series.md). Steps that change more keep their own.
STEP_EVEN_BELOW = 2.0
#: The fine-tunes after the start model, the steps' at their base share and every step's quantisation-aware one
#: (:attr:`StepwiseConfig.qat_iterations`), together with what every step costs besides (:data:`STEP_FIXED_COST`) take
#: at most this many times the start model's points (iterations times batch; a fine-tune's point, its share of the
#: measurements of where it is wrong included, costs about what a start model's does), for a series of up to
#: :data:`~apmgsrn.training.series_packing.SHARE_STEPS` steps; a longer one gets it in proportion to its steps
#: (:func:`~apmgsrn.training.series_packing.series_growth`). Fine-tunes that take more are shortened in proportion,
#: their measurements with them, so a series of steps that change little trains in about the time the 30
#: viscous-finger steps take (4.1-4.9 times one step's model), or that in proportion; steps that change much still
#: get more. Those 30 steps (29 x 200 x 0.9 + 30 x 250 x 0.375 + 30 x 16 = 8,513 start-model iterations' points)
#: are just within it (the hybrid's start model, trained 1.4 times as long, takes 0.6 of it, :data:`START_POINT_COST`:
#: they get 0.85 of their share). Before the fine-tune towards the packing and the steps' own costs counted, and the
#: measurements shortened with the fine-tunes, the cap (4, on the steps alone) let 60 steps train in 8.1 times one step
#: (641.2 s; now 393.4 s, 4.95 times). A cap that shortened the 30 steps' fine-tunes to 0.92 of their share trained them
#: in 373.6 s instead of 385.5-397.7 and lost 0.12-0.15 dB on every seed's steps, step 5's margin over its own models
#: (mean of 3 seeds) falling from +0.19 to +0.01 dB (docs/time_series.md). Capping the change-driven iterations too was
#: tried and not kept: a volume shifted 4 voxels a step (10 steps, 1,285 iterations each) then fell to 54.0-54.2 dB on
#: its last steps, below independent models.
STEPS_BUDGET_CAP = 4.26
#: What every step costs besides its fine-tunes' iterations, in start-model iterations: the first measurement of
#: every voxel of each of its two fine-tunes, the check against its neighbour's grids, its checkpoint, its share
#: of the packing search (13.5 s over the 30 viscous-finger steps besides 0.18 s a step of first measurements:
#: 0.63 s a step, 16.7 start iterations of 37.7 ms; CPU, one thread).
STEP_FIXED_COST = 16
#: The least share of their base the fine-tunes of a series too long for the budget are shortened to (the
#: budget is then exceeded: the steps' own costs alone take it).
LEAST_BUDGET_SCALE = 0.05
#: Voxels compared to measure how much a step differs from its neighbour (a regular subset of larger steps).
CHANGE_VOXELS = 1 << 20
#: Voxels on which a step's fine-tune must end better than the neighbour's grids it started from, else the step
#: keeps those (:func:`_train_step`): every voxel of a smaller step, else this many drawn at random (seeded by the
#: step, so the same in every run).
CHECK_VOXELS = 1 << 16
#: A step whose fine-tune ends more than this many dB below the start model (RMS error ratio
#: ``10^(TRACK_DB / 20)``) is fine-tuned again with its placement moving (viscous-finger steps end within
#: 0.5 dB of the start and never are; a volume shifted 4 voxels a step is 9 dB below by its third step).
TRACK_DB = 3.0
#: The moving placement's learning rate, as a multiple of the start model's ``placement_lr`` (scaled by the
#: fine-tune's schedule).
TRACK_PLACEMENT_LR_SHARE = 2.0
#: How a step's fine-tune measures where it is wrong (:attr:`TrainConfig.error_measurements` and
#: :attr:`~TrainConfig.error_parts`, when the model kind draws so): 20 times, as one volume's training, but each
#: time only half of the voxels in turn. Three viscous-finger steps fine-tuned from their neighbours (400
#: iterations) ended 65.76 dB (mean) so against 65.69 measuring all of them, in 7.2 s a step against 8.3; the
#: time saved pays for a longer quantisation-aware fine-tune (docs/time_series.md).
STEP_ERROR_MEASUREMENTS, STEP_ERROR_PARTS = 20, 2
#: Share of every batch at voxel positions that a stepwise series trains with unless told otherwise
#: (what it was measured with; uniform points alone cost 2-4 dB on the viscous-finger steps).
STEPWISE_VOXEL_FRACTION = 0.5
#: The share of a step's fine-tune points drawn between the voxels, as a share of the start model's
#: (:func:`step_voxel_fraction`; every step's fine-tune towards the packing draws the same). The start model has
#: taught the decoder what lies between the voxels; steps fine-tuned from it with a quarter of their points there
#: instead of half ended 0.04-1.2 dB higher over the voxels on every step measured of the 30 viscous-finger steps
#: and of the same steps at 128^3 (three seeds each). Between the voxels (against the data's trilinear
#: interpolation) they lose more, 0.9-1.6 dB at 64^3 and 0.3-0.9 at 128^3 (one seed): the 64^3 steps stay
#: 0.85-3.8 dB above independent models there, the 128^3 ones fall to between 0.34 below and 0.20 above them. The
#: issue's measure is the voxels' (docs/time_series.md).
STEP_OFF_VOXEL_SHARE = 0.5


@dataclass(frozen=True)
class StepwiseConfig:
    """How a series is trained step by step.

    Attributes:
        start: the step the first model is trained on: ``"auto"`` (the step with the most detail),
            ``"first"``, ``"last"``, or a step index.
        step_iterations: fine-tune iterations of every other step (None: a tenth of the start model's), counted
            at the start model's batch (a model kind with a smaller step batch, :data:`STEP_BATCH_SHARES`, runs
            proportionally more).
        step_lr: their learning rate (None: 0.3 times the start model's).
        step_sparsity: how hard a step's features are pulled back to its neighbour's during its fine-tune
            (:class:`PullTowardsStart`; 0: not at all; None: the model kind's default, :data:`STEP_SPARSITY_OF`).
            The more entries keep their neighbour's value, the fewer bytes the packed file's time predictor
            spends on the step, and the less closely the step fits its data.
        qat_iterations: the quantisation-aware fine-tune every step gets once all are trained (the packing's,
            :attr:`~apmgsrn.training.series_packing.SeriesPacking.qat_iterations`), before
            :meth:`budget_scale` shortens it with the steps': it shares their budget.
    """

    start: int | str = "auto"
    step_iterations: int | None = None
    step_lr: float | None = None
    step_sparsity: float | None = None
    qat_iterations: int = 0

    def __post_init__(self) -> None:
        """Refuse values training cannot run with (:class:`~apmgsrn.errors.InvalidArgument`)."""
        if isinstance(self.start, str):
            if self.start not in STARTS:
                raise InvalidArgument(f"start={self.start!r}: must be auto, first, last or a step index",
                                      arguments=("start",))
        else:
            check_int("start", self.start, 0)
        if self.step_iterations is not None:
            check_int("step_iterations", self.step_iterations, 1)
        if self.step_lr is not None:
            check_number("step_lr", self.step_lr, 0.0)
        if self.step_sparsity is not None:
            check_number("step_sparsity", self.step_sparsity, 0.0)
        check_int("qat_iterations", self.qat_iterations, 0)

    def sparsity(self, model: str) -> float:
        """The pull of :attr:`step_sparsity` for steps of a ``model`` kind series."""
        return self.step_sparsity if self.step_sparsity is not None else STEP_SPARSITY_OF.get(model, 0.0)

    def base_iterations(self, config: TrainConfig) -> int:
        """Fine-tune iterations of a step that differs little from its neighbour."""
        return self.step_iterations or max(1, round(config.iterations * STEP_ITERATION_SHARE))

    def step_config(self, config: TrainConfig, factor: float = 1.0, scale: float = 1.0,
                    lr_share: float = STEP_LR_SHARE, batch_share: float = 1.0, point_share: float = 1.0
                    ) -> TrainConfig:
        """How a step after the start is fine-tuned: its grids only (the density loss never starts), for
        ``factor`` times :meth:`base_iterations` (more when the step differs from its neighbour by more than
        :data:`STEP_CHANGE_SCALE` times the start model's error: :func:`change_factor`, :func:`step_factors`).

        Args:
            config: the start model's training.
            factor: the base's multiple (1: a step that differs little from its neighbour).
            scale: a long series' share of the base (:meth:`budget_scale`), and of the measurements of where
                the step is wrong (:func:`shortened_measurements`).
            lr_share: the learning rate's share of the start model's (:data:`STEP_LR_SHARES`), unless ``step_lr``.
            batch_share: the batch's share of the start model's (:data:`STEP_BATCH_SHARES`); the iterations
                above are counted at the start model's batch and divided by it.
            point_share: the iterations above times this (:data:`STEP_POINT_SHARES`).
        """
        iterations = max(1, round(self.base_iterations(config) * factor * scale * point_share / batch_share))
        lr = config.lr * lr_share if self.step_lr is None else self.step_lr
        return replace(config, iterations=iterations, lr=lr, density_start=iterations + 1, history_every=None,
                       stop_after_lr_cuts=None, batch_size=max(1, round(config.batch_size * batch_share)),
                       error_measurements=shortened_measurements(STEP_ERROR_MEASUREMENTS, scale),
                       error_parts=STEP_ERROR_PARTS, voxel_fraction=step_voxel_fraction(config.voxel_fraction))


    def budget_scale(self, config: TrainConfig, steps: int, batch_share: float = 1.0, point_share: float = 1.0,
                     start_share: float = 1.0) -> float:
        """The share of :meth:`base_iterations` and of :attr:`qat_iterations` (and of their measurements of where
        they are wrong) every step gets so that the ``steps`` steps after the start (at ``point_share`` of the
        base's points), the quantisation-aware fine-tune of all ``steps + 1`` (at ``batch_share`` of the start
        model's batch) and what every step costs besides (:data:`STEP_FIXED_COST`) together take at most
        :data:`STEPS_BUDGET_CAP` times the configured start model's points (in proportion to the steps beyond
        :data:`~apmgsrn.training.series_packing.SHARE_STEPS`), less what a start model trained
        ``start_share`` times as long (:data:`START_ITERATION_SHARES`) takes beyond them at
        :data:`START_POINT_COST` (1 for a series short enough, and when ``step_iterations`` was given; at least
        :data:`LEAST_BUDGET_SCALE`). Steps that change much keep their extra iterations in proportion
        (:meth:`step_config`)."""
        if self.step_iterations is not None or steps < 1:
            return 1.0
        points = steps * self.base_iterations(config) * point_share + (steps + 1) * self.qat_iterations * batch_share
        return min(1.0, max(self._allowed(config, steps, start_share) / points, LEAST_BUDGET_SCALE))

    def _allowed(self, config: TrainConfig, steps: int, start_share: float) -> float:
        """The points :meth:`budget_scale` lets the fine-tunes of ``steps`` steps after the start take
        (:data:`STEPS_BUDGET_CAP` times the series' :func:`~apmgsrn.training.series_packing.series_growth`)."""
        cap = STEPS_BUDGET_CAP * series_growth(steps + 1) - START_POINT_COST * (start_share - 1)
        return cap * config.iterations - (steps + 1) * STEP_FIXED_COST

    def spare_factor(self, config: TrainConfig, factors: list[float], batch_share: float = 1.0,
                     point_share: float = 1.0, start_share: float = 1.0) -> float:
        """How many more times :meth:`base_iterations` the steps after the start (their :func:`step_factors`
        ``factors``) may run in all before they and the quantisation-aware fine-tune take the budget of
        :meth:`budget_scale`: what a short series, or one of few steps that change much (each at most
        :data:`STEP_ITERATION_CAP` times the base), leaves unspent (0 once the budget shortens them, and when
        ``step_iterations`` was given). :func:`spend_spare` shares it out."""
        steps = len(factors)
        if self.step_iterations is not None or steps < 1:
            return 0.0
        base = self.base_iterations(config) * point_share
        used = sum(factors) * base + (steps + 1) * self.qat_iterations * batch_share
        return max(0.0, (self._allowed(config, steps, start_share) - used) / base)

    def largest_factor(self, config: TrainConfig, steps: int, point_share: float = 1.0,
                       start_share: float = 1.0) -> float:
        """A bound on any step's factor after :func:`spend_spare` (what a resumed checkpoint's counts are checked
        against)."""
        base = self.base_iterations(config) * point_share
        return STEP_ITERATION_CAP * (1 + max(0.0, self._allowed(config, steps, start_share)) / base)

    def shortened_qat(self, config: TrainConfig, steps: int, batch_share: float = 1.0, point_share: float = 1.0,
                      start_share: float = 1.0) -> int:
        """:attr:`qat_iterations` at the share of :meth:`budget_scale` (at least one when there are any)."""
        if not self.qat_iterations:
            return 0
        scale = self.budget_scale(config, steps, batch_share, point_share, start_share)
        return max(1, round(self.qat_iterations * scale))


def step_voxel_fraction(voxel_fraction: float) -> float:
    """The share of a step's fine-tune points on voxels where the start model's is ``voxel_fraction``: its points
    between the voxels cut to :data:`STEP_OFF_VOXEL_SHARE` of the start model's share."""
    return 1.0 - (1.0 - voxel_fraction) * STEP_OFF_VOXEL_SHARE


def change_factor(change: float, error: float) -> float:
    """How many times :meth:`StepwiseConfig.base_iterations` a step gets that differs from its neighbour by
    ``change`` where the start model's RMS error is ``error``: 1 up to :data:`STEP_CHANGE_SCALE` times the error,
    then in proportion, at most :data:`STEP_ITERATION_CAP`."""
    return min(max(change / (STEP_CHANGE_SCALE * max(error, 1e-12)), 1.0), STEP_ITERATION_CAP)


def step_factors(changes: list[float], error: float) -> list[float]:
    """:func:`change_factor` of every step's change, those below :data:`STEP_EVEN_BELOW` replaced by their mean:
    the same iterations in all, spread evenly over the steps that change little."""
    factors = [change_factor(c, error) for c in changes]
    small = [f for f in factors if f < STEP_EVEN_BELOW]
    even = sum(small) / len(small) if small else 1.0
    return [even if f < STEP_EVEN_BELOW else f for f in factors]


def spend_spare(factors: list[float], spare: float) -> list[float]:
    """``factors`` lengthened by ``spare`` more times the base in all (:meth:`StepwiseConfig.spare_factor`),
    shared in proportion to them: a step that changes more gets more of it.

    Measured (seed 0, two threads, alone; docs/time_series.md): the first 15 of the 30 viscous-finger steps, whose
    steps left 45 % of the budget unspent, went from 2.76 to 3.45 times one step's training, every step but the
    start 0.48-0.64 dB higher; three steps 40 apart (t010, t050, t090), whose two fine-tunes stopped at
    :data:`STEP_ITERATION_CAP`, from 2.66 to 3.48 times, +0.48 and +0.29 dB. A series the budget shortens (the 30
    steps) is unchanged."""
    total = sum(factors)
    return [f * (1 + spare / total) for f in factors] if total > 0 else list(factors)


def shortened_measurements(measurements: int, scale: float) -> int:
    """A fine-tune's measurements of where it is wrong when a long series shortens it to ``scale`` of its share
    (:meth:`StepwiseConfig.budget_scale`): as many per iteration, at least one."""
    return max(1, round(measurements * min(scale, 1.0)))


def step_pull(sparsity: float, iterations: int, base: int) -> float:
    """The pull (:class:`PullTowardsStart`) of a step's fine-tune of ``iterations`` where a step that differs little
    from its neighbour is fine-tuned for ``base`` (:meth:`StepwiseConfig.step_config` at factor and scale 1) and
    pulled at ``sparsity``: that up to :data:`STEP_EVEN_BELOW` times the base (the steps that change little,
    :func:`step_factors`), weaker in proportion on a longer fine-tune, so that its pull over all its iterations is
    no stronger than theirs.

    The pull acts at every iteration, so it adds up over a fine-tune, and a step that differs much from its
    neighbour (up to :data:`STEP_ITERATION_CAP` times the base, more where a short series spends the budget its
    steps leave) was held back hardest exactly where it has furthest to go. On three steps 40 apart, t010
    fine-tuned from t050 for its 9,321 iterations reached 70.62 dB at 0.01 and 74.33 at a sixteenth of it (74.26
    unpulled; its own model 72.90; docs/time_series.md). Ten steps of a volume shifted 4 voxels a step (4,800
    iterations each, now pulled at 0.002) ended 0.40-0.95 dB higher on steps 2-9, above their own models on all 7
    steps measured (two were below). The cost falls on a series whose packing is held at its target: the crop of
    the 30 viscous-finger steps to half their height, whose later fine-tunes (1,086-1,467 iterations) now code larger,
    lost 0.13-0.28 dB on every measured step. The 30 steps themselves (579 iterations each, the base 480) keep the
    pull they were measured with."""
    return sparsity * min(1.0, STEP_EVEN_BELOW * base / max(iterations, 1))


def step_shares(model: str, device: torch.device) -> tuple[float, float, float]:
    """A ``model`` kind series' steps' batch and points as shares of the start model's, and the start model's
    iterations as a share of the configured ones, where they train (:data:`STEP_BATCH_SHARES`,
    :data:`STEP_POINT_SHARES`, :data:`START_ITERATION_SHARES`: on a CPU; on a GPU, where a step is bound by kernel
    launches, a smaller batch would not take proportionally less time, and none of them was measured)."""
    if device.type != "cpu":
        return 1.0, 1.0, 1.0
    return STEP_BATCH_SHARES.get(model, 1.0), STEP_POINT_SHARES.get(model, 1.0), START_ITERATION_SHARES.get(model, 1.0)


def series_trainer(stepwise: StepwiseConfig | None, show_progress: bool = True) -> Callable[..., TrainedField]:
    """What trains a series (the ``train`` argument of :func:`~apmgsrn.training.fit.fit`): step by step with
    ``stepwise`` (:func:`train_stepwise`), else one joint model (:func:`~apmgsrn.training.fit.train_prepared`)."""
    if stepwise is None:
        return train_prepared
    return partial(train_stepwise, stepwise=stepwise, show_progress=show_progress)


def tracking_config(step: TrainConfig) -> TrainConfig:
    """A step's fine-tune (:meth:`StepwiseConfig.step_config`) with the reconstruction error moving its grids'
    placement too, through the whole fine-tune."""
    return replace(step, placement_loss="reconstruction", freeze_fraction=1.0,
                   placement_lr=step.placement_lr * TRACK_PLACEMENT_LR_SHARE)


def stepwise_config(field: FieldConfig, steps: int, storage: str = "float32") -> SeriesFieldConfig:
    """The series model a stepwise run fills: one basis slice and one placement per step, keyframe weights
    (the identity)."""
    return SeriesFieldConfig(field, SeriesConfig(steps=steps, basis=steps, coefficients="keyframes", storage=storage,
                                                 placement="per_step"))


def detail(values: torch.Tensor) -> float:
    """Mean magnitude of the forward differences along the three axes of ``[D, H, W]`` values."""
    return sum(float(values.diff(dim=axis).abs().mean()) for axis in range(3) if values.shape[axis] > 1)


def choose_start(values: torch.Tensor, start: int | str) -> int:
    """The start step of ``[T, D, H, W]`` values.

    Raises:
        ApmgsrnError: a step index outside the series.
    """
    steps = values.shape[0]
    if start == "first":
        return 0
    if start == "last":
        return steps - 1
    if start == "auto":
        scores = [detail(values[t]) for t in range(steps)]
        return max(range(steps), key=lambda t: (scores[t], t))
    if not 0 <= start < steps:
        raise ApmgsrnError(f"start={start} is outside the series of {steps} steps; pass 0..{steps - 1}",
                           arguments=("start",))
    return int(start)


def change(values: torch.Tensor, step: int, neighbour: int) -> float:
    """RMS difference between two steps of ``[T, D, H, W]`` values (a regular subset of at most about
    :data:`CHANGE_VOXELS` voxels)."""
    stride = max(1, values[step].numel() // CHANGE_VOXELS)
    difference = values[step].reshape(-1)[::stride] - values[neighbour].reshape(-1)[::stride]
    return float(difference.square().mean().sqrt())


def step_order(start: int, steps: int) -> list[tuple[int, int]]:
    """``(step, neighbour)`` pairs in training order: away from ``start``, nearest first, each step starting
    from its neighbour on the start's side (already trained when its turn comes)."""
    order = sorted(range(steps), key=lambda t: (abs(t - start), t))[1:]
    return [(t, t + 1 if t < start else t - 1) for t in order]


# ------------------------------------------------------------------------------------ steps checkpoint
@dataclass
class _Progress:
    """Where a stepwise run stands: the start step, the steps done in order, each one's fine-tune iterations
    (0 for the start; both fine-tunes of a tracked step) and whether its placement moved, the start model's
    RMS error and the training state so far."""

    start: int
    done: list[int]
    iterations: list[int]
    tracked: list[bool]
    error: float
    state: TrainingState


def _save_steps(path: Path, field: SeriesField, progress: _Progress, fingerprint: dict) -> None:
    """The series field so far and the steps done, atomically to ``path`` (it may replace the start model's
    training checkpoint of the same run)."""
    description = {"fingerprint": as_json(fingerprint), "start": progress.start, "done": progress.done,
                   "step_iterations": progress.iterations, "tracked": progress.tracked, "error": progress.error,
                   "state": asdict(progress.state)}
    data = file_bytes({k: v.detach().cpu().contiguous() for k, v in field.state_dict().items()},
                      STEPS_CHECKPOINT_KIND, description)
    atomic_write(path, lambda temp: Path(temp).write_bytes(data), "training checkpoint")


def _load_steps(path: Path, field: SeriesField, fingerprint: dict, iterations: int) -> _Progress:
    """Restore a steps checkpoint of this run into ``field``, and where the run stands (``iterations``: the
    most the whole run can take, a bound on every counter of its state).

    Raises:
        ApmgsrnError: another run's checkpoint, or a damaged one (checked before anything is loaded).
    """
    description = read_header(path).description
    if description.get("fingerprint") != as_json(fingerprint):
        raise ApmgsrnError(f"{path}: checkpoint was made with other data or settings; rerun with the same data "
                           "and options, or delete it to start over")
    steps = field.steps
    try:
        start = require_int(description.get("start"), "start", 0, steps - 1)
        done = description.get("done")
        if not isinstance(done, list) or not done or done[0] != start or len(set(done)) != len(done):
            raise DescriptionError("steps done are not a list that begins with the start")
        for index, step in enumerate(done):
            require_int(step, f"done[{index}]", 0, steps - 1)
        if done != [start] + [t for t, _ in step_order(start, steps)][: len(done) - 1]:
            raise DescriptionError("steps done are not in training order")
        counts = description.get("step_iterations")
        if not isinstance(counts, list) or len(counts) != len(done):
            raise DescriptionError("step iterations do not match the steps done")
        for index, count in enumerate(counts):
            require_int(count, f"step_iterations[{index}]", 0)
        tracked = description.get("tracked")
        if not isinstance(tracked, list) or len(tracked) != len(done) or not all(isinstance(t, bool) for t in tracked):
            raise DescriptionError("tracked steps do not match the steps done")
        error = require_number(description.get("error"), "error")
        if not error >= 0:
            raise DescriptionError("error is negative")
        state = state_from_json(description.get("state"), iterations)
        expected = {k: (tuple(v.shape), v.dtype) for k, v in field.state_dict().items()}
        tensors = load_tensors(path)
        check_tensors(tensors, expected)
    except (DescriptionError, ValueError, TypeError) as exc:
        raise ApmgsrnError(f"{path}: training checkpoint is damaged ({exc}); delete it to start over") from None
    if not all(bool(torch.isfinite(t).all()) for t in tensors.values()):
        raise ApmgsrnError(f"{path}: training checkpoint holds NaN or Inf; delete it to start over")
    field.load_state_dict(tensors)
    return _Progress(start, list(done), list(counts), list(tracked), error, state)


# ------------------------------------------------------------------------------------------ training
@torch.no_grad()
def _adopt(series: SeriesField, start_field: NeuralField) -> None:
    """The start model's placement, decoder and grids into the series field (its grids and placement become
    every step's until that step is trained)."""
    encoder, start = series.encoder, start_field.encoder
    for name in encoder.step_parameters:
        getattr(encoder, name).copy_(getattr(start, name).unsqueeze(0).expand_as(getattr(encoder, name)))
    series.decoder.load_state_dict(start_field.decoder.state_dict())


def step_worker(series: SeriesField) -> NeuralField:
    """A single-step field with the series' decoder (frozen): the steps' fine-tunes train it."""
    return series.step_field(0).train()  # a materialised copy; its grids and placement are set per step


@torch.no_grad()
def load_step(worker: NeuralField, series: SeriesField, step: int) -> None:
    """Step ``step``'s grids (or tables) and placement into the worker."""
    for name in series.encoder.step_parameters:
        getattr(worker.encoder, name).copy_(getattr(series.encoder, name)[step])


@torch.no_grad()
def store_step(worker: NeuralField, series: SeriesField, step: int) -> None:
    """The worker's grids (or tables) and placement as step ``step``'s."""
    for name in series.encoder.step_parameters:
        getattr(series.encoder, name)[step].copy_(getattr(worker.encoder, name))


class PullTowardsStart(TrainingCallback):
    """The proximal step of an L1 penalty on how far some parameters move from where a fine-tune starts.

    After every iteration each entry's change is shrunk towards zero by ``strength`` times its parameter
    group's current learning rate, and set to zero where it is smaller than that (a soft threshold). Adam moves
    every entry a little at every iteration, wherever its gradient is only noise; the pull undoes such moves.
    The changes that remain are smaller, so more of them round to zero in the packed file's time predictor,
    and, pulled hard enough, many entries keep their neighbour's value exactly.
    """

    def __init__(self, parameters: list[torch.Tensor], strength: float):
        self.strength = strength
        self.starts = {id(p): p.detach().clone() for p in parameters}

    @torch.no_grad()
    def after_step(self, trainer: Trainer, iteration: int, losses) -> None:
        for group in trainer.network_optimizer.param_groups:
            threshold = self.strength * group["lr"]
            for parameter in group["params"]:
                start = self.starts.get(id(parameter))
                if start is not None:
                    pull_towards(parameter, start, threshold)


def _fine_tune(worker: NeuralField, values: torch.Tensor, config: TrainConfig, track: bool,
               features: tuple[str, ...], check: tuple[torch.Tensor, torch.Tensor], sparsity: float = 0.0) -> float:
    """Fine-tune the worker's ``features`` (grids, or the hybrid's tables; with ``track`` its placement too)
    on one step, from where they are, pulled back towards there with ``sparsity`` (:class:`PullTowardsStart`);
    its RMS error then on the step's ``check`` sample (:func:`check_sample`)."""
    for name in features:
        getattr(worker.encoder, name).requires_grad_(True)
    for parameter in worker.encoder.placement_parameters():
        parameter.requires_grad_(track)
    pull = [PullTowardsStart([getattr(worker.encoder, name) for name in features], sparsity)] if sparsity > 0 else []
    Trainer(worker, values, tracking_config(config) if track else config, None, {}, pull, warm=True).run()
    return math.sqrt(_voxel_error(worker, check))


def check_sample(values: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points and targets a step's fine-tune is checked on: every voxel of a step of at most
    :data:`CHECK_VOXELS`, else that many drawn at random (seeded by the step)."""
    if values.numel() > CHECK_VOXELS:
        return draw_batch(values, CHECK_VOXELS, 1.0, torch.Generator(values.device).manual_seed(step))
    return voxel_coordinates(tuple(values.shape)).to(values.device), values.reshape(-1)


@torch.no_grad()
def _voxel_error(worker: NeuralField, check: tuple[torch.Tensor, torch.Tensor]) -> float:
    """Mean squared error of the worker at the ``(points, targets)`` of a step's check sample."""
    points, targets = check
    return float((worker.normalized(points).view(-1) - targets).square().mean())


def _train_step(worker: NeuralField, series: SeriesField, values: torch.Tensor, t: int, neighbour: int,
                config: TrainConfig, error: float, track_first: bool, sparsity: float = 0.0) -> tuple[bool, int]:
    """Train step ``t`` from ``neighbour`` into the series field (see the module docstring): first the way that
    ended the neighbour's training (placement kept, or moving with ``track_first``); if that ends more than
    :data:`TRACK_DB` below the start model, the other way too, and the better of the two is kept. Should the
    kept one fit :data:`CHECK_VOXELS` of the step's voxels worse than the neighbour's grids it started from (a
    short fine-tune whose first, noisy updates it could not undo), the step keeps the neighbour's.

    Returns:
        Whether the kept fine-tune moved the placement (the neighbour's way, when the step keeps its grids), and
        how many fine-tunes ran (1 or 2).
    """
    features = series.encoder.step_features
    check = check_sample(values, t)
    load_step(worker, series, neighbour)
    start = _voxel_error(worker, check)
    first = _fine_tune(worker, values, config, track_first, features, check, sparsity)
    tracked, runs = track_first, 1
    if first > error * 10 ** (TRACK_DB / 20):
        kept = {k: v.clone() for k, v in worker.encoder.state_dict().items()}
        load_step(worker, series, neighbour)
        second = _fine_tune(worker, values, config, not track_first, features, check, sparsity)
        if second >= first:
            worker.encoder.load_state_dict(kept)
        tracked, runs = (track_first if second >= first else not track_first), 2
    if _voxel_error(worker, check) > start:
        load_step(worker, series, neighbour)
        tracked = track_first
    store_step(worker, series, t)
    return tracked, runs


def train_stepwise(
    prepared: PreparedValues,
    field_config: SeriesFieldConfig,
    train_config: TrainConfig,
    volume_shape: tuple[int, int, int],
    checkpoint: Path | None = None,
    fingerprint: dict | None = None,
    callbacks: list[TrainingCallback] | tuple = (),
    stepwise: StepwiseConfig = StepwiseConfig(),
    show_progress: bool = True,
) -> TrainedField:
    """Train a series step by step (see the module docstring); the signature of
    :func:`~apmgsrn.training.fit.train_prepared`, plus how to step.

    Args:
        prepared: ``[T, D, H, W]`` values and their scaling.
        field_config: a series config with one basis slice per step (:func:`stepwise_config`).
        train_config: how the start model trains (the steps' fine-tunes: :meth:`StepwiseConfig.step_config`).
        volume_shape: ``(D, H, W)`` of every step.
        checkpoint: the run's checkpoint (resumed when there: the start model's or a steps checkpoint).
        fingerprint: what a resumed checkpoint must match.
        callbacks: called around the start model's iterations (its progress display).
        stepwise: the start step and the steps' fine-tune.
        show_progress: show one line of progress over the steps.

    Returns:
        The series field; its state counts every iteration and second of the start model and the steps.

    Raises:
        ApmgsrnError: a config that does not give every step its grids, or a damaged checkpoint.
        TrainingInterrupted: Ctrl-C, after the checkpoint is safe.
    """
    if not field_config.series.per_step_grids:
        raise ApmgsrnError("stepwise training fills one grid set per step: basis = steps, keyframe coefficients")
    values = prepared.values
    steps = values.shape[0]
    lr_share = STEP_LR_SHARES.get(field_config.field.model, STEP_LR_SHARE)
    batch_share, point_share, start_share = step_shares(field_config.field.model, values.device)
    start_iterations = max(1, round(train_config.iterations * start_share))
    sparsity = stepwise.sparsity(field_config.field.model)
    fingerprint = {**(fingerprint or {}), "stepwise": asdict(stepwise), "train": asdict(train_config)}
    if prepared.constant:
        return TrainedField(build_field(prepared, field_config, volume_shape, train_config.seed).eval(),
                            TrainingState(), 0)
    resumed = checkpoint is not None and checkpoint.exists() and read_header(checkpoint).kind == STEPS_CHECKPOINT_KIND
    if resumed:
        series = build_field(prepared, field_config, volume_shape, train_config.seed)
        largest = stepwise.largest_factor(train_config, steps - 1, point_share, start_share)
        most = start_iterations + steps * 2 * math.ceil(  # two fine-tunes of a step at most
            stepwise.base_iterations(train_config) * largest * point_share / batch_share)
        progress = _load_steps(checkpoint, series, fingerprint, most)
        resumed_from = progress.state.iteration
        worker = step_worker(series)
    else:
        start = choose_start(values, stepwise.start)
        if checkpoint is not None and checkpoint.exists() and read_header(checkpoint).kind != CHECKPOINT_KIND:
            raise ApmgsrnError(f"{checkpoint}: not a training checkpoint; remove it or pass another out=",
                               arguments=("out",))
        first = train_prepared(replace(prepared, values=values[start]), field_config.field,
                               replace(train_config, iterations=start_iterations, error_sampling=START_ERROR_SAMPLING),
                               volume_shape, checkpoint,
                               {**fingerprint, "start": start}, callbacks)
        # Built after the start model, which thus starts exactly as a model of that step alone would (building
        # a decoder draws from the global random generator).
        series = build_field(prepared, field_config, volume_shape, train_config.seed)
        _adopt(series, first.field)
        worker = step_worker(series)
        # Its RMS error at the voxels, not its last batch's: a batch drawn where the model is wrong
        # (TrainConfig.error_sampling) overstates it.
        error = math.sqrt(_voxel_error(first.field, check_sample(values[start], start)))
        progress = _Progress(start, [start], [0], [False], error, first.state)
        resumed_from = first.resumed_from
        if checkpoint is not None:  # the start model, before the polish below
            _save_steps(checkpoint, series, progress, fingerprint)
    state = progress.state
    scale = stepwise.budget_scale(train_config, steps - 1, batch_share, point_share, start_share)
    order = step_order(progress.start, steps)
    factors = step_factors([change(values, t, n) for t, n in order], progress.error)
    factors = spend_spare(factors, stepwise.spare_factor(train_config, factors, batch_share, point_share, start_share))
    factors = dict(zip((t for t, _ in order), factors))
    todo = [(t, n) for t, n in order if t not in progress.done]
    # A step's that changes little (the start step's own fine-tune below; step_pull's base), and every other one's.
    base = stepwise.step_config(train_config, lr_share=lr_share, batch_share=batch_share, point_share=point_share)
    configs = {t: stepwise.step_config(train_config, factors[t], scale, lr_share, batch_share, point_share)
               for t, _ in order}
    pulls = {t: step_pull(sparsity, config.iterations, base.iterations) for t, config in configs.items()}
    polish = train_config.error_guided and train_config.error_sampling != START_ERROR_SAMPLING
    display = Progress(steps, unit="step", description="steps", initial=steps - len(todo), enabled=show_progress)
    try:
        if polish and progress.iterations[0] == 0:  # not yet done (a checkpoint records it)
            # The start step's own grids fine-tuned like any step's, from themselves, with the model kind's draws
            # where the step is wrong (the shared decoder stays what uniform draws made it).
            began = time.perf_counter()
            _train_step(worker, series, values[progress.start], progress.start, progress.start, base,
                        progress.error, track_first=False, sparsity=sparsity)
            progress.iterations[0] = base.iterations
            state.iteration += base.iterations
            state.elapsed += time.perf_counter() - began
            if checkpoint is not None:
                _save_steps(checkpoint, series, progress, fingerprint)
        for t, neighbour in todo:
            began = time.perf_counter()
            moved = dict(zip(progress.done, progress.tracked))
            tracked, runs = _train_step(worker, series, values[t], t, neighbour, configs[t], progress.error,
                                        track_first=moved[neighbour], sparsity=pulls[t])
            iterations = configs[t].iterations * runs
            progress.done.append(t)
            progress.iterations.append(iterations)
            progress.tracked.append(tracked)
            state.iteration += iterations
            state.elapsed += time.perf_counter() - began
            if checkpoint is not None:
                _save_steps(checkpoint, series, progress, fingerprint)
            display.set_fields(step=t, iterations=iterations, **({"placement": "moved"} if tracked else {}))
            display.update(1)
    except KeyboardInterrupt:
        display.close(completed=False)
        if checkpoint is None:
            raise
        raise TrainingInterrupted(state.iteration, checkpoint) from None
    display.close(completed=True)
    series.requires_grad_(True)
    by_step = dict(zip(progress.done, progress.iterations))
    summary = {"start": progress.start, "start_iterations": start_iterations,
               "step_iterations": [by_step[t] for t in range(steps)],
               "step_lr": base.lr,
               "tracked_steps": sorted(t for t, moved in zip(progress.done, progress.tracked) if moved),
               "budget_scale": round(scale, 6), "step_sparsity": sparsity,
               "step_pull_iterations": round(STEP_EVEN_BELOW * base.iterations),
               "weaker_pull_steps": sorted(t for t, pull in pulls.items() if pull < sparsity)}
    return TrainedField(series.eval(), state, resumed_from, summary={"stepwise": summary})

