"""The pure-PyTorch multi-grid reference against analytic answers and a direct per-point evaluation."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from apmgsrn.ops.multigrid import (
    feature_density_reference,
    local_coordinates,
    multigrid_features_reference,
)


def direct_features(points, matrices, translations, grids):
    """Per point, per grid, per corner, in float64: the zero-padded corner-aligned trilinear rule."""
    m, c, d, h, w = grids.shape
    sizes = (w, h, d)  # x, y, z
    out = torch.zeros(points.shape[0], m * c, dtype=torch.float64)
    for n, p in enumerate(points.double()):
        for i in range(m):
            local = matrices[i].double() @ p + translations[i].double()  # [3] x, y, z
            f = [((local[k] + 1) / 2 * (sizes[k] - 1)).item() for k in range(3)]
            lo = [math.floor(v) for v in f]
            for corner in itertools.product((0, 1), repeat=3):
                idx = [lo[k] + corner[k] for k in range(3)]
                if not all(0 <= idx[k] < sizes[k] for k in range(3)):
                    continue  # zero padding: corners outside the grid contribute nothing
                weight = 1.0
                for k in range(3):
                    frac = f[k] - lo[k]
                    weight *= frac if corner[k] else 1 - frac
                x, y, z = idx
                out[n, i * c : (i + 1) * c] += weight * grids[i, :, z, y, x].double()
    return out


def random_maps(m: int, spread: float = 0.3, generator=None):
    matrices = torch.eye(3) + torch.randn(m, 3, 3, generator=generator) * spread
    translations = torch.randn(m, 3, generator=generator) * spread
    return matrices, translations


def test_matches_direct_evaluation_with_points_outside():
    g = torch.Generator().manual_seed(1)
    m, c = 3, 2
    grids = torch.randn(m, c, 4, 5, 6, generator=g)
    matrices, translations = random_maps(m, generator=g)
    points = torch.rand(60, 3, generator=g) * 3 - 1.5  # many fall outside some grid
    got = multigrid_features_reference(points, matrices, translations, grids)
    want = direct_features(points, matrices, translations, grids)
    assert got.shape == (60, m * c)
    assert torch.allclose(got.double(), want, atol=1e-5)
    assert (want == 0).any() and (want != 0).any()  # the sample covers both cases


def test_exact_on_linear_fields():
    # A linear field sampled at the voxels is reproduced exactly inside the grid.
    d, h, w = 5, 6, 7
    zs, ys, xs = torch.meshgrid(
        torch.linspace(-1, 1, d), torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij"
    )
    field = lambda x, y, z: 0.5 * x - 2.0 * y + 1.5 * z + 0.25  # noqa: E731
    grids = torch.stack([field(xs, ys, zs), -field(xs, ys, zs)])[:, None]  # [2, 1, D, H, W]
    matrices = torch.stack([torch.eye(3), torch.diag(torch.tensor([1.5, 0.8, 1.2]))])
    translations = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05]])
    points = torch.rand(500, 3) * 1.2 - 0.6
    local = local_coordinates(points, matrices, translations)  # [M, N, 3]
    assert local.abs().max() <= 1  # every point inside both grids
    got = multigrid_features_reference(points, matrices, translations, grids)
    want = torch.stack([field(*local[0].unbind(-1)), -field(*local[1].unbind(-1))], dim=1)
    assert torch.allclose(got, want, atol=1e-5)


def test_zero_padding_fades_over_one_cell_beyond_the_border():
    w = 9  # cell width 2 / (w - 1) = 0.25 in local units
    grids = torch.ones(1, 1, 3, 3, w)
    matrices, translations = torch.eye(3)[None], torch.zeros(1, 3)
    s = torch.tensor([0.0, 0.2, 0.5, 0.9, 1.0, 1.5])  # fraction of a cell beyond x = 1
    points = torch.stack([1 + s * 0.25, torch.zeros_like(s), torch.zeros_like(s)], dim=1)
    got = multigrid_features_reference(points, matrices, translations, grids)[:, 0]
    want = (1 - s).clamp(min=0)
    assert torch.allclose(got, want, atol=1e-6)
    # and symmetrically at x = -1, and along z
    points_neg = torch.stack([-1 - s * 0.25, torch.zeros_like(s), torch.zeros_like(s)], dim=1)
    got_neg = multigrid_features_reference(points_neg, matrices, translations, grids)[:, 0]
    assert torch.allclose(got_neg, want, atol=1e-6)
    points_z = torch.stack([torch.zeros_like(s), torch.zeros_like(s), 1 + s * 1.0], dim=1)  # d = 3: cell 1
    got_z = multigrid_features_reference(points_z, matrices, translations, grids)[:, 0]
    assert torch.allclose(got_z, want, atol=1e-6)


def test_concatenation_is_grid_major():
    m, c = 3, 2
    grids = torch.arange(m * c, dtype=torch.float32).view(m, c, 1, 1, 1).expand(m, c, 2, 2, 2).contiguous()
    matrices, translations = torch.eye(3).repeat(m, 1, 1), torch.zeros(m, 3)
    got = multigrid_features_reference(torch.zeros(4, 3), matrices, translations, grids)
    assert torch.equal(got, torch.arange(m * c, dtype=torch.float32).expand(4, -1))


def test_feature_density_reference_formula():
    g = torch.Generator().manual_seed(2)
    matrices, translations = random_maps(4, generator=g)
    points = torch.rand(50, 3, generator=g) * 2 - 1
    got = feature_density_reference(points, matrices, translations, power=3)
    want = torch.zeros(50, dtype=torch.float64)
    for i in range(4):
        local = points.double() @ matrices[i].double().T + translations[i].double()
        want += torch.linalg.det(matrices[i].double()) * torch.exp(-(local**6).sum(-1))
    assert torch.allclose(got.double(), want, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("power", [1, 10])
def test_feature_density_of_an_axis_aligned_grid(power):
    # One grid scaled by 2 about the origin: rho = 8 exp(-sum (2 p)^(2P)), 8 at the centre.
    matrices, translations = (2 * torch.eye(3))[None], torch.zeros(1, 3)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [0.5, 0.5, 0.0]])
    got = feature_density_reference(points, matrices, translations, power)
    local = 2 * points.double()
    want = 8 * torch.exp(-(local ** (2 * power)).sum(-1))
    assert torch.allclose(got.double(), want, rtol=1e-5)
