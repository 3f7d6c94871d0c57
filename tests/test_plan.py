"""The plan (apmgsrn.planning): one resolution of every default, the same from the command line and from Python,
printed by ``train --dry-run``, run by ``train`` and ``fit``, and recorded in the model file."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

import apmgsrn
from apmgsrn.cli.main import build_parser, main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.options import TrainOptions, flag, option_names


def dry_run(argv: list[str]) -> tuple[int, dict | None, str]:
    """(exit code, the printed plan or None, stderr) of ``train ARGV --dry-run --json``."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["train", *argv, "--dry-run", "--json"])
    return code, (json.loads(out.getvalue()) if code == 0 else None), err.getvalue()


def api_plan(data, **options) -> dict:
    """What :func:`apmgsrn.plan` resolves, as the JSON values the command line prints."""
    return json.loads(json.dumps(apmgsrn.plan(data, **options).to_dict()))


@pytest.fixture(scope="module")
def volume(test_data) -> str:
    return str(test_data / "neghip_64x64x64_uint8.raw")


@pytest.fixture(scope="module")
def series(test_data) -> str:
    return str(test_data / "viscous_fingers_run01" / "*.vti")


@pytest.mark.parametrize(("argv", "options"), [
    ([], {}),
    (["--preset", "medium", "--iterations", "500"], {"preset": "medium", "iterations": 500}),
    (["--ratio", "300"], {"ratio": 300.0}),
    (["--model", "fvsrn", "--resolution", "8", "--seed", "3"], {"model": "fvsrn", "resolution": 8, "seed": 3}),
    (["--bricks", "2,2,1", "--ghost-cells", "2"], {"bricks": "2,2,1", "ghost_cells": 2}),
])
def test_the_dry_run_of_a_volume_is_the_plan_of_the_api(volume, argv, options):
    code, printed, err = dry_run([volume, "--device", "cpu", *argv])
    assert code == 0, err
    assert printed == api_plan(volume, device="cpu", **options)
    assert printed["input"] == "volume" and printed["shape"] == [64, 64, 64]


def test_the_dry_run_of_a_series_is_the_plan_of_the_api(series):
    code, printed, err = dry_run([series, "--device", "cpu", "--iterations", "300"])
    assert code == 0, err
    assert printed == api_plan(series, device="cpu", iterations=300)
    assert printed["input"] == "series" and printed["steps"] == 4 and printed["stepwise"] is not None
    assert printed["packing_kind"] == "SeriesPacking"  # a stepwise series is packed by default


def test_what_the_plan_resolves(volume, series):
    """Defaults that the plan decides, checked through the plan (not re-derived here)."""
    plain = apmgsrn.plan(volume, device="cpu")
    sized = apmgsrn.plan(volume, device="cpu", ratio=300)
    # a byte target packs, and resizes the model to land near it
    assert plain.packing is None and sized.packing.target_bytes == plain.stored_bytes // 300
    assert sized.field != plain.field
    # a joint series splits every batch over its steps and trains longer than one volume
    joint = apmgsrn.plan(series, device="cpu", series_training="joint")
    assert joint.stepwise is None and joint.training.iterations > plain.training.iterations
    # what is given wins over every default
    given = apmgsrn.plan(volume, device="cpu", voxel_fraction=0.25, lr_schedule="constant", seed=7)
    assert (given.training.voxel_fraction, given.training.lr_schedule, given.training.seed) == (0.25, "constant", 7)


def test_every_option_is_a_flag_of_train_and_a_keyword_of_fit():
    parser = build_parser()
    train = parser._subparsers._group_actions[0].choices["train"]
    flags = {option for action in train._actions for option in action.option_strings}
    assert {flag(name) for name in option_names()} <= flags
    # the parsed command line holds exactly the options' values (defaults included)
    args = train.parse_args(["x.nc", "--out", "m.apmgsrn"])
    assert TrainOptions.from_namespace(args) == TrainOptions()


def test_bad_options_are_refused_in_one_line(volume, series, capsys):
    with pytest.raises(ApmgsrnError, match="unknown option learning_rate"):
        apmgsrn.plan(volume, learning_rate=0.1)
    code, _, err = dry_run([volume, "--step-iterations", "5"])  # a series option for one volume
    assert code == 2 and err.count("\n") == 1 and "--step-iterations applies to a time series" in err
    code, _, err = dry_run([volume, "--size", "1000", "--ratio", "10"])
    assert code == 2 and "give one of them" in err
    code, _, err = dry_run([series, "--basis", "3"])  # joint-only option on a stepwise series
    assert code == 2 and "--series-training joint" in err
    assert main(["train", volume]) == 2  # no --out, no --dry-run
    assert "--out is required" in capsys.readouterr().err


def test_the_model_file_records_its_plan_and_info_shows_it(volume, tmp_path, capsys):
    out = tmp_path / "m.apmgsrn"
    argv = [volume, "--out", str(out), "--model", "apmgsrn", "--iterations", "12", "--batch-size", "512",
            "--grids", "2", "--resolution", "4", "--width", "8", "--device", "cpu"]
    code, planned, _ = dry_run(argv)
    assert code == 0
    assert main(["train", *argv, "--json"]) == 0
    capsys.readouterr()
    recorded = apmgsrn.load(out).description.training["plan"]
    expected = {k: v for k, v in planned.items() if k != "data"} | {"files": 1}
    assert recorded == expected
    assert main(["info", str(out)]) == 0
    assert "plan            apmgsrn volume on cpu, 12 iterations x 512 points, seed 0" in capsys.readouterr().out


def test_fit_runs_the_plan_it_resolves(test_data):
    data = np.load(test_data / "neghip_32x32x32_uint8.npy")
    options = dict(model="apmgsrn", iterations=8, batch_size=256, grids=2, resolution=4, width=8, device="cpu")
    model = apmgsrn.fit(data, progress=False, **options)
    planned = apmgsrn.plan(data, **options)
    recorded = model.description.training["plan"]
    assert recorded == json.loads(json.dumps(planned.record()))
    assert model.description.training["iterations"] == 8
