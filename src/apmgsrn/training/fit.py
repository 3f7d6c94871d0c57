"""Fit one model to one volume: prepare the data, train, save the model file (the ``train`` command)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig
from apmgsrn.models.value_transform import ValueTransform, fit_value_transform
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.training.checkpoint import checkpoint_path_for
from apmgsrn.training.trainer import Trainer, TrainConfig


@dataclass(frozen=True)
class PreparedVolume:
    """A volume ready for training: values scaled to ``[0, 1]`` in fitted units, on the device."""

    values: torch.Tensor  # [D, H, W] float32 in [0, 1]
    data: np.ndarray  # [D, H, W] float32 in data units (for the final PSNR)
    transform: ValueTransform
    fit_min: float
    fit_max: float
    value_min: float
    value_max: float


def prepare_volume(volume, transform: str, log_offset: float, device: torch.device) -> PreparedVolume:
    """Read, check, transform and scale a volume for training.

    Raises:
        ApmgsrnError: non-finite values (without a fill value) or a transform the data does not allow.
    """
    from apmgsrn.data import check_finite

    check_finite(volume)
    data = volume.to_numpy()
    value_min, value_max = float(data.min()), float(data.max())
    value_transform = fit_value_transform(transform, [data], value_min, log_offset, str(volume.path))
    fitted = value_transform.apply(data)
    fit_min, fit_max = float(fitted.min()), float(fitted.max())
    span = fit_max - fit_min
    # A constant volume has no range: fit zeros, and the output scaling returns the constant exactly.
    scaled = (fitted - fit_min) / (span if span > 0 else 1.0)
    values = torch.from_numpy(np.ascontiguousarray(scaled, dtype=np.float32)).to(device)
    return PreparedVolume(values, data, value_transform, fit_min, fit_max, value_min, value_max)


@dataclass(frozen=True)
class FitResult:
    field: NeuralField
    model_path: Path
    model_bytes: int
    seconds: float
    iterations: int
    frozen_at: int | None
    psnr: float


def fit_volume(
    volume,
    field_config: FieldConfig,
    train_config: TrainConfig,
    out: Path,
    device: torch.device,
    transform: str = "none",
    log_offset: float = 0.0,
    resume: bool = False,
    progress: bool = True,
) -> FitResult:
    """Train a model on ``volume`` and save it to ``out`` (checkpointing to ``out.ckpt`` on the way).

    Args:
        volume: a :class:`apmgsrn.data.Volume`.
        field_config: the model to build.
        train_config: how to train.
        out: model file to write (atomically).
        device: training device.
        transform: value transform (``none``, ``log10``, ``zscore``).
        log_offset: offset for ``log10``.
        resume: continue from ``out.ckpt`` if it exists.
        progress: progress bar when attached to a terminal.
    """
    from apmgsrn.device import keep_large_allocations_cached
    from apmgsrn.inference.evaluate import evaluate_tensor

    out = Path(out)
    if not out.absolute().parent.is_dir():
        raise ApmgsrnError(f"{out}: output folder {out.parent} does not exist; create it or choose another --out")
    checkpoint = checkpoint_path_for(out)
    if checkpoint.exists() and not resume:
        raise ApmgsrnError(
            f"{checkpoint}: an interrupted run left this checkpoint; pass --resume to continue it, "
            "or delete it to start over"
        )
    if device.type == "cpu":
        keep_large_allocations_cached()
    prepared = prepare_volume(volume, transform, log_offset, device)
    generator = torch.Generator().manual_seed(train_config.seed)
    field = NeuralField(
        field_config,
        fit_min=prepared.fit_min,
        fit_max=prepared.fit_max,
        value_min=prepared.value_min,
        value_max=prepared.value_max,
        transform=prepared.transform,
        volume_shape=volume.shape,
        generator=generator,
    ).to(device)
    source = SourceInfo.of_volume(volume)
    fingerprint = {"source": source.to_dict(), "shape": list(volume.shape), "field": field_config.to_dict(),
                   "transform": asdict(prepared.transform)}
    trainer = Trainer(field, prepared.values, train_config, checkpoint, fingerprint, progress)
    state = trainer.run(resume=resume)
    psnr = evaluate_tensor(field, torch.from_numpy(prepared.data))
    training = {
        "iterations": state.iteration,
        "batch_size": train_config.batch_size,
        "seconds": round(state.elapsed, 3),
        "frozen_at": state.frozen_at,
        "final_reconstruction_loss": state.history["reconstruction"][-1] if state.history["reconstruction"] else None,
        "final_density_loss": _last_finite(state.history["density"]),
        "psnr": psnr,
        "device": str(device),
        "config": asdict(train_config),
        "history": state.history,
    }
    save_field(out, field, source, training)
    if checkpoint.exists():
        checkpoint.unlink()
    return FitResult(field, out, out.stat().st_size, state.elapsed, state.iteration, state.frozen_at, psnr)


def _last_finite(values: list[float]) -> float | None:
    for value in reversed(values):
        if value == value:  # not NaN
            return value
    return None
