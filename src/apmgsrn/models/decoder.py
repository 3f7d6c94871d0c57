"""The decoder MLP shared by every encoder (docs/method.md §2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_HIDDEN_LAYERS, MAX_WIDTH = 64, 8192


@dataclass(frozen=True)
class DecoderConfig:
    """``hidden_layers`` layers of ``width`` units, ReLU between, no biases, one output."""

    hidden_layers: int = 2
    width: int = 64

    def __post_init__(self) -> None:
        if not 1 <= self.hidden_layers <= MAX_HIDDEN_LAYERS or not 1 <= self.width <= MAX_WIDTH:
            raise ValueError(
                f"invalid decoder size: {self} (1..{MAX_HIDDEN_LAYERS} hidden layers, width 1..{MAX_WIDTH})"
            )

    def layer_sizes(self, in_features: int) -> list[int]:
        """Units of every layer, input first: ``[in, width, ..., width, 1]``."""
        return [in_features] + [self.width] * self.hidden_layers + [1]

    def parameter_shapes(self, in_features: int) -> dict[str, tuple[int, ...]]:
        """Shape of every stored weight (``nn.Sequential`` names: linear layers at even indices)."""
        sizes = self.layer_sizes(in_features)
        return {f"{2 * i}.weight": (sizes[i + 1], sizes[i]) for i in range(len(sizes) - 1)}


class Decoder(nn.Sequential):
    """MLP ``[N, in_features] -> [N, 1]`` with Xavier (Glorot) initialised, bias-free layers."""

    def __init__(self, in_features: int, config: DecoderConfig, generator: torch.Generator | None = None):
        sizes = config.layer_sizes(in_features)
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1], bias=False))
            if i < len(sizes) - 2:
                layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)
        self.config = config
        with torch.no_grad():
            for layer in self:
                if isinstance(layer, nn.Linear):
                    fan_out, fan_in = layer.weight.shape
                    bound = (6.0 / (fan_in + fan_out)) ** 0.5
                    layer.weight.uniform_(-bound, bound, generator=generator)

    def weights(self) -> list[torch.Tensor]:
        """The linear layers' weights ``[out, in]``, input layer first."""
        return [layer.weight for layer in self if isinstance(layer, nn.Linear)]

    def forward(self, features: torch.Tensor, hidden_dtype: torch.dtype | None = None) -> torch.Tensor:
        """``[N, in_features] -> [N, 1]``.

        Args:
            features: encoder output.
            hidden_dtype: dtype of the hidden layers' matrix products (``None``: the features' dtype).
                ``torch.bfloat16`` runs them 3-4x faster on CPUs with AVX512-BF16 or AMX; weights stay
                float32 (cast on use, so gradients arrive in float32) and the output layer runs in float32,
                so the fitted value is not rounded to bfloat16's 8-bit mantissa.
        """
        weights = self.weights()
        x = features if hidden_dtype is None else features.to(hidden_dtype)
        for weight in weights[:-1]:
            x = torch.relu(nn.functional.linear(x, weight.to(x.dtype)))
        return nn.functional.linear(x.to(weights[-1].dtype), weights[-1])
