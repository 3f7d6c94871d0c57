"""Optional value transforms applied before training and inverted on decode (docs/method.md §1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from apmgsrn.arguments import check_choice, check_number
from apmgsrn.choices import VALUE_TRANSFORMS as TRANSFORMS
from apmgsrn.errors import ApmgsrnError


@dataclass(frozen=True)
class ValueTransform:
    """``log10``: ``log10(v + offset)`` (e.g. cosmology density); ``zscore``: ``(v - mean) / std``.

    The transform is saved with the model; the model outputs data units after :meth:`inverse`.
    """

    kind: str = "none"
    offset: float = 0.0
    mean: float = 0.0
    std: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in TRANSFORMS:
            raise ValueError(f"value transform must be one of {TRANSFORMS}, not {self.kind!r}")

    def apply(self, values: np.ndarray) -> np.ndarray:
        """Data units -> the units the network is fitted in (float32)."""
        if self.kind == "log10":
            return np.log10(values + np.float32(self.offset)).astype(np.float32)
        if self.kind == "zscore":
            return ((values - np.float32(self.mean)) / np.float32(self.std)).astype(np.float32)
        return values

    def inverse(self, values: torch.Tensor) -> torch.Tensor:
        """Fitted units -> data units."""
        if self.kind == "log10":
            return torch.pow(10.0, values) - self.offset
        if self.kind == "zscore":
            return values * self.std + self.mean
        return values

    def apply_scalar(self, value: float) -> float:
        return float(self.apply(np.asarray([value], dtype=np.float32))[0])


def fit_value_transform(kind: str, slabs, data_min: float, offset: float = 0.0, source: str = "") -> ValueTransform:
    """Build a transform of ``kind`` for a volume, streaming its slabs when statistics are needed.

    Args:
        kind: ``"none"``, ``"log10"`` or ``"zscore"``.
        slabs: iterable of float32 arrays covering the volume (only read for ``zscore``).
        data_min: the volume's minimum (``log10`` needs ``data_min + offset > 0``).
        offset: added before ``log10``.
        source: the file, for error messages.

    Returns:
        The transform.
    """
    check_choice("transform", kind, TRANSFORMS)
    check_number("log_offset", offset)
    if kind == "log10":
        if not data_min + offset > 0:
            raise ApmgsrnError(
                f"{source}: transform=log10 needs values > 0, but the minimum is {data_min:g}; "
                f"pass log_offset=VALUE with VALUE > {0.0 - data_min:g}", arguments=("transform", "log_offset"),
            )
        return ValueTransform("log10", offset=offset)
    if kind == "zscore":
        count, total, total_sq = 0, 0.0, 0.0
        for block in slabs:
            block = block.astype(np.float64)
            count += block.size
            total += float(block.sum())
            total_sq += float(np.square(block).sum())
        mean = total / count
        std = math.sqrt(max(total_sq / count - mean * mean, 0.0))
        return ValueTransform("zscore", mean=mean, std=std if std > 0 else 1.0)
    return ValueTransform(kind)
