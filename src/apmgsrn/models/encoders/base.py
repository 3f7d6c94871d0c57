"""What every encoder offers the field, the trainer and the loaders (defaults for encoders without grids
that move)."""

from __future__ import annotations

import torch
from torch import nn

#: dtype a stored parameter may take in a model file (``"float32"`` or ``"float16"``; the rest of the library
#: trains and evaluates in float32 and rounds to this when training ends).
STORAGE_DTYPES = {"float32": torch.float32, "float16": torch.float16}


class Encoder(nn.Module):
    """Base of the encoders: ``forward(points [N, 3], detach_placement) -> [N, out_features]``.

    Encoders whose grids are placed by learned maps (APMGSRN) override :meth:`placement_parameters` and
    :meth:`grid_boxes`; the trainer's density step and the pictures of grid placement use them.
    """

    out_features: int

    def placement_parameters(self) -> list[nn.Parameter]:
        """Parameters moved by the feature-density loss (none: nothing is placed)."""
        return []

    def grid_boxes(self) -> torch.Tensor | None:
        """Corners ``[M, 8, 3]`` of placed grids in global coordinates, or None when nothing is placed."""
        return None

    def learning_rate_multipliers(self) -> dict[nn.Parameter, float]:
        """Learning-rate multipliers of some parameters (per-component learning rates; the rest learn at 1x)."""
        return {}

    def initialize_from_volume(self, values: torch.Tensor) -> None:
        """Start from the training volume ``[D, H, W]`` in ``[0, 1]`` (called once before training; nothing here)."""

    def prefers_ordered_batches(self) -> bool:
        """Whether a CPU step runs faster on a batch sorted by position (feature tables larger than the
        caches: consecutive points then share cache lines). The loss, a mean, is the same in any order."""
        return False

    def thread_invariant(self, threads: int) -> bool:
        """Whether forward and backward give the same numbers on any CPU thread count up to ``threads``
        (the trainer then lets :class:`apmgsrn.threads.ThreadGovernor` change it mid-run). False unless an
        encoder knows better."""
        return False

    def decoded(self, points: torch.Tensor, weights: list[torch.Tensor]) -> torch.Tensor | None:
        """``decoder(self(points))`` ``[N]`` by a fused inference kernel, or None where there is none (the
        field then runs encoder and decoder itself).

        Args:
            points: ``[N, 3]``.
            weights: the decoder's linear layers (see :meth:`apmgsrn.models.decoder.Decoder.weights`).
        """
        return None

    def fused_mse_step(self, points: torch.Tensor, target: torch.Tensor,
                       weights: list[torch.Tensor]) -> torch.Tensor | None:
        """One reconstruction step by a fused training kernel: the prediction ``decoder(self(points))`` ``[N]``,
        with the gradient of its mean squared error to ``target`` ``[N]`` stored as ``.grad`` of the feature
        parameters and decoder weights that require one, replacing what was there (the placement gets none: the
        reconstruction path detaches it). None where there is no such kernel (or none for a decoder that
        learns): nothing is changed then; the trainer runs autograd.

        Args:
            points: ``[N, 3]``.
            target: ``[N]`` the values to fit.
            weights: the decoder's linear layers.
        """
        return None

    def check_parameters(self) -> str | None:
        """Why these parameters cannot be a trained model (NaN/Inf, ...), or None when they can."""
        for name, tensor in self.named_parameters():
            if not bool(torch.isfinite(tensor).all()):
                return f"parameter {name} holds NaN or Inf"
        return None
