"""The fused training step's decoder products on AMX's tile unit (ops/tile_products_cpu.py, used by
ops/field_train_cpu.py) against autograd through the reference and against the vector unit's float32 step.

The tile unit multiplies bfloat16 halves of every float32 factor (hi*hi + hi*lo + lo*hi), which keeps about 16
bits of each product: where no hidden activation lies near zero, the step matches float64 autograd to float32's
tolerances. Near zero, a ReLU can fall the other way than in float32 (a sum 1e-5 of its scale from zero), and
that point's gradient then takes or skips the unit: on a trained model a few units a batch, which moves a
gradient entry by up to about 4e-3 of the largest one (measured over 12 batches of two neghip fits); the fit
itself is unchanged (300-iteration fits of neghip, seeds 0-5: the median PSNR 0.004 dB from the vector unit's).
Tests that need the tile unit skip where the CPU has none (AVX2 machines, AVX-512 without AMX)."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from apmgsrn.ops import field_train_cpu
from apmgsrn.ops.level_grids import level_grid_train_step_reference
from apmgsrn.ops.tile_products_cpu import TILE_DEPTH, pair_layout
from apmgsrn.training.points import draw_batch
from level_fields import neghip, odd_level_field

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))


def tile_unit_here() -> bool:
    lib = field_train_cpu.LIBRARY.load() if HAS_COMPILER else None
    return lib is not None and bool(lib.amx_ready())


needs_tile_unit = pytest.mark.skipif(not tile_unit_here(), reason="no AMX tile unit on this CPU (or no compiler)")


def test_pair_layout_interleaves_row_pairs_and_its_halves_add_up_to_the_matrix():
    g = torch.Generator().manual_seed(0)
    matrix = torch.randn(6, 5, generator=g) * torch.logspace(-3, 3, 5)  # magnitudes over six decades
    hi, lo = pair_layout(matrix)
    assert hi.shape == lo.shape == (3, 10) and hi.dtype == torch.int16

    def unpaired(half):
        return half.view(torch.bfloat16).float().reshape(3, 5, 2).transpose(1, 2).reshape(6, 5)

    assert torch.equal(unpaired(hi), matrix.to(torch.bfloat16).float())  # [p, 2n + b] is matrix[2p + b, n]
    total = unpaired(hi) + unpaired(lo)
    assert ((total - matrix).abs() <= matrix.abs() * 2.0**-16).all()  # 16 bits of every entry


def test_the_tile_unit_takes_only_widths_that_are_multiples_of_its_depth():
    class Ready:
        @staticmethod
        def amx_ready():
            return 1

    assert field_train_cpu.tile_unit_takes(TILE_DEPTH, [2 * TILE_DEPTH, TILE_DEPTH], Ready)
    assert not field_train_cpu.tile_unit_takes(48, [64], Ready)  # padded features not a multiple
    assert not field_train_cpu.tile_unit_takes(32, [64, 48], Ready)
    Ready.amx_ready = staticmethod(lambda: 0)
    assert not field_train_cpu.tile_unit_takes(32, [64], Ready)


def margined_model():
    """The small preset's shapes (32 features, hidden 64 and 64) with every hidden pre-activation far from zero
    on points in [-1, 1]^3: features of positive tables, and each hidden unit's weights all of one sign (half
    the units always on, half always off)."""
    field, _ = odd_level_field(12, 2, 11, 8, 1, [64, 64])
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        field.encoder.level_table.copy_(0.5 + torch.rand(field.encoder.level_table.shape, generator=g))
        field.encoder.grids.copy_(0.5 + torch.rand(field.encoder.grids.shape, generator=g))
    sign = torch.cat([torch.ones(32), -torch.ones(32)]).view(64, 1)
    w1 = sign * torch.rand(64, 32, generator=g) / 32**0.5
    w2 = sign * torch.rand(64, 64, generator=g) / 64**0.5
    w3 = torch.randn(1, 64, generator=g) / 8
    encoder = field.encoder
    with torch.no_grad():
        table = torch.cat([encoder.level_table, encoder.grids.reshape(-1)])
        return encoder.maps(), table, encoder.layout, [w1, w2, w3]


def assert_close_to_scale(value, expected, atol):
    scale = expected.abs().max().clamp_min(1e-12)
    torch.testing.assert_close((value / scale).double(), (expected / scale).double(), rtol=0, atol=atol)


@needs_tile_unit
@pytest.mark.parametrize("n,threads", [(1, 1), (33, 1), (300, 2), (4000, 1), (4000, 2)])
def test_the_tile_unit_step_matches_float64_autograd_where_no_activation_is_near_zero(n, threads):
    maps, table, layout, weights = margined_model()
    g = torch.Generator().manual_seed(n)
    points = torch.rand(n, 3, generator=g) * 2 - 1
    target = torch.rand(n, generator=g) * 4
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        prediction, grad, weight_grads = field_train_cpu.level_grid_train_step_cpu(
            points, maps, table, layout, weights, target, True, tile_unit=True)
    finally:
        torch.set_num_threads(before)
    exact = level_grid_train_step_reference(points.double(), maps.double(), table.double(), layout,
                                            [w.double() for w in weights], target.double())
    assert_close_to_scale(prediction, exact[0], 1e-5)
    assert exact[1].abs().max() > 0
    assert_close_to_scale(grad, exact[1], 1e-4)
    for got, expected in zip(weight_grads, exact[2]):
        assert got.shape == expected.shape
        assert_close_to_scale(got, expected, 1e-4)


@needs_tile_unit
@pytest.mark.parametrize("threads", [1, 2])
def test_the_tile_unit_step_on_a_trained_model_agrees_with_the_vector_unit(test_data, threads):
    """A trained hybrid (ReLU zeros where training put them) on a real volume's batch: the same prediction, and
    gradients that differ only where a near-zero activation's ReLU fell the other way (see the module's note)."""
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import preset_config
    from apmgsrn.training.trainer import Trainer, TrainConfig

    volume = neghip(test_data)
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=(64, 64, 64),
                        generator=torch.Generator().manual_seed(0))
    Trainer(field, volume, TrainConfig(iterations=40, batch_size=4096)).run()
    encoder = field.encoder
    with torch.no_grad():
        table = torch.cat([encoder.level_table, encoder.grids.reshape(-1)])
        maps, weights = encoder.maps(), field.decoder.weights()
    points, target = draw_batch(volume, 6000, 0.5, torch.Generator().manual_seed(7))
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        steps = [field_train_cpu.level_grid_train_step_cpu(points, maps, table, encoder.layout, weights, target,
                                                           True, tile_unit=unit) for unit in (True, False)]
    finally:
        torch.set_num_threads(before)
    (prediction, grad, weight_grads), (vector_prediction, vector_grad, vector_weight_grads) = steps
    assert_close_to_scale(prediction, vector_prediction, 2e-5)
    for got, expected in zip([grad, *weight_grads], [vector_grad, *vector_weight_grads]):
        assert float((got - expected).norm() / expected.norm()) <= 1e-2
        assert_close_to_scale(got, expected, 1e-2)
