"""The CPU ground-truth sampler (ops/trilinear_cpu.py) against ``F.grid_sample``: bit for bit, on real volumes."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import torch

from apmgsrn.ops.trilinear import sample_volume, sample_volume_reference

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
pytestmark = pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler: sample_volume is the reference")

# (file, (D, H, W)) of raw uint8 volumes in tests/data
VOLUMES = [("neghip_64x64x64_uint8.raw", (64, 64, 64)), ("richtmyer_meshkov_t20_96x64x48_uint8.raw", (48, 64, 96))]


def real_volume(test_data, name, shape) -> torch.Tensor:
    return torch.from_numpy(np.fromfile(test_data / name, dtype=np.uint8).reshape(shape).astype(np.float32))


def points_with_edge_cases(n: int, seed: int) -> torch.Tensor:
    """Random points in [-1.2, 1.2]^3 (some outside: clamped to the border) plus corners, faces and NaN."""
    points = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * 2.4 - 1.2
    special = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0],
                            [float("nan"), 0.0, 0.0], [0.5, float("nan"), -0.5], [5.0, -7.0, 1.0 - 1e-7]])
    points[: len(special)] = special
    return points


def same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal bit for bit, NaN where the other is NaN (a point with a NaN coordinate samples NaN)."""
    return torch.equal(torch.isnan(a), torch.isnan(b)) and torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0))


@pytest.fixture(scope="module")
def kernel():
    from apmgsrn.ops import trilinear_cpu

    assert trilinear_cpu.LIBRARY.available(), trilinear_cpu.LIBRARY.error
    return trilinear_cpu


@pytest.mark.parametrize("name,shape", VOLUMES)
@pytest.mark.parametrize("threads", [1, 2])
def test_kernel_is_grid_sample_bit_for_bit_on_real_volumes(kernel, test_data, name, shape, threads):
    volume = real_volume(test_data, name, shape)
    points = points_with_edge_cases(50_000, seed=threads)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        fast = kernel.sample_volume_cpu(volume, points)
    finally:
        torch.set_num_threads(before)
    reference = sample_volume_reference(volume, points)
    # bit for bit; a point with a NaN coordinate samples NaN in both (the contract of apmgsrn.ops)
    torch.testing.assert_close(fast, reference, rtol=0, atol=0, equal_nan=True)
    assert bool(torch.isnan(fast[4:6]).all()) and not bool(torch.isnan(fast[6:]).any())


@pytest.mark.parametrize("shape", [(1, 5, 7), (3, 1, 4), (2, 2, 1)])
def test_kernel_on_single_voxel_axes(kernel, test_data, shape):
    full = real_volume(test_data, *VOLUMES[0])
    volume = full[20 : 20 + shape[0], 30 : 30 + shape[1], 10 : 10 + shape[2]].contiguous()
    points = points_with_edge_cases(2000, seed=5)
    assert same(kernel.sample_volume_cpu(volume, points), sample_volume_reference(volume, points))


def test_sample_volume_dispatches_to_the_kernel_only_where_it_is_exact(kernel, test_data, monkeypatch):
    volume = real_volume(test_data, *VOLUMES[0])
    points = points_with_edge_cases(1000, seed=6)
    calls = []
    original = kernel.sample_volume_cpu
    monkeypatch.setattr(kernel, "sample_volume_cpu", lambda *a: calls.append(1) or original(*a))
    sample_volume(volume, points)
    assert calls == [1]
    # float64 and a strided volume go to grid_sample
    assert same(sample_volume(volume.double(), points.double()), sample_volume_reference(volume.double(), points.double()))
    strided = volume[:, :, ::2]
    assert same(sample_volume(strided, points), sample_volume_reference(strided, points))
    # gradients need grid_sample's backward
    leaf = points.clone().requires_grad_(True)
    sample_volume(volume, leaf).sum().backward()
    assert leaf.grad is not None and calls == [1]
