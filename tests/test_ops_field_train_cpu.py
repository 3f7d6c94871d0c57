"""The fused CPU training step of level grids under a frozen decoder (ops/field_train_cpu.py) against autograd
through the reference, in prediction and gradient, and its use by the trainer (a series' step fine-tunes)."""

from __future__ import annotations

import copy
import os
import shutil

import numpy as np
import pytest
import torch

from apmgsrn.inference.evaluate import evaluate
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops import field_train_cpu
from apmgsrn.ops.level_grids import level_grid_mse_step, level_grid_mse_step_reference
from apmgsrn.training.points import draw_batch
from apmgsrn.training.trainer import Trainer, TrainConfig
from level_fields import ODD_SIZES, neghip, odd_level_field

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
pytestmark = pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler: training runs autograd")


@pytest.fixture(scope="module")
def trained_hybrid(test_data) -> NeuralField:
    """The hybrid small preset after a short fit to a real volume (dense and hashed levels, adaptive grids, the
    ReLU zeros of a trained decoder), its decoder then frozen as a series' steps have it."""
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=(64, 64, 64),
                        generator=torch.Generator().manual_seed(0))
    Trainer(field, neghip(test_data), TrainConfig(iterations=40, batch_size=4096)).run()
    field.decoder.requires_grad_(False)
    for parameter in field.encoder.placement_parameters():
        parameter.requires_grad_(False)
    return field


def parts(field: NeuralField):
    encoder = field.encoder
    with torch.no_grad():
        table = torch.cat([encoder.level_table, encoder.grids.reshape(-1)])
        return encoder.maps(), table, encoder.layout, field.decoder.weights()


def assert_step_matches(fused, reference) -> None:
    (prediction, grad), (ref_prediction, ref_grad) = fused, reference
    # another summation order and fused multiply-adds: float32 rounding, relative to each one's scale
    scale = ref_prediction.abs().max().clamp_min(1e-6)
    torch.testing.assert_close(prediction / scale, ref_prediction / scale, rtol=0, atol=1e-5)
    grad_scale = ref_grad.abs().max()
    assert grad_scale > 0
    torch.testing.assert_close(grad / grad_scale, ref_grad / grad_scale, rtol=0, atol=1e-4)


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_step_on_a_real_volume_matches_autograd_through_the_reference(test_data, trained_hybrid, threads,
                                                                          vector_unit):
    layout = trained_hybrid.encoder.layout
    assert any(layout.hashed) and not all(layout.hashed)
    # a training batch as the trainer draws it: voxels with their values, uniform points with trilinear targets
    points, target = draw_batch(neghip(test_data), 6000, 0.5, torch.Generator().manual_seed(threads))
    maps, table, layout, weights = parts(trained_hybrid)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        fused = level_grid_mse_step(points, maps, table, layout, weights, target)
    finally:
        torch.set_num_threads(before)
    assert fused is not None
    assert_step_matches(fused, level_grid_mse_step_reference(points, maps, table, layout, weights, target))


@pytest.mark.parametrize("levels,features,log2_table_size,grids,grid_features,widths", ODD_SIZES)
def test_fused_step_of_odd_sizes_matches_the_reference(levels, features, log2_table_size, grids, grid_features,
                                                       widths):
    field, weights = odd_level_field(levels, features, log2_table_size, grids, grid_features, widths)
    g = torch.Generator().manual_seed(2)
    maps, table, layout, _ = parts(field)
    points = torch.rand(3000, 3, generator=g) * 2.2 - 1.1  # some outside every adaptive grid
    target = torch.randn(3000, generator=g)
    fused = level_grid_mse_step(points, maps, table, layout, weights, target)
    assert fused is not None
    assert_step_matches(fused, level_grid_mse_step_reference(points, maps, table, layout, weights, target))


def test_the_kernel_runs_only_for_float32_cpu_tensors_and_the_cpu_backend(trained_hybrid):
    maps, table, layout, weights = parts(trained_hybrid)
    points, target = torch.rand(100, 3) * 2 - 1, torch.rand(100)
    assert level_grid_mse_step(points.double(), maps, table, layout, weights, target) is None
    assert level_grid_mse_step(points, maps, table, layout, weights, target.double()) is None
    assert level_grid_mse_step(points, maps, table, layout, weights, target, backend="torch") is None
    prediction, grad = level_grid_mse_step(torch.empty(0, 3), maps, table, layout, weights, torch.empty(0))
    assert prediction.shape == (0,) and grad.shape == table.shape and not grad.any()
    assert not field_train_cpu.trainable(table.numel(), [])  # no hidden layer: not a decoder of this kind


def test_the_field_sets_the_features_gradients_as_autograd_would(test_data, trained_hybrid, vector_unit):
    field = copy.deepcopy(trained_hybrid)
    field.encoder.grids.requires_grad_(False)  # only the table learns: the grids get no gradient
    points, target = draw_batch(neghip(test_data), 4000, 0.5, torch.Generator().manual_seed(3))
    field.zero_grad(set_to_none=True)
    prediction = field.fused_mse_step(points, target)
    assert prediction is not None and field.encoder.grids.grad is None
    fused_grad = field.encoder.level_table.grad.clone()
    field.zero_grad(set_to_none=True)
    expected = field.normalized(points, detach_placement=True).view(-1)
    (expected - target).square().mean().backward()
    assert_step_matches((prediction, fused_grad), (expected.detach(), field.encoder.level_table.grad))
    # a decoder that learns gets its own gradients from the kernel too
    field.decoder.requires_grad_(True)
    field.zero_grad(set_to_none=True)
    assert field.fused_mse_step(points, target) is not None
    assert all(w.grad is not None for w in field.decoder.weights())


def test_a_frozen_decoder_fine_tune_trains_through_the_kernel_as_through_autograd(test_data, trained_hybrid,
                                                                                  monkeypatch):
    """A series' step fine-tune (the decoder and placement kept, the features learning) on a real step: it runs
    the fused step, and ends where the same fine-tune through autograd ends (float32 rounding apart)."""
    steps = sorted((test_data / "viscous_fingers_run01").glob("*.vti"))
    from apmgsrn.data import open_volume

    volume = np.asarray(open_volume(steps[0]).read(), dtype=np.float32)
    volume = (volume - volume.min()) / (volume.max() - volume.min())  # the field's [0, 1]
    values = torch.from_numpy(volume)
    config = TrainConfig(iterations=60, batch_size=4096, lr=0.01, density_start=61, voxel_fraction=0.5,
                         error_sampling=1.0, seed=2)
    calls = []
    original = NeuralField.fused_mse_step
    psnr = {}
    for path in ("fused", "autograd"):
        field = copy.deepcopy(trained_hybrid)  # a model of another volume: the fine-tune has much to do
        field.volume_shape = tuple(values.shape)
        if path == "fused":
            monkeypatch.setattr(NeuralField, "fused_mse_step", lambda *a: calls.append(1) or original(*a))
        else:
            monkeypatch.setattr(NeuralField, "fused_mse_step", lambda *a: None)
        decoder = copy.deepcopy(field.decoder.state_dict())
        Trainer(field, values, config, warm=True).run()
        assert all(torch.equal(a, b) for a, b in zip(decoder.values(), field.decoder.state_dict().values()))
        psnr[path] = evaluate(field.eval(), volume).psnr
    assert len(calls) == config.iterations
    start = evaluate(copy.deepcopy(trained_hybrid).eval(), volume).psnr
    assert psnr["fused"] > start + 5 and psnr["autograd"] > start + 5
    assert abs(psnr["fused"] - psnr["autograd"]) < 0.2
