"""The decoder MLP shared by every encoder (SPEC section 2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class DecoderConfig:
    """``hidden_layers`` layers of ``width`` units, ReLU between, no biases, one output."""

    hidden_layers: int = 2
    width: int = 64

    def __post_init__(self) -> None:
        if self.hidden_layers < 1 or self.width < 1:
            raise ValueError(f"invalid decoder size: {self}")


class Decoder(nn.Sequential):
    """MLP ``[N, in_features] -> [N, 1]`` with Xavier (Glorot) initialised, bias-free layers."""

    def __init__(self, in_features: int, config: DecoderConfig, generator: torch.Generator | None = None):
        sizes = [in_features] + [config.width] * config.hidden_layers + [1]
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
