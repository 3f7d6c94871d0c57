"""The fVSRN and NGP baselines: real sizes, exact encodings against independent references, training."""

import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.models.encoders.dense_grid import DenseGridConfig, DenseGridEncoder
from apmgsrn.models.encoders.hash_grid import HashGridConfig, HashGridEncoder, _WeightedGather
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.training.trainer import Trainer, TrainConfig


def decoder_parameters(inputs: int) -> int:
    return inputs * 64 + 64 * 64 + 64


def test_preset_parameter_counts_are_the_real_ones():
    # fVSRN: C x R^3 grid + decoder over C + 36 inputs (sin and cos of 6 frequencies on 3 axes).
    assert NeuralField(preset_config("fvsrn", "small")).parameter_count() == 2 * 32**3 + decoder_parameters(38)
    assert NeuralField(preset_config("fvsrn", "medium")).parameter_count() == 4 * 64**3 + decoder_parameters(40)
    # NGP small: level 0 is 8^3 = 512 vertices (dense), level 1 is 10^3 = 1000 (dense), the other 15 levels
    # are capped at 2^11 entries; 2 features each.
    small = preset_config("ngp", "small").encoder
    assert small.level_resolutions()[:3] == [8, 10, 13] and small.level_resolutions()[-1] == 256
    assert small.level_table_sizes() == [512, 1000] + [2048] * 15
    entries = 512 + 1000 + 15 * 2048
    small_count = NeuralField(preset_config("ngp", "small")).parameter_count()
    assert small_count == 2 * entries + decoder_parameters(34) == 70_800
    medium = preset_config("ngp", "medium").encoder
    assert medium.level_resolutions()[-1] == 512 and max(medium.level_table_sizes()) == 2**15
    assert NeuralField(preset_config("ngp", "medium")).parameter_count() == 1_033_424


def test_hash_grid_dense_levels_are_trilinear_grids():
    # Levels small enough to be stored densely are plain grids: vertex (x, y, z) at row x + N y + N^2 z,
    # vertex coordinate u * s + 0.5. Reference: grid_sample on the same numbers laid out as a volume.
    config = HashGridConfig(levels=3, features=2, log2_table_size=16, base_resolution=4, finest_resolution=16)
    encoder = HashGridEncoder(config, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        encoder.table.normal_(generator=torch.Generator().manual_seed(1))
    points = torch.rand(2000, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    scales, resolutions = config.level_scales(), config.level_resolutions()
    sizes, offset = config.level_table_sizes(), 0
    # Stay clear of the far border, where tiny-cuda-nn's index wraps to the next row.
    limit = min((r - 1.5) / s for r, s in zip(resolutions, scales))
    points = points[((points + 1) / 2 < limit).all(1)]
    features = encoder(points)
    for level, (scale, r) in enumerate(zip(scales, resolutions)):
        assert r**3 <= sizes[level]
        grid = encoder.table[offset : offset + r**3].detach().t().reshape(1, 2, r, r, r)  # [1, F, z, y, x]
        vertex = (points + 1) / 2 * scale + 0.5
        expected = F.grid_sample(grid, (vertex / (r - 1) * 2 - 1).view(1, -1, 1, 1, 3), align_corners=True)
        torch.testing.assert_close(features[:, 2 * level : 2 * level + 2], expected.view(2, -1).t(),
                                   atol=1e-5, rtol=1e-5)
        offset += sizes[level]


def test_hash_grid_hashed_levels_follow_the_instant_ngp_hash():
    # Independent reference in Python integers: rows (x * 1) xor (y * 2654435761) xor (z * 805459861)
    # mod 2^32 mod 2^T, trilinear weights from the fractional vertex coordinate.
    config = HashGridConfig(levels=2, features=3, log2_table_size=6, base_resolution=8, finest_resolution=32)
    encoder = HashGridEncoder(config)
    with torch.no_grad():
        encoder.table.normal_(generator=torch.Generator().manual_seed(3))
    table = encoder.table.detach().double().numpy()
    points = torch.rand(50, 3, generator=torch.Generator().manual_seed(4)) * 2 - 1
    features = encoder(points).detach().double().numpy()
    sizes, scales = config.level_table_sizes(), config.level_scales()
    assert sizes == [64, 64] and all(r**3 > 64 for r in config.level_resolutions())
    for i, p in enumerate(points.tolist()):
        for level in range(2):
            vertex = [((c + 1) / 2) * np.float32(scales[level]) + 0.5 for c in p]
            lower = [math.floor(v) for v in vertex]
            expected = np.zeros(3)
            for corner in range(8):
                offs = [(corner >> a) & 1 for a in range(3)]
                x, y, z = (lo + o for lo, o in zip(lower, offs))
                row = ((x * 1) ^ (y * 2654435761) ^ (z * 805459861)) % 2**32 % 64 + 64 * level
                weight = math.prod(v - lo if o else 1 - (v - lo) for v, lo, o in zip(vertex, lower, offs))
                expected += weight * table[row]
            np.testing.assert_allclose(features[i, 3 * level : 3 * level + 3], expected, atol=1e-5)


def test_hash_grid_gather_gradient_is_exact():
    table = torch.randn(40, 2, dtype=torch.float64, requires_grad=True)
    rows = torch.randint(0, 40, (3, 8, 25), dtype=torch.int32)  # [L, 8, N], repeated rows included
    weights = torch.rand(3, 8, 25, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: _WeightedGather.apply(t, rows, weights), (table,))


def test_dense_grid_is_exact_on_linear_fields_and_fourier_terms_follow_the_spec():
    config = DenseGridConfig(features=1, resolution=(5, 6, 7), frequencies=3)
    encoder = DenseGridEncoder(config)
    d, h, w = config.resolution
    z, y, x = torch.meshgrid(torch.linspace(-1, 1, d), torch.linspace(-1, 1, h), torch.linspace(-1, 1, w),
                             indexing="ij")
    with torch.no_grad():
        encoder.grid.copy_((0.5 + 2 * x - y + 0.25 * z)[None, None])
    points = torch.rand(300, 3) * 2 - 1
    out = encoder(points)
    assert out.shape == (300, 1 + 6 * 3)
    px, py, pz = points.unbind(1)
    torch.testing.assert_close(out[:, 0], 0.5 + 2 * px - py + 0.25 * pz, atol=1e-5, rtol=1e-5)
    angles = points[:, :, None] * (math.pi * torch.tensor([1.0, 2.0, 4.0]))  # [N, 3 axes, 3 frequencies]
    torch.testing.assert_close(out[:, 1:10], torch.sin(angles).reshape(300, 9))
    torch.testing.assert_close(out[:, 10:19], torch.cos(angles).reshape(300, 9))


def test_steps_schedule_cuts_at_40_60_80_percent():
    field = NeuralField(preset_config("fvsrn", "small", resolution=(4, 4, 4)))
    trainer = Trainer(field, torch.zeros(4, 4, 4), TrainConfig(iterations=100, batch_size=8, lr_schedule="steps"))
    rates = [trainer.learning_rate(i) for i in (0, 39, 40, 59, 60, 79, 80, 99)]
    expected = [0.01, 0.01, 0.0033, 0.0033, 0.01 * 0.33**2, 0.01 * 0.33**2, 0.01 * 0.33**3, 0.01 * 0.33**3]
    assert rates == pytest.approx(expected)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("model", ["fvsrn", "ngp"])
def test_baseline_trains_saves_and_reports_its_real_size(model, neghip_crop, tmp_path, capsys):
    path, data = neghip_crop
    out = tmp_path / f"{model}.apmgsrn"
    code = main(["train", str(path), "--model", model, "--out", str(out), "--iterations", "40",
                 "--batch-size", "1024", "--device", "cpu", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    # Better than the best constant (the mean) after 40 iterations: measured +4.0 dB (fvsrn), +12.5 (ngp).
    constant_psnr = 20 * math.log10(data.max() - data.min()) - 10 * math.log10(float(data.var()))
    assert summary["psnr"] > constant_psnr + 2
    field = apmgsrn.load(out)
    points = torch.rand(500, 3) * 2 - 1
    reloaded = apmgsrn.load(out)
    assert torch.equal(field(points), reloaded(points))
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["model"] == model
    assert info["parameters"] == field.description.parameters == summary["parameters"]
    assert info["parameter_bytes"] == 4 * info["parameters"]
    assert info["file_bytes"] == out.stat().st_size > info["parameter_bytes"]


def test_options_of_another_model_are_refused_in_one_line(neghip_crop, tmp_path, capsys):
    path, _ = neghip_crop
    code = main(["train", str(path), "--model", "ngp", "--grids", "4", "--out", str(tmp_path / "x.apmgsrn"),
                 "--iterations", "2", "--device", "cpu"])
    assert code == 2
    assert "grids" in capsys.readouterr().err


@pytest.mark.gpu
def test_tiny_cuda_nn_hash_grid_matches_the_pytorch_one():
    pytest.importorskip("tinycudann")
    config = preset_config("ngp", "small").encoder
    reference = HashGridEncoder(config).cuda()
    with torch.no_grad():
        reference.table.uniform_(-1, 1)
    fast = HashGridEncoder(HashGridConfig(**{**config.__dict__, "backend": "tcnn"})).cuda()
    fast.load_state_dict(reference.state_dict())
    points = torch.rand(100_000, 3, device="cuda") * 2 - 1
    expected, actual = reference(points), fast(points)
    torch.testing.assert_close(actual, expected, atol=1e-4, rtol=1e-3)
    weights = torch.randn_like(expected)
    (expected * weights).sum().backward()
    (actual * weights).sum().backward()
    torch.testing.assert_close(fast.table.grad, reference.table.grad, atol=1e-3, rtol=1e-3)
