"""The public Python API: open a model file as a module that knows what it is."""

from __future__ import annotations

import os

import torch
from torch import nn

import apmgsrn.decomposition.brick_model  # noqa: F401 - registers the brick-model loader
from apmgsrn.device import inference_dtype
from apmgsrn.io import ModelDescription, open_model
from apmgsrn.models.field import NeuralField


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

    def set_precision(self, precision: str) -> Model:
        """Choose the arithmetic of inference (decode, eval, render); training is not affected.

        Args:
            precision: ``"float32"`` (the fused float32 kernel on CPUs, exact to float32 rounding),
                ``"bfloat16"`` (the decoder's hidden layers in bfloat16: fast where the CPU multiplies it
                natively, a PSNR cost that docs/benchmarks.md measures), or ``"auto"`` (bfloat16 on such
                CPUs, float32 elsewhere).

        Returns:
            The model.

        Raises:
            InvalidArgument: an unknown precision.
        """
        device = next((p.device for p in self.parameters()), torch.device("cpu"))
        dtype = inference_dtype(precision, device)
        for module in self.modules():
            if isinstance(module, NeuralField):
                module.inference_dtype = dtype
        return self


def load(path: str | os.PathLike, device: torch.device | str = "cpu", precision: str = "auto") -> Model:
    """Open a model file or a brick-model folder; never executes code from it.

    Args:
        path: the ``.apmgsrn`` file or brick-model folder.
        device: where to put the network.
        precision: arithmetic of inference, see :meth:`Model.set_precision` (``"auto"``: bfloat16 on CPUs
            with native bfloat16, float32 elsewhere).

    Raises:
        ApmgsrnError: the file is missing, corrupt, foreign, hostile or from a newer version.
    """
    loaded = open_model(path, device)
    return Model(loaded.field, loaded.description).eval().set_precision(precision)
