"""Emission-absorption compositing, front to back, with opacity corrected for the step length.

Opacity correction. The transfer function's opacity ``a`` is the opacity of a slab one *reference step*
thick (``longest box side / reference_samples``); a sample standing for a length ``dt`` of the ray gets
``alpha = 1 - (1 - a) ** (dt / reference_step)``, so images do not depend on ``samples_per_ray``.

Compositing is front to back: ``C += T * alpha * colour``, ``T *= 1 - alpha``, background added with the
final ``T``. A sample that finds ``T < early_termination`` contributes nothing and ends its ray.
"""

from __future__ import annotations

import math

import torch


def corrected_alpha(opacity: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    """Opacity of a sample from the opacity per reference step.

    Args:
        opacity: opacities ``a`` per reference step (any shape).
        exponent: the same shape: the sample's length in reference steps, ``dt / reference_step``.

    Returns:
        ``1 - (1 - a) ** exponent``.
    """
    return 1.0 - torch.pow(1.0 - opacity, exponent)


class FrontToBack:
    """Colour and transmittance of a chunk of rays, composited a block of samples at a time."""

    def __init__(self, rays: int, device: torch.device, early_termination: float) -> None:
        """Args:
        rays: rays in the chunk.
        device: where the sums live.
        early_termination: transmittance below which a ray ends (0: never).
        """
        self.color = torch.zeros((rays, 3), dtype=torch.float32, device=device)
        self.transmittance = torch.ones(rays, dtype=torch.float32, device=device)
        self.early_termination = early_termination

    def add(
        self,
        rays: torch.Tensor,
        alpha: torch.Tensor,
        colors: torch.Tensor | None,
        chosen: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Composite the next ``K`` samples of some rays behind what they hold.

        Args:
            rays: ``[A]`` ray ids.
            alpha: ``[A, K]`` sample opacities, in ray order (0 for samples that were skipped).
            colors: sample colours: ``[A * K, 3]`` for every sample, or ``[S, 3]`` for the samples ``chosen``
                lists; None when no sample has a colour.
            chosen: ``[S]`` flat indices into ``[A * K]`` of the samples ``colors`` belongs to; None when
                ``colors`` covers every sample.

        Returns:
            ``[A]`` the rays' transmittance after these samples (frozen at the termination point).
        """
        live, k = alpha.shape
        ray_t = self.transmittance[rays]
        after = ray_t[:, None] * torch.cumprod(1.0 - alpha, dim=1)  # [A, K] T after each sample
        before = torch.cat([ray_t[:, None], after[:, :-1]], dim=1)  # [A, K] T before each sample
        keep = before >= self.early_termination  # early termination: later samples contribute nothing
        weight = before * alpha * keep  # [A, K]
        if colors is not None and chosen is None:
            self.color[rays] += (weight[..., None] * colors.view(live, k, 3)).sum(dim=1)
        elif colors is not None:
            self.color.index_add_(0, rays[chosen // k], weight.view(-1)[chosen, None] * colors)
        # The ray's transmittance stops at its termination point (monotone: the smallest kept value).
        ray_t = torch.where(keep, after, torch.full_like(after, math.inf)).amin(dim=1)
        self.transmittance[rays] = ray_t
        return ray_t
