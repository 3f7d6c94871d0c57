"""The feature-density loss against a direct float64 evaluation of the SPEC formulas."""

import math

import torch

from apmgsrn.ops.multigrid import feature_density
from apmgsrn.training.losses import feature_density_loss


def direct_density_loss(rho, h, eps=1e-16):
    """SPEC section 3, written out literally in float64."""
    rho = rho.double()
    h = h.double()
    rho_s = rho / rho.sum()
    h_bar = h.mean()
    target = torch.exp(h_bar / (h + eps) * torch.log(rho_s + eps))
    target = target / target.sum()
    return (target * torch.log(target / rho_s)).mean()


def test_density_loss_matches_spec_formula():
    gen = torch.Generator().manual_seed(1)
    rho = torch.rand(4096, generator=gen, dtype=torch.float64) + 0.1
    # Errors within a factor 3 of each other keep the literal formula inside float64 range.
    h = (torch.rand(4096, generator=gen, dtype=torch.float64) + 0.5) * 1e-3
    ours = feature_density_loss(rho, h)
    assert math.isclose(float(ours), float(direct_density_loss(rho, h)), rel_tol=1e-9)


def test_density_loss_stays_finite_where_the_literal_formula_underflows():
    # A near-zero error drives rho* of that point to exp(-huge): the literal formula gives 0 * log 0.
    rho = torch.rand(4096, dtype=torch.float32) + 0.1
    h = torch.rand(4096, dtype=torch.float32) * 1e-3
    h[0] = 0.0
    assert torch.isnan(direct_density_loss(rho, h))
    loss = feature_density_loss(rho.requires_grad_(True), h)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(rho.grad).all()


def test_density_loss_is_zero_when_error_is_uniform():
    # Uniform error: target = rho_s, so the KL divergence vanishes.
    rho = torch.rand(1000, dtype=torch.float64) + 0.5
    h = torch.full((1000,), 0.3, dtype=torch.float64)
    assert abs(float(feature_density_loss(rho, h))) < 1e-12


def test_density_loss_gradient_pulls_density_towards_high_error():
    # Two points, equal density: the one with larger error should gain density after a gradient step.
    rho = torch.tensor([1.0, 1.0], dtype=torch.float64, requires_grad=True)
    h = torch.tensor([1.0, 0.01], dtype=torch.float64)
    feature_density_loss(rho, h).backward()
    assert rho.grad[0] < rho.grad[1]


def test_density_loss_gradient_matches_direct_formula():
    gen = torch.Generator().manual_seed(2)
    base = torch.rand(512, generator=gen, dtype=torch.float64) + 0.2
    h = torch.rand(512, generator=gen, dtype=torch.float64) + 0.5
    a = base.clone().requires_grad_(True)
    b = base.clone().requires_grad_(True)
    feature_density_loss(a, h).backward()
    # The target is a constant: differentiate the direct formula with the target detached.
    rho_s = b / b.sum()
    with torch.no_grad():
        t = torch.exp(h.mean() / (h + 1e-16) * torch.log(rho_s + 1e-16))
        t = t / t.sum()
    (t * torch.log(t / rho_s)).mean().backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-7, atol=1e-12)


def test_feature_density_of_identity_grid_is_flat_top():
    # One grid equal to the domain: density ~1 deep inside, falling sharply only near the border.
    matrices = torch.eye(3)[None]
    translations = torch.zeros(1, 3)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [1.0, 0.0, 0.0], [1.3, 0.0, 0.0]])
    rho = feature_density(points, matrices, translations, power=10)
    assert abs(float(rho[0]) - 1.0) < 1e-6
    assert float(rho[1]) > 0.98  # 0.8^20 ~ 0.0115 -> exp(-0.0115)
    assert abs(float(rho[2]) - math.exp(-1.0)) < 1e-6
    assert float(rho[3]) < 1e-3


def test_feature_density_scales_with_determinant():
    # det(A) weights each grid: a grid shrunk to half size (A = 2I) has 8x the density at its centre.
    points = torch.zeros(1, 3)
    rho_big = feature_density(points, torch.eye(3)[None], torch.zeros(1, 3))
    rho_small = feature_density(points, 2 * torch.eye(3)[None], torch.zeros(1, 3))
    assert abs(float(rho_small / rho_big) - 8.0) < 1e-5
