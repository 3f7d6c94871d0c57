"""A neural field plus a sparse voxel correction: the network with an error bound (docs/method.md §10).

The correction holds a value at the few voxels where the network alone misses the data by more than the
bound, zero elsewhere, and is interpolated like the data (trilinearly between voxels, exactly its own value
at a voxel). The field's output is the network's plus the correction's, in data units, so at every voxel it
is within the bound the packer verified, and between voxels it stays a smooth field that any point query,
decode, render or the viewer evaluates directly.
"""

from __future__ import annotations

import torch

from apmgsrn.models.field import NeuralField
from apmgsrn.ops.sparse_trilinear import sample_sparse_volume


class CorrectedField(NeuralField):
    """A :class:`NeuralField` whose output adds a sparse voxel correction (data units).

    Args:
        *args, **kwargs: as :class:`NeuralField`.
        max_error: the bound the correction was made for (data units); kept for reports.

    The correction is set with :meth:`set_correction`; until then it is empty (the plain network).
    """

    def __init__(self, *args, max_error: float = 0.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.max_error = float(max_error)
        # Buffers follow .to(device) but are not parameters or state: files store them their own way.
        self.register_buffer("correction_indices", torch.zeros(0, dtype=torch.int64), persistent=False)
        self.register_buffer("correction_values", torch.zeros(0, dtype=torch.float32), persistent=False)

    def set_correction(self, indices: torch.Tensor, values: torch.Tensor) -> None:
        """Use ``values`` ``[K]`` (data units) at flat voxel ``indices`` ``[K]`` (strictly increasing)."""
        device = self.correction_indices.device
        self.correction_indices = indices.to(device=device, dtype=torch.int64)
        self.correction_values = values.to(device=device, dtype=torch.float32)

    @property
    def correction_count(self) -> int:
        """Voxels that carry a correction."""
        return int(self.correction_indices.numel())

    def correction(self, points: torch.Tensor) -> torch.Tensor:
        """The interpolated correction at ``points`` ``[N, 3]`` -> ``[N, 1]`` (data units)."""
        values = sample_sparse_volume(self.correction_indices, self.correction_values, self.volume_shape, points)
        return values.view(-1, 1).to(points.dtype)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Network plus correction, ``[N, 3] -> [N, 1]`` in data units."""
        return super().forward(points) + self.correction(points)
