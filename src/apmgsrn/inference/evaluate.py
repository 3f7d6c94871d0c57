"""How well a field reproduces a volume (docs/method.md §8): PSNR and largest error over every voxel,
streamed over z-slabs of the volume, with the check that the volume is the one the field was trained on (a time
series, per step: :mod:`apmgsrn.series.evaluate`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from apmgsrn.data import Volume, format_xyz
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.slabs import field_slabs
from apmgsrn.progress import Progress
from apmgsrn.recipes import RUNTIME


@dataclass(frozen=True)
class Evaluation:
    """Errors of a reconstruction in data units; ``psnr`` is ``inf`` for an exact one.

    Attributes:
        psnr: ``20 log10(data_max - data_min) - 10 log10(mse)``, dB.
        mse: mean squared error over the compared voxels.
        max_abs_error: largest absolute error.
        data_min, data_max: value range of the ground truth (every voxel, also when only a subset
            was compared).
    """

    psnr: float
    mse: float
    max_abs_error: float
    data_min: float
    data_max: float

    def to_dict(self) -> dict:
        return asdict(self)


def psnr_from_mse(mse: float, data_range: float) -> float:
    """``20 log10(range) - 10 log10(MSE)``; ``inf`` when the MSE is zero."""
    if mse <= 0:
        return math.inf
    if data_range <= 0:
        return -math.inf
    return 20 * math.log10(data_range) - 10 * math.log10(mse)


class ErrorAccumulator:
    """Squared-error sum, largest absolute error and the truth's range over blocks, in float64."""

    def __init__(self) -> None:
        self.squared = 0.0
        self.count = 0
        self.max_abs = 0.0
        self.data_min = math.inf
        self.data_max = -math.inf

    def add(self, prediction: np.ndarray | torch.Tensor, truth: np.ndarray) -> None:
        """Compare one block: ``prediction`` and ``truth`` of the same number of voxels, data units."""
        predicted = np.asarray(prediction, dtype=np.float64).reshape(-1)
        expected = np.asarray(truth, dtype=np.float64).reshape(-1)
        diff = predicted - expected
        self.squared += float(np.dot(diff, diff))
        self.count += diff.size
        if diff.size:
            self.max_abs = max(self.max_abs, float(np.abs(diff).max()))
        self.add_range(truth)

    def add_range(self, truth: np.ndarray) -> None:
        """Widen the truth's value range by voxels that are not compared (a strided subset's slab)."""
        if truth.size:
            self.data_min = min(self.data_min, float(truth.min()))
            self.data_max = max(self.data_max, float(truth.max()))

    def result(self) -> Evaluation:
        mse = self.squared / max(self.count, 1)
        return Evaluation(
            psnr=psnr_from_mse(mse, self.data_max - self.data_min),
            mse=mse,
            max_abs_error=self.max_abs,
            data_min=self.data_min,
            data_max=self.data_max,
        )


def check_volume_shape(shape: tuple[int, ...], trained_shape: tuple[int, ...], where: str) -> None:
    """Refuse a volume whose shape is not the one the model was trained on.

    Args:
        shape: ``(D, H, W)`` of the volume given.
        trained_shape: ``(D, H, W)`` the model was trained on.
        where: the volume's file, for the message.

    Raises:
        ApmgsrnError: the shapes differ.
    """
    if tuple(shape) != tuple(trained_shape):
        raise ApmgsrnError(
            f"{where}: volume is {format_xyz(shape)} (x*y*z) but the model was trained on "
            f"{format_xyz(trained_shape)}; pass the matching volume"
        )


def evaluate(
    field,
    truth: Volume | np.ndarray,
    trained_shape: tuple[int, int, int] | None = None,
    max_voxels: int | None = None,
    progress: bool = False,
    slab_voxels: int = RUNTIME.slab_voxels,
    batch_size: int = RUNTIME.query_batch,
) -> Evaluation:
    """Compare ``field`` with every voxel of ``truth`` (or a regular subset), one z-slab at a time.

    Args:
        field: module ``[N, 3] -> [N, 1]`` in data units.
        truth: the ground truth ``[D, H, W]`` in data units: a :class:`~apmgsrn.data.Volume` (read one
            slab at a time) or an array in memory.
        trained_shape: the shape the field was trained on; a volume of another shape is refused.
        max_voxels: compare only every ``s``-th voxel along each axis, ``s`` chosen for about this many
            voxels (None: all of them); the value range still covers every voxel.
        progress: show progress (see :mod:`apmgsrn.progress`).
        slab_voxels: evaluated voxels per slab.
        batch_size: points per forward pass.

    Raises:
        ApmgsrnError: the shape differs from ``trained_shape``, or the truth holds NaN or Inf.
    """
    shape = tuple(truth.shape)
    where = str(truth.path) if isinstance(truth, Volume) else "volume"
    if trained_shape is not None:
        check_volume_shape(shape, trained_shape, where)
    size = math.prod(shape)
    stride = 1
    if max_voxels and size > max_voxels:
        stride = max(1, math.ceil((size / max_voxels) ** (1 / 3)))
    errors = ErrorAccumulator()
    compared = math.prod(len(range(0, n, stride)) for n in shape)
    with Progress(compared, unit="voxel", description="eval", enabled=progress) as shown:
        for z, predicted in field_slabs(field, shape, slab_voxels, stride, batch_size):
            block = truth.read(z) if isinstance(truth, Volume) else truth[z]  # [dz, H, W]
            if not np.isfinite(block).all():
                raise ApmgsrnError(
                    f"{where}: holds NaN or Inf voxels (z {z.start}:{z.stop}); "
                    "pass fill_nonfinite=VALUE to replace them (e.g. fill_nonfinite=0)", arguments=("fill_nonfinite",),
                )
            errors.add(predicted.numpy(), block[::stride, ::stride, ::stride])
            errors.add_range(block)
            shown.update(predicted.numel())
    return errors.result()


def compare_arrays(restored: np.ndarray, truth: np.ndarray) -> Evaluation:
    """Errors of a whole restored array (a decompressed or decoded volume) against the truth."""
    errors = ErrorAccumulator()
    errors.add(restored, truth)
    return errors.result()
