"""Where the samples of a ray lie, and what length of the ray each one stands for.

Rays are clipped to the box ``[-e, e]`` (``e`` the extent, longest half side 1). The step length is fixed
(``step = longest box side / samples_per_ray``), so ``samples_per_ray`` samples cross the box along its
longest axis (a ray along the diagonal of a cube takes up to ``sqrt(3)`` times as many). Sample ``i`` of a
ray sits at ``t_near + (i + u) * step`` with ``u = 0.5``, or a per-pixel hashed offset in ``[0, 1)`` when
jitter is on (seeded, so a pixel always gets the same offset whatever the order pixels are rendered in).
Each sample stands for the part of the ray closer to it than to its neighbours, clipped to the box, so
the segment lengths ``dt_i`` add up to the chord exactly and a homogeneous medium obeys Beer-Lambert
exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from apmgsrn.rendering.bounds import intersect_box


def pixel_jitter(pixels: torch.Tensor, seed: int) -> torch.Tensor:
    """A fixed pseudo-random offset in [0, 1) per pixel index (integer hash), independent of render order.

    Args:
        pixels: ``[R]`` integer pixel (or ray) ids.
        seed: changes every offset.

    Returns:
        ``[R]`` float32 offsets.
    """
    mask = 0xFFFFFFFF
    h = (pixels.to(torch.int64) * 0x27D4EB2D + (seed * 0x165667B1 + 0x3C6EF372)) & mask
    h = h ^ (h >> 15)
    h = (h * 0x2C1B3C6D) & mask
    h = h ^ (h >> 12)
    h = (h * 0x297A2D39) & mask
    h = h ^ (h >> 15)
    return (h >> 8).to(torch.float32) / float(1 << 24)  # 24 bits: exact in float32, never reaches 1


def sample_offsets(pixels: torch.Tensor, jitter: bool, seed: int) -> torch.Tensor:
    """Where in its step each ray's samples sit: the middle (0.5), or a hashed offset per pixel.

    Args:
        pixels: ``[R]`` ray ids (on the render device).
        jitter: hashed offsets instead of the middle.
        seed: seed of the hash.

    Returns:
        ``[R]`` float32 offsets in [0, 1).
    """
    if jitter:
        return pixel_jitter(pixels, seed)
    return torch.full((pixels.shape[0],), 0.5, device=pixels.device)


@dataclass
class RaySamples:
    """The samples of a chunk of rays: sample ``i`` of ray ``r`` at ``t_near[r] + (i + offset[r]) * step``.

    Attributes:
        t_near, t_far: ``[R]`` where each ray enters and leaves the box (``t_near >= 0``).
        offset: ``[R]`` position of the samples within their steps.
        count: ``[R]`` int64 samples of each ray inside the box.
        first, last: ``[R]`` int64 half-open range of the samples worth marching (all of them, or those near
            the visible cells).
        step: the step length, world units.
    """

    t_near: torch.Tensor
    t_far: torch.Tensor
    offset: torch.Tensor
    count: torch.Tensor
    first: torch.Tensor
    last: torch.Tensor
    step: float

    @classmethod
    def through_box(
        cls, origins: torch.Tensor, directions: torch.Tensor, extent: torch.Tensor, step: float, offset: torch.Tensor
    ) -> "RaySamples":
        """Every sample of each ray inside the box ``[-extent, extent]``.

        Args:
            origins, directions: ``[R, 3]`` world-space rays.
            extent: ``[3]`` half sizes of the box.
            step: step length.
            offset: ``[R]`` from :func:`sample_offsets`.

        Returns:
            The samples, ``first = 0`` and ``last = count``.
        """
        t_near, t_far = intersect_box(origins, directions, -extent, extent)
        t_near = t_near.clamp(min=0.0)
        length = (t_far - t_near).clamp(min=0.0)  # [R]
        count = torch.ceil(length / step - offset).clamp(min=0).to(torch.int64)
        return cls(t_near, t_far, offset, count, torch.zeros_like(count), count.clone(), step)

    def within(
        self, origins: torch.Tensor, directions: torch.Tensor, box: tuple[torch.Tensor, torch.Tensor] | None
    ) -> "RaySamples":
        """Keep, of each ray, the samples near a box inside the volume (the box around the visible cells).

        Args:
            origins, directions: ``[R, 3]`` the same rays.
            box: ``(low [3], high [3])`` world-space corners, or None to keep no sample at all.

        Returns:
            The samples with ``first``/``last`` narrowed: one sample of slack either side of the box, so
            the per-sample cell test decides the rest.
        """
        count = self.count
        if box is None:
            return RaySamples(self.t_near, self.t_far, self.offset, count, self.first, self.first.clone(), self.step)
        t_in, t_out = intersect_box(origins, directions, box[0], box[1])
        hits = t_out > t_in
        first_in = torch.floor((t_in - self.t_near) / self.step - self.offset).to(torch.int64) - 1
        last_in = torch.ceil((t_out - self.t_near) / self.step - self.offset).to(torch.int64) + 1
        first = torch.where(hits, first_in.clamp(min=0), count).clamp(max=count)
        last = torch.where(hits, torch.minimum(last_in, count), count).clamp(min=first)
        return RaySamples(self.t_near, self.t_far, self.offset, count, first, last, self.step)

    def positions(self, rays: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Ray parameters of samples.

        Args:
            rays: ``[A]`` ray ids.
            index: ``[A, K]`` sample indices along those rays.

        Returns:
            ``[A, K]`` float32 ``t``.
        """
        return self.t_near[rays, None] + (index.to(torch.float32) + self.offset[rays, None]) * self.step

    def segment_lengths(self, rays: torch.Tensor, index: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Length of ray each sample stands for: half a step either side, clipped to the box.

        Args:
            rays: ``[A]`` ray ids.
            index: ``[A, K]`` sample indices.
            t: ``[A, K]`` their :meth:`positions`.

        Returns:
            ``[A, K]`` lengths (0 past the last sample).
        """
        half_step = 0.5 * self.step
        low = torch.where(index == 0, self.t_near[rays, None], t - half_step)
        high = torch.where(index == self.count[rays, None] - 1, self.t_far[rays, None], t + half_step)
        return (high - low).clamp_(min=0.0)
