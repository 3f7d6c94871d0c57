"""Adaptive multi-grid encoding (SPEC section 2) and feature density (SPEC section 3).

Reference implementation in pure PyTorch: every point is mapped into all ``M`` local grid frames and
sampled with one batched ``grid_sample``. Sampling is *zero-padded trilinear* (corner-aligned): a corner
outside the grid contributes zero, so a feature fades to zero over the half cell beyond the grid's border,
and is exactly zero one cell beyond it. Accelerated backends must match this function in forward and
backward.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def local_coordinates(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor
) -> torch.Tensor:
    """Map global points into every grid's local frame, ``G_i(p) = A_i p + t_i``.

    Args:
        points: ``[N, 3]`` global coordinates in ``[-1, 1]^3``.
        matrices: ``[M, 3, 3]`` the ``A_i``.
        translations: ``[M, 3]`` the ``t_i``.

    Returns:
        ``[M, N, 3]`` local coordinates; the grid occupies ``[-1, 1]^3`` there.
    """
    return torch.matmul(points, matrices.transpose(1, 2)) + translations[:, None, :]  # [M, N, 3]


def multigrid_features_reference(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
) -> torch.Tensor:
    """Concatenated features of all grids at the points, grid-major.

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]`` feature grids.

    Returns:
        ``[N, M * C]`` features; column ``i * C + c`` is channel ``c`` of grid ``i``.
    """
    m, c = grids.shape[:2]
    n = points.shape[0]
    local = local_coordinates(points, matrices, translations)  # [M, N, 3]
    sampled = F.grid_sample(
        grids, local.view(m, n, 1, 1, 3), mode="bilinear", padding_mode="zeros", align_corners=True
    )  # [M, C, N, 1, 1]
    return sampled.view(m * c, n).t()  # [N, M * C]


def multigrid_features(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
    backend: str = "auto",
) -> torch.Tensor:
    """Dispatch to a backend (``"auto"``, ``"torch"``, or an accelerated one where available).

    See :func:`multigrid_features_reference` for shapes and semantics.
    """
    if backend in ("auto", "torch"):
        return multigrid_features_reference(points, matrices, translations, grids)
    raise ValueError(f"unknown multigrid backend {backend!r}")


def feature_density(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    power: int = 10,
) -> torch.Tensor:
    """Flat-top Gaussian feature density ``rho(p) = sum_i det(A_i) exp(-sum_d G_i(p)_d^(2P))``.

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        power: ``P`` of the super-Gaussian (SPEC: 10).

    Returns:
        ``[N]`` unnormalised density.
    """
    local = local_coordinates(points, matrices, translations)  # [M, N, 3]
    falloff = torch.exp(-local.pow(2 * power).sum(-1))  # [M, N]
    det = torch.linalg.det(matrices)  # [M]
    return (det[:, None] * falloff).sum(0)  # [N]
