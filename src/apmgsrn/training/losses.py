"""Training losses: reconstruction (docs/method.md §4) and feature density (docs/method.md §3)."""

from __future__ import annotations

import torch


def feature_density_loss(
    density: torch.Tensor, error: torch.Tensor, mean_density: float | None = None, eps: float = 1e-16
) -> torch.Tensor:
    """KL divergence from the current feature density to the error-driven target density.

    ``rho_s = rho / sum rho``; ``rho* = exp(h_bar / (h + eps) * log(rho_s + eps))`` normalised to sum 1
    and held constant; ``L = mean(rho* log(rho* / rho_s))``. The target is normalised in log space so
    that densities far below float range do not turn into ``0 * log 0``.

    With ``mean_density`` (the mean density over the domain if every grid lay inside it, which is a
    constant: each grid carries the same feature mass whatever its transform), ``rho_s = rho / (N *
    mean_density)`` instead: the share of *all* features at each point. The batch normalisation of the
    paper cannot see feature mass that leaves the domain, so on dense data it lets grids grow without
    bound; this one charges for it.

    Args:
        density: ``[N]`` unnormalised feature density ``rho`` (differentiable w.r.t. the grid placements).
        error: ``[N]`` per-point squared reconstruction error ``h`` (no gradient needed).
        mean_density: None for the paper's batch normalisation, else the all-inside mean density.
        eps: docs/method.md's small constant.

    Returns:
        Scalar loss.
    """
    if mean_density is None:
        density_share = density / density.sum()  # rho_s, [N]
    else:
        density_share = density / (density.shape[0] * mean_density)  # [N]
    log_share = torch.log(density_share + eps)  # [N]
    with torch.no_grad():
        error = error.detach()
        log_target = error.mean() / (error + eps) * log_share.detach()  # log of unnormalised rho*
        log_target = log_target - torch.logsumexp(log_target, dim=0)  # normalise: sum rho* = 1
        target = log_target.exp()
    return (target * (log_target - log_share)).mean()
