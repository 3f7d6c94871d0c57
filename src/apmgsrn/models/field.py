"""A neural field ``f(p) = d(e(p))`` with min/max output scaling and the inverse value transform."""

from __future__ import annotations

import torch
from torch import nn

from apmgsrn.models.decoder import Decoder
from apmgsrn.models.registry import ENCODERS, FieldConfig
from apmgsrn.models.value_transform import ValueTransform


class NeuralField(nn.Module):
    """Maps points ``[N, 3]`` in ``[-1, 1]^3`` to values ``[N, 1]`` in data units.

    The decoder learns ``m(y)`` in about ``[0, 1]``; the output is ``m(y) * (max - min) + min`` in the
    fitted (transformed) units, then the inverse value transform gives data units.

    Attributes:
        config: what was built (fitted to ``volume_shape``: see :meth:`FieldConfig.fitted_to`).
        fit_min, fit_max: value range in fitted units (after the value transform).
        value_min, value_max: value range of the training data in data units.
        volume_shape: ``(D, H, W)`` of the training volume.
        transform: the value transform.
    """

    def __init__(
        self,
        config: FieldConfig,
        fit_min: float = 0.0,
        fit_max: float = 1.0,
        value_min: float | None = None,
        value_max: float | None = None,
        transform: ValueTransform = ValueTransform(),
        volume_shape: tuple[int, int, int] = (0, 0, 0),
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        self.volume_shape = tuple(int(s) for s in volume_shape)
        self.config = config.fitted_to(self.volume_shape)
        self.encoder = ENCODERS[config.model][1](self.config.encoder, generator=generator)
        self.decoder = Decoder(self.encoder.out_features, config.decoder, generator=generator)
        self.fit_min = float(fit_min)
        self.fit_max = float(fit_max)
        self.value_min = float(fit_min if value_min is None else value_min)
        self.value_max = float(fit_max if value_max is None else value_max)
        self.transform = transform
        # dtype of the decoder's hidden layers in inference (None: float32, the fused kernel where it runs);
        # set by apmgsrn.load(precision=...)
        self.inference_dtype: torch.dtype | None = None

    def normalized(
        self, points: torch.Tensor, detach_placement: bool = False, hidden_dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """Decoder output ``m(y)`` ``[N, 1]`` (about ``[0, 1]``), the quantity the trainer fits.

        ``hidden_dtype``: see :meth:`~apmgsrn.models.decoder.Decoder.forward` (training only).
        Without gradients, the hidden layers run in :attr:`inference_dtype` when it is set; in float32,
        an encoder's fused inference kernel runs where it has one
        (:meth:`~apmgsrn.models.encoders.base.Encoder.decoded`); ``backend="torch"`` in the encoder's
        config keeps the reference.
        """
        if hidden_dtype is None and not torch.is_grad_enabled():
            if self.inference_dtype is not None:
                return self.decoder(self.encoder(points), self.inference_dtype)
            fused = self.encoder.decoded(points, self.decoder.weights())  # [N] or None
            if fused is not None:
                return fused.view(-1, 1)
        return self.decoder(self.encoder(points, detach_placement=detach_placement), hidden_dtype)

    def fused_mse_step(self, points: torch.Tensor, target: torch.Tensor) -> torch.Tensor | None:
        """One reconstruction step by the encoder's fused training kernel, where it has one (float32): the
        decoder output ``[N]`` at ``points``, with the gradient of its mean squared error to ``target`` ``[N]``
        stored as the ``.grad`` of the encoder's learning features and of the decoder's learning weights
        (replacing it) (:meth:`~apmgsrn.models.encoders.base.Encoder.fused_mse_step`). None elsewhere: nothing
        changed."""
        return self.encoder.fused_mse_step(points, target, self.decoder.weights())

    @torch.no_grad()
    def fused_inference(self) -> bool:
        """Whether float32 inference without gradients runs an encoder's fused kernel where this field lives
        (asked of the encoder on no points)."""
        points = torch.empty(0, 3, device=self.decoder.weights()[0].device)
        return self.encoder.decoded(points, self.decoder.weights()) is not None

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Values in data units ``[N, 1]`` at ``points`` ``[N, 3]``."""
        if self.value_min == self.value_max:
            # A constant volume: its value exactly, whatever the transform would round it to.
            return torch.full((points.shape[0], 1), self.value_min, dtype=points.dtype, device=points.device)
        fitted = self.normalized(points) * (self.fit_max - self.fit_min) + self.fit_min
        return self.transform.inverse(fitted)

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    @torch.no_grad()
    def round_to_storage(self) -> None:
        """Round every parameter stored in less than float32 (``config.stored_dtypes()``) to that precision,
        in place, so that what is measured after training is exactly what the model file gives back."""
        stored = self.config.stored_dtypes()
        for name, parameter in self.named_parameters():
            if stored[name] != torch.float32:
                parameter.copy_(parameter.to(stored[name]).to(parameter.dtype))

    def check_parameters(self) -> str | None:
        """Why these parameters cannot be a trained model (NaN/Inf, a singular grid map), or None."""
        problem = self.encoder.check_parameters()
        if problem is None:
            for name, tensor in self.decoder.named_parameters():
                if not bool(torch.isfinite(tensor).all()):
                    return f"decoder parameter {name} holds NaN or Inf"
        return problem
