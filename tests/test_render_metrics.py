"""Image PSNR and SSIM against closed forms and scikit-image's reference implementation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from apmgsrn.rendering.metrics import image_psnr, image_ssim


def _image(seed: int, height: int = 40, width: int = 48) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    smooth = torch.stack([torch.sin(6 * x) * 0.5 + 0.5, y, x * y], dim=-1)
    return (0.8 * smooth + 0.2 * torch.rand(height, width, 3, generator=gen)).clamp(0, 1)


def test_psnr_closed_form():
    a = torch.zeros(10, 10, 3)
    b = torch.full((10, 10, 3), 0.1)
    assert image_psnr(b, a) == pytest.approx(20.0)  # MSE 0.01
    assert image_psnr(a, a) == math.inf
    with pytest.raises(ValueError, match="shape"):
        image_psnr(a, torch.zeros(10, 11, 3))


def test_ssim_is_one_for_identical_images_and_falls_with_noise():
    image = _image(0)
    assert image_ssim(image, image) == pytest.approx(1.0)
    gen = torch.Generator().manual_seed(1)
    light = (image + 0.02 * torch.randn(image.shape, generator=gen)).clamp(0, 1)
    heavy = (image + 0.2 * torch.randn(image.shape, generator=gen)).clamp(0, 1)
    assert 1.0 > image_ssim(light, image) > image_ssim(heavy, image) > 0.0


def test_ssim_matches_scikit_image():
    metrics = pytest.importorskip("skimage.metrics")
    a, b = _image(2), _image(3)
    expected = metrics.structural_similarity(
        a.numpy().astype(np.float64), b.numpy().astype(np.float64), channel_axis=-1, data_range=1.0,
        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    )
    assert image_ssim(a, b) == pytest.approx(expected, abs=1e-9)
    gray = metrics.structural_similarity(
        a[..., 0].numpy().astype(np.float64), b[..., 0].numpy().astype(np.float64), data_range=1.0,
        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    )
    assert image_ssim(a[..., 0], b[..., 0]) == pytest.approx(gray, abs=1e-9)
