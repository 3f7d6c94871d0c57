"""Image metrics of a render against the reference render: PSNR and SSIM (docs/method.md §8).

SSIM follows Wang et al. (2004): an 11 x 11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03,
population statistics, computed per colour channel over the window positions that fit inside the image
and averaged; the same settings as scikit-image's ``structural_similarity(..., gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1)``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def image_psnr(image: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """PSNR in dB of an image against a reference.

    Args:
        image, reference: ``[H, W, C]`` (or any equal shape) in ``[0, data_range]``.
        data_range: the value span (1 for float images).

    Returns:
        ``20 log10(data_range) - 10 log10(MSE)``; ``inf`` for identical images.
    """
    _check(image, reference)
    mse = float(torch.mean((image.double() - reference.double()) ** 2))
    if mse == 0.0:
        return math.inf
    return 20.0 * math.log10(data_range) - 10.0 * math.log10(mse)


def image_ssim(image: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """Mean structural similarity of an image against a reference.

    Args:
        image, reference: ``[H, W, C]`` or ``[H, W]``, at least 11 pixels each way.
        data_range: the value span (1 for float images).

    Returns:
        SSIM in [-1, 1] (1: identical).
    """
    _check(image, reference)
    if image.dim() == 2:
        image, reference = image[..., None], reference[..., None]
    height, width = image.shape[:2]
    size, sigma = 11, 1.5
    if height < size or width < size:
        raise ValueError(f"SSIM needs images of at least {size}x{size} pixels, got {width}x{height}")
    x = image.double().permute(2, 0, 1)[:, None]  # [C, 1, H, W]
    y = reference.double().permute(2, 0, 1)[:, None]
    offsets = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    gauss = torch.exp(-(offsets**2) / (2 * sigma**2))
    gauss = gauss / gauss.sum()
    window = (gauss[:, None] * gauss[None, :])[None, None]  # [1, 1, 11, 11]

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window)  # 'valid' positions only, as the reference implementation crops

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


def _check(image: torch.Tensor, reference: torch.Tensor) -> None:
    if image.shape != reference.shape:
        raise ValueError(f"images differ in shape: {tuple(image.shape)} vs {tuple(reference.shape)}")
