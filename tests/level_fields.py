"""Hybrid fields of odd sizes for the tests of the fused level-grid kernels (inference and training)."""

from __future__ import annotations

import numpy as np
import torch

from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config

#: (levels, features, log2 table size, adaptive grids, their features, hidden widths)
ODD_SIZES = [
    (12, 2, 11, 8, 1, [64, 64]),  # the small preset's shapes
    (3, 3, 6, 0, 1, [20]),        # no adaptive grids, every fine level hashed, features not a vector's multiple
    (5, 1, 14, 2, 3, [3, 9, 40]),  # dense levels only, odd widths, three hidden layers
    (4, 2, 8, 1, 2, [130, 17]),   # a hidden layer wider than a register block
]


def odd_level_field(levels: int, features: int, log2_table_size: int, grids: int, grid_features: int,
                    widths: list[int]) -> tuple[NeuralField, list[torch.Tensor]]:
    """A hybrid field of these sizes on a 40 x 24 x 32 lattice, its features drawn away from their tiny start,
    and decoder weights of the given hidden widths (drawn, odd widths in every layer)."""
    config = preset_config("hybrid", "small", levels=levels, features=features, log2_table_size=log2_table_size,
                           grids=grids, grid_features=grid_features, hidden_layers=len(widths), width=widths[0])
    field = NeuralField(config, volume_shape=(40, 24, 32), generator=torch.Generator().manual_seed(levels))
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        field.encoder.level_table.copy_(torch.randn(field.encoder.level_table.shape, generator=g))
        field.encoder.grids.copy_(torch.randn(field.encoder.grids.shape, generator=g))
    sizes = [field.encoder.out_features, *widths, 1]
    weights = [torch.randn(o, i, generator=g) / i**0.5 for i, o in zip(sizes[:-1], sizes[1:])]
    return field, weights


def neghip(test_data) -> torch.Tensor:
    """The real neghip 64^3 volume of tests/data as float32 values in [0, 1]."""
    raw = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    return torch.from_numpy(raw.astype(np.float32) / 255.0)
