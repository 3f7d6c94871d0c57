"""Packed time-series model files (series/packed_file.py, series/packing.py, ``apmgsrn pack`` of a series):
the ``time`` predictor, what is written loads back into exactly the field the packer measured, close steps code
smaller along time, hostile files are one-line errors before anything large is allocated. Real data: the four
consecutive viscous-fingering steps of tests/data, fitted by a short loop here (every step's own grids, started
from the same grids, as a step-by-step training leaves them close)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.series.data import open_series
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.io import SeriesStepInfo, SourceInfo, codec, model_kind, open_model, save_field
from apmgsrn.io.container import PACKED_SERIES_KIND, check_replaceable, file_bytes
from apmgsrn.io.packed import encode_quantized, payload_file_bytes, read_payload_file
from apmgsrn.io.quantization import quantize
from apmgsrn.series.file import declared_steps
from apmgsrn.series.evaluate import evaluate_series
from apmgsrn.series.file import save_series
from apmgsrn.series import field as series_module
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.series.field import SeriesConfig, SeriesField, SeriesFieldConfig
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.training.packing import group_means
from apmgsrn.series.packing import (
    pack_series,
    packed_series_field,
    series_overhead,
    sensitivity_steps,
    series_sensitivity,
    shared_steps,
    write_packed_series,
)

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), width=16)


@pytest.fixture(scope="module")
def pattern(test_data) -> str:
    """The four steps, as the command line names them."""
    return str(test_data / "viscous_fingers_run01" / "*.vti")


@pytest.fixture(scope="module")
def field(pattern) -> SeriesField:


    """A series field with every step's own grids (keyframes, K = T) fitted to the real steps as a step-by-step
    training does: step 0 first, then every step's grids, started from step 0's, fine-tuned (so consecutive
    steps stay close). About 41 dB on every step."""
    truth = open_series(pattern).to_numpy()  # [4, 32, 32, 32]
    steps = truth.shape[0]
    low, high = float(truth.min()), float(truth.max())
    config = SeriesFieldConfig(TINY, SeriesConfig(steps=steps, basis=steps, coefficients="keyframes"))
    field = SeriesField(config, fit_min=low, fit_max=high, volume_shape=truth.shape[1:],
                        generator=torch.Generator().manual_seed(0))
    values = torch.from_numpy((truth - low) / (high - low))  # [T, D, H, W] in [0, 1]
    generator = torch.Generator().manual_seed(1)

    def fit(which: list[int], iterations: int, lr: float) -> None:
        optimizer = torch.optim.Adam(field.parameters(), lr=lr)
        for _ in range(iterations):
            points = torch.rand(len(which), 512, 3, generator=generator) * 2 - 1  # [G, n, 3]
            target = torch.cat([sample_volume(values[t], group) for t, group in zip(which, points)])
            loss = (field.normalized(points.view(-1, 3), torch.tensor(which)).view(-1) - target).square().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

    fit([0], 150, 0.01)
    with torch.no_grad():
        field.encoder.grids[1:] = field.encoder.grids[0]
    fit(list(range(steps)), 100, 0.003)
    return field.eval()


def step_entries(steps: int) -> list[SeriesStepInfo]:
    return [SeriesStepInfo(30 + t, f"step{t}.vti", (0.0, 1.0)) for t in range(steps)]


@pytest.fixture(scope="module")
def packed_file(field, tmp_path_factory):
    """(path, PackedSeries) of the fitted field at 8 bits."""
    packed = pack_series(field, 8)
    path = tmp_path_factory.mktemp("packed_series") / "p.apmgsrn"
    write_packed_series(path, field, packed, SourceInfo(path="step0.vti"), {"iterations": 150, "history": {"a": [1.0]}},
                        step_entries(field.steps), {"mode": "bits", "bits": 8})
    return path, packed


# ------------------------------------------------------------------------------------------ the time predictor
def test_the_time_predictor_is_the_difference_along_the_first_axis_and_round_trips():
    rng = np.random.default_rng(0)
    for shape in ((2, 3, 4, 5), (5, 2, 3, 4, 4, 4)):
        levels = rng.integers(-300, 300, size=shape)
        residuals = codec.predict(levels.reshape(-1), shape, "time")
        assert np.array_equal(residuals.reshape(shape)[1:], np.diff(levels, axis=0))
        assert np.array_equal(residuals.reshape(shape)[0], levels[0])
        assert np.array_equal(codec.reconstruct(residuals, shape, "time"), levels.reshape(-1))
    # Offered for series tensors with a time axis only; single fields' choices are unchanged.
    assert "time" in codec.series_predictors_for((4, 2, 1, 8, 8, 8))
    assert "time" not in codec.series_predictors_for((1, 2, 1, 8, 8, 8))  # one basis grid
    assert "time" in codec.series_predictors_for((4, 8192))  # a hybrid's level tables, one row per step
    assert "time" not in codec.series_predictors_for((4,))  # no axis besides time
    assert codec.predictors_for((4, 2, 8, 8, 8)) == ("none", "delta", "lorenzo")


def test_grid_steps_are_shared_by_every_step_of_a_grid_and_channel(field):
    grids = field.encoder.grids.detach().numpy()  # [K, M, C, D, H, W]
    steps, group = shared_steps(grids, 8)
    k, m, c = grids.shape[:3]
    assert group == 8**3 and steps.shape == (k * m * c,)
    per_channel = steps.reshape(k, m * c)
    assert (per_channel == per_channel[0]).all()
    # The largest magnitude over the steps fits in 8 signed bits, and not in 7.
    levels = quantize(grids, steps, group).levels
    assert np.abs(levels).max() == 127


# ------------------------------------------------------------------------------------------ round trip
def test_a_packed_series_loads_into_the_field_the_packer_measured(field, packed_file, pattern):
    path, packed = packed_file
    model = open_model(path)
    description = model.description
    assert description.kind == "packed-series" and model_kind(path) == "packed-series"
    assert declared_steps(path) == 4
    for name, value in model.field.state_dict().items():
        assert torch.equal(value, packed.state[name]), name
    in_memory = packed_series_field(field, packed)
    points = torch.rand(20_000, 3) * 2 - 1
    with torch.no_grad():
        for t in range(field.steps):
            assert torch.equal(model.field.step_field(t)(points), in_memory.step_field(t)(points))
    # The series' layout and every byte of the file are accounted for.
    assert [s.label for s in description.series.steps] == [30, 31, 32, 33]
    assert description.series.config == field.config.series and description.volume_shape == (32, 32, 32)
    packing = description.packing
    assert sum(p.bytes for p in packing.parts) + packing.container_bytes == path.stat().st_size
    assert [p.name for p in packing.parts] == ["description", *field.config.parameter_shapes()]
    assert "history" not in description.training
    # What 8 bits cost on the real steps.
    truth = open_series(pattern)
    before = evaluate_series(field.step_field, truth)
    after = evaluate_series(model.field.step_field, truth)
    assert before.psnr > 38 and -0.05 < before.psnr - after.psnr < 0.2
    # The Python API saves it back as a float32 series file, which loads to the same values.
    saved = apmgsrn.load(path).save(path.with_name("float32.apmgsrn"))
    again = apmgsrn.load(saved)
    assert again.description.kind == "series"
    assert all(torch.equal(v, packed.state[k]) for k, v in again.field.state_dict().items())


def test_close_steps_code_smaller_along_time(field):
    grids = field.encoder.grids.detach()
    quantized = quantize(grids, *shared_steps(grids.numpy(), 8))
    along_time = encode_quantized("encoder.grids", quantized, ("time",))
    spatial = encode_quantized("encoder.grids", quantized, codec.predictors_for(quantized.shape))
    assert len(along_time.data) < 0.85 * len(spatial.data)  # measured 0.79 (the first step costs in full)
    assert pack_series(field, 8).tensors[0].predictor == "time"


def test_fewer_bits_give_fewer_grid_bytes_and_bits_are_checked(field):
    sizes = {bits: len(pack_series(field, bits).tensors[0].data) for bits in (8, 10)}
    assert sizes[8] < sizes[10]
    for bits in (1, 17, 32, 8.0):
        with pytest.raises(InvalidArgument, match="bits"):
            pack_series(field, bits)
    finer = len(pack_series(field, 8, finer=0.5).tensors[0].data)
    assert sizes[8] < finer < sizes[10]  # half a bit finer than 8 bits: more bytes, fewer than 10 bits take
    for bad in (-0.1, 1.0):
        with pytest.raises(InvalidArgument, match="finer"):
            pack_series(field, 8, finer=bad)


def test_residual_grids_are_packed_too(field, tmp_path):
    config = SeriesFieldConfig(TINY, SeriesConfig(steps=4, basis=2, coefficients="learned", residual=4))
    series = SeriesField(config, volume_shape=(32, 32, 32), generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        series.encoder.residuals.normal_(0, 0.01, generator=torch.Generator().manual_seed(3))
    packed = pack_series(series, 10)
    encodings = {t.name: t.encoding for t in packed.tensors}
    assert encodings["encoder.residuals"] == "quantized" and encodings["encoder.coefficients"] == "float32"
    path = tmp_path / "r.apmgsrn"
    write_packed_series(path, series, packed, SourceInfo(), {}, step_entries(4), {})
    loaded = apmgsrn.load(path).field
    assert all(torch.equal(v, packed.state[k]) for k, v in loaded.state_dict().items())


def test_series_kinds_replace_each_other_but_never_a_single_model(field, packed_file, tmp_path):
    path, packed = packed_file
    series_path = tmp_path / "s.apmgsrn"
    save_series(series_path, field, SourceInfo(), {}, step_entries(4))
    write_packed_series(series_path, field, packed, SourceInfo(), {}, step_entries(4), {})  # series -> packed
    assert model_kind(series_path) == "packed-series"
    save_series(series_path, field, SourceInfo(), {}, step_entries(4))  # packed -> series
    assert model_kind(series_path) == "series"
    single = tmp_path / "f.apmgsrn"
    save_field(single, NeuralField(TINY, volume_shape=(8, 8, 8)), SourceInfo(), {})
    with pytest.raises(ApmgsrnError, match="never overwritten"):
        write_packed_series(single, field, packed, SourceInfo(), {}, step_entries(4), {})
    with pytest.raises(ApmgsrnError, match="never overwritten"):
        check_replaceable(path, "field")


# ------------------------------------------------------------------------------------------ hostile files
def file_parts(path) -> tuple[dict, list[bytes]]:
    """The description and the parameter sections of a packed file."""
    file = read_payload_file(path, model_kind(path), "a packed model")
    return file.description, list(file.chunks[1:])


def write_parts(path, description: dict, sections: list[bytes], kind: str = PACKED_SERIES_KIND,
                sizes: list[int] | None = None):
    """A packed file of these parts; ``sizes``: the section sizes to declare instead of the true ones."""
    if sizes is None:
        path.write_bytes(payload_file_bytes(kind, description, sections))
        return path
    parts = [codec.compress_description(json.dumps(description).encode()), *sections]
    payload = torch.frombuffer(bytearray(b"".join(parts)), dtype=torch.uint8)
    path.write_bytes(file_bytes({"payload": payload}, kind, {"sections": sizes, "coding": codec.DESCRIPTION_CODING}))
    return path


def _set(keys, value):
    def mutate(description, sections):
        target = description
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value
    return mutate


def _section(index, change):
    def mutate(description, sections):
        sections[index] = change(sections[index])
    return mutate


HOSTILE = {
    "grid section truncated": (_section(0, lambda b: b[: len(b) // 2]), "corrupt|inconsistent"),
    "grid section corrupt": (_section(0, lambda b: b[:40] + bytes(len(b) - 40)), "corrupt"),
    "steps NaN": (_section(0, lambda b: b"\x00\x7e" + b[2:]), "not positive and finite"),
    "steps zero": (_section(0, lambda b: b"\x00\x00" + b[2:]), "not positive and finite"),
    "a million steps": (_set(["series", "steps"], 1 << 20), "inconsistent"),
    "4096 basis grids": (lambda d, s: (_set(["series", "steps"], 4096)(d, s), _set(["series", "basis"], 4096)(d, s)),
                         "inconsistent"),
    "resolution 300^3": (_set(["field", "encoder", "resolution"], [300, 300, 300]), "inconsistent"),
    "predictor unknown": (_set(["tensors", 0, 2], "exec"), "unknown predictor"),
    "time on the grid maps": (_set(["tensors", 1], ["quantized", 36, "time", 1]), "unknown predictor"),
    "steps list short": (lambda d, s: d["steps"].pop(), "inconsistent"),
    "series kind unknown": (_set(["series", "coefficients"], "pickle"), "inconsistent"),
    "a tensor fewer": (lambda d, s: d["tensors"].pop(), "inconsistent"),
    "width 3": (_set(["tensors", 0, 3], 3), "inconsistent"),
}


@pytest.fixture()
def no_series_built(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a series field was built from a file that should have been refused first")
    monkeypatch.setattr(series_module.SeriesField, "__init__", refuse)


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_packed_series_files_are_one_line_errors(packed_file, tmp_path, case, capsys, no_series_built):
    description, sections = file_parts(packed_file[0])
    mutate, message = HOSTILE[case]
    mutate(description, sections)
    hostile = write_parts(tmp_path / "h.apmgsrn", description, sections)
    with pytest.raises(ApmgsrnError, match=message):
        apmgsrn.load(hostile)
    assert main(["info", str(hostile)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_section_sizes_that_disagree_with_the_payload_are_refused(packed_file, tmp_path, no_series_built):
    description, sections = file_parts(packed_file[0])
    true = [len(codec.compress_description(json.dumps(description).encode())), *map(len, sections)]
    for sizes in ([*true[:-1], true[-1] + 1], true[:-1], [-1, *true[1:]], []):
        hostile = write_parts(tmp_path / "h.apmgsrn", description, sections, sizes=sizes)
        with pytest.raises(ApmgsrnError, match="not an apmgsrn model file|inconsistent"):
            apmgsrn.load(hostile)


def test_a_packed_single_field_may_not_name_the_time_predictor(tmp_path):
    from apmgsrn.io.packed import packed_file_bytes
    from apmgsrn.training.packing import bits_quantizer, encode_field

    single = NeuralField(TINY, volume_shape=(8, 8, 8), generator=torch.Generator().manual_seed(0))
    tensors, _ = encode_field(single, bits_quantizer(single, 8))
    good = tmp_path / "good.apmgsrn"
    good.write_bytes(packed_file_bytes(single, tensors, SourceInfo(), {}, {}))
    description, sections = file_parts(good)
    assert apmgsrn.load(good).description.kind == "packed-field"
    description["tensors"][0][2] = "time"  # the grids [M, C, D, H, W]: 5-D, M > 1, yet not a time axis
    hostile = write_parts(tmp_path / "h.apmgsrn", description, sections, kind="packed-field")
    with pytest.raises(ApmgsrnError, match="unknown predictor"):
        apmgsrn.load(hostile)


# ------------------------------------------------------------------------------------------ command line
def run_json(argv, capsys) -> tuple[int, dict]:
    capsys.readouterr()
    code = main([*argv, "--json"])
    return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_pack_info_and_eval_of_a_series_model(field, pattern, tmp_path, capsys):
    float32 = tmp_path / "s.apmgsrn"
    save_series(float32, field, SourceInfo(path="step0.vti"), {"iterations": 150}, step_entries(4))
    out = tmp_path / "p.apmgsrn"
    code, packed = run_json(["pack", str(float32), pattern, "--out", str(out)], capsys)
    assert code == 0 and packed["bits"] == 10 and packed["file_bytes"] == out.stat().st_size
    assert abs(packed["psnr_cost"]) < 0.02 and len(packed["per_step"]) == 4
    assert out.stat().st_size * 2 < float32.stat().st_size
    code, info = run_json(["info", str(out)], capsys)
    assert code == 0 and info["series"]["steps"] == 4
    assert sum(p["bytes"] for p in info["packing"]["parts"]) + info["packing"]["container_bytes"] == out.stat().st_size
    # info's per-step PSNR is the packed model's, as eval measures it again.
    code, figures = run_json(["eval", str(out), pattern], capsys)
    assert code == 0 and figures["psnr"] == pytest.approx(packed["psnr"], abs=1e-3)
    for row, step in zip(figures["per_step"], info["series"]["per_step"]):
        assert row["psnr"] == pytest.approx(step["psnr"], abs=1e-6)
    assert main(["info", str(out)]) == 0 and "time        4 steps" in capsys.readouterr().out


def test_pack_a_series_to_a_size_takes_the_finest_steps_that_fit(field, pattern, tmp_path, capsys):
    """A size between what 7 and 8 bits take: the largest whole width that fits (7), its steps then made finer
    by sixteenths of a bit as far as the size allows (how many follows the values' coding); the file fits, and the
    next sixteenth would not."""
    float32 = tmp_path / "s.apmgsrn"
    save_series(float32, field, SourceInfo(), {}, step_entries(4))
    sensitivity = series_sensitivity(field)
    sizes = {bits: pack_series(field, bits, sensitivity).parameter_bytes for bits in (7, 8)}
    loaded = apmgsrn.load(float32)  # the description and framing a target allows for, as pack measures them
    overhead = series_overhead(loaded.field, loaded.description.source, loaded.description.training,
                               list(loaded.description.series.steps))
    budget = (sizes[7] + sizes[8]) // 2 + overhead
    code, packed = run_json(["pack", str(float32), pattern, "--out", str(tmp_path / "p.apmgsrn"),
                             "--size", str(budget)], capsys)
    assert code == 0 and 7 <= packed["bits"] < 8 and packed["file_bytes"] <= budget
    report = apmgsrn.load(tmp_path / "p.apmgsrn").description.packing.report
    assert report["target_bytes"] == budget and report["bits"] == packed["bits"]
    refined = pack_series(field, 7, sensitivity, packed["bits"] - 7)
    assert sizes[7] <= refined.parameter_bytes <= budget - overhead
    # Within a sixteenth of a bit of the finest that fits.
    assert pack_series(field, 7, sensitivity, packed["bits"] - 7 + 1 / 16).parameter_bytes > budget - overhead


@pytest.mark.parametrize("options, message", [
    (["--size", "1000", "--ratio", "10"], "--size and --ratio both set the file size"),
    (["--max-error", "0.1"], "--max-error: a time series packs to a bit width or a size only"),
    (["--size", "2000"], r"--size 2000: the series' parameters alone take .* bytes even at 2 bits"),
    (["--bits", "1"], "--bits"),
    (["--bits", "32"], "--bits"),
    (["--qat-iterations", "20"], "does not record its training settings, which a quantisation-aware fine-tune"),
    (["--decoder-iterations", "20"], "does not record its training settings, which the decoder's fine-tune"),
])
def test_pack_options_that_do_not_apply_to_a_series_exit_2(field, pattern, tmp_path, capsys, options, message):
    float32 = tmp_path / "s.apmgsrn"
    save_series(float32, field, SourceInfo(), {}, step_entries(4))
    capsys.readouterr()
    assert main(["pack", str(float32), pattern, "--out", str(tmp_path / "p.apmgsrn"), *options]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(message, err)
    assert not (tmp_path / "p.apmgsrn").exists()


# ------------------------------------------------------------------------------------------ hybrid series
@pytest.fixture(scope="module")
def hybrid_series(pattern) -> SeriesField:
    """A stepwise series of tiny hybrid models of the four real steps (about 37 dB)."""
    from apmgsrn.training.fit import prepare_values
    from apmgsrn.series.steps import StepwiseConfig, stepwise_config, train_stepwise
    from apmgsrn.training.trainer import TrainConfig

    prepared = prepare_values(open_series(pattern).to_numpy(), "none", 0.0, "viscous fingers", torch.device("cpu"))
    tiny = preset_config("hybrid", "small", levels=6, log2_table_size=10, grids=4, resolution=8, width=16)
    return train_stepwise(prepared, stepwise_config(tiny, 4), TrainConfig(iterations=150, batch_size=2048,
                          voxel_fraction=0.5), (32, 32, 32), stepwise=StepwiseConfig(start=1),
                          show_progress=False).field


def test_a_hybrid_series_codes_its_tables_along_time_and_loads_back(hybrid_series, pattern, tmp_path):
    """A stepwise series of hybrid models: its level tables and grids take one step per group shared by
    every time step, the level tables are coded along time, and the file loads into the field the packer
    measured, 10 bits costing at most 0.1 dB on the real steps."""
    truth = open_series(pattern)
    field = hybrid_series
    packed = pack_series(field, 10)
    by_name = {t.name: t for t in packed.tensors}
    assert by_name["encoder.level_table"].predictor == "time"
    for name, group in (("encoder.grids", 8**3), ("encoder.level_table", None)):  # one grid; runs of a table
        steps, size = shared_steps_of(field, name)
        assert group is None or size == group
        assert (steps.reshape(4, -1) == steps.reshape(4, -1)[0]).all()  # the same step at every time step
    path = tmp_path / "h.apmgsrn"
    write_packed_series(path, field, packed, SourceInfo(path="step0.vti"), {"iterations": 150},
                        step_entries(4), {"mode": "bits", "bits": 10})
    model = open_model(path)
    assert model.description.config.model == "hybrid" and model.description.kind == "packed-series"
    for name, value in model.field.state_dict().items():
        assert torch.equal(value, packed.state[name]), name
    before = evaluate_series(field.step_field, truth)
    after = evaluate_series(model.field.step_field, truth)
    assert before.psnr > 35 and -0.05 < before.psnr - after.psnr < 0.1  # 37.2 dB after this short fit
    # Between two steps a hybrid series interpolates the two steps' values (their grids sit apart).
    points = torch.rand(1000, 3) * 2 - 1
    with torch.no_grad():
        halfway = model.field(torch.cat([points, torch.full((1000, 1), -1 + 2 * 0.5 / 3)], dim=1))
        expected = (model.field.step_field(0)(points) + model.field.step_field(1)(points)) / 2
    assert torch.allclose(halfway, expected, atol=1e-5)


def test_steps_that_follow_the_output_lose_less_than_uniform_ones_in_about_the_same_bytes(hybrid_series,
                                                                                         pattern):
    """Sensitivity-allocated shared steps: finer where an element moves the output more (the coarse levels of
    the table, whose entries each reach many voxels), the same mean log2 step as the uniform ones of the bit
    width, and on the real steps a smaller PSNR cost for about the same bytes."""
    from apmgsrn.series.packing import series_sensitivity, slice_group

    field, truth = hybrid_series, open_series(pattern)
    sensitivity = series_sensitivity(field)
    assert set(sensitivity) == {"encoder.level_table", "encoder.grids"}
    before = evaluate_series(field.step_field, truth).psnr
    costs, sizes = {}, {}
    for label, given in (("uniform", None), ("sensitivity", sensitivity)):
        packed = pack_series(field, 4, given)
        restored = packed_series_field(field, packed)
        costs[label] = before - evaluate_series(restored.step_field, truth).psnr
        sizes[label] = packed.parameter_bytes
    # 4 bits on this tiny series: 1.12 dB against 1.75 (3 to 8 bits: 40-60 % of the uniform cost, bytes +-1 %)
    assert costs["sensitivity"] < 0.8 * costs["uniform"]
    assert sizes["sensitivity"] < 1.05 * sizes["uniform"]
    # Steps per group follow 1 / sqrt(sensitivity): the most sensitive run of the table gets the finest step.
    table = dict(field.named_parameters())["encoder.level_table"].detach().numpy()
    uniform, group = shared_steps(table, 4, slice_group("hybrid", "encoder.level_table", table.shape))
    allocated = sensitivity_steps({"encoder.level_table": (uniform, group)},
                                  {"encoder.level_table": sensitivity["encoder.level_table"]})
    steps = allocated["encoder.level_table"][: len(uniform) // field.steps].astype(np.float64)
    means = group_means(sensitivity["encoder.level_table"], group)
    assert np.argmin(steps) == np.argmax(means) and np.argmax(steps) == np.argmin(means)
    weight = np.log2(steps).mean() - np.log2(uniform[: len(steps)].astype(np.float64)).mean()
    assert abs(weight) < 0.01  # one tensor: the same mean log2 step (float16 rounding aside)


def test_the_sensitivity_of_some_parameters_is_theirs_among_all(hybrid_series):
    """Asked for the per-step tensors only, the sensitivity is what it is among every parameter's: the grid
    placement then takes no gradient, so the level tables' backward runs through the fused kernel where it can,
    and its sums match the autograd reference's."""
    from apmgsrn.training.packing import parameter_sensitivity
    from apmgsrn.series.packing import SHARED_STEP_TENSORS

    step = hybrid_series.step_field(2)
    before = [p.requires_grad for p in step.parameters()]
    every = parameter_sensitivity(step, 1 << 14)
    some = parameter_sensitivity(step, 1 << 14, names=SHARED_STEP_TENSORS)
    assert set(some) == set(SHARED_STEP_TENSORS) and len(every) > len(some)
    for name in SHARED_STEP_TENSORS:
        assert some[name].max() > 0
        np.testing.assert_allclose(some[name], every[name], rtol=1e-3, atol=1e-6 * every[name].max())
    assert [p.requires_grad for p in step.parameters()] == before  # left as they were


def test_a_size_search_codes_its_trials_with_the_first_ones_predictors_and_keeps_the_smallest(hybrid_series):
    """``pack_series(predictors=...)`` codes a tensor with those predictors only (never smaller than the best of
    all); a size target's search takes its trials that way and codes the width it keeps with every predictor
    again: the packing kept is the unrestricted one of its width, and fits."""
    from apmgsrn.series.packing import SeriesPacking, chosen_predictors

    field = hybrid_series
    sensitivity = series_sensitivity(field)
    free = pack_series(field, 6, sensitivity)
    assert chosen_predictors(free)["encoder.level_table"] == ("time",)
    forced = pack_series(field, 6, sensitivity, predictors={"encoder.level_table": ("none",)})
    table = {t.name: t for t in forced.tensors}["encoder.level_table"]
    assert table.predictor == "none" and forced.parameter_bytes > free.parameter_bytes
    target = (pack_series(field, 6, sensitivity).parameter_bytes + pack_series(field, 7, sensitivity).parameter_bytes
              ) // 2 + series_overhead(field)
    kept = SeriesPacking(8, target, 4).pack(field)
    assert kept.bits == 6 and 0 <= kept.finer < 1  # 6 fits, 7 does not; the sixteenths follow the coding
    again = pack_series(field, kept.bits, sensitivity, kept.finer)
    assert kept.parameter_bytes == again.parameter_bytes <= target - series_overhead(field)
    assert [t.predictor for t in kept.tensors] == [t.predictor for t in again.tensors]


@pytest.mark.parametrize("between", [(5, 6, 0.5), (6, 7, 0.1), (6, 7, 0.9), (8, 9, 0.3)])
def test_a_size_search_takes_the_finest_sixteenth_of_a_bit_that_fits_in_few_trials(hybrid_series, monkeypatch,
                                                                                     between):
    """Targets between two whole widths (near either end or the middle, far below the top): the width kept
    fits, the next sixteenth of a bit does not, and the search coded fewer trials than a bisection of the
    lattice would (the 96 sixteenths from 4 bits to 10 take it 7; besides the top and the width kept)."""
    from apmgsrn.series import packing as series_packing
    from apmgsrn.series.packing import SeriesPacking

    field = hybrid_series
    sensitivity = series_sensitivity(field)
    lower, upper, share = between
    sizes = [pack_series(field, bits, sensitivity).parameter_bytes for bits in (lower, upper)]
    target = round(sizes[0] + share * (sizes[1] - sizes[0])) + series_overhead(field)
    budget = target - series_overhead(field)
    trials = []
    original = series_packing.pack_series
    monkeypatch.setattr(series_packing, "pack_series",
                        lambda *a, **k: trials.append(k.get("predictors")) or original(*a, **k))
    kept = SeriesPacking(10, target, 4).pack(field)
    monkeypatch.setattr(series_packing, "pack_series", original)
    assert lower <= kept.bit_width < upper and kept.parameter_bytes <= budget
    finer = kept.bit_width + 1 / 16
    assert pack_series(field, int(finer), sensitivity, finer - int(finer)).parameter_bytes > budget
    assert len([t for t in trials if t is not None]) <= 6


def test_a_size_search_where_not_even_the_fewest_bits_fit(hybrid_series):
    """Strict: one line naming what the fewest bits take; otherwise packed at the fewest bits anyway."""
    from apmgsrn.series.packing import SeriesPacking

    field = hybrid_series
    fewest = pack_series(field, 5, series_sensitivity(field))
    with pytest.raises(InvalidArgument, match=f"take {fewest.parameter_bytes:,} bytes even at 5 bits"):
        SeriesPacking(10, 1000, 5).pack(field)
    loose = SeriesPacking(10, 1000, 5, strict=False).pack(field)
    assert loose.bit_width == 5 and loose.parameter_bytes == fewest.parameter_bytes


def shared_steps_of(field, name):
    from apmgsrn.series.packing import slice_group

    values = dict(field.named_parameters())[name].detach().numpy()
    return shared_steps(values, 10, slice_group(field.config.field.model, name, values.shape))


def test_the_default_packing_is_sized_by_the_stored_single_step_file_and_keeps_a_hybrid_at_7_bits():
    """``train``'s default: within five single-step files of the preset as stored (a hybrid's float16 tables at
    2 bytes a value) up to 30 steps, in proportion beyond, lowering the bit width to 6 for APMGSRN, never below 7
    for the hybrid (its pulled tables lose about 0.45 dB at 7 bits on the viscous-finger steps and 1.7 at 6)."""
    import math

    from apmgsrn.models.registry import stored_bytes
    from apmgsrn.series.packing import default_series_packing
    from apmgsrn.series.steps import stepwise_config

    shape = (64, 64, 64)
    for kind, lowest in (("apmgsrn", 6), ("hybrid", 7)):
        single = preset_config(kind, "small")
        packing = default_series_packing(stepwise_config(single, 30), shape, 2000)
        fitted = single.fitted_to(shape)
        assert packing.target_bytes == 5 * stored_bytes(fitted) and packing.bits == 10
        assert packing.min_bits == lowest and not packing.strict
        # fine-tuned towards the packing first: the hybrid's steps, 250 iterations after the start model's 2,000
        assert packing.qat_iterations == (250 if kind == "hybrid" else 0)
        assert default_series_packing(stepwise_config(single, 3), shape, 2000).target_bytes == packing.target_bytes
        assert default_series_packing(stepwise_config(single, 60), shape, 2000).target_bytes == \
            10 * stored_bytes(fitted)
    hybrid = preset_config("hybrid", "small").fitted_to(shape)
    values = sum(math.prod(s) for s in hybrid.parameter_shapes().values())
    assert 2 * values < stored_bytes(hybrid) < 3 * values  # float16 tables, float32 decoder and placement
