"""The quantisation-aware fine-tune of a stepwise series (series/qat.py): every step's grids trained
towards the steps the packed file rounds them to, on the real viscous-finger steps in tests/data."""

from __future__ import annotations

import copy
import json
import types
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.series.data import open_series
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.recipes import HYBRID, PACKING, SERIES
from apmgsrn.training.fit import prepare_values
from apmgsrn.series.decoder import fine_tune_decoder
from apmgsrn.series.fit import fit_series
from apmgsrn.series.evaluate import evaluate_series
from apmgsrn.series.packing import (
    SeriesPacking,
    default_series_decoder,
    default_series_qat,
    pack_series,
    packed_series_field,
    series_overhead,
    series_sensitivity,
)
from apmgsrn.series.qat import (
    RoundedForward,
    element_steps,
    fine_tune_rounded,
    qat_lanes,
    stored_train_config,
)
from apmgsrn.series.steps import StepwiseConfig, step_voxel_fraction, stepwise_config, train_stepwise
from apmgsrn.training.trainer import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_HYBRID = dict(levels=6, log2_table_size=10, grids=4, resolution=8, width=16)
CONFIG = TrainConfig(iterations=150, batch_size=2048, voxel_fraction=0.5, error_sampling=1.0)


@pytest.fixture(scope="module")
def pattern(test_data) -> str:
    return str(test_data / "viscous_fingers_run01" / "*.vti")


@pytest.fixture(scope="module")
def prepared(pattern):
    return prepare_values(open_series(pattern).to_numpy(), "none", 0.0, "viscous fingers", torch.device("cpu"))


@pytest.fixture(scope="module")
def hybrid_series(prepared):
    """A stepwise series of tiny hybrid models of the four real steps, float32."""
    tiny = preset_config("hybrid", "small", **TINY_HYBRID)
    return train_stepwise(prepared, stepwise_config(tiny, 4), CONFIG, (32, 32, 32), stepwise=StepwiseConfig(start=1),
                          show_progress=False).field


def file_bytes_for(parameter_bytes: int, field) -> int:
    """The file size whose packing budget for the series ``field`` (what its description and framing leave:
    series_overhead) is ``parameter_bytes``."""
    return parameter_bytes + series_overhead(field)


def test_packing_on_the_steps_a_packing_used_gives_the_same_file(hybrid_series):
    """PackedSeries.steps are the steps that were used: packing on them again reproduces every section."""
    packed = pack_series(hybrid_series, 6, series_sensitivity(hybrid_series), finer=0.5)
    assert set(packed.steps) == {"encoder.level_table", "encoder.grids"}
    again = pack_series(hybrid_series, 6, finer=0.5, steps=packed.steps)
    assert [t.data for t in again.tensors] == [t.data for t in packed.tensors]
    assert all(torch.equal(again.state[name], value) for name, value in packed.state.items())


def test_rounded_forward_computes_with_rounded_values_and_updates_the_floats():
    """Straight-through: the parameter holds step * round(x / step) while training; what the optimiser adds to
    it is added to x; at the end the parameter holds x."""
    step = torch.tensor([0.5, 0.25])
    parameter = torch.nn.Parameter(torch.tensor([0.3, 0.3]))
    rounded = RoundedForward([parameter], [step])
    rounded.on_start(None)
    assert torch.equal(parameter.detach(), torch.tensor([0.5, 0.25]))
    with torch.no_grad():
        parameter -= torch.tensor([0.1, 0.1])  # an optimiser's update
    rounded.after_step(None, 1, None)
    assert torch.allclose(rounded.floats[0], torch.tensor([0.2, 0.2]))
    assert torch.equal(parameter.detach(), torch.tensor([0.0, 0.25]))  # round(0.4) * 0.5, round(0.8) * 0.25
    rounded.on_end(None)
    assert torch.allclose(parameter.detach(), torch.tensor([0.2, 0.2]))


def test_element_steps_give_every_element_its_groups_step(hybrid_series):
    packed = pack_series(hybrid_series, 6, series_sensitivity(hybrid_series))
    steps = element_steps(hybrid_series, packed)
    table = hybrid_series.encoder.level_table
    assert steps["level_table"].shape == table.shape[1:]
    # Quantising one step's slice element-wise gives what the packer stored for that step.
    for t in range(hybrid_series.steps):
        rounded = torch.round(table[t].detach() / steps["level_table"]) * steps["level_table"]
        assert torch.allclose(rounded, packed.state["encoder.level_table"][t], atol=1e-6)


def test_a_quantisation_aware_fine_tune_lowers_what_packing_costs_on_the_real_steps(hybrid_series, prepared,
                                                                                       pattern):
    """At 5 bits every step, fine-tuned towards its rounded grids and packed on the same steps, ends closer to the
    data than the same field packed without it, in about the same bytes."""
    truth = open_series(pattern)
    packing = SeriesPacking(5, min_bits=5)
    packed = packing.pack(hybrid_series)
    plain = evaluate_series(packed_series_field(hybrid_series, packed).step_field, truth)
    tuned = copy.deepcopy(hybrid_series)
    ran, seconds = fine_tune_rounded(tuned, prepared.values, packed, CONFIG, 40, show_progress=False)
    assert ran == 40 * 4 and seconds > 0
    repacked = packing.repack(tuned, packed)
    assert repacked.steps.keys() == packed.steps.keys()
    assert all(np.array_equal(repacked.steps[k], packed.steps[k]) for k in packed.steps)
    after = evaluate_series(packed_series_field(tuned, repacked).step_field, truth)
    assert after.psnr > plain.psnr + 0.3
    assert all(a.psnr > p.psnr for a, p in zip(after.steps, plain.steps))
    assert repacked.parameter_bytes < 1.1 * packed.parameter_bytes
    # The decoder and the placement are what they were.
    for name, value in hybrid_series.state_dict().items():
        if "decoder" in name or name in ("encoder.matrices", "encoder.translations"):
            assert torch.equal(value, tuned.state_dict()[name]), name


def test_the_fine_tune_towards_the_packing_draws_its_points_as_the_steps_do(hybrid_series, prepared, monkeypatch):
    """Every step's fine-tune towards the packing draws as many of its points between the voxels as the steps'
    own fine-tunes (half the start model's share), for the iterations asked."""
    from apmgsrn.series import qat as series_qat

    seen = []

    class Spy(series_qat.Trainer):
        def __init__(self, field, values, config, *args, **kwargs):
            seen.append(config)
            super().__init__(field, values, config, *args, **kwargs)

    monkeypatch.setattr(series_qat, "Trainer", Spy)
    packed = pack_series(hybrid_series, 5, series_sensitivity(hybrid_series))
    fine_tune_rounded(copy.deepcopy(hybrid_series), prepared.values, packed, CONFIG, 3, show_progress=False)
    assert len(seen) == hybrid_series.steps
    assert {c.voxel_fraction for c in seen} == {step_voxel_fraction(CONFIG.voxel_fraction)} == {0.75}
    assert {c.iterations for c in seen} == {3}


def test_steps_fine_tuned_side_by_side_give_what_one_thread_gives(hybrid_series, prepared):
    """With two threads the steps are fine-tuned two at a time, each on one thread (series_qat.qat_lanes): every
    step ends exactly as it does in a one-thread process, the thread count is given back, and every step ran."""
    packed = pack_series(hybrid_series, 5, series_sensitivity(hybrid_series))
    alone, side_by_side = copy.deepcopy(hybrid_series), copy.deepcopy(hybrid_series)
    assert qat_lanes(4, torch.device("cpu")) == 1  # this module runs on one thread
    fine_tune_rounded(alone, prepared.values, packed, CONFIG, 30, show_progress=False)
    torch.set_num_threads(2)
    try:
        assert qat_lanes(4, torch.device("cpu")) == 2 and qat_lanes(1, torch.device("cpu")) == 1
        ran, _ = fine_tune_rounded(side_by_side, prepared.values, packed, CONFIG, 30, show_progress=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    assert ran == 30 * 4
    for name, value in alone.state_dict().items():
        assert torch.equal(value, side_by_side.state_dict()[name]), name
    assert not torch.equal(alone.encoder.level_table, hybrid_series.encoder.level_table)  # the fine-tune ran


def test_repack_packs_anew_when_the_fine_tuned_field_no_longer_fits(hybrid_series, prepared):
    """A size target is never exceeded: if the fine-tune's values code larger than the target, the field is
    packed again from scratch (coarser steps)."""
    packing = SeriesPacking(8, target_bytes=1)  # nothing fits: pack gives the smallest, refused (strict)
    loose = SeriesPacking(8, target_bytes=10**9)
    packed = loose.pack(hybrid_series)
    assert loose.repack(hybrid_series, packed).parameter_bytes == packed.parameter_bytes
    with pytest.raises(InvalidArgument, match="even at 2 bits"):
        packing.repack(hybrid_series, packed)


def test_repack_undoes_the_fine_tune_of_as_few_steps_as_make_the_file_fit(hybrid_series):
    """Where the fine-tuned values code larger than the target allows, the steps whose integers moved most get
    their values from before the fine-tune back until the file fits: here a "fine-tune" that moved the table
    entries of steps 1 and 3 by one or two quantisation steps each (decorrelating them along time), so those are
    the ones restored, not all of them; on the same quantisation steps, the field left holding what was packed."""
    from apmgsrn.series.packing import step_tensors

    to_tune = SeriesPacking(6, min_bits=6).pack(hybrid_series)
    tuned = copy.deepcopy(hybrid_series)
    before = step_tensors(tuned)
    table = tuned.encoder.level_table
    element = element_steps(tuned, to_tune)["level_table"]
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for t in (1, 3):
            table[t] += element * torch.randint(-2, 3, element.shape, generator=generator)
    moved = step_tensors(tuned)
    grown = pack_series(tuned, 6, finer=to_tune.finer, steps=to_tune.steps).parameter_bytes
    assert grown > to_tune.parameter_bytes
    budget = (grown + to_tune.parameter_bytes) // 2
    packing = SeriesPacking(6, target_bytes=file_bytes_for(budget, tuned), min_bits=4)
    assert packing.target_bytes - series_overhead(tuned) == budget
    repacked = packing.repack(tuned, to_tune, before)
    assert repacked.parameter_bytes <= budget
    assert repacked.restored and set(repacked.restored) <= {1, 3} and repacked.bit_width == to_tune.bit_width
    assert all(np.array_equal(repacked.steps[k], to_tune.steps[k]) for k in to_tune.steps)
    held = step_tensors(tuned)
    for name in held:
        for t in range(4):
            assert torch.equal(held[name][t], (before if t in repacked.restored else moved)[name][t])
    again = pack_series(tuned, 6, finer=to_tune.finer, steps=to_tune.steps)
    assert all(torch.equal(again.state[k], repacked.state[k]) for k in again.state)
    # Without the values from before, the field is packed anew instead: the packing's own search from its top width
    # down, on steps of its own, to a file that fits (which width fits follows the trained values' coding: at most
    # the top, not necessarily below it).
    anew = copy.deepcopy(tuned)
    with torch.no_grad():
        anew.encoder.level_table.copy_(moved["encoder.level_table"])
    packed_anew = packing.repack(anew, to_tune)
    assert packed_anew.restored == () and packed_anew.bit_width <= packing.bits
    assert packed_anew.parameter_bytes <= budget
    assert [t.data for t in packed_anew.tensors] == [t.data for t in packing.pack(anew).tensors]


def test_the_packing_to_tune_towards_leaves_room_for_the_fine_tuned_values(hybrid_series, prepared):
    """With a size target the packing a fine-tune trains towards keeps PACKING.tuned_bytes_margin of the target free, so
    the fine-tuned field, packed on the same steps, still fits (without the margin, a target the bisection
    filled would send it back to packing anew on other steps)."""
    tight = SeriesPacking(8, target_bytes=file_bytes_for(pack_series(hybrid_series, 6).parameter_bytes, hybrid_series),
                          min_bits=4, qat_iterations=20)
    plain, to_tune = replace(tight, qat_iterations=0).pack(hybrid_series), tight.pack(hybrid_series)
    budget = tight.target_bytes - series_overhead(hybrid_series)
    assert plain.parameter_bytes <= budget and to_tune.parameter_bytes <= (1 - PACKING.tuned_bytes_margin) * tight.target_bytes
    # a smaller budget, a width no finer (how many sixteenths finer the margin costs follows the values' coding)
    assert to_tune.bit_width <= plain.bit_width
    tuned = copy.deepcopy(hybrid_series)
    fine_tune_rounded(tuned, prepared.values, to_tune, CONFIG, 20, show_progress=False)
    repacked = tight.repack(tuned, to_tune)
    assert all(np.array_equal(repacked.steps[k], to_tune.steps[k]) for k in to_tune.steps)  # the same steps
    assert repacked.parameter_bytes <= budget
    assert SeriesPacking(8, qat_iterations=20).pack(hybrid_series).bit_width == 8  # no target: no margin


def test_a_packing_that_leaves_less_room_than_the_margin_shortens_the_fine_tune_in_proportion(hybrid_series):
    """Where the bit width is at its floor and the packing cannot leave PACKING.tuned_bytes_margin of the target free, the
    fine-tune towards it runs in proportion to the room left (what it would code larger does not fit, and would be
    undone); with the margin left, or no target, it runs whole; with no room, not at all."""
    floor = SeriesPacking(6, min_bits=6).pack(hybrid_series).parameter_bytes
    framing = series_overhead(hybrid_series)  # the description and framing

    def tuned(target: int) -> tuple[int, int]:
        packing = SeriesPacking(6, target_bytes=target, min_bits=6, strict=False, qat_iterations=40)
        packed = packing.pack(hybrid_series)
        assert packed.bit_width == 6  # at its floor whatever the target
        return packing.tune_iterations(packed), packed.parameter_bytes

    roomy = int((floor + framing) / (1 - PACKING.tuned_bytes_margin)) + 8
    assert tuned(roomy) == (40, floor)
    half = int((floor + framing) / (1 - PACKING.tuned_bytes_margin / 2))
    iterations, _ = tuned(half)
    assert 19 <= iterations <= 21
    assert tuned(floor + framing - 1)[0] == 0  # over the target already
    assert SeriesPacking(6, min_bits=6, qat_iterations=40).tune_iterations(
        SeriesPacking(6, min_bits=6).pack(hybrid_series)) == 40  # no target


@pytest.mark.parametrize("iterations", [7, 0])
def test_train_fine_tunes_towards_the_packing_as_long_as_the_room_allows(pattern, tmp_path, capsys, monkeypatch,
                                                                        iterations):
    """``train`` runs the fine-tune for the iterations :meth:`SeriesPacking.tune_iterations` gives (none for 0),
    records them and counts them."""
    from apmgsrn.series import qat as series_qat

    monkeypatch.setattr(SeriesPacking, "tune_iterations", lambda self, packed: iterations)
    calls = []

    def spy(*args, **kwargs):
        calls.append(args[4])
        return fine_tune_rounded(*args, **kwargs)

    monkeypatch.setattr(series_qat, "fine_tune_rounded", spy)
    assert main(["train", pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
                 "--resolution", "8", "--width", "16", "--iterations", "60", "--batch-size", "2048", "--device",
                 "cpu", "--bits", "6", "--qat-iterations", "30", "--decoder-iterations", "0", "--json",
                 "--out", str(tmp_path / "s.apmgsrn")]) == 0
    capsys.readouterr()
    description = apmgsrn.load(tmp_path / "s.apmgsrn").description
    assert calls == ([iterations] if iterations else [])
    assert description.packing.report["qat_iterations"] == iterations
    stepwise = description.training["stepwise"]
    assert description.training["iterations"] == (stepwise["start_iterations"] + sum(stepwise["step_iterations"])
                                                  + 4 * iterations)


# Slow tier: three series trained; that train runs the fine-tune for the iterations it is given and counts them is
# checked in the default tier by test_train_fine_tunes_towards_the_packing_as_long_as_the_room_allows.
@pytest.mark.slow
def test_train_with_qat_iterations_records_them_and_counts_them(pattern, tmp_path, capsys):
    """``train --qat-iterations N`` on a series: the file's packing entry and ``info`` name them, and the training
    counts them (iterations and seconds); without the option a hybrid series gets its default share of the
    iterations, and 0 turns the fine-tune off."""
    common = [pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
              "--resolution", "8", "--width", "16", "--iterations", "100", "--batch-size", "2048", "--device", "cpu",
              "--bits", "6", "--step-iterations", "10", "--decoder-iterations", "0",
              "--json"]  # the base: no spare budget shared to the steps
    assert main(["train", *common, "--qat-iterations", "0", "--out", str(tmp_path / "plain.apmgsrn")]) == 0
    plain = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert apmgsrn.load(tmp_path / "plain.apmgsrn").description.packing.report["qat_iterations"] == 0
    assert main(["train", *common, "--out", str(tmp_path / "default.apmgsrn")]) == 0
    capsys.readouterr()
    default = default_series_qat("hybrid", 100)
    assert default == round(100 * HYBRID.series_qat_share) > 0
    assert apmgsrn.load(tmp_path / "default.apmgsrn").description.packing.report["qat_iterations"] == default
    assert main(["train", *common, "--qat-iterations", "30", "--out", str(tmp_path / "qat.apmgsrn")]) == 0
    tuned = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    model = apmgsrn.load(tmp_path / "qat.apmgsrn")
    assert model.description.packing.report["qat_iterations"] == 30
    assert model.description.training["iterations"] == apmgsrn.load(tmp_path / "plain.apmgsrn").description.training[
        "iterations"] + 30 * 4
    assert tuned["psnr"] > plain["psnr"]


def test_a_long_series_shortens_its_fine_tune_towards_the_packing_with_its_steps(pattern, tmp_path, monkeypatch):
    """The quantisation-aware fine-tune shares the steps' budget: where the budget is short, fitting the series
    (what ``train`` runs) shortens both by one share, their measurements of where they are wrong with them, and the
    file records the iterations that ran."""
    from apmgsrn.series import qat as series_qat

    seen = {}

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return fine_tune_rounded(*args, **kwargs)

    monkeypatch.setattr(series_qat, "fine_tune_rounded", spy)

    # 30 of 100 start iterations' points after the 4 steps' own costs and what the hybrid's longer start model
    # (its start_iteration_share, on a CPU) takes
    extra = SERIES.start_point_cost * (HYBRID.start_iteration_share - 1)
    short = replace(SERIES, steps_budget_cap=(30 + 4 * SERIES.step_fixed_cost) / 100 + extra)
    series = open_series(pattern)
    config = stepwise_config(preset_config("hybrid", "small", **TINY_HYBRID), len(series))
    train = TrainConfig(iterations=100, batch_size=2048,
                        **training_defaults("hybrid", voxel_fraction=SERIES.voxel_fraction))
    fit_series(series, config, train, tmp_path / "s.apmgsrn", torch.device("cpu"), progress=False,
               stepwise=StepwiseConfig(recipe=short), packing=SeriesPacking(6, min_bits=6, qat_iterations=40))
    description = apmgsrn.load(tmp_path / "s.apmgsrn").description
    stepwise = description.training["stepwise"]
    # 3 steps x 10 x 0.9 + 4 steps x 40 x 0.375 = 87 points of the start's batch, 30 allowed
    assert stepwise["budget_scale"] == pytest.approx(30 / 87, abs=1e-6)
    qat = description.packing.report["qat_iterations"]
    assert qat == round(40 * 30 / 87) < 40
    assert stepwise["start_iterations"] == round(100 * HYBRID.start_iteration_share)
    start = stepwise["start_iterations"]
    assert description.training["iterations"] == start + sum(stepwise["step_iterations"]) + 4 * qat
    assert seen["measurements"] == round(PACKING.qat_measurements * 30 / 87) < PACKING.qat_measurements


def test_a_packed_series_counts_its_packing_and_fine_tune_in_its_training_time(pattern, tmp_path, capsys, monkeypatch):
    """``train`` waits for the packing search and the fine-tune towards it, so the time it reports counts them:
    here a clock that jumps 1,000 s between their start and end."""
    from apmgsrn.series import fit as fit_module  # the packing is timed in the series fit

    clock = iter([0.0, 1000.0])
    monkeypatch.setattr(fit_module, "time", types.SimpleNamespace(perf_counter=lambda: next(clock)))
    assert main(["train", pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
                 "--resolution", "8", "--width", "16", "--iterations", "60", "--batch-size", "2048", "--device",
                 "cpu", "--size", "40000", "--qat-iterations", "5", "--json",
                 "--out", str(tmp_path / "s.apmgsrn")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 1000 < summary["seconds"] < 1000 + 600
    assert next(clock, None) is None  # read once before the search and once after the repacking


def test_pack_with_qat_iterations_fine_tunes_a_float_series_file(pattern, tmp_path, capsys):
    """``apmgsrn pack SERIES DATA --qat-iterations N`` fine-tunes a float series file's steps from the training
    settings it recorded: closer to the data than the same packing without, the iterations in the report; a
    file whose recorded settings are damaged is refused in one line."""
    floats = tmp_path / "f.apmgsrn"
    assert main(["train", pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
                 "--resolution", "8", "--width", "16", "--iterations", "100", "--batch-size", "2048", "--device",
                 "cpu", "--storage", "float32", "--out", str(floats)]) == 0
    capsys.readouterr()
    figures = {}
    for label, extra in (("plain", []), ("tuned", ["--qat-iterations", "30"])):
        out = tmp_path / f"{label}.apmgsrn"
        assert main(["pack", str(floats), pattern, "--bits", "5", "--json", "--out", str(out), *extra]) == 0
        figures[label] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert figures["tuned"]["qat_iterations"] == 30 and figures["plain"]["qat_iterations"] == 0
    assert figures["tuned"]["psnr"] > figures["plain"]["psnr"] + 0.2
    assert figures["tuned"]["file_bytes"] < 1.1 * figures["plain"]["file_bytes"]
    # The float file is untouched (the fine-tune works on the loaded copy).
    assert apmgsrn.load(floats).description.kind == "series"


def test_pack_fine_tunes_the_decoder_of_a_float_series_file_as_train_does(pattern, tmp_path, capsys):
    """``apmgsrn pack SERIES DATA`` fine-tunes a stepwise hybrid series' shared decoder to the packed grids, as
    ``train`` packs it: by default for 0.15 x the iterations the file recorded; with ``--decoder-iterations N``
    every step ends closer to its data than the same packing without, in a file as large within the decoder's
    margin, the iterations in the report and ``info``. A model of one volume refuses the option in one line."""
    floats = tmp_path / "f.apmgsrn"
    assert main(["train", pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
                 "--resolution", "8", "--width", "16", "--iterations", "100", "--batch-size", "2048", "--device",
                 "cpu", "--storage", "float32", "--out", str(floats)]) == 0
    capsys.readouterr()
    assert main(["pack", str(floats), pattern, "--bits", "7", "--out", str(tmp_path / "default.apmgsrn")]) == 0
    assert "fine-tuning the shared decoder to the packed grids, 15 iterations" in capsys.readouterr().out
    figures = {}
    for iterations in ("0", "60"):
        out = tmp_path / f"d{iterations}.apmgsrn"
        assert main(["pack", str(floats), pattern, "--bits", "7", "--decoder-iterations", iterations, "--json",
                     "--out", str(out)]) == 0
        figures[iterations] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    plain, tuned = figures["0"], figures["60"]
    assert plain["decoder_iterations"] == 0 and tuned["decoder_iterations"] == 60
    assert all(t["psnr"] > p["psnr"] for t, p in zip(tuned["per_step"], plain["per_step"]))
    assert abs(tuned["file_bytes"] - plain["file_bytes"]) < 0.002 * plain["file_bytes"]  # the decoder's coding
    assert main(["info", str(tmp_path / "d60.apmgsrn")]) == 0
    assert "decoder fine-tuned 60 iterations" in capsys.readouterr().out
    single = tmp_path / "one.apmgsrn"
    assert main(["train", str(sorted(Path(pattern).parent.glob("*.vti"))[0]), "--iterations", "20", "--batch-size",
                 "1024", "--resolution", "8", "--width", "16", "--device", "cpu", "--out", str(single)]) == 0
    capsys.readouterr()
    assert main(["pack", str(single), str(sorted(Path(pattern).parent.glob("*.vti"))[0]), "--decoder-iterations",
                 "10", "--out", str(tmp_path / "p1.apmgsrn")]) == 2
    err = capsys.readouterr().err
    assert "--decoder-iterations: fine-tunes the decoder a time series' steps share" in err and err.count("\n") == 1


def test_stored_train_config_refuses_damaged_settings():
    assert stored_train_config({"config": {"lr": 0.01, "iterations": 10}}, "m").lr == 0.01
    for training, message in (({}, "does not record its training settings"),
                              ({"config": {"iterations": -4}}, "recorded training settings are damaged"),
                              ({"config": {"betas": "x"}}, "recorded training settings are damaged")):
        with pytest.raises(ApmgsrnError, match=message):
            stored_train_config(training, "m")


def test_pack_with_qat_iterations_refuses_a_joint_series_in_one_line(pattern, tmp_path, capsys):
    joint = tmp_path / "j.apmgsrn"
    assert main(["train", pattern, "--series-training", "joint", "--basis", "2", "--storage", "float32",
                 "--iterations", "30", "--batch-size", "1024", "--device", "cpu", "--resolution", "8", "--width", "16",
                 "--out", str(joint)]) == 0
    capsys.readouterr()
    out = tmp_path / "p.apmgsrn"
    for option in ("--qat-iterations", "--decoder-iterations"):
        assert main(["pack", str(joint), pattern, "--bits", "8", option, "5", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {option}: ") and "a joint series has no grids of its own per step" in err
        assert err.count("\n") == 1 and not out.exists()
    # by default a joint series' decoder is left as it is
    assert main(["pack", str(joint), pattern, "--bits", "8", "--json", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["decoder_iterations"] == 0


def test_the_decoder_fine_tuned_to_the_coded_grids_fits_the_real_steps_closer(hybrid_series, prepared, pattern):
    """The shared decoder alone trained on all four packed steps at once: the series fits them closer (every
    step's error relative to before falls, on the mean), and every grid, level table and placement is what the
    file gives back, untouched."""
    truth = open_series(pattern)
    field = copy.deepcopy(hybrid_series)
    packed = pack_series(field, 5)
    field.load_state_dict(packed.state)
    before = evaluate_series(field.step_field, truth)
    ran, seconds = fine_tune_decoder(field, prepared.values, CONFIG, 60)
    assert ran == 60 and seconds > 0
    after = evaluate_series(field.step_field, truth)
    gains = [a.psnr - b.psnr for a, b in zip(after.steps, before.steps)]
    assert sum(gains) / len(gains) > 0.05, gains
    for name, value in packed.state.items():
        if not name.startswith("decoder."):
            assert torch.equal(value, field.state_dict()[name]), name
    assert any(not torch.equal(packed.state[name], value) for name, value in field.state_dict().items()
               if name.startswith("decoder."))


def test_a_decoder_fine_tune_that_fits_worse_is_put_back(hybrid_series, prepared):
    """At a learning rate far too large the fine-tune ends with a larger error: the decoder is put back exactly
    and no iteration is counted."""
    field = copy.deepcopy(hybrid_series)
    kept = copy.deepcopy(field.state_dict())
    ran, _ = fine_tune_decoder(field, prepared.values, replace(CONFIG, lr=50.0), 20)
    assert ran == 0
    assert all(torch.equal(value, field.state_dict()[name]) for name, value in kept.items())
    assert all(p.requires_grad for p in field.parameters())  # as it came


def test_tune_decoder_packs_the_same_integers_with_the_new_decoder(hybrid_series, prepared):
    """SeriesPacking.tune_decoder: the field holds the packing's values, the fine-tune changes only the decoder, and
    the new packing codes every quantised tensor to the same bytes; nothing runs without decoder_iterations."""
    field = copy.deepcopy(hybrid_series)
    packing = SeriesPacking(5, min_bits=5, decoder_iterations=40)
    packed = packing.pack(field)
    calls = []

    def tune(iterations):
        calls.append(iterations)
        return fine_tune_decoder(field, prepared.values, CONFIG, iterations)[0]

    again, ran = packing.tune_decoder(field, packed, tune)
    assert calls == [40] and ran == 40
    quantized = {t.name: t.data for t in packed.tensors if t.encoding == "quantized"}
    assert quantized and {t.name: t.data for t in again.tensors if t.name in quantized} == quantized
    assert all(torch.equal(again.state[name], value) for name, value in field.state_dict().items())
    assert not torch.equal(again.state["decoder.0.weight"], packed.state["decoder.0.weight"])
    assert abs(again.parameter_bytes - packed.parameter_bytes) < 0.01 * packed.parameter_bytes
    untouched = copy.deepcopy(hybrid_series)
    same, none = replace(packing, decoder_iterations=0).tune_decoder(untouched, packed, tune)
    assert same is packed and none == 0 and calls == [40]
    assert all(torch.equal(packed.state[name], value) for name, value in untouched.state_dict().items())


def test_a_packing_past_its_target_still_takes_the_fine_tuned_decoder(hybrid_series, prepared):
    """The default cap is not strict: where not even min_bits fits, the series is packed there anyway, and the
    decoder's fine-tune is kept if its weights code within the room a packing inside the target would leave."""
    field = copy.deepcopy(hybrid_series)
    packing = SeriesPacking(5, 4000, min_bits=5, strict=False, decoder_iterations=40)
    packed = packing.pack(field)
    assert packed.parameter_bytes > 4000 - series_overhead(field)
    again, ran = packing.tune_decoder(field, packed,
                                      lambda n: fine_tune_decoder(field, prepared.values, CONFIG, n)[0])
    assert ran == 40 and again is not packed
    assert not torch.equal(again.state["decoder.0.weight"], packed.state["decoder.0.weight"])


def test_a_packing_whose_decoder_is_fine_tuned_after_coding_leaves_it_room(hybrid_series):
    """With decoder_iterations the coded parameters fit the recipe's decoder_bytes_margin of the decoder's float32
    bytes inside the target (its fine-tuned weights code a few bytes larger or smaller), here a margin made large
    enough to cost a finer bit width; the model kind's default is a share of the iterations."""
    wide = replace(PACKING, decoder_bytes_margin=3.0)
    decoder_bytes = 4 * sum(p.numel() for p in hybrid_series.decoder.parameters())
    eight = pack_series(hybrid_series, 8, series_sensitivity(hybrid_series))
    target = eight.parameter_bytes + series_overhead(hybrid_series)  # 8 bits fit, to the byte
    budget = target - series_overhead(hybrid_series)
    plain = SeriesPacking(8, target, 2, recipe=wide).pack(hybrid_series)
    room = SeriesPacking(8, target, 2, decoder_iterations=10, recipe=wide).pack(hybrid_series)
    assert plain.bit_width == 8 and plain.parameter_bytes <= budget
    assert room.bit_width < 8 and room.parameter_bytes <= budget - 3 * decoder_bytes
    assert default_series_decoder("hybrid", 2000) == round(2000 * HYBRID.series_decoder_share) > 0
    assert default_series_decoder("apmgsrn", 2000) == 0
    with pytest.raises(InvalidArgument):
        SeriesPacking(decoder_iterations=-1)


# Slow tier: three series trained; the decoder's fine-tune to the coded grids is checked in the default tier by
# test_pack_fine_tunes_the_decoder_of_a_float_series_file_as_train_does and the SeriesPacking tests.
@pytest.mark.slow
def test_train_fine_tunes_the_decoder_to_the_coded_grids_and_counts_it(pattern, tmp_path, capsys, monkeypatch):
    """``train`` of a hybrid series fine-tunes the decoder by default (its share of --iterations),
    ``--decoder-iterations N`` sets how long and 0 turns it off; the file records the iterations kept (none where
    the decoder was put back) and ``info`` names them, the training counts them, and the series fits its steps
    closer in about the same bytes."""
    from apmgsrn.series import qat as series_qat

    calls = []

    def spy(*args, **kwargs):
        ran, seconds = fine_tune_decoder(*args, **kwargs)
        calls.append((args[3], ran))
        return ran, seconds

    monkeypatch.setattr(series_qat, "fine_tune_decoder", spy)
    common = [pattern, "--model", "hybrid", "--levels", "6", "--log2-table-size", "10", "--grids", "4",
              "--resolution", "8", "--width", "16", "--iterations", "100", "--batch-size", "2048", "--device", "cpu",
              "--bits", "6", "--step-iterations", "10", "--qat-iterations", "10", "--json"]
    runs = {}
    for name, option in (("plain", ["--decoder-iterations", "0"]), ("default", []),
                         ("tuned", ["--decoder-iterations", "60"])):
        assert main(["train", *common, *option, "--out", str(tmp_path / f"{name}.apmgsrn")]) == 0
        runs[name] = (json.loads(capsys.readouterr().out.strip().splitlines()[-1]),
                      apmgsrn.load(tmp_path / f"{name}.apmgsrn").description)
    default = default_series_decoder("hybrid", 100)
    assert [asked for asked, _ in calls] == [default, 60]
    report = {name: description.packing.report["decoder_iterations"] for name, (_, description) in runs.items()}
    assert report == {"plain": 0, "default": calls[0][1], "tuned": 60}
    iterations = {name: description.training["iterations"] for name, (_, description) in runs.items()}
    assert iterations["tuned"] == iterations["plain"] + 60
    assert runs["tuned"][0]["psnr"] > runs["plain"][0]["psnr"]
    assert abs(runs["tuned"][0]["model_bytes"] - runs["plain"][0]["model_bytes"]) < 0.01 * runs["plain"][0][
        "model_bytes"]
    assert main(["info", str(tmp_path / "tuned.apmgsrn")]) == 0
    assert "decoder fine-tuned 60 iterations" in capsys.readouterr().out


def test_decoder_iterations_are_refused_where_no_decoder_is_fine_tuned(pattern, tmp_path, capsys):
    """--decoder-iterations on a float series file, a joint series, one volume, or below 0: a one-line error
    naming it, exit code 2, no file."""
    common = [pattern, "--model", "hybrid", "--iterations", "10", "--device", "cpu"]
    for extra, named in ((["--storage", "float32"], "--storage"), (["--series-training", "joint"], "joint"),
                         (["--bits", "6"], "--decoder-iterations")):
        value = "-1" if named == "--decoder-iterations" else "5"
        assert main(["train", *common, *extra, "--decoder-iterations", value,
                     "--out", str(tmp_path / "s.apmgsrn")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--decoder-iterations" in err and named in err, err
    one_step = sorted(Path(pattern).parent.glob("*.vti"))[0]
    assert main(["train", str(one_step), "--iterations", "10", "--decoder-iterations", "5",
                 "--out", str(tmp_path / "v.apmgsrn")]) == 2
    assert "--decoder-iterations applies to a time series" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.apmgsrn"))


def test_a_series_whose_target_holds_every_step_coded_alone_is_trained_unpulled():
    """The pull towards the neighbour only saves bytes: where the packing's target holds every step's tables and
    grids at its bit width with nothing taken from the neighbour (a few steps of the small hybrid within five
    single-step files), ``budgeted`` trains the steps unpulled; a longer series keeps the model kind's pull, a
    pull asked for is kept, and a float series (no target) is left as it is."""
    from apmgsrn.series.packing import SHARED_STEP_TENSORS, default_series_packing
    from apmgsrn.series.qat import budgeted

    shape = (64, 64, 64)

    def trained_with(steps, stepwise=StepwiseConfig(), packed=True):
        config = stepwise_config(preset_config("hybrid", "small"), steps)
        packing = default_series_packing(config, shape, 2000) if packed else None
        chosen, *_ = budgeted(stepwise, packing, TrainConfig(iterations=2000, batch_size=32768), steps, config,
                              shape, torch.device("cpu"), show_progress=False)
        return chosen, packing, config.fitted_to(shape)

    def fresh_bytes(packing, config):  # every step coded alone at the packing's bits
        shapes = config.parameter_shapes()
        return sum(np.prod(shapes[name]) for name in SHARED_STEP_TENSORS) * packing.bits / 8

    holding = [steps for steps in range(2, 40) if trained_with(steps)[0].step_sparsity == 0.0]
    assert holding and holding == list(range(2, holding[-1] + 1))  # the shortest series, up to a length
    last = holding[-1]
    for steps in (last, last + 1):
        chosen, packing, config = trained_with(steps)
        holds = fresh_bytes(packing, config) <= packing.target_bytes
        assert holds == (steps == last) == (chosen.step_sparsity == 0.0)
    assert trained_with(30)[0].step_sparsity is None  # the kind's pull (StepwiseConfig.sparsity)
    assert trained_with(3, StepwiseConfig(step_sparsity=0.01))[0].step_sparsity == 0.01
    assert trained_with(3, packed=False)[0].step_sparsity is None
