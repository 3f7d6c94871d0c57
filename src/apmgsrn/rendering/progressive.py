"""Progressive rendering: coarse-to-fine pixel order, a full image after every pass (docs/method.md §7).

Pass ``j`` renders the pixels on the lattice of stride ``strides[j]`` (rows and columns that are
multiples of it) that no earlier pass rendered; with strides 8, 4, 2, 1 the passes hold 1/64, 3/64,
12/64 and 48/64 of the pixels, each new lattice filling the gaps of the previous one in a checkerboard
pattern. After each pass the whole image is made by bilinear interpolation between the lattice pixels
rendered so far (pixels past the last lattice row or column hold its value), so the last pass gives
exactly the full render. Within a pass the renderer works in batches of ``batch_size`` points, so a
small batch size gives the first image sooner and a large one finishes the frame sooner.

:class:`ProgressiveRender` is the schedule with its image buffer; a caller that must be able to drop a
pass half way (the viewer, when the camera moves) renders the next pass's pixels in chunks itself;
:func:`render_progressive` runs every pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch

from apmgsrn.rendering.camera import Camera
from apmgsrn.rendering.raymarch import RenderStatistics, VolumeRenderer


@dataclass
class ProgressiveImage:
    """One refinement: the upsampled image ``[H, W, 3]`` (CPU float32) after a pass."""

    image: torch.Tensor
    stride: int  # lattice stride available so far (1: the final image)
    pass_index: int
    pixels_rendered: int  # pixels rendered by all passes so far
    pixels_total: int
    statistics: RenderStatistics  # work of this pass

    @property
    def done(self) -> bool:
        return self.stride == 1


def check_strides(strides: tuple[int, ...]) -> None:
    """Refuse strides that do not decrease strictly to 1.

    Args:
        strides: lattice strides of the passes.

    Raises:
        ValueError: they do not.
    """
    if not strides or strides[-1] != 1 or any(b >= a for a, b in zip(strides, strides[1:])):
        raise ValueError(f"strides must decrease strictly to 1, got {strides}")


def pass_pixels(width: int, height: int, strides: tuple[int, ...] = (8, 4, 2, 1)) -> list[torch.Tensor]:
    """Linear pixel indices of each pass, in order (they partition the image).

    Args:
        width, height: image size.
        strides: decreasing lattice strides, ending with 1.

    Returns:
        One ``[N_j]`` int64 tensor per stride: the lattice pixels of that stride no coarser pass has.
    """
    check_strides(strides)
    rows = torch.arange(height)[:, None]
    cols = torch.arange(width)[None, :]
    done = torch.zeros((height, width), dtype=torch.bool)
    passes = []
    for stride in strides:
        on_lattice = (rows % stride == 0) & (cols % stride == 0)  # [H, W]
        new = on_lattice & ~done
        passes.append(new.view(-1).nonzero().squeeze(1))
        done |= new
    return passes


def _axis_weights(size: int, stride: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each pixel of an axis: lower and upper lattice index and the weight of the upper one."""
    count = (size - 1) // stride + 1  # lattice points on this axis
    position = torch.arange(size, dtype=torch.float32) / stride
    low = position.floor().to(torch.int64).clamp(max=count - 1)
    high = (low + 1).clamp(max=count - 1)
    weight = (position - low.to(torch.float32)).clamp(0.0, 1.0)
    weight = torch.where(high == low, torch.zeros_like(weight), weight)  # past the last lattice point: hold
    return low, high, weight


def upsample(image: torch.Tensor, stride: int) -> torch.Tensor:
    """Fill an image from its lattice pixels of a stride by bilinear interpolation.

    Args:
        image: ``[H, W, 3]`` whose pixels at rows and columns that are multiples of ``stride`` are known.
        stride: the lattice stride (1 returns the image itself).

    Returns:
        ``[H, W, 3]``, equal to ``image`` on the lattice.
    """
    if stride == 1:
        return image
    height, width = image.shape[:2]
    lattice = image[::stride, ::stride]  # [h, w, 3]
    r0, r1, rw = (t.to(image.device) for t in _axis_weights(height, stride))
    c0, c1, cw = (t.to(image.device) for t in _axis_weights(width, stride))
    top = lattice[r0]  # [H, w, 3]
    bottom = lattice[r1]
    rows = top + (bottom - top) * rw[:, None, None]
    left = rows[:, c0]  # [H, W, 3]
    right = rows[:, c1]
    return left + (right - left) * cw[None, :, None]


class ProgressiveRender:
    """The coarse-to-fine render of one view: the passes, the pixels rendered so far, the image after each."""

    def __init__(self, renderer: VolumeRenderer, camera: Camera, strides: tuple[int, ...] = (8, 4, 2, 1)) -> None:
        """Args:
        renderer: the renderer (field, transfer function, settings).
        camera: the view and image size.
        strides: lattice strides of the passes, decreasing to 1.
        """
        self.renderer = renderer
        self.camera = camera
        self.strides = tuple(strides)
        self.passes = pass_pixels(camera.width, camera.height, self.strides)
        self.next_pass = 0
        self.pixels_rendered = 0
        self._buffer = torch.zeros((camera.width * camera.height, 3), dtype=torch.float32, device=renderer.device)
        self._pass_statistics = RenderStatistics()

    @property
    def done(self) -> bool:
        """Every pass rendered."""
        return self.next_pass >= len(self.passes)

    @property
    def next_pixels(self) -> torch.Tensor:
        """``[N]`` linear pixel indices of the next pass (render them, in any chunks, then :meth:`finish_pass`)."""
        return self.passes[self.next_pass]

    def render_pixels(self, pixels: torch.Tensor) -> RenderStatistics:
        """Render some pixels of the next pass into the image buffer.

        Args:
            pixels: ``[N]`` linear pixel indices.

        Returns:
            The work it took.
        """
        if pixels.numel() == 0:
            return RenderStatistics()
        colors, statistics = self.renderer.render_pixels(self.camera, pixels)
        self._buffer[pixels.to(self.renderer.device)] = colors
        self._pass_statistics.add(statistics)
        return statistics

    def finish_pass(self) -> ProgressiveImage:
        """Close the next pass (its pixels rendered) and make the full image from everything rendered so far.

        Returns:
            The image after this pass.
        """
        stride = self.strides[self.next_pass]
        self.pixels_rendered += self.passes[self.next_pass].numel()
        camera = self.camera
        image = upsample(self._buffer.view(camera.height, camera.width, 3), stride).cpu()
        result = ProgressiveImage(
            image=image,
            stride=stride,
            pass_index=self.next_pass,
            pixels_rendered=self.pixels_rendered,
            pixels_total=camera.width * camera.height,
            statistics=self._pass_statistics,
        )
        self.next_pass += 1
        self._pass_statistics = RenderStatistics()
        return result

    def __iter__(self) -> Iterator[ProgressiveImage]:
        """Render the remaining passes, yielding the image after each."""
        while not self.done:
            self.render_pixels(self.next_pixels)
            yield self.finish_pass()


def render_progressive(
    renderer: VolumeRenderer, camera: Camera, strides: tuple[int, ...] = (8, 4, 2, 1)
) -> Iterator[ProgressiveImage]:
    """Render coarse to fine, yielding the full upsampled image after each pass.

    Args:
        renderer: the renderer (field, transfer function, settings).
        camera: the view and image size.
        strides: lattice strides of the passes, decreasing to 1.

    Yields:
        :class:`ProgressiveImage` after each pass; the last one equals ``renderer.render(camera).image``.
    """
    return iter(ProgressiveRender(renderer, camera, strides))
