"""Progressive rendering: coarse-to-fine pixel order, a full image after every pass (SPEC section 7).

Pass ``j`` renders the pixels on the lattice of stride ``strides[j]`` (rows and columns that are
multiples of it) that no earlier pass rendered; with strides 8, 4, 2, 1 the passes hold 1/64, 3/64,
12/64 and 48/64 of the pixels, each new lattice filling the gaps of the previous one in a checkerboard
pattern. After each pass the whole image is shown by nearest-lattice upsampling (every pixel takes the
colour of the lattice pixel at the top-left corner of its block), so the last pass gives exactly the full
render. Within a pass the renderer works in batches of ``batch_size`` points, so a small batch size gives
the first image sooner and a large one finishes the frame sooner.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch

from apmgsrn.render.camera import Camera
from apmgsrn.render.raymarch import RenderStatistics, VolumeRenderer


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


def pass_pixels(width: int, height: int, strides: tuple[int, ...] = (8, 4, 2, 1)) -> list[torch.Tensor]:
    """Linear pixel indices of each pass, in order (they partition the image).

    Args:
        width, height: image size.
        strides: decreasing lattice strides, ending with 1.

    Returns:
        One ``[N_j]`` int64 tensor per stride.
    """
    if not strides or strides[-1] != 1 or any(b >= a for a, b in zip(strides, strides[1:])):
        raise ValueError(f"strides must decrease strictly to 1, got {strides}")
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


def upsample_index(width: int, height: int, stride: int) -> torch.Tensor:
    """For every pixel, the linear index of the lattice pixel (stride ``stride``) it copies. ``[H * W]``."""
    rows = (torch.arange(height) // stride) * stride
    cols = (torch.arange(width) // stride) * stride
    return (rows[:, None] * width + cols[None, :]).view(-1)


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
    width, height = camera.width, camera.height
    buffer = torch.zeros((width * height, 3), dtype=torch.float32, device=renderer.device)
    rendered = 0
    for pass_index, (stride, pixels) in enumerate(zip(strides, pass_pixels(width, height, strides))):
        if pixels.numel() > 0:
            colors, stats = renderer.render_pixels(camera, pixels)
            buffer[pixels.to(renderer.device)] = colors
        else:
            stats = RenderStatistics()
        rendered += pixels.numel()
        index = upsample_index(width, height, stride).to(renderer.device)
        image = buffer[index].view(height, width, 3).cpu()
        yield ProgressiveImage(
            image=image,
            stride=stride,
            pass_index=pass_index,
            pixels_rendered=rendered,
            pixels_total=width * height,
            statistics=stats,
        )
