"""Adaptive multi-grid encoder: M feature grids, each placed in the domain by a learned affine map."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from apmgsrn.models.encoders.base import Encoder
from apmgsrn.ops.multigrid import feature_density, feature_mass, multigrid_decoded, multigrid_features

GRID_INITS = ("default", "large", "small")
#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_GRIDS, MAX_FEATURES, MAX_RESOLUTION = 4096, 1024, 4096


@dataclass(frozen=True)
class AdaptiveMultiGridConfig:
    """What to build (docs/method.md §2).

    Attributes:
        grids: number of grids ``M``.
        features: feature channels per grid ``C``.
        resolution: grid resolution ``(D, H, W)``.
        init: ``"default"`` (grids near the domain, docs/method.md §2's noise), ``"large"`` (grids 20 % larger than the
            domain) or ``"small"`` (small grids scattered at random; the paper found it worse).
        backend: multigrid sampling backend (``"auto"`` picks the fastest available).
    """

    grids: int = 16
    features: int = 1
    resolution: tuple[int, int, int] = (16, 16, 16)
    init: str = "default"
    backend: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", tuple(int(r) for r in self.resolution))
        if (
            not 1 <= self.grids <= MAX_GRIDS
            or not 1 <= self.features <= MAX_FEATURES
            or len(self.resolution) != 3
            or not 2 <= min(self.resolution) <= max(self.resolution) <= MAX_RESOLUTION
        ):
            raise ValueError(
                f"invalid multi-grid size: {self} (1..{MAX_GRIDS} grids, 1..{MAX_FEATURES} features, "
                f"resolution 2..{MAX_RESOLUTION})"
            )
        if self.init not in GRID_INITS:
            raise ValueError(f"grid init must be one of {GRID_INITS}, not {self.init!r}")

    @property
    def out_features(self) -> int:
        """Width of the encoding: ``M * C``."""
        return self.grids * self.features

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter (checked against a model file before anything is built)."""
        m, c = self.grids, self.features
        return {"grids": (m, c, *self.resolution), "matrices": (m, 3, 3), "translations": (m, 3)}


class AdaptiveMultiGridEncoder(Encoder):
    """Encodes points ``[N, 3]`` to ``[N, M * C]`` features (grid-major concatenation).

    Parameters: ``grids`` ``[M, C, D, H, W]`` (reconstruction loss), ``matrices`` ``[M, 3, 3]`` and
    ``translations`` ``[M, 3]`` (the maps ``G_i(p) = A_i p + t_i`` to each grid's local ``[-1, 1]^3``;
    moved by the feature-density loss only).
    """

    def __init__(self, config: AdaptiveMultiGridConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.config = config
        self.out_features = config.out_features
        shapes = config.parameter_shapes()
        self.grids = nn.Parameter(torch.empty(shapes["grids"]))
        self.matrices = nn.Parameter(torch.empty(shapes["matrices"]))
        self.translations = nn.Parameter(torch.empty(shapes["translations"]))
        self.reset_parameters(generator)

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Initialisation of docs/method.md §2: diag(A) ~ N(1, 0.05), off-diagonal A and t ~ N(0, 0.05),
        F ~ U(+-1e-4)."""
        m = self.config.grids
        self.grids.uniform_(-1e-4, 1e-4, generator=generator)
        noise = torch.randn(m, 3, 3, generator=generator) * 0.05
        self.matrices.copy_(torch.eye(3) + noise)
        self.translations.copy_(torch.randn(m, 3, generator=generator) * 0.05)
        if self.config.init == "large":
            # A grid 20 % larger than the domain: local coordinates shrink by 1 / 1.2.
            self.matrices.div_(1.2)
        elif self.config.init == "small":
            # Small grids (a quarter of the domain) scattered uniformly: A = 4 I, centre c -> t = -4 c.
            centres = torch.rand(m, 3, generator=generator) * 1.5 - 0.75
            self.matrices.copy_(torch.eye(3) * 4 + noise)
            self.translations.copy_(-4 * centres)

    def forward(self, points: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features at ``points`` ``[N, 3]`` -> ``[N, M * C]``.

        Args:
            points: global coordinates in ``[-1, 1]^3``.
            detach_placement: True on the reconstruction path (docs/method.md §4, step 1), so only the grids
                and the decoder learn from the reconstruction error.
        """
        matrices, translations = self.matrices, self.translations
        if detach_placement:
            matrices, translations = matrices.detach(), translations.detach()
        return multigrid_features(points, matrices, translations, self.grids, backend=self.config.backend)

    def decoded(self, points: torch.Tensor, weights: list[torch.Tensor]) -> torch.Tensor | None:
        """Encoder and decoder in one pass on the CPU when no gradient is wanted (see
        :func:`~apmgsrn.ops.multigrid.multigrid_decoded`); None elsewhere."""
        return multigrid_decoded(points, self.matrices, self.translations, self.grids, weights, self.config.backend)

    def feature_density(self, points: torch.Tensor, power: int = 10) -> torch.Tensor:
        """Unnormalised feature density ``rho`` at ``points`` ``[N, 3]`` -> ``[N]`` (docs/method.md §3)."""
        return feature_density(points, self.matrices, self.translations, power)

    def mean_feature_density(self, power: int = 10) -> float:
        """Mean density over the domain ``[-1, 1]^3`` (volume 8) if every grid lay inside it."""
        return self.config.grids * feature_mass(power) / 8.0

    def thread_invariant(self, threads: int) -> bool:
        """Every kernel splits its work by point or by grid, never by thread, except the fused backward
        with fewer grids than threads (per-thread partial gradients); the density backward sums fixed runs
        of points in order."""
        return self.config.grids >= threads

    def placement_parameters(self) -> list[nn.Parameter]:
        """The parameters the density loss moves."""
        return [self.matrices, self.translations]

    def feature_parameters(self) -> list[nn.Parameter]:
        """The parameters the reconstruction loss moves."""
        return [self.grids]

    def check_parameters(self) -> str | None:
        """NaN/Inf parameters, or a singular placement matrix (its inverse places the grid in the domain)."""
        problem = super().check_parameters()
        if problem is None and not bool((torch.linalg.det(self.matrices.detach().double()).abs() > 1e-12).all()):
            problem = "a grid's placement matrix is singular"
        return problem

    @torch.no_grad()
    def grid_boxes(self) -> torch.Tensor:
        """Corners of every grid in global coordinates ``[M, 8, 3]`` (for pictures and ``info``)."""
        return placed_boxes(self.matrices, self.translations)


@torch.no_grad()
def placed_boxes(matrices: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """Corners ``[M, 8, 3]`` in global coordinates of grids placed by ``A [M, 3, 3]`` and ``t [M, 3]`` (the local
    ``[-1, 1]^3`` mapped back through ``A^-1 (l - t)``); corner ``k`` has x from bit 0, y from bit 1, z from bit 2."""
    corners = torch.tensor(
        [[x, y, z] for z in (-1.0, 1.0) for y in (-1.0, 1.0) for x in (-1.0, 1.0)], device=matrices.device
    )  # [8, 3] local
    inverse = torch.linalg.inv(matrices.double())  # [M, 3, 3]
    shifted = corners.double()[None] - translations.double()[:, None, :]  # [M, 8, 3]
    return torch.matmul(shifted, inverse.transpose(1, 2)).float()  # [M, 8, 3]
