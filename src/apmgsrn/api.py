"""The public Python API: open a model file as a module that knows what it is."""

from __future__ import annotations

import os

import torch
from torch import nn

import apmgsrn.decomposition.brick_model  # noqa: F401 - registers the brick-model loader
import apmgsrn.decomposition.series_bricks  # noqa: F401 - registers the time-series brick-model loader
from apmgsrn.io import ModelDescription, open_model


class Model(nn.Module):
    """A model opened from a file: ``model(points)`` maps ``[N, 3]`` points in ``[-1, 1]^3`` to ``[N, 1]``
    values in data units.

    Attributes:
        field: the network (a single field or a routed brick model).
        description: what its file says (volume shape, value range, source, training summary, bricks...).
    """

    def __init__(self, field: nn.Module, description: ModelDescription):
        super().__init__()
        self.field = field
        self.description = description

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.field(points)


def load(path: str | os.PathLike, device: torch.device | str = "cpu") -> Model:
    """Open a model file or a brick-model folder; never executes code from it.

    Args:
        path: the ``.apmgsrn`` file or brick-model folder.
        device: where to put the network.

    Raises:
        ApmgsrnError: the file is missing, corrupt, foreign, hostile or from a newer version.
    """
    loaded = open_model(path, device)
    return Model(loaded.field, loaded.description).eval()
