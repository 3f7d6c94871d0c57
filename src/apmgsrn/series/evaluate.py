"""How well a time-series model reproduces its steps: per step and over every voxel of every step
(docs/method.md §10), one step (and one slab) at a time through :func:`apmgsrn.inference.evaluate.evaluate`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from apmgsrn.inference.evaluate import Evaluation, evaluate, psnr_from_mse
from apmgsrn.progress import Progress
from apmgsrn.recipes import RUNTIME


@dataclass(frozen=True)
class SeriesEvaluation:
    """Errors of a time-series model, per step and over every voxel of every step (docs/method.md §10).

    Attributes:
        steps: one :class:`Evaluation` per step evaluated, in order (each with its own step's value range).
        indices: the step index of each entry of ``steps``.
        overall: over all voxels of those steps, with the value range of all of them.
    """

    steps: tuple[Evaluation, ...]
    indices: tuple[int, ...]
    overall: Evaluation

    @property
    def psnr(self) -> float:
        """PSNR over every voxel of every step, dB."""
        return self.overall.psnr

    @property
    def max_abs_error(self) -> float:
        """Largest absolute error over every step."""
        return self.overall.max_abs_error

    @property
    def worst_step(self) -> int:
        """Index (into the series) of the step with the lowest PSNR."""
        return self.indices[min(range(len(self.steps)), key=lambda i: self.steps[i].psnr)]

    def to_dict(self) -> dict:
        return {"overall": self.overall.to_dict(),
                "steps": [{"step": i, **e.to_dict()} for i, e in zip(self.indices, self.steps)]}


def evaluate_series(
    step_field,
    truth,
    indices: Sequence[int] | None = None,
    trained_shape: tuple[int, int, int] | None = None,
    max_voxels: int | None = None,
    progress: bool = False,
    slab_voxels: int = RUNTIME.slab_voxels,
    batch_size: int = RUNTIME.query_batch,
) -> SeriesEvaluation:
    """Compare a time-series model with every voxel of every step, one step (and one slab) at a time.

    Args:
        step_field: ``step index -> field`` (``[N, 3] -> [N, 1]`` in data units) of that step, e.g. a series
            field's ``step_field``.
        truth: a :class:`~apmgsrn.series.data.VolumeSeries` (each step read when it is compared) or a
            ``[T, D, H, W]`` array in data units.
        indices: the steps to compare (default: every step).
        trained_shape: the shape every step must have.
        max_voxels: per step, compare a regular subset of about this many voxels (see :func:`evaluate`).
        progress: show progress, one tick per step.
        slab_voxels: evaluated voxels per slab.
        batch_size: points per forward pass.

    Raises:
        ApmgsrnError: a step of another shape, or holding NaN or Inf.
    """
    indices = tuple(range(len(truth))) if indices is None else tuple(indices)
    options = dict(trained_shape=trained_shape, max_voxels=max_voxels, slab_voxels=slab_voxels, batch_size=batch_size)
    results = []
    with Progress(len(indices), unit="step", description="eval", enabled=progress) as shown:
        for index in indices:
            if isinstance(truth, np.ndarray):
                results.append(evaluate(step_field(index), truth[index], **options))
            else:
                with truth.volume(index) as step:
                    results.append(evaluate(step_field(index), step, **options))
            shown.update(1)
    # Every step has the same number of voxels, so the overall MSE is the mean of the steps' MSEs.
    low, high = min(r.data_min for r in results), max(r.data_max for r in results)
    mse = sum(r.mse for r in results) / len(results)
    overall = Evaluation(psnr=psnr_from_mse(mse, high - low), mse=mse,
                         max_abs_error=max(r.max_abs_error for r in results), data_min=low, data_max=high)
    return SeriesEvaluation(tuple(results), indices, overall)
