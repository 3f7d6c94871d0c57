"""Writing rendered images: PNG files, side-by-side comparisons and error images."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from apmgsrn.atomic import atomic_write
from apmgsrn.errors import ApmgsrnError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def as_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` (or ``[H, W, 4]``) uint8 from a float image in [0, 1] (tensor or array) or a uint8 array."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    if image.dtype == np.uint8:
        return image
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_image(image: torch.Tensor | np.ndarray, path: str | os.PathLike) -> Path:
    """Write an ``[H, W, 3]`` image; the format follows the file suffix (PNG recommended).

    Args:
        image: float in [0, 1] or uint8.
        path: output file.

    Returns:
        The path written.

    Raises:
        ApmgsrnError: unknown suffix, missing or unwritable folder, or a failed write (nothing is left under
            ``path`` then: the file is written atomically).
    """
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise ApmgsrnError(f"{path}: unknown image type {path.suffix!r}; use a .png file name")
    pixels = Image.fromarray(as_uint8(image))
    return atomic_write(path, pixels.save, "image")


def side_by_side(left: torch.Tensor, right: torch.Tensor, gap: int = 4) -> torch.Tensor:
    """Two ``[H, W, 3]`` images next to each other with a white gap. Returns ``[H, 2W + gap, 3]``."""
    if left.shape != right.shape:
        raise ValueError("side-by-side images must have the same shape")
    spacer = torch.ones((left.shape[0], gap, 3), dtype=left.dtype)
    return torch.cat([left.cpu(), spacer, right.cpu()], dim=1)


def error_image(
    image: torch.Tensor, reference: torch.Tensor, scale: float | None = None, colormap: str = "magma"
) -> tuple[torch.Tensor, float]:
    """Per-pixel error ``mean_c |image - reference|`` shown with a colour map.

    Args:
        image, reference: ``[H, W, 3]`` in [0, 1].
        scale: the error mapped to the top of the colour map (None: the largest error, at least 1e-6).
        colormap: a matplotlib colour map name.

    Returns:
        ``([H, W, 3] image, scale used)``.
    """
    import matplotlib  # heavy: only when an error image is asked for

    error = (image.double() - reference.double()).abs().mean(dim=-1)  # [H, W]
    top = float(scale) if scale is not None else max(float(error.max()), 1e-6)
    normalized = (error / top).clamp(0.0, 1.0).numpy()
    rgba = matplotlib.colormaps[colormap](normalized)  # [H, W, 4]
    return torch.from_numpy(rgba[..., :3].astype(np.float32)), top
