"""Dense feature grid plus Fourier features (the fVSRN baseline of docs/method.md §5)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from apmgsrn.models.encoders.base import Encoder
from apmgsrn.ops.multigrid import multigrid_features

#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated);
#: beyond 2^24 pi a Fourier term aliases at float32 precision anyway.
MAX_FEATURES, MAX_RESOLUTION, MAX_FREQUENCIES = 1024, 4096, 24


@dataclass(frozen=True)
class DenseGridConfig:
    """What to build (docs/method.md §5, fVSRN column).

    Attributes:
        features: feature channels ``C`` of the grid.
        resolution: grid resolution ``(D, H, W)``; the grid spans the domain ``[-1, 1]^3``, corner-aligned.
        frequencies: Fourier frequencies ``K``: ``sin`` and ``cos`` of ``2^k pi p`` for ``k < K``, per axis.
        backend: grid sampling backend of :func:`apmgsrn.ops.multigrid.multigrid_features` (``"auto"``
            picks the fastest available).
    """

    features: int = 2
    resolution: tuple[int, int, int] = (32, 32, 32)
    frequencies: int = 6
    backend: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", tuple(int(r) for r in self.resolution))
        if (
            not 1 <= self.features <= MAX_FEATURES
            or len(self.resolution) != 3
            or not 2 <= min(self.resolution) <= max(self.resolution) <= MAX_RESOLUTION
            or not 0 <= self.frequencies <= MAX_FREQUENCIES
        ):
            raise ValueError(
                f"invalid dense-grid size: {self} (1..{MAX_FEATURES} features, resolution 2..{MAX_RESOLUTION}, "
                f"0..{MAX_FREQUENCIES} frequencies)"
            )

    @property
    def out_features(self) -> int:
        """Width of the encoding: ``C + 6 K``."""
        return self.features + 6 * self.frequencies

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter (checked against a model file before anything is built)."""
        return {"grid": (1, self.features, *self.resolution)}


class DenseGridEncoder(Encoder):
    """Encodes points ``[N, 3]`` to ``[N, C + 6 K]``: grid features, then ``sin``, then ``cos`` terms.

    Parameter: ``grid`` ``[1, C, D, H, W]``, initialised ``U(-1e-4, 1e-4)`` like the other encoders.
    The Fourier terms have no parameters; they give the decoder the fine detail a coarse grid misses.

    The grid is sampled as a one-grid multi-grid with the identity map: inside ``[-1, 1]^3`` that is
    plain corner-aligned trilinear interpolation, and it runs on the fused multi-grid kernels.
    """

    def __init__(self, config: DenseGridConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.config = config
        self.out_features = config.out_features
        self.grid = nn.Parameter(torch.empty(config.parameter_shapes()["grid"]))
        # Angular frequencies 2^k pi, k = 0..K-1: the lowest spans the domain once.
        frequencies = math.pi * 2.0 ** torch.arange(config.frequencies, dtype=torch.float32)
        self.register_buffer("frequencies", frequencies, persistent=False)
        # A coordinate so large that its highest angle would overflow (±inf included) reads as the largest one
        # that does not: sin and cos stay finite for every finite or infinite input (NaN stays NaN).
        self.coordinate_limit = torch.finfo(torch.float32).max / (2.0 * math.pi * 2.0 ** max(config.frequencies - 1, 0))
        self.register_buffer("identity", torch.eye(3)[None], persistent=False)  # [1, 3, 3]
        self.register_buffer("origin", torch.zeros(1, 3), persistent=False)  # [1, 3]
        with torch.no_grad():
            self.grid.uniform_(-1e-4, 1e-4, generator=generator)

    def forward(self, points: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features at ``points`` ``[N, 3]`` -> ``[N, C + 6 K]``.

        Args:
            points: global coordinates in ``[-1, 1]^3``.
            detach_placement: ignored (this encoder places no grids).
        """
        n = points.shape[0]
        grid_features = multigrid_features(
            points, self.identity, self.origin, self.grid, backend=self.config.backend
        )  # [N, C]
        if self.config.frequencies == 0:
            return grid_features
        far = points.clamp(-self.coordinate_limit, self.coordinate_limit)  # see __init__
        angles = (far[:, :, None] * self.frequencies).reshape(n, -1)  # [N, 3 K], axis-major
        return torch.cat([grid_features, torch.sin(angles), torch.cos(angles)], dim=1)  # [N, C + 6 K]
