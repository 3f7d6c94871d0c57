"""The fused CPU inference kernels (ops/field_cpu.py: encoder + decoder MLP in one pass) against the reference
``decoder(multigrid_features_reference(...))`` for APMGSRN's encoder and ``decoder(level_grid_features_reference(...))``
for level grids (the hybrid's). Inference only, so forward only."""

from __future__ import annotations

import os
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops import field_cpu
from apmgsrn.ops.level_grids import level_grid_decoded, level_grid_features_reference
from apmgsrn.ops.multigrid import multigrid_decoded, multigrid_features_reference
from apmgsrn.training.trainer import Trainer, TrainConfig
from level_fields import ODD_SIZES, odd_level_field

HAS_COMPILER = bool(os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc"))
pytestmark = pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler: decoding runs the reference")


def reference(points, encoder, weights) -> torch.Tensor:
    features = multigrid_features_reference(points, encoder.matrices, encoder.translations, encoder.grids)
    x = features
    for w in weights[:-1]:
        x = torch.relu(x @ w.t())
    return (x @ weights[-1].t()).view(-1)


def points(n: int, seed: int) -> torch.Tensor:
    """Points in [-1.1, 1.1]^3 (some outside every grid) plus the domain's corners and centre."""
    p = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * 2.2 - 1.1
    p[:3] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    return p


def assert_matches(fused: torch.Tensor, ref: torch.Tensor) -> None:
    # other summation order and fused multiply-adds: float32 rounding, relative to the output's scale
    scale = ref.abs().max().clamp_min(1e-6)
    torch.testing.assert_close(fused / scale, ref / scale, rtol=0, atol=1e-5)


@pytest.fixture(scope="module")
def trained_small(test_data) -> NeuralField:
    """The small preset after a short fit to a real volume (ReLU zeros as a trained decoder has them)."""
    raw = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    field = NeuralField(preset_config("apmgsrn", "small"), generator=torch.Generator().manual_seed(0))
    Trainer(field, torch.from_numpy(raw.astype(np.float32) / 255.0), TrainConfig(iterations=40, batch_size=4096)).run()
    return field.eval()


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_decoding_of_a_trained_model_matches_the_reference(trained_small, threads):
    pts = points(20_000, seed=threads)
    weights = trained_small.decoder.weights()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            fused = multigrid_decoded(pts, trained_small.encoder.matrices, trained_small.encoder.translations,
                                      trained_small.encoder.grids, weights)
            ref = reference(pts, trained_small.encoder, weights)
    finally:
        torch.set_num_threads(before)
    assert fused is not None
    assert_matches(fused, ref)


@pytest.mark.parametrize("name", ["reference_field.apmgsrn", "render_reference_model.apmgsrn"])
def test_models_loaded_through_the_api_decode_fused_and_match(test_data, name, monkeypatch):
    model = apmgsrn.load(test_data / name)
    field = model.field
    pts = points(5000, seed=7)
    from apmgsrn.ops import field_cpu

    calls = []
    original = field_cpu.multigrid_decoder_cpu
    monkeypatch.setattr(field_cpu, "multigrid_decoder_cpu", lambda *a: calls.append(1) or original(*a))
    with torch.no_grad():
        values = model(pts).view(-1)
        expected = field.transform.inverse(
            reference(pts, field.encoder, field.decoder.weights())[:, None] * (field.fit_max - field.fit_min)
            + field.fit_min
        ).view(-1)
    assert calls == [1]  # the user's path is the fused one
    assert_matches(values, expected)


@pytest.mark.parametrize(
    "grids,features,resolution,widths",
    [(16, 1, (16, 16, 16), [64, 64]), (4, 3, (5, 7, 9), [20]), (1, 1, (2, 2, 2), [3, 9, 40]),
     (8, 2, (6, 6, 6), [130, 17])],
)
def test_fused_decoding_of_odd_sizes_matches_the_reference(grids, features, resolution, widths):
    g = torch.Generator().manual_seed(grids + features)
    matrices = torch.eye(3) + torch.randn(grids, 3, 3, generator=g) * 0.3
    translations = torch.randn(grids, 3, generator=g) * 0.3
    grid_values = torch.randn(grids, features, *resolution, generator=g)
    sizes = [grids * features, *widths, 1]
    weights = [torch.randn(o, i, generator=g) / i**0.5 for i, o in zip(sizes[:-1], sizes[1:])]
    pts = points(3000, seed=1)

    class Encoder:  # what reference() reads
        pass

    encoder = Encoder()
    encoder.matrices, encoder.translations, encoder.grids = matrices, translations, grid_values
    with torch.no_grad():
        fused = multigrid_decoded(pts, matrices, translations, grid_values, weights)
    assert fused is not None
    assert_matches(fused, reference(pts, encoder, weights))


def test_fused_kernel_runs_only_where_no_gradient_is_wanted_and_inputs_are_float32(trained_small):
    encoder, weights = trained_small.encoder, trained_small.decoder.weights()
    pts = points(500, seed=3)
    args = (encoder.matrices, encoder.translations, encoder.grids)
    assert multigrid_decoded(pts, *args, weights) is None  # grad enabled: training takes the autograd path
    with torch.no_grad():
        assert multigrid_decoded(pts.double(), *args, weights) is None
        assert multigrid_decoded(pts, *args, weights, backend="torch") is None
    # with gradients the field still works and its gradient reaches the grids
    trained_small.zero_grad()
    trained_small(pts).sum().backward()
    assert encoder.grids.grad is not None and encoder.grids.grad.abs().sum() > 0
    trained_small.zero_grad(set_to_none=True)
    with torch.no_grad():
        assert multigrid_decoded(torch.empty(0, 3), *args, weights).shape == (0,)


def test_bfloat16_inference_is_close_to_float32_and_auto_follows_the_cpu(test_data, monkeypatch):
    """load(precision=...) on a real trained model: bfloat16 hidden layers agree with float32 to bfloat16's
    precision; "auto" picks bfloat16 only on CPUs that multiply it natively, and only for a field that has no
    fused float32 kernel (which decodes faster there: docs/benchmarks_decode.md)."""
    from apmgsrn import device
    from apmgsrn.arguments import InvalidArgument

    path = test_data / "reference_field.apmgsrn"
    pts = points(5000, seed=11)
    exact = apmgsrn.load(path, precision="float32")
    low = apmgsrn.load(path, precision="bfloat16")
    assert low.field.inference_dtype is torch.bfloat16 and exact.field.inference_dtype is None
    with torch.no_grad():
        a, b = exact(pts).view(-1), low(pts).view(-1)
    value_range = exact.field.value_max - exact.field.value_min
    error = (a - b).abs().max() / value_range
    assert 0 < error < 0.02  # really rounded, and only to bfloat16's 8-bit mantissa
    assert apmgsrn.load(path).field.inference_dtype is None  # float32 unless asked: a bound holds
    monkeypatch.setattr(device, "cpu_has_native_bfloat16", lambda: True)
    assert apmgsrn.load(path, precision="auto").field.inference_dtype is None  # the fused kernel runs
    unfused = apmgsrn.load(path)
    unfused.field.encoder.config = replace(unfused.field.encoder.config, backend="torch")
    assert not unfused.field.fused_inference()
    assert unfused.set_precision("auto").field.inference_dtype is torch.bfloat16
    monkeypatch.setattr(device, "cpu_has_native_bfloat16", lambda: False)
    assert apmgsrn.load(path, precision="auto").field.inference_dtype is None
    assert unfused.set_precision("auto").field.inference_dtype is None
    with pytest.raises(InvalidArgument, match="precision"):
        apmgsrn.load(path, precision="int4")


def test_eval_and_decode_take_the_precision_and_eval_reports_float32_unless_asked(test_data, tmp_path, capsys):
    """`--precision` reaches apmgsrn.load: eval's default is the float32 network's PSNR, bfloat16 when asked
    costs little; decode --precision bfloat16 writes values within bfloat16's rounding of float32's."""
    import json

    from apmgsrn.cli.main import main

    model = str(test_data / "reference_field.apmgsrn")
    volume = str(test_data / "reference_neghip_24.npy")
    psnr = {}
    for precision in (None, "float32", "bfloat16"):
        extra = [] if precision is None else ["--precision", precision]
        assert main(["eval", model, volume, "--device", "cpu", "--json", *extra]) == 0
        psnr[precision] = json.loads(capsys.readouterr().out)["psnr"]
    assert psnr[None] == psnr["float32"]
    assert psnr["bfloat16"] != psnr["float32"] and abs(psnr["bfloat16"] - psnr["float32"]) < 0.5
    decoded = {}
    for precision in ("float32", "bfloat16"):
        out = tmp_path / f"{precision}.npy"
        assert main(["decode", model, "--out", str(out), "--device", "cpu", "--precision", precision]) == 0
        decoded[precision] = np.load(out)
    difference = np.abs(decoded["bfloat16"] - decoded["float32"]).max()
    value_range = float(decoded["float32"].max() - decoded["float32"].min())
    assert 0 < difference < 0.02 * value_range
    capsys.readouterr()
    assert main(["decode", model, "--out", str(tmp_path / "x.npy"), "--precision", "int4"]) == 2
    assert "--precision" in capsys.readouterr().err


# ------------------------------------------------------------------------------ level grids (the hybrid)
def level_parts(field: NeuralField) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    encoder = field.encoder
    return encoder.maps(), torch.cat([encoder.level_table, encoder.grids.reshape(-1)]), field.decoder.weights()


def level_reference(pts: torch.Tensor, field: NeuralField) -> torch.Tensor:
    maps, table, weights = level_parts(field)
    x = level_grid_features_reference(pts, maps, table, field.encoder.layout)
    for w in weights[:-1]:
        x = torch.relu(x @ w.t())
    return (x @ weights[-1].t()).view(-1)


@pytest.fixture(scope="module")
def trained_hybrid(test_data) -> NeuralField:
    """The hybrid small preset after a short fit to a real volume (dense and hashed levels, adaptive grids,
    the ReLU zeros of a trained decoder)."""
    raw = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    values = torch.from_numpy(raw.astype(np.float32) / 255.0)
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=(64, 64, 64),
                        generator=torch.Generator().manual_seed(0))
    Trainer(field, values, TrainConfig(iterations=40, batch_size=4096)).run()
    return field.eval()


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_decoding_of_a_trained_hybrid_matches_the_reference(trained_hybrid, threads):
    assert any(trained_hybrid.encoder.layout.hashed) and not all(trained_hybrid.encoder.layout.hashed)
    pts = points(20_000, seed=threads)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            fused = level_grid_decoded(pts, *level_parts(trained_hybrid)[:2], trained_hybrid.encoder.layout,
                                       trained_hybrid.decoder.weights())
            ref = level_reference(pts, trained_hybrid)
    finally:
        torch.set_num_threads(before)
    assert fused is not None
    assert_matches(fused, ref)


def test_a_hybrid_field_decodes_fused_for_users_and_the_reference_where_asked(trained_hybrid, monkeypatch):
    calls = []
    original = field_cpu.level_grid_decoder_cpu
    monkeypatch.setattr(field_cpu, "level_grid_decoder_cpu", lambda *a: calls.append(1) or original(*a))
    pts = points(5000, seed=7)
    with torch.no_grad():
        values = trained_hybrid.normalized(pts).view(-1)
    assert calls == [1]  # the user's path (eval, decode, render, the error guide) is the fused one
    assert_matches(values, level_reference(pts, trained_hybrid))
    # gradients wanted: the autograd path, whose gradient reaches the tables
    trained_hybrid.zero_grad()
    trained_hybrid.normalized(pts).sum().backward()
    assert calls == [1] and trained_hybrid.encoder.level_table.grad.abs().sum() > 0
    trained_hybrid.zero_grad(set_to_none=True)
    maps, table, weights = level_parts(trained_hybrid)
    layout = trained_hybrid.encoder.layout
    with torch.no_grad():
        assert level_grid_decoded(pts.double(), maps, table, layout, weights) is None
        assert level_grid_decoded(pts, maps, table, layout, weights, backend="torch") is None
        assert level_grid_decoded(torch.empty(0, 3), maps, table, layout, weights).shape == (0,)


@pytest.mark.parametrize("levels,features,log2_table_size,grids,grid_features,widths", ODD_SIZES)
def test_fused_level_decoding_of_odd_sizes_matches_the_reference(levels, features, log2_table_size, grids,
                                                                  grid_features, widths):
    field, weights = odd_level_field(levels, features, log2_table_size, grids, grid_features, widths)
    maps, table, _ = level_parts(field)
    pts = points(3000, seed=1)
    with torch.no_grad():
        fused = level_grid_decoded(pts, maps, table, field.encoder.layout, weights)
        x = level_grid_features_reference(pts, maps, table, field.encoder.layout)
        for w in weights[:-1]:
            x = torch.relu(x @ w.t())
    assert fused is not None
    assert_matches(fused, (x @ weights[-1].t()).view(-1))


def test_a_series_step_of_hybrids_evaluates_through_the_fused_kernel(test_data, tmp_path, monkeypatch):
    steps = sorted((test_data / "viscous_fingers_run01").glob("*.vti"))[:2]
    model = apmgsrn.fit([str(p) for p in steps], model="hybrid", iterations=30, batch_size=2048, device="cpu",
                        progress=False)
    calls = []
    original = field_cpu.level_grid_decoder_cpu
    monkeypatch.setattr(field_cpu, "level_grid_decoder_cpu", lambda *a: calls.append(1) or original(*a))
    step = model.field.step_field(1)
    pts = points(2000, seed=5)
    with torch.no_grad():
        values = step.normalized(pts).view(-1)
    assert calls == [1]
    assert_matches(values, level_reference(pts, step))
