"""Packed model files (training/packing.py, io/packed.py) on real volumes: what is written loads back through
``apmgsrn.load`` into exactly the field the packer measured, smaller than float32 at the PSNR cost the file
reports; an error bound holds at every voxel of every volume in tests/data."""

from __future__ import annotations


import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.data import open_volume
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.io import SourceInfo
from apmgsrn.models.corrected_field import CorrectedField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.sparse_trilinear import sample_sparse_volume
from apmgsrn.ops.trilinear import sample_volume, voxel_coordinates
from apmgsrn.training.fit import fit_volume
from apmgsrn.training.packing import PackConfig, fitted_values, pack_field, write_packed
from apmgsrn.training.trainer import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")
FAST = dict(sensitivity_points=1 << 14)


@pytest.fixture()
def reference(test_data):
    """The committed reference model (loaded afresh: a fine-tune changes it) and the real crop it was trained
    on (data units)."""
    model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    truth = np.load(test_data / "reference_neghip_24.npy").astype(np.float32)
    return model, truth


def pack(model, truth, **config):
    return pack_field(model.field, truth, PackConfig(**{**FAST, **config}), model.description.source,
                      model.description.training)


def all_voxels(field, shape) -> np.ndarray:
    """The field at every voxel, computed here point by point (not through the evaluation code)."""
    with torch.no_grad():
        return field(voxel_coordinates(shape)).view(shape).numpy()


# ------------------------------------------------------------------------------- sparse interpolation
def test_sparse_interpolation_is_trilinear_interpolation_of_the_zero_filled_volume(reference):
    _, truth = reference
    torch.manual_seed(3)
    dense = torch.from_numpy(truth.copy())
    dense[dense < np.percentile(truth, 80)] = 0  # keep the largest fifth, zero elsewhere
    indices = torch.nonzero(dense.reshape(-1)).view(-1)
    values = dense.reshape(-1)[indices]
    points = torch.cat([torch.rand(20_000, 3) * 2.4 - 1.2, voxel_coordinates(truth.shape)])  # also outside
    sparse = sample_sparse_volume(indices, values, truth.shape, points)
    # Points within the snap (1e-4 voxel units) of a voxel take the voxel's value: off by at most that much of a
    # step per axis.
    snap = 1e-4
    assert torch.allclose(sparse, sample_volume(dense, points), rtol=0, atol=3 * snap * float(dense.max()))
    # At the voxels: exactly the stored values, zero elsewhere (no blend with a neighbour).
    at_voxels = sample_sparse_volume(indices, values, truth.shape, voxel_coordinates(truth.shape))
    assert torch.equal(at_voxels, dense.reshape(-1))


def test_sparse_interpolation_of_nothing_is_zero():
    points = torch.rand(10, 3) * 2 - 1
    empty = sample_sparse_volume(torch.zeros(0, dtype=torch.int64), torch.zeros(0), (4, 5, 6), points)
    assert torch.equal(empty, torch.zeros(10))


# ------------------------------------------------------------------------------- packed files
def test_a_packed_file_loads_into_the_field_the_packer_measured(reference, tmp_path):
    model, truth = reference
    result = pack(model, truth, bits=8)
    path = tmp_path / "packed.apmgsrn"
    written = write_packed(path, result)
    assert written == path.stat().st_size == result.file_bytes
    loaded = apmgsrn.load(path)
    points = torch.rand(50_000, 3) * 2 - 1
    with torch.no_grad():
        assert torch.equal(loaded(points), result.field(points))
    description = loaded.description
    packing = description.packing
    assert description.kind == "packed-field" and description.parameters == model.description.parameters
    # Every byte is accounted for: the parts plus the container framing are the file.
    assert sum(part.bytes for part in packing.parts) + packing.container_bytes == path.stat().st_size
    assert {p.name for p in packing.parts} == {"description", *model.field.state_dict()}
    assert all(p.bits is not None and p.bits <= 8 for p in packing.parts if p.encoding == "quantized")
    # The PSNR the file reports is the one measured again here, over every voxel.
    again = evaluate(loaded.field, truth)
    assert packing.report["psnr"] == pytest.approx(again.psnr, abs=1e-3)
    assert packing.report["float32_psnr"] == pytest.approx(evaluate(model.field, truth).psnr, abs=1e-3)
    assert path.stat().st_size * 3 < model.description.file_bytes


def test_the_psnr_cost_allowed_is_kept_and_buys_a_smaller_file(reference):
    model, truth = reference
    tight, loose = pack(model, truth, psnr_loss=0.05), pack(model, truth, psnr_loss=0.5)
    for result, allowed in ((tight, 0.05), (loose, 0.5)):
        measured = evaluate(result.field, truth)
        assert result.report["float32_psnr"] - measured.psnr <= allowed + 1e-3
    assert loose.file_bytes < tight.file_bytes < model.description.file_bytes / 3


def test_a_size_target_is_met(reference):
    model, truth = reference
    for target in (1500, 2500):
        result = pack(model, truth, target_bytes=target)
        assert target * 0.9 <= result.file_bytes <= target


def test_a_size_target_below_the_coarsest_packing_is_a_clear_error(reference):
    model, truth = reference
    with pytest.raises(apmgsrn.errors.ApmgsrnError, match="target_bytes=100: even with every parameter"):
        pack(model, truth, target_bytes=100)


def test_quantisation_aware_fine_tune_recovers_psnr_at_few_bits(reference, test_data):
    model, truth = reference
    plain = pack(model, truth, bits=4)
    tuned_model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    values = fitted_values(tuned_model.field, truth)
    tuned = pack_field(tuned_model.field, truth, PackConfig(bits=4, qat_iterations=150, **FAST),
                       model.description.source, {}, values=values, batch_size=2048)
    assert tuned.report["qat_iterations"] == 150 and plain.report["qat_iterations"] == 0
    assert tuned.report["psnr"] > plain.report["psnr"] + 0.2


def test_the_fine_tune_draws_its_points_as_the_models_kind_trains(reference, test_data, monkeypatch):
    """The quantisation-aware fine-tune draws the share of its batches exactly at voxel centres that it is
    given (none, or half here), and pack_field gives it the share the model's kind trains with."""
    from apmgsrn.recipes import model_recipe
    from apmgsrn.training import packing

    model, truth = reference
    values = fitted_values(model.field, truth)
    d, h, w = values.shape
    seen = []
    original = type(model.field).normalized

    def recording(self, points, **kwargs):
        seen.append(points.detach().clone())
        return original(self, points, **kwargs)

    monkeypatch.setattr(type(model.field), "normalized", recording)
    quantizer = packing.bits_quantizer(model.field, 8)
    for fraction in (0.0, 0.5):
        seen.clear()
        field = apmgsrn.load(test_data / "reference_field.apmgsrn").field
        packing.quantization_aware_fine_tune(field, values, quantizer, 3, 2048, 1e-3, voxel_fraction=fraction)
        points = torch.cat(seen)
        scaled = (points + 1) / 2 * torch.tensor([w - 1, h - 1, d - 1], dtype=points.dtype)
        on_lattice = (scaled - scaled.round()).abs().amax(dim=1) < 1e-4
        assert on_lattice.float().mean().item() == pytest.approx(fraction, abs=0.02)

    passed = {}
    monkeypatch.setattr(packing, "quantization_aware_fine_tune",
                        lambda *args, **kwargs: passed.setdefault("fraction", args[7]))
    pack_field(model.field, truth, PackConfig(bits=6, qat_iterations=5, **FAST), model.description.source, {},
               values=values, batch_size=2048)
    assert passed["fraction"] == model_recipe(model.field.config.model).voxel_fraction


# ------------------------------------------------------------------------------- error bound
TEST_VOLUMES = {
    "neghip": ("neghip_64x64x64_uint8.raw", None, "none"),
    "neghip32": ("neghip_32x32x32_uint8.npy", None, "none"),
    "neghip24": ("reference_neghip_24.npy", None, "none"),
    "darkmatter": ("darkmatter_density_64.h5", None, "log10"),
    "c60": ("c60_80x64x48_uint8.raw", None, "none"),
    "richtmyer": ("richtmyer_meshkov_t20_96x64x48_uint8.raw", None, "none"),
    "miranda": ("miranda_density_80x64x48.nc", None, "none"),
    "channel": ("channel_pressure_96x64x48.nc", None, "none"),
    "cth pressure": ("cth_armor_penetration_88x32x32.vtr", "Pressure", "none"),
    "cth armor fraction": ("cth_armor_penetration_88x32x32.vtr", "Volume Fraction for Armor Plate", "none"),
    **{f"fingers {step}": (f"viscous_fingers_run01/0{step}_density_0{step}_064_2.0.vti", None, "none")
       for step in (30, 31, 32, 33)},
}


@pytest.mark.parametrize("name", sorted(TEST_VOLUMES))
def test_the_error_bound_holds_at_every_voxel(test_data, tmp_path, name):
    file, variable, transform = TEST_VOLUMES[name]
    volume = open_volume(test_data / file, variable=variable)
    truth = volume.to_numpy()
    config = preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), features=2, width=16)
    trained = fit_volume(volume, config, TrainConfig(iterations=40, batch_size=2048, decoder_precision="float32"),
                         tmp_path / "f.apmgsrn", torch.device("cpu"), transform=transform, progress=False)
    span = float(truth.max() - truth.min())
    bound = 0.01 * span  # a poor 40-iteration network: many voxels need a correction
    result = pack_field(trained.field, truth, PackConfig(bits=8, max_error=bound), SourceInfo.of_volume(volume), {})
    write_packed(tmp_path / "b.apmgsrn", result)
    loaded = apmgsrn.load(tmp_path / "b.apmgsrn")
    assert isinstance(loaded.field, CorrectedField) and loaded.description.packing.max_error == bound
    errors = np.abs(all_voxels(loaded, truth.shape).astype(np.float64) - truth.astype(np.float64))
    assert errors.max() <= bound, f"{name}: {errors.max()} > {bound}"
    network_errors = np.abs(all_voxels(trained.field, truth.shape) - truth)
    assert result.correction.indices.size >= int((network_errors > 1.01 * bound).sum()) > 0
    assert loaded.description.packing.corrected_voxels == result.correction.indices.size
    # Between voxels the model stays a field: finite, and within the data's range give or take the bound.
    with torch.no_grad():
        between = loaded(torch.rand(20_000, 3) * 2 - 1)
    assert torch.isfinite(between).all()


def test_a_tight_bound_on_float_data_holds_and_costs_more(test_data, tmp_path):
    volume = open_volume(test_data / "miranda_density_80x64x48.nc")
    truth = volume.to_numpy()
    config = preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), features=2, width=16)
    trained = fit_volume(volume, config, TrainConfig(iterations=40, batch_size=2048, decoder_precision="float32"),
                         tmp_path / "f.apmgsrn", torch.device("cpu"), progress=False)
    span = float(truth.max() - truth.min())
    sizes = []
    for share in (1e-2, 1e-4):
        bound = share * span
        result = pack_field(trained.field, truth, PackConfig(bits=8, max_error=bound), SourceInfo.of_volume(volume), {})
        errors = np.abs(all_voxels(result.field, truth.shape).astype(np.float64) - truth)
        assert errors.max() <= bound
        assert result.report["bounded_max_abs_error"] <= bound
        sizes.append(result.file_bytes)
    assert sizes[1] > sizes[0]


def test_a_bound_below_float32_resolution_is_a_clear_error(reference):
    model, truth = reference
    with pytest.raises(apmgsrn.errors.ApmgsrnError, match="max_error=1e-09: too small"):
        pack(model, truth, bits=8, max_error=1e-9)


def test_bits_32_keeps_the_float32_network_exactly_beside_a_bound(reference, tmp_path):
    model, truth = reference
    result = pack(model, truth, bits=32, max_error=8.0)
    write_packed(tmp_path / "f.apmgsrn", result)
    loaded = apmgsrn.load(tmp_path / "f.apmgsrn")
    assert all(part.encoding in ("float32", "json", "voxels") for part in loaded.description.packing.parts)
    points = torch.rand(5000, 3) * 2 - 1
    with torch.no_grad():
        network = super(CorrectedField, loaded.field).forward(points)  # the network alone, no correction
        assert torch.equal(network, model(points))
    assert np.abs(all_voxels(loaded, truth.shape) - truth).max() <= 8.0
