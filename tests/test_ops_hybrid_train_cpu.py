"""The fused CPU reconstruction step of the hybrid with a learning decoder (ops/field_train_cpu.py,
``level_grid_train_step``) against autograd through the reference: prediction, loss and every parameter's
gradient (the level tables', the adaptive grids', each decoder weight's), and the trainer's use of it."""

from __future__ import annotations

import copy
import os
import shutil

import pytest
import torch

from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.level_grids import level_grid_train_step, level_grid_train_step_reference
from apmgsrn.training.points import draw_batch
from apmgsrn.training.trainer import Trainer, TrainConfig
from level_fields import ODD_SIZES, neghip, odd_level_field

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
pytestmark = pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler: training runs autograd")


@pytest.fixture(scope="module")
def trained_hybrid(test_data) -> NeuralField:
    """The hybrid small preset after a short fit to a real volume (dense and hashed levels, adaptive grids moved
    by the density step, the ReLU zeros of a trained decoder); everything but the placement still learns."""
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=(64, 64, 64),
                        generator=torch.Generator().manual_seed(0))
    Trainer(field, neghip(test_data), TrainConfig(iterations=40, batch_size=4096)).run()
    return field


def parts(field: NeuralField, weights: list[torch.Tensor] | None = None):
    encoder = field.encoder
    with torch.no_grad():
        table = torch.cat([encoder.level_table, encoder.grids.reshape(-1)])
        return encoder.maps(), table, encoder.layout, field.decoder.weights() if weights is None else weights


def assert_close_to_scale(value: torch.Tensor, expected: torch.Tensor, atol: float) -> None:
    """Equal up to ``atol`` times the reference's largest magnitude (another summation order, fused
    multiply-adds: float32 rounding)."""
    scale = expected.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(value / scale, expected / scale, rtol=0, atol=atol)


def assert_step_matches(fused, reference, target: torch.Tensor) -> None:
    """Prediction and loss to 1e-5 of their scale, every gradient to 1e-4 of its own (measured on the preset's
    shapes: about 2e-6 and 4e-6 at 1 and 2 threads)."""
    (prediction, grad, weight_grads), (ref_prediction, ref_grad, ref_weight_grads) = fused, reference
    assert_close_to_scale(prediction, ref_prediction, 1e-5)
    loss, ref_loss = (prediction - target).square().mean(), (ref_prediction - target).square().mean()
    assert abs(float(loss) - float(ref_loss)) <= 1e-5 * float(ref_loss)
    assert ref_grad.abs().max() > 0
    assert_close_to_scale(grad, ref_grad, 1e-4)
    assert len(weight_grads) == len(ref_weight_grads)
    for got, expected in zip(weight_grads, ref_weight_grads):
        assert got.shape == expected.shape and expected.abs().max() > 0
        assert_close_to_scale(got, expected, 1e-4)


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_learning_step_on_a_real_volume_matches_autograd_through_the_reference(test_data, trained_hybrid,
                                                                                     threads, vector_unit):
    layout = trained_hybrid.encoder.layout
    assert any(layout.hashed) and not all(layout.hashed)
    points, target = draw_batch(neghip(test_data), 6000, 0.5, torch.Generator().manual_seed(threads))
    maps, table, layout, weights = parts(trained_hybrid)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        fused = level_grid_train_step(points, maps, table, layout, weights, target)
    finally:
        torch.set_num_threads(before)
    assert fused is not None
    reference = level_grid_train_step_reference(points, maps, table, layout, weights, target)
    assert_step_matches(fused, reference, target)


@pytest.mark.parametrize("levels,features,log2_table_size,grids,grid_features,widths", ODD_SIZES)
def test_fused_learning_step_of_odd_sizes_matches_the_reference(levels, features, log2_table_size, grids,
                                                                grid_features, widths):
    field, weights = odd_level_field(levels, features, log2_table_size, grids, grid_features, widths)
    g = torch.Generator().manual_seed(2)
    maps, table, layout, _ = parts(field)
    n = 300 if levels == 12 else 3000  # also a batch that ends inside a tile
    points = torch.rand(n, 3, generator=g) * 2.2 - 1.1  # some outside every adaptive grid
    target = torch.randn(n, generator=g)
    fused = level_grid_train_step(points, maps, table, layout, weights, target)
    assert fused is not None
    assert_step_matches(fused, level_grid_train_step_reference(points, maps, table, layout, weights, target), target)


@pytest.mark.parametrize("n", [1, 7, 129])
def test_tiny_cases_match_float64_autograd(n):
    """Gradcheck-like: a tiny model (2 levels, 1 adaptive grid, hidden widths 5 and 3) on a few points, where the
    fused float32 step must agree with autograd in float64 to float32 rounding."""
    field, weights = odd_level_field(2, 2, 4, 1, 1, [5, 3])
    g = torch.Generator().manual_seed(n)
    maps, table, layout, _ = parts(field)
    points = torch.rand(n, 3, generator=g) * 2 - 1
    target = torch.randn(n, generator=g)
    fused = level_grid_train_step(points, maps, table, layout, weights, target)
    assert fused is not None
    exact = level_grid_train_step_reference(points.double(), maps.double(), table.double(), layout,
                                            [w.double() for w in weights], target.double())
    prediction, grad, weight_grads = fused
    torch.testing.assert_close(prediction.double(), exact[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad.double(), exact[1], rtol=1e-4, atol=1e-6)
    for got, expected in zip(weight_grads, exact[2]):
        torch.testing.assert_close(got.double(), expected, rtol=1e-4, atol=1e-6)


def test_the_learning_step_runs_only_for_float32_cpu_tensors_and_the_cpu_backend(trained_hybrid):
    maps, table, layout, weights = parts(trained_hybrid)
    points, target = torch.rand(100, 3) * 2 - 1, torch.rand(100)
    assert level_grid_train_step(points.double(), maps, table, layout, weights, target) is None
    assert level_grid_train_step(points, maps, table, layout, weights, target, backend="torch") is None
    prediction, grad, weight_grads = level_grid_train_step(torch.empty(0, 3), maps, table, layout, weights,
                                                           torch.empty(0))
    assert prediction.shape == (0,) and grad.shape == table.shape and not grad.any()
    assert all(g.shape == w.shape and not g.any() for g, w in zip(weight_grads, weights))


def test_the_field_sets_every_learning_gradient_as_autograd_would(test_data, trained_hybrid, vector_unit):
    field = copy.deepcopy(trained_hybrid)
    field.decoder.weights()[1].requires_grad_(False)  # a frozen weight gets no gradient
    points, target = draw_batch(neghip(test_data), 4000, 0.5, torch.Generator().manual_seed(3))
    field.zero_grad(set_to_none=True)
    prediction = field.fused_mse_step(points, target)
    assert prediction is not None
    learning = [p for p in field.parameters() if p.requires_grad]
    fused = {id(p): p.grad.clone() for p in learning if p.grad is not None}
    assert field.decoder.weights()[1].grad is None
    assert all(p.grad is None for p in field.encoder.placement_parameters())  # the reconstruction detaches them
    field.zero_grad(set_to_none=True)
    expected = field.normalized(points, detach_placement=True).view(-1)
    (expected - target).square().mean().backward()
    assert_close_to_scale(prediction, expected.detach(), 1e-5)
    reference = {id(p): p.grad for p in learning if p.grad is not None}
    assert fused.keys() == reference.keys() and len(reference) == 4  # table, grids, two decoder weights
    for key, grad in reference.items():
        assert_close_to_scale(fused[key], grad, 1e-4)


def test_training_through_the_fused_step_ends_where_autograd_ends(test_data):
    """The trainer takes the fused step for the default model (a learning decoder, moving grids), and a short
    fit through it fits the volume as closely as the autograd path does. Parameters are not compared: Adam
    turns the float32 rounding of a near-zero gradient into a full step of either sign, so the two paths'
    weights part by about the learning rate while their fits agree."""
    volume = neghip(test_data)
    config = TrainConfig(iterations=30, batch_size=2048, seed=1, density_start=5)
    fields = {}
    for fused in (True, False):
        field = NeuralField(preset_config("hybrid", "small"), volume_shape=(64, 64, 64),
                            generator=torch.Generator().manual_seed(0))
        trainer = Trainer(field, volume, config)
        trainer.fused_step = fused
        calls = []
        original = field.fused_mse_step
        field.fused_mse_step = lambda *a: calls.append(1) or original(*a)  # type: ignore[method-assign]
        trainer.run()
        assert len(calls) == (config.iterations if fused else 0)
        fields[fused] = field
    from apmgsrn.inference.evaluate import evaluate

    truth = volume.numpy()
    fused_psnr, autograd_psnr = (evaluate(fields[f].eval(), truth).psnr for f in (True, False))
    assert abs(fused_psnr - autograd_psnr) <= 0.05, (fused_psnr, autograd_psnr)  # 0.0003 dB measured


def test_the_density_backward_with_denormal_terms_matches_float64_and_leaves_denormals_on():
    """The density's gradient on a batch whose terms are mostly denormal products (points near the grids'
    borders, a gradient of 1e-30 there, as the density loss makes it): the kernel, which counts them as zero,
    agrees with autograd in float64 to float32 rounding; and the caller's float arithmetic keeps its
    denormals afterwards."""
    from apmgsrn.ops.multigrid import feature_density, feature_density_reference

    g = torch.Generator().manual_seed(5)
    matrices = torch.eye(3).expand(4, 3, 3) + 0.05 * torch.randn(4, 3, 3, generator=g)
    translations = 0.3 * torch.randn(4, 3, generator=g)
    points = torch.rand(20000, 3, generator=g) * 2.4 - 1.2
    weights = torch.randn(20000, generator=g)
    weights[:19000] *= 1e-30  # tiny factors: their products with the falloff fall below 2^-126
    grads = []
    kernel = lambda *args: feature_density(*args, backend="cpu")  # noqa: E731
    for dtype, density in ((torch.float32, kernel), (torch.float64, feature_density_reference)):
        a = matrices.to(dtype).clone().requires_grad_(True)
        t = translations.to(dtype).clone().requires_grad_(True)
        (density(points.to(dtype), a, t, 10) * weights.to(dtype)).sum().backward()
        grads.append((a.grad, t.grad))
    for got, exact in zip(grads[0], grads[1]):
        assert_close_to_scale(got.double(), exact, 1e-5)
    tiny = torch.tensor([1e-38]) * torch.tensor([1e-3])
    assert float(tiny) > 0  # a denormal result, not flushed to zero
