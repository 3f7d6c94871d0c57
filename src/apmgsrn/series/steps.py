"""Warm-started steps: a time series trained one step after another, every step with its own feature grids.

The default way ``apmgsrn train`` fits a series (measured against one shared model of all steps in
docs/time_series.md):

1. **Start step.** The step with the most detail (largest mean gradient magnitude of its values,
   :func:`choose_start`) gets a single-step model trained on it alone, with the whole budget of one volume
   (more where the model kind's steps gain from it, ``ModelRecipe.start_iteration_share``; its voxel points drawn
   uniformly, ``SERIES.start_error_sampling``; then its own grids get a step's fine-tune from themselves, drawn
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
   more than ``SERIES.track_db`` below the start model: then the step is fine-tuned again from its neighbour
   with the reconstruction error moving its grids' placement too (``placement_loss="reconstruction"``), and
   the better of the two is kept. Structures that travel across the domain are followed this way; every
   step stores its own placement (192 floats at the small size). A step whose neighbour's placement moved
   is fine-tuned with a moving placement first (the motion usually goes on), and with the placement kept
   only if that ends more than ``SERIES.track_db`` below.

The result is a :class:`~apmgsrn.series.field.SeriesField` with one basis slice per step (keyframe
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
from dataclasses import asdict, dataclass, field, replace
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
from apmgsrn.series.field import SeriesConfig, SeriesField, SeriesFieldConfig
from apmgsrn.ops.trilinear import voxel_coordinates
from apmgsrn.progress import Progress
from apmgsrn.recipes import SERIES, ModelRecipe, SeriesRecipe, model_recipe
from apmgsrn.training.checkpoint import CHECKPOINT_KIND, TrainingState, check_tensors, state_from_json
from apmgsrn.training.fit import PreparedValues, TrainedField, build_field, train_prepared
from apmgsrn.training.optimizer import pull_towards
from apmgsrn.training.points import draw_batch
from apmgsrn.series.packing import series_growth
from apmgsrn.training.trainer import TrainConfig, Trainer, TrainingCallback, TrainingInterrupted, as_json

STEPS_CHECKPOINT_KIND = "series-steps"
#: Start choices besides a step index.
STARTS = ("auto", "first", "last")


@dataclass(frozen=True)
class StepwiseConfig:
    """How a series is trained step by step.

    Attributes:
        start: the step the first model is trained on: ``"auto"`` (the step with the most detail),
            ``"first"``, ``"last"``, or a step index.
        step_iterations: fine-tune iterations of every other step (None: a tenth of the start model's), counted
            at the start model's batch (a model kind with a smaller step batch, ``ModelRecipe.step_batch_share``, runs
            proportionally more).
        step_lr: their learning rate (None: 0.3 times the start model's).
        step_sparsity: how hard a step's features are pulled back to its neighbour's during its fine-tune
            (:class:`PullTowardsStart`; 0: not at all; None: the model kind's default, ``ModelRecipe.step_sparsity``).
            The more entries keep their neighbour's value, the fewer bytes the packed file's time predictor
            spends on the step, and the less closely the step fits its data.
        qat_iterations: the quantisation-aware fine-tune every step gets once all are trained (the packing's,
            :attr:`~apmgsrn.series.packing.SeriesPacking.qat_iterations`), before
            :meth:`budget_scale` shortens it with the steps': it shares their budget.
        recipe: the tuned numbers of the steps' training (a run's fingerprint leaves them out: :meth:`settings`).
    """

    start: int | str = "auto"
    step_iterations: int | None = None
    step_lr: float | None = None
    step_sparsity: float | None = None
    qat_iterations: int = 0
    recipe: SeriesRecipe = field(default=SERIES, repr=False)

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

    def settings(self) -> dict:
        """The fields as a run's fingerprint records them: all but :attr:`recipe`, which the code fixes."""
        return {name: value for name, value in asdict(self).items() if name != "recipe"}

    def sparsity(self, model: str) -> float:
        """The pull of :attr:`step_sparsity` for steps of a ``model`` kind series."""
        return self.step_sparsity if self.step_sparsity is not None else model_recipe(model).step_sparsity

    def base_iterations(self, config: TrainConfig) -> int:
        """Fine-tune iterations of a step that differs little from its neighbour."""
        return self.step_iterations or max(1, round(config.iterations * self.recipe.step_iteration_share))

    def step_config(self, config: TrainConfig, factor: float = 1.0, scale: float = 1.0,
                    lr_share: float = ModelRecipe.step_lr_share, batch_share: float = 1.0, point_share: float = 1.0
                    ) -> TrainConfig:
        """How a step after the start is fine-tuned: its grids only (the density loss never starts), for
        ``factor`` times :meth:`base_iterations` (more when the step differs from its neighbour by more than
        ``SERIES.step_change_scale`` times the start model's error: :func:`change_factor`, :func:`step_factors`).

        Args:
            config: the start model's training.
            factor: the base's multiple (1: a step that differs little from its neighbour).
            scale: a long series' share of the base (:meth:`budget_scale`), and of the measurements of where
                the step is wrong (:func:`shortened_measurements`).
            lr_share: the learning rate's share of the start model's (``ModelRecipe.step_lr_share``), unless
                ``step_lr``.
            batch_share: the batch's share of the start model's (``ModelRecipe.step_batch_share``); the iterations
                above are counted at the start model's batch and divided by it.
            point_share: the iterations above times this (``ModelRecipe.step_point_share``).
        """
        iterations = max(1, round(self.base_iterations(config) * factor * scale * point_share / batch_share))
        lr = config.lr * lr_share if self.step_lr is None else self.step_lr
        return replace(config, iterations=iterations, lr=lr, density_start=iterations + 1, history_every=None,
                       stop_after_lr_cuts=None, batch_size=max(1, round(config.batch_size * batch_share)),
                       error_measurements=shortened_measurements(self.recipe.step_error_measurements, scale),
                       error_parts=self.recipe.step_error_parts,
                       voxel_fraction=step_voxel_fraction(config.voxel_fraction, self.recipe))


    def budget_scale(self, config: TrainConfig, steps: int, batch_share: float = 1.0, point_share: float = 1.0,
                     start_share: float = 1.0) -> float:
        """The share of :meth:`base_iterations` and of :attr:`qat_iterations` (and of their measurements of where
        they are wrong) every step gets so that the ``steps`` steps after the start (at ``point_share`` of the
        base's points), the quantisation-aware fine-tune of all ``steps + 1`` (at ``batch_share`` of the start
        model's batch) and what every step costs besides (``SERIES.step_fixed_cost``) together take at most
        ``SERIES.steps_budget_cap`` times the configured start model's points (in proportion to the steps beyond
        ``SERIES.share_steps``), less what a start model trained
        ``start_share`` times as long (``ModelRecipe.start_iteration_share``) takes beyond them at
        ``SERIES.start_point_cost`` (1 for a series short enough, and when ``step_iterations`` was given; at least
        ``SERIES.least_budget_scale``). Steps that change much keep their extra iterations in proportion
        (:meth:`step_config`)."""
        if self.step_iterations is not None or steps < 1:
            return 1.0
        points = steps * self.base_iterations(config) * point_share + (steps + 1) * self.qat_iterations * batch_share
        return min(1.0, max(self._allowed(config, steps, start_share) / points, self.recipe.least_budget_scale))

    def _allowed(self, config: TrainConfig, steps: int, start_share: float) -> float:
        """The points :meth:`budget_scale` lets the fine-tunes of ``steps`` steps after the start take
        (``SERIES.steps_budget_cap`` times the series' :func:`~apmgsrn.series.packing.series_growth`)."""
        recipe = self.recipe
        cap = recipe.steps_budget_cap * series_growth(steps + 1, recipe) - recipe.start_point_cost * (start_share - 1)
        return cap * config.iterations - (steps + 1) * recipe.step_fixed_cost

    def spare_factor(self, config: TrainConfig, factors: list[float], batch_share: float = 1.0,
                     point_share: float = 1.0, start_share: float = 1.0) -> float:
        """How many more times :meth:`base_iterations` the steps after the start (their :func:`step_factors`
        ``factors``) may run in all before they and the quantisation-aware fine-tune take the budget of
        :meth:`budget_scale`: what a short series, or one of few steps that change much (each at most
        ``SERIES.step_iteration_cap`` times the base), leaves unspent (0 once the budget shortens them, and when
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
        return self.recipe.step_iteration_cap * (1 + max(0.0, self._allowed(config, steps, start_share)) / base)

    def shortened_qat(self, config: TrainConfig, steps: int, batch_share: float = 1.0, point_share: float = 1.0,
                      start_share: float = 1.0) -> int:
        """:attr:`qat_iterations` at the share of :meth:`budget_scale` (at least one when there are any)."""
        if not self.qat_iterations:
            return 0
        scale = self.budget_scale(config, steps, batch_share, point_share, start_share)
        return max(1, round(self.qat_iterations * scale))


def step_voxel_fraction(voxel_fraction: float, recipe: SeriesRecipe = SERIES) -> float:
    """The share of a step's fine-tune points on voxels where the start model's is ``voxel_fraction``: its points
    between the voxels cut to ``SERIES.step_off_voxel_share`` of the start model's."""
    return 1.0 - (1.0 - voxel_fraction) * recipe.step_off_voxel_share


def change_factor(change: float, error: float, recipe: SeriesRecipe = SERIES) -> float:
    """How many times :meth:`StepwiseConfig.base_iterations` a step gets that differs from its neighbour by
    ``change`` where the start model's RMS error is ``error``: 1 up to ``SERIES.step_change_scale`` times the error,
    then in proportion, at most ``SERIES.step_iteration_cap``."""
    return min(max(change / (recipe.step_change_scale * max(error, 1e-12)), 1.0), recipe.step_iteration_cap)


def step_factors(changes: list[float], error: float, recipe: SeriesRecipe = SERIES) -> list[float]:
    """:func:`change_factor` of every step's change, those below ``SERIES.step_even_below`` replaced by their mean:
    the same iterations in all, spread evenly over the steps that change little."""
    factors = [change_factor(c, error, recipe) for c in changes]
    small = [f for f in factors if f < recipe.step_even_below]
    even = sum(small) / len(small) if small else 1.0
    return [even if f < recipe.step_even_below else f for f in factors]


def spend_spare(factors: list[float], spare: float) -> list[float]:
    """``factors`` lengthened by ``spare`` more times the base in all (:meth:`StepwiseConfig.spare_factor`),
    shared in proportion to them: a step that changes more gets more of it (the first 15 viscous-finger steps:
    +0.48-0.64 dB on every step but the start; docs/time_series.md). A series the budget shortens is unchanged."""
    total = sum(factors)
    return [f * (1 + spare / total) for f in factors] if total > 0 else list(factors)


def shortened_measurements(measurements: int, scale: float) -> int:
    """A fine-tune's measurements of where it is wrong when a long series shortens it to ``scale`` of its share
    (:meth:`StepwiseConfig.budget_scale`): as many per iteration, at least one."""
    return max(1, round(measurements * min(scale, 1.0)))


def step_pull(sparsity: float, iterations: int, base: int, recipe: SeriesRecipe = SERIES) -> float:
    """The pull (:class:`PullTowardsStart`) of a step's fine-tune of ``iterations`` where a step that differs little
    from its neighbour is fine-tuned for ``base`` (:meth:`StepwiseConfig.step_config` at factor and scale 1) and
    pulled at ``sparsity``: that up to ``SERIES.step_even_below`` times the base (the steps that change little,
    :func:`step_factors`), weaker in proportion on a longer fine-tune, so that its pull over all its iterations is
    no stronger than theirs.

    The pull acts at every iteration, so it adds up over a fine-tune: at full strength a step that differs much from
    its neighbour would be held back hardest exactly where it has furthest to go (t010 fine-tuned from t050 for
    9,321 iterations: 70.62 dB pulled at 0.01, 74.33 at a sixteenth of it; docs/time_series.md)."""
    return sparsity * min(1.0, recipe.step_even_below * base / max(iterations, 1))


def step_shares(model: str, device: torch.device) -> tuple[float, float, float]:
    """A ``model`` kind series' steps' batch and points as shares of the start model's, and the start model's
    iterations as a share of the configured ones, where they train (its recipe's ``step_batch_share``,
    ``step_point_share`` and ``start_iteration_share``: on a CPU; on a GPU, where a step is bound by kernel
    launches, a smaller batch would not take proportionally less time, and none of them is measured)."""
    if device.type != "cpu":
        return 1.0, 1.0, 1.0
    recipe = model_recipe(model)
    return recipe.step_batch_share, recipe.step_point_share, recipe.start_iteration_share


def series_trainer(stepwise: StepwiseConfig | None, show_progress: bool = True) -> Callable[..., TrainedField]:
    """What trains a series (the ``train`` argument of :func:`~apmgsrn.training.fit.fit`): step by step with
    ``stepwise`` (:func:`train_stepwise`), else one joint model (:func:`~apmgsrn.training.fit.train_prepared`)."""
    if stepwise is None:
        return train_prepared
    return partial(train_stepwise, stepwise=stepwise, show_progress=show_progress)


def tracking_config(step: TrainConfig, recipe: SeriesRecipe = SERIES) -> TrainConfig:
    """A step's fine-tune (:meth:`StepwiseConfig.step_config`) with the reconstruction error moving its grids'
    placement too, through the whole fine-tune."""
    return replace(step, placement_loss="reconstruction", freeze_fraction=1.0,
                   placement_lr=step.placement_lr * recipe.track_placement_lr_share)


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


def change(values: torch.Tensor, step: int, neighbour: int, recipe: SeriesRecipe = SERIES) -> float:
    """RMS difference between two steps of ``[T, D, H, W]`` values (a regular subset of at most about
    ``SERIES.change_voxels`` voxels)."""
    stride = max(1, values[step].numel() // recipe.change_voxels)
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
    atomic_write(path, lambda temp: Path(temp).write_bytes(data), "training checkpoint", model_part=True)


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
               features: tuple[str, ...], check: tuple[torch.Tensor, torch.Tensor], sparsity: float = 0.0,
               recipe: SeriesRecipe = SERIES) -> float:
    """Fine-tune the worker's ``features`` (grids, or the hybrid's tables; with ``track`` its placement too)
    on one step, from where they are, pulled back towards there with ``sparsity`` (:class:`PullTowardsStart`);
    its RMS error then on the step's ``check`` sample (:func:`check_sample`)."""
    for name in features:
        getattr(worker.encoder, name).requires_grad_(True)
    for parameter in worker.encoder.placement_parameters():
        parameter.requires_grad_(track)
    pull = [PullTowardsStart([getattr(worker.encoder, name) for name in features], sparsity)] if sparsity > 0 else []
    Trainer(worker, values, tracking_config(config, recipe) if track else config, None, {}, pull, warm=True).run()
    return math.sqrt(_voxel_error(worker, check))


def check_sample(values: torch.Tensor, step: int, recipe: SeriesRecipe = SERIES) -> tuple[torch.Tensor, torch.Tensor]:
    """Points and targets a step's fine-tune is checked on: every voxel of a step of at most
    ``SERIES.check_voxels``, else that many drawn at random (seeded by the step)."""
    if values.numel() > recipe.check_voxels:
        return draw_batch(values, recipe.check_voxels, 1.0, torch.Generator(values.device).manual_seed(step))
    return voxel_coordinates(tuple(values.shape)).to(values.device), values.reshape(-1)


@torch.no_grad()
def _voxel_error(worker: NeuralField, check: tuple[torch.Tensor, torch.Tensor]) -> float:
    """Mean squared error of the worker at the ``(points, targets)`` of a step's check sample."""
    points, targets = check
    return float((worker.normalized(points).view(-1) - targets).square().mean())


def _train_step(worker: NeuralField, series: SeriesField, values: torch.Tensor, t: int, neighbour: int,
                config: TrainConfig, error: float, track_first: bool, sparsity: float = 0.0,
                recipe: SeriesRecipe = SERIES) -> tuple[bool, int]:
    """Train step ``t`` from ``neighbour`` into the series field (see the module docstring): first the way that
    ended the neighbour's training (placement kept, or moving with ``track_first``); if that ends more than
    ``SERIES.track_db`` below the start model, the other way too, and the better of the two is kept. Should the
    kept one fit ``SERIES.check_voxels`` of the step's voxels worse than the neighbour's grids it started from (a
    short fine-tune whose first, noisy updates it could not undo), the step keeps the neighbour's.

    Returns:
        Whether the kept fine-tune moved the placement (the neighbour's way, when the step keeps its grids), and
        how many fine-tunes ran (1 or 2).
    """
    features = series.encoder.step_features
    check = check_sample(values, t, recipe)
    load_step(worker, series, neighbour)
    start = _voxel_error(worker, check)
    first = _fine_tune(worker, values, config, track_first, features, check, sparsity, recipe)
    tracked, runs = track_first, 1
    if first > error * 10 ** (recipe.track_db / 20):
        kept = {k: v.clone() for k, v in worker.encoder.state_dict().items()}
        load_step(worker, series, neighbour)
        second = _fine_tune(worker, values, config, not track_first, features, check, sparsity, recipe)
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
    recipe = stepwise.recipe
    lr_share = model_recipe(field_config.field.model).step_lr_share
    batch_share, point_share, start_share = step_shares(field_config.field.model, values.device)
    start_iterations = max(1, round(train_config.iterations * start_share))
    sparsity = stepwise.sparsity(field_config.field.model)
    fingerprint = {**(fingerprint or {}), "stepwise": stepwise.settings(), "train": asdict(train_config)}
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
                               replace(train_config, iterations=start_iterations,
                                       error_sampling=recipe.start_error_sampling),
                               volume_shape, checkpoint,
                               {**fingerprint, "start": start}, callbacks)
        # Built after the start model, which thus starts exactly as a model of that step alone would (building
        # a decoder draws from the global random generator).
        series = build_field(prepared, field_config, volume_shape, train_config.seed)
        _adopt(series, first.field)
        worker = step_worker(series)
        # Its RMS error at the voxels, not its last batch's: a batch drawn where the model is wrong
        # (TrainConfig.error_sampling) overstates it.
        error = math.sqrt(_voxel_error(first.field, check_sample(values[start], start, recipe)))
        progress = _Progress(start, [start], [0], [False], error, first.state)
        resumed_from = first.resumed_from
        if checkpoint is not None:  # the start model, before the polish below
            _save_steps(checkpoint, series, progress, fingerprint)
    state = progress.state
    scale = stepwise.budget_scale(train_config, steps - 1, batch_share, point_share, start_share)
    order = step_order(progress.start, steps)
    factors = step_factors([change(values, t, n, recipe) for t, n in order], progress.error, recipe)
    factors = spend_spare(factors, stepwise.spare_factor(train_config, factors, batch_share, point_share, start_share))
    factors = dict(zip((t for t, _ in order), factors))
    todo = [(t, n) for t, n in order if t not in progress.done]
    # A step's that changes little (the start step's own fine-tune below; step_pull's base), and every other one's.
    base = stepwise.step_config(train_config, lr_share=lr_share, batch_share=batch_share, point_share=point_share)
    configs = {t: stepwise.step_config(train_config, factors[t], scale, lr_share, batch_share, point_share)
               for t, _ in order}
    pulls = {t: step_pull(sparsity, config.iterations, base.iterations, recipe) for t, config in configs.items()}
    polish = train_config.error_guided and train_config.error_sampling != recipe.start_error_sampling
    display = Progress(steps, unit="step", description="steps", initial=steps - len(todo), enabled=show_progress)
    try:
        if polish and progress.iterations[0] == 0:  # not yet done (a checkpoint records it)
            # The start step's own grids fine-tuned like any step's, from themselves, with the model kind's draws
            # where the step is wrong (the shared decoder stays what uniform draws made it).
            began = time.perf_counter()
            _train_step(worker, series, values[progress.start], progress.start, progress.start, base,
                        progress.error, track_first=False, sparsity=sparsity, recipe=recipe)
            progress.iterations[0] = base.iterations
            state.iteration += base.iterations
            state.elapsed += time.perf_counter() - began
            if checkpoint is not None:
                _save_steps(checkpoint, series, progress, fingerprint)
        for t, neighbour in todo:
            began = time.perf_counter()
            moved = dict(zip(progress.done, progress.tracked))
            tracked, runs = _train_step(worker, series, values[t], t, neighbour, configs[t], progress.error,
                                        track_first=moved[neighbour], sparsity=pulls[t], recipe=recipe)
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
               "step_pull_iterations": round(recipe.step_even_below * base.iterations),
               "weaker_pull_steps": sorted(t for t, pull in pulls.items() if pull < sparsity)}
    return TrainedField(series.eval(), state, resumed_from, summary={"stepwise": summary})

