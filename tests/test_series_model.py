"""The time-series model (issue 16): basis grids over time, materialised steps, its model file (safe, checked
before allocation), and its training through the one pipeline. Real data: the four consecutive
viscous-fingering steps of tests/data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import apmgsrn
from apmgsrn.series.data import open_series
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.decode import decode_array
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.io import SeriesStepInfo, SourceInfo, load_field, save_field
from apmgsrn.io.container import sealed_file_bytes
from apmgsrn.series import field as series_module
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.series.field import (
    SeriesConfig,
    SeriesField,
    SeriesFieldConfig,
    keyframe_weights,
    step_time,
    time_position,
)
from apmgsrn.training.fit import prepare_values, train_prepared
from apmgsrn.series.fit import fit_series
from apmgsrn.series.evaluate import evaluate_series
from apmgsrn.series.file import save_series
from apmgsrn.training.trainer import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), width=16)


@pytest.fixture(scope="module")
def series(test_data):
    return open_series(str(test_data / "viscous_fingers_run01" / "*.vti"))


@pytest.fixture(scope="module")
def truth(series) -> np.ndarray:
    return series.to_numpy()  # [4, 32, 32, 32]


def random_field(config: SeriesConfig, seed: int = 0) -> SeriesField:
    """A series field with every parameter random (not its initial values), so steps differ."""
    field = SeriesField(SeriesFieldConfig(TINY, config), fit_min=-1.0, fit_max=3.0, volume_shape=(9, 10, 11),
                        generator=torch.Generator().manual_seed(seed))
    generator = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for name, parameter in field.named_parameters():
            if name.startswith("encoder.") and name not in ("encoder.matrices", "encoder.translations"):
                parameter.copy_(torch.rand(parameter.shape, generator=generator) * 2 - 1)
        if config.placement == "per_step":  # every step's grids somewhere else
            field.encoder.translations.add_(torch.rand(field.encoder.translations.shape, generator=generator) * 0.4 - 0.2)
    return field.eval()


def test_keyframe_weights_interpolate_linearly_in_time():
    weights = keyframe_weights(7, 3)  # keyframes at steps 0, 3, 6
    assert torch.allclose(weights.sum(1), torch.ones(7))
    assert torch.allclose(weights[0], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(weights[1], torch.tensor([2 / 3, 1 / 3, 0.0]))
    assert torch.allclose(weights[3], torch.tensor([0.0, 1.0, 0.0]))
    assert torch.allclose(weights[5], torch.tensor([0.0, 1 / 3, 2 / 3]))
    assert torch.equal(keyframe_weights(5, 5), torch.eye(5))


def test_time_coordinate_is_corner_aligned_like_space():
    assert [step_time(t, 5) for t in range(5)] == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert step_time(0, 1) == 0.0
    assert time_position(0.25, 5) == 2.5 and time_position(-3.0, 5) == 0.0 and time_position(2.0, 5) == 4.0


@pytest.mark.parametrize("config", [SeriesConfig(5, 3, "learned", residual=4), SeriesConfig(5, 2, "keyframes"),
                                    SeriesConfig(5, 5, "keyframes", placement="per_step")])
def test_a_materialised_step_is_the_series_field_at_that_step(config):
    field = random_field(config)
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    for step in range(5):
        single = field.step_field(step)
        assert isinstance(single, NeuralField) and single.config == TINY
        with torch.no_grad():
            # The training path (groups of points at whole steps) and the 4-D forward agree with it.
            normalized = field.normalized(points, torch.tensor([step])).view(-1)
            trained_path = normalized * (field.fit_max - field.fit_min) + field.fit_min
            forward = field(torch.cat([points, torch.full((300, 1), step_time(step, 5))], 1)).view(-1)
        expected = single(points).view(-1)
        assert torch.allclose(trained_path, expected, atol=1e-5)
        assert torch.allclose(forward, expected, atol=1e-5)
    # Two steps in one call: each group is its own step.
    with torch.no_grad():
        pair = field.normalized(torch.cat([points, points]), torch.tensor([1, 3])).view(2, -1)
        assert torch.allclose(pair[0], field.step_field(1).normalized(points).view(-1), atol=1e-5)
        assert torch.allclose(pair[1], field.step_field(3).normalized(points).view(-1), atol=1e-5)
    assert not torch.allclose(field.step_field(0)(points), field.step_field(4)(points))


def test_between_steps_the_grids_are_interpolated():
    field = random_field(SeriesConfig(5, 3, "learned", residual=4))
    middle = field.time_field(step_time(2.25, 5))
    expected = torch.lerp(field.step_field(2).encoder.grids, field.step_field(3).encoder.grids, 0.25)
    assert torch.allclose(middle.encoder.grids, expected, atol=1e-6)
    assert torch.equal(field.time_field(step_time(4, 5)).encoder.grids, field.step_field(4).encoder.grids)


def test_steps_placed_apart_are_interpolated_by_value_between_steps():
    field = random_field(SeriesConfig(5, 5, "keyframes", placement="per_step"))
    assert not torch.equal(field.step_field(2).encoder.translations, field.step_field(3).encoder.translations)
    points = torch.rand(200, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.no_grad():
        between = field(torch.cat([points, torch.full((200, 1), step_time(2.25, 5))], 1))
        expected = torch.lerp(field.step_field(2)(points), field.step_field(3)(points), 0.25)
    assert torch.allclose(between, expected, atol=1e-5)
    with pytest.raises(ValueError, match="no grids between them"):
        field.time_field(step_time(2.25, 5))
    assert torch.equal(field.time_field(step_time(3, 5)).encoder.translations, field.encoder.translations[3])


def test_a_per_step_placement_reloads_exactly(tmp_path):
    field = random_field(SeriesConfig(3, 3, "keyframes", placement="per_step"))
    path = tmp_path / "placed.apmgsrn"
    steps = [SeriesStepInfo(label=float(t), name=f"s{t}", value_range=(-1.0, 3.0)) for t in range(3)]
    save_series(path, field, SourceInfo(), {}, steps)
    loaded = apmgsrn.load(path).field
    assert loaded.config.series.placement == "per_step" and loaded.encoder.matrices.shape == (3, 4, 3, 3)
    for name, parameter in field.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], parameter), name
    # One step's placement singular, or placements stored for fewer steps than declared: one-line refusals.
    singular = rewrite(path, tmp_path / "singular.apmgsrn",
                       tensors=lambda tensors: tensors["encoder.matrices"][2, 1].zero_())
    with pytest.raises(ApmgsrnError, match="singular"):
        apmgsrn.load(singular)
    short = rewrite(path, tmp_path / "short.apmgsrn",
                    tensors=lambda tensors: tensors.update({"encoder.matrices": tensors["encoder.matrices"][:2].clone()}))
    with pytest.raises(ApmgsrnError) as caught:
        apmgsrn.load(short)
    assert "\n" not in str(caught.value)


def test_materialising_leaves_the_global_random_state_alone():
    field = random_field(SeriesConfig(3, 2))
    torch.manual_seed(5)
    expected = torch.rand(3)
    torch.manual_seed(5)
    field.step_field(1)
    assert torch.equal(torch.rand(3), expected)


@pytest.mark.parametrize("bad", [dict(steps=0), dict(steps=3, basis=4), dict(steps=3, basis=0),
                                 dict(steps=3, residual=1), dict(steps=3, coefficients="splines"),
                                 dict(steps=3, basis=1, coefficients="keyframes"),
                                 dict(steps=3, mixing=2, coefficients="keyframes"), dict(steps=3, mixing=0),
                                 dict(steps=3, storage="int8"), dict(steps=3, placement="moving"),
                                 dict(steps=3, basis=2, coefficients="keyframes", placement="per_step")])
def test_series_configs_out_of_range_are_refused(bad):
    with pytest.raises(ValueError):
        SeriesConfig(**{"basis": 1, **bad})


def test_a_one_step_series_trains_exactly_like_one_volume(truth):
    """The series path through the one trainer is the single-volume path when there is one step."""
    config = TrainConfig(iterations=60, batch_size=2048, seed=3)
    prepared = prepare_values(truth[0], "none", 0.0, "step 0", torch.device("cpu"))
    single = train_prepared(prepared, TINY, config, truth.shape[1:])
    prepared_series = prepare_values(truth[:1], "none", 0.0, "step 0", torch.device("cpu"))
    series = train_prepared(prepared_series, SeriesFieldConfig(TINY, SeriesConfig(1, 1, "keyframes")), config,
                            truth.shape[1:])
    assert series.state.history["reconstruction"] == single.state.history["reconstruction"]
    assert torch.equal(series.field.step_field(0).encoder.grids, single.field.encoder.grids)


def test_every_step_gets_an_equal_share_of_the_batches(truth):
    from apmgsrn.training.trainer import Trainer

    prepared = prepare_values(truth, "none", 0.0, "series", torch.device("cpu"))
    field = SeriesField(SeriesFieldConfig(TINY, SeriesConfig(4, 2)))
    trainer = Trainer(field, prepared.values, TrainConfig(iterations=10, batch_size=64, steps_per_iteration=3))
    drawn = torch.cat([trainer.batch_steps(i) for i in range(8)])  # 24 draws = 6 rounds of the 4 steps
    assert torch.bincount(drawn, minlength=4).tolist() == [6, 6, 6, 6]
    assert torch.equal(trainer.batch_steps(5), trainer.batch_steps(5))  # a function of the iteration


def test_fit_series_saves_a_model_that_reloads_exactly(series, truth, tmp_path):
    out = tmp_path / "series.apmgsrn"
    config = SeriesFieldConfig(TINY, SeriesConfig(4, 2, "learned", residual=4))
    result = fit_series(series, config, TrainConfig(iterations=80, batch_size=2048), out, torch.device("cpu"),
                        progress=False)
    model = apmgsrn.load(out)
    description = model.description
    assert description.kind == "series" and description.series.config == config.series
    assert [s.label for s in description.series.steps] == [30, 31, 32, 33]
    assert description.series.steps[2].name == "032_density_032_064_2.0.vti"
    assert description.series.steps[1].value_range == (float(truth[1].min()), float(truth[1].max()))
    assert description.volume_shape == (32, 32, 32) and description.file_bytes == out.stat().st_size
    for step in range(4):
        assert torch.equal(model.field.step_field(step).encoder.grids, result.field.step_field(step).encoder.grids)
    # The per-step figures it saved are what evaluating it again gives, step by step.
    evaluation = evaluate_series(model.field.step_field, truth)
    saved = description.training["steps"]
    for step in range(4):
        direct = evaluate(model.field.step_field(step), truth[step])
        assert evaluation.steps[step].psnr == pytest.approx(direct.psnr)
        assert saved[step]["psnr"] == pytest.approx(direct.psnr, abs=1e-6)
    # Over the whole series: the MSE over every voxel of every step and the range of all of them.
    decoded = np.stack([decode_array(model.field.step_field(t), truth.shape[1:]) for t in range(4)])
    mse = float(np.mean((decoded.astype(np.float64) - truth) ** 2))
    assert evaluation.overall.mse == pytest.approx(mse, rel=1e-6)
    assert evaluation.overall.data_min == float(truth.min()) and evaluation.overall.data_max == float(truth.max())
    data_range = float(truth.max()) - float(truth.min())
    assert evaluation.psnr == pytest.approx(20 * np.log10(data_range) - 10 * np.log10(mse), abs=1e-4)
    assert evaluation.max_abs_error == pytest.approx(float(np.abs(decoded - truth).max()), rel=1e-6)


# ------------------------------------------------------------------------------------------- hostile files
@pytest.fixture()
def series_file(tmp_path) -> Path:
    field = random_field(SeriesConfig(3, 2, "learned", residual=3))
    steps = [SeriesStepInfo(t, f"s{t}.vti", (0.0, 1.0)) for t in range(3)]
    path = tmp_path / "series.apmgsrn"
    save_series(path, field, SourceInfo(path="s0.vti"), {"iterations": 1}, steps)
    return path


def rewrite(path: Path, out: Path, description=None, tensors=None) -> Path:
    with open(path, "rb") as f:
        length = int.from_bytes(f.read(8), "little")
        meta = json.loads(f.read(length))["__metadata__"]
    current = json.loads(meta["description"])
    if description is not None:
        description(current)
    meta["description"] = json.dumps(current)
    stored = load_file(str(path))
    if tensors is not None:
        tensors(stored)
    out.write_bytes(sealed_file_bytes(stored, meta))  # checksums made anew
    return out


@pytest.fixture()
def no_series_built(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a module was built from a file that should have been refused first")
    monkeypatch.setattr(series_module.SeriesField, "__init__", refuse)


def _set(keys, value):
    def mutate(d):
        for key in keys[:-1]:
            d = d[key]
        d[keys[-1]] = value
    return mutate


@pytest.mark.parametrize("case, mutate", [
    ("a million steps", _set(["series", "steps"], 1_000_000)),
    ("more basis grids than stored", _set(["series", "basis"], 3)),
    ("a larger residual", _set(["series", "residual"], 200)),
    ("keyframes (no stored weights)", _set(["series", "coefficients"], "keyframes")),
    ("unknown weights", _set(["series", "coefficients"], "cubic")),
    ("steps list too short", lambda d: d["steps"].pop()),
    ("a step range inverted", _set(["steps", 1, "value_min"], 5.0)),
    ("a step label that is text", _set(["steps", 0, "label"], "zero")),
    ("no series entry", lambda d: d.pop("series")),
    ("an unknown series entry", _set(["series", "splines"], 3)),
    ("a lattice of weights not stored", _set(["series", "mixing"], 2)),
    ("an unknown storage", _set(["series", "storage"], "int4")),
    ("an unknown placement", _set(["series", "placement"], "moving")),
    ("a per-step placement of shared grids", _set(["series", "placement"], "per_step")),
])
def test_malformed_series_files_are_refused_before_building(series_file, tmp_path, no_series_built, case, mutate):
    bad = rewrite(series_file, tmp_path / "bad.apmgsrn", description=mutate)
    with pytest.raises(ApmgsrnError) as caught:
        apmgsrn.load(bad)
    assert "inconsistent" in str(caught.value) and "\n" not in str(caught.value)


def test_non_finite_series_weights_are_refused(series_file, tmp_path):
    def poison(tensors):
        tensors["encoder.coefficients"][1, 0, 0, 0] = float("nan")
    bad = rewrite(series_file, tmp_path / "nan.apmgsrn", tensors=poison)
    with pytest.raises(ApmgsrnError, match="NaN"):
        apmgsrn.load(bad)


def test_a_series_file_is_not_a_single_field_and_old_files_still_load(series_file, tmp_path):
    with pytest.raises(ApmgsrnError, match="not a single model"):
        load_field(series_file)
    single = NeuralField(TINY, volume_shape=(4, 4, 4))
    path = tmp_path / "single.apmgsrn"
    save_field(path, single, SourceInfo(), {})
    model = apmgsrn.load(path)
    assert model.description.kind == "field" and model.description.series is None


def test_a_lattice_of_weights_that_is_constant_mixes_like_one_weight_per_grid():
    plain = random_field(SeriesConfig(5, 3, "learned"))
    lattice = SeriesField(SeriesFieldConfig(TINY, SeriesConfig(5, 3, "learned", mixing=3)))
    with torch.no_grad():
        lattice.load_state_dict({**plain.state_dict(),
                                 "encoder.coefficients": plain.encoder.coefficients[..., None, None, None].expand(
                                     -1, -1, -1, -1, 3, 3, 3).clone()})
        steps = torch.tensor([0, 2, 4])
        assert torch.allclose(lattice.encoder.step_grids(steps), plain.encoder.step_grids(steps), atol=1e-6)
        # A weight changed at one lattice node changes the grid near that node only.
        lattice.encoder.coefficients[2, 0, 0, 1, 0, 0, 0] += 1.0
        difference = lattice.encoder.step_grids(torch.tensor([2]))[0, 0, 0] - plain.encoder.step_grids(
            torch.tensor([2]))[0, 0, 0]  # [D, H, W] of grid 0
        changed = (difference.abs() > 1e-6).nonzero()
        # 8 grid nodes under a lattice of 3: node 0's weight falls to zero at grid node 3.5.
        assert len(changed) == 4**3 and changed.max() == 3


def test_float16_storage_halves_the_grids_and_reloads_what_was_measured(series, truth, tmp_path):
    config = SeriesFieldConfig(TINY, SeriesConfig(4, 2, "learned", residual=3, storage="float16", mixing=2))
    out = tmp_path / "half.apmgsrn"
    result = fit_series(series, config, TrainConfig(iterations=40, batch_size=1024), out, torch.device("cpu"),
                        progress=False)
    stored = load_file(str(out))
    assert stored["encoder.grids"].dtype == torch.float16 and stored["encoder.coefficients"].dtype == torch.float16
    assert stored["encoder.residuals"].dtype == torch.float16 and stored["decoder.0.weight"].dtype == torch.float32
    model = apmgsrn.load(out)
    for step in range(4):
        # The PSNR fit_series reported is the reloaded file's.
        assert evaluate(model.field.step_field(step), truth[step]).psnr == pytest.approx(
            result.evaluation.steps[step].psnr, abs=1e-9)
    full = SeriesFieldConfig(TINY, SeriesConfig(4, 2, "learned", residual=3, mixing=2))
    grid_numbers = sum(v.numel() for k, v in stored.items() if k in ("encoder.grids", "encoder.residuals",
                                                                   "encoder.coefficients"))
    float32_file = tmp_path / "full.apmgsrn"
    save_series(float32_file, SeriesField(full), SourceInfo(), {}, [SeriesStepInfo(t, "", (0.0, 1.0)) for t in range(4)])
    save_series(tmp_path / "half_again.apmgsrn", model.field, SourceInfo(), {},
                [SeriesStepInfo(t, "", (0.0, 1.0)) for t in range(4)])
    # Compare the tensor bytes (the JSON headers differ in length: offsets, value scaling).
    assert _tensor_bytes(float32_file) - _tensor_bytes(tmp_path / "half_again.apmgsrn") == 2 * grid_numbers


def _tensor_bytes(path: Path) -> int:
    """Bytes of a safetensors file after its 8-byte length prefix and JSON header."""
    data = path.read_bytes()
    return len(data) - 8 - int.from_bytes(data[:8], "little")


def test_a_float16_file_claiming_float32_grids_is_refused(series_file, tmp_path):
    bad = rewrite(series_file, tmp_path / "f16.apmgsrn", description=_set(["series", "storage"], "float16"))
    with pytest.raises(ApmgsrnError, match="stored as F32, not F16"):
        apmgsrn.load(bad)


def test_the_python_api_decodes_any_step_and_saves_a_series_model(series_file, tmp_path):
    model = apmgsrn.load(series_file)
    shape = model.description.volume_shape
    for time in (None, 2):
        expected = decode_array(model.field.step_field(time or 0), shape)
        np.testing.assert_array_equal(np.asarray(model.decode(time=time)), expected)
    with pytest.raises(ApmgsrnError, match=r"time=3: the model holds 3 time steps \(time=0..2\)"):
        model.decode(time=3)
    copy = model.save(tmp_path / "copy.apmgsrn")
    again = apmgsrn.load(copy)
    assert again.description.series == model.description.series
    np.testing.assert_array_equal(np.asarray(again.decode(time=1)), np.asarray(model.decode(time=1)))
    other = tmp_path / "other.npy"
    other.write_bytes(b"not a model")
    with pytest.raises(ApmgsrnError, match="never overwritten"):
        again.save(other)
    assert other.read_bytes() == b"not a model"
