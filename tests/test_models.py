"""Model construction, initialisation, gradient routing and save/load round trips."""

import pickle

import pytest
import torch

import apmgsrn
from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.models.value_transform import ValueTransform
from apmgsrn.ops.trilinear import sample_volume, voxel_coordinates
from apmgsrn.io import SourceInfo, model_kind, save_field
from apmgsrn.training.losses import feature_density_loss


def small_field(**kw):
    return NeuralField(preset_config("apmgsrn", "small", **kw), fit_min=-2.0, fit_max=3.0,
                       volume_shape=(8, 9, 10), generator=torch.Generator().manual_seed(0))


def test_preset_parameter_counts_are_the_real_ones():
    # SPEC section 5 counts 70,976 / 1,055,040: the reference code stores each transform as a 4x4
    # homogeneous matrix (16 numbers). Ours stores A (9) and t (3): 64 fewer for 16 grids.
    grids, transforms = 16 * 16**3, 16 * 12
    decoder = 16 * 64 + 64 * 64 + 64
    assert small_field().parameter_count() == grids + transforms + decoder == 70_976 - 64
    medium = NeuralField(preset_config("apmgsrn", "medium"))
    assert medium.parameter_count() == 16 * 2 * 32**3 + transforms + 32 * 64 + 64 * 64 + 64 == 1_055_040 - 64


def test_explicit_flags_override_the_preset():
    config = preset_config("apmgsrn", "small", grids=4, resolution=(8, 16, 32), width=32, hidden_layers=3)
    field = NeuralField(config)
    assert field.encoder.grids.shape == (4, 1, 8, 16, 32)
    assert sum(isinstance(m, torch.nn.Linear) for m in field.decoder) == 4
    assert field.decoder[0].in_features == 4 and field.decoder[0].out_features == 32


def test_initialisation_follows_spec():
    gen = torch.Generator().manual_seed(3)
    field = NeuralField(preset_config("apmgsrn", "small", grids=512), generator=gen)
    enc = field.encoder.requires_grad_(False)
    diag = torch.diagonal(enc.matrices, dim1=1, dim2=2)
    off = enc.matrices[~torch.eye(3, dtype=bool).expand(512, 3, 3)]
    assert abs(float(diag.mean()) - 1.0) < 0.01 and abs(float(diag.std()) - 0.05) < 0.01
    assert abs(float(off.std()) - 0.05) < 0.01 and abs(float(enc.translations.std()) - 0.05) < 0.01
    assert float(enc.grids.abs().max()) <= 1e-4
    for layer in field.decoder:
        if isinstance(layer, torch.nn.Linear):
            assert layer.bias is None


def test_large_and_small_grid_inits():
    large = small_field(init="large").encoder.grid_boxes()
    default = small_field().encoder.grid_boxes()
    extent = lambda b: (b.max(1).values - b.min(1).values).mean()  # noqa: E731
    assert extent(large) > 1.15 * extent(default)
    small = small_field(init="small").encoder.grid_boxes()
    assert extent(small) < 0.6


def test_output_scaling_and_inverse_transform():
    field = NeuralField(preset_config("apmgsrn", "small"), fit_min=1.0, fit_max=3.0,
                        transform=ValueTransform("log10"))
    points = torch.rand(7, 3) * 2 - 1
    normalized = field.normalized(points)
    expected = torch.pow(10.0, normalized * 2.0 + 1.0)
    torch.testing.assert_close(field(points), expected)


def test_reconstruction_gradients_reach_only_grids_and_decoder():
    field = small_field()
    points = torch.rand(256, 3) * 2 - 1
    field.normalized(points, detach_placement=True).square().mean().backward()
    assert field.encoder.matrices.grad is None and field.encoder.translations.grad is None
    assert field.encoder.grids.grad is not None and field.encoder.grids.grad.abs().sum() > 0
    assert all(layer.weight.grad is not None for layer in field.decoder if isinstance(layer, torch.nn.Linear))


def test_bfloat16_decoder_matches_float32_in_forward_and_backward():
    """The trainer's bfloat16 hidden layers against the float32 reference: same values and gradients
    to bfloat16's precision (8-bit mantissa), float32 output and float32 gradients."""
    field = small_field()
    points = torch.rand(4096, 3) * 2 - 1
    results = []
    for dtype in (None, torch.bfloat16):
        field.zero_grad(set_to_none=True)
        out = field.normalized(points, detach_placement=True, hidden_dtype=dtype)
        (out.square().mean()).backward()
        linears = [m.weight for m in field.decoder if isinstance(m, torch.nn.Linear)]
        grads = [p.grad.clone() for p in (field.encoder.grids, *linears)]
        results.append((out.detach(), grads))
    (ref, ref_grads), (low, low_grads) = results
    assert low.dtype == torch.float32 and all(g.dtype == torch.float32 for g in low_grads)
    scale = float(ref.abs().max())
    assert float((low - ref).abs().max()) < 0.02 * scale and not torch.equal(low, ref)
    for g_ref, g_low in zip(ref_grads, low_grads):
        assert float((g_low - g_ref).norm() / g_ref.norm()) < 0.08  # three bfloat16 products deep


def test_decoder_precision_is_chosen_by_option_and_device():
    from apmgsrn.device import inference_dtype
    from apmgsrn.training.trainer import TrainConfig

    cpu = torch.device("cpu")
    assert inference_dtype("float32", cpu) is None
    assert inference_dtype("bfloat16", cpu) is torch.bfloat16
    assert inference_dtype("auto", torch.device("meta")) is None  # auto: bfloat16 only on such CPUs
    with pytest.raises(ValueError, match="decoder_precision="):
        TrainConfig(decoder_precision="half")


def test_density_gradients_reach_only_transforms():
    field = small_field()
    points = torch.rand(256, 3) * 2 - 1
    error = torch.rand(256)
    feature_density_loss(field.encoder.feature_density(points), error).backward()
    assert field.encoder.matrices.grad.abs().sum() > 0 and field.encoder.translations.grad.abs().sum() > 0
    assert field.encoder.grids.grad is None
    assert all(layer.weight.grad is None for layer in field.decoder if isinstance(layer, torch.nn.Linear))


def test_save_load_round_trip_gives_identical_outputs(tmp_path):
    field = small_field()
    with torch.no_grad():
        field.encoder.grids.normal_()  # make the output non-trivial
    path = tmp_path / "m.apmgsrn"
    save_field(path, field, SourceInfo(path="x.nc"), {"iterations": 5})
    loaded = apmgsrn.load(path)
    points = torch.rand(1000, 3) * 2 - 1
    assert torch.equal(field(points), loaded(points))
    assert loaded.description.volume_shape == (8, 9, 10) and loaded.description.training["iterations"] == 5
    assert loaded.description.source.path == "x.nc"
    assert loaded.description.file_bytes == path.stat().st_size
    assert model_kind(path) == "field"
    assert not list(tmp_path.glob(".*tmp"))  # atomic write left no temp file


def test_corrupt_truncated_and_foreign_model_files_are_refused(tmp_path):
    field = small_field()
    good = tmp_path / "good.apmgsrn"
    save_field(good, field, SourceInfo(), {})
    data = good.read_bytes()
    cases = {
        "truncated": data[: len(data) // 2],
        "garbage": b"\x00\x01garbage" * 50,
        "empty": b"",
        "broken_header": data[:8] + b"[" + data[9:],
    }
    for name, content in cases.items():
        path = tmp_path / f"{name}.apmgsrn"
        path.write_bytes(content)
        with pytest.raises(ApmgsrnError, match="not an apmgsrn model file"):
            apmgsrn.load(path)
        assert model_kind(path) is None


def test_model_from_a_newer_format_version_is_refused(tmp_path):
    from apmgsrn.io import container

    path = tmp_path / "future.apmgsrn"
    original = container.FORMAT_VERSION
    container.FORMAT_VERSION = original + 1
    try:
        save_field(path, small_field(), SourceInfo(), {})
    finally:
        container.FORMAT_VERSION = original
    with pytest.raises(ApmgsrnError, match="newer apmgsrn"):
        apmgsrn.load(path)


class _Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_pickle_crafted_to_run_code_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.apmgsrn"
    path.write_bytes(pickle.dumps({"state": _Exploit(str(marker))}))
    torch_style = tmp_path / "evil.pt"
    torch.save({"x": _Exploit(str(marker))}, torch_style)
    for candidate in (path, torch_style):
        with pytest.raises(ApmgsrnError):
            apmgsrn.load(candidate)
    assert not marker.exists()


def test_sample_volume_is_exact_on_linear_fields():
    # Trilinear interpolation reproduces any affine function of the coordinates exactly.
    shape = (5, 7, 9)
    coords = voxel_coordinates(shape)  # [n, 3] (x, y, z)
    values = (0.5 + 2 * coords[:, 0] - 3 * coords[:, 1] + 0.25 * coords[:, 2]).reshape(shape)
    points = torch.rand(500, 3) * 2 - 1
    expected = 0.5 + 2 * points[:, 0] - 3 * points[:, 1] + 0.25 * points[:, 2]
    torch.testing.assert_close(sample_volume(values, points), expected, atol=1e-5, rtol=1e-5)
    # Voxel positions give the voxel values back.
    torch.testing.assert_close(sample_volume(values, coords), values.reshape(-1), atol=1e-5, rtol=1e-5)


def test_strided_voxel_coordinates_match_strided_voxels():
    shape = (5, 7, 9)
    full = voxel_coordinates(shape).reshape(*shape, 3)
    assert torch.equal(voxel_coordinates(shape, stride=2), full[::2, ::2, ::2].reshape(-1, 3))
    assert torch.equal(voxel_coordinates(shape, slice(1, 4), stride=3), full[1:4][::3, ::3, ::3].reshape(-1, 3))


def test_value_transforms_round_trip_and_fit_statistics():
    import numpy as np

    from apmgsrn.models.value_transform import fit_value_transform

    data = np.random.default_rng(0).gamma(2.0, 3.0, size=(6, 7, 8)).astype(np.float32) + 0.5
    zscore = fit_value_transform("zscore", [data[:3], data[3:]], float(data.min()))
    assert zscore.mean == pytest.approx(float(data.mean()), rel=1e-6)
    assert zscore.std == pytest.approx(float(data.std()), rel=1e-5)
    for transform in (zscore, fit_value_transform("log10", [], float(data.min()))):
        back = transform.inverse(torch.from_numpy(transform.apply(data)))
        torch.testing.assert_close(back, torch.from_numpy(data), rtol=1e-5, atol=1e-5)
    with pytest.raises(ApmgsrnError, match="log_offset="):
        fit_value_transform("log10", [], 0.0, source="x.nc")
    shifted = fit_value_transform("log10", [], 0.0, offset=1.0)
    assert shifted.apply_scalar(0.0) == 0.0
