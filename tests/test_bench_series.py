"""``bench series``: the series against own models on any series, with figures that are the model files' own,
criteria computed from them, and a rerun that trains only what is missing."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from apmgsrn.bench.results import SeriesStepRow, read_rows
from apmgsrn.bench.series import measured_steps, series_criteria
from apmgsrn.cli.main import main

pytestmark = pytest.mark.usefixtures("one_thread")

RUN = Path(__file__).parent / "data" / "viscous_fingers_run01"
BUDGET = ["--iterations", "40", "--batch-size", "2048", "--device", "cpu"]


def _eval_json(capsys, *args) -> dict:
    capsys.readouterr()
    assert main(["eval", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_series_benchmark_measures_the_model_files_and_resumes(tmp_path, capsys):
    out = tmp_path / "bench"
    data = str(RUN / "*.vti")
    assert main(["bench", "series", data, "--steps", "0,3", "--out", str(out), *BUDGET]) == 0
    printed = capsys.readouterr().out
    assert len(re.findall(r"^\[\d+/2\] own model of step", printed, flags=re.M)) == 2

    rows = read_rows(out / "series.csv", SeriesStepRow)
    series = sorted((r for r in rows if r.method == "series"), key=lambda r: r.step)
    own = {r.step: r for r in rows if r.method == "own"}
    files = sorted(RUN.glob("*.vti"))
    assert [r.step for r in series] == [0, 1, 2, 3] and sorted(own) == [0, 3]
    assert [r.file for r in series] == [f.name for f in files]
    assert all(r.model == "hybrid" and r.iterations == 40 and r.batch_size == 2048 for r in rows)

    # The series' figures are its model file's, step by step, as eval measures them on the data.
    model = Path(series[0].model_file)
    assert model.stat().st_size == series[0].file_bytes
    evaluation = _eval_json(capsys, model, data)
    for row, step in zip(series, evaluation["per_step"]):
        assert row.psnr == pytest.approx(step["psnr"], abs=1e-3)
        assert row.max_abs_error == pytest.approx(step["max_abs_error"], rel=1e-4)
    # Each own model's are its own file's on its step alone.
    for t, row in own.items():
        single = _eval_json(capsys, row.model_file, files[t])
        assert row.psnr == pytest.approx(single["psnr"], abs=1e-3)
        assert Path(row.model_file).stat().st_size == row.file_bytes
        assert np.isfinite(row.psnr_between) and row.train_seconds > 0

    # The report states the criteria as the rows give them.
    report = (out / "series.md").read_text()
    criteria = series_criteria(rows)
    above = sum(series[t].psnr >= own[t].psnr for t in (0, 3))
    assert criteria.steps_at_least == above
    assert f"| {above} of 2 steps;" in report
    assert f"({series[0].file_bytes / max(own[0].file_bytes, own[3].file_bytes):.2f} files)" in report
    median = (own[0].train_seconds + own[3].train_seconds) / 2
    assert f"({series[0].train_seconds / median:.2f} x)" in report
    for t in (0, 3):
        assert f"| {t} | {files[t].name} | {own[t].psnr:.2f} | {series[t].psnr:.2f} |" in report
    with Image.open(out / "series.png") as chart:
        assert chart.format == "PNG" and chart.width > 300

    # Another step measured: only its own model trains; the series and the other models are reused.
    stamp = model.stat().st_mtime_ns
    assert main(["bench", "series", data, "--steps", "0,2,3", "--out", str(out), *BUDGET]) == 0
    printed = capsys.readouterr().out
    assert re.findall(r"own model of step (\d+)", printed) == ["2"]
    assert "trained as apmgsrn train does" not in printed
    assert model.stat().st_mtime_ns == stamp
    assert len(read_rows(out / "series.csv", SeriesStepRow)) == 7
    assert "| 2 | " in (out / "series.md").read_text()


def test_measured_steps_are_spread_evenly_with_both_ends():
    for count in (8, 30, 61, 300):
        steps = measured_steps(count)
        gaps = np.diff(steps)
        assert len(steps) == 7 and steps[0] == 0 and steps[-1] == count - 1
        assert gaps.min() >= 1 and gaps.max() - gaps.min() <= 1
    assert measured_steps(5) == [0, 1, 2, 3, 4]


def test_series_benchmark_refuses_a_step_outside_the_series(tmp_path, capsys):
    code = main(["bench", "series", str(RUN / "*.vti"), "--steps", "0,4", "--out", str(tmp_path / "b"), *BUDGET])
    assert code == 2
    error = capsys.readouterr().err.strip()
    assert "step 4 is not in the series" in error and len(error.splitlines()) == 1
    assert main(["bench", "series", str(RUN / "*.vti"), "--steps", "a", "--out", str(tmp_path / "b")]) == 2


def test_a_series_along_a_time_dimension_measures_as_its_files_do(tmp_path, capsys):
    """The 4 bundled steps written as one NetCDF variable (time, z, y, x): the same series, the same figures."""
    netCDF4 = pytest.importorskip("netCDF4")
    from apmgsrn.data import open_volume

    files = sorted(RUN.glob("*.vti"))
    values = np.stack([open_volume(f).to_numpy() for f in files])  # [T, D, H, W]
    path = tmp_path / "run.nc"
    with netCDF4.Dataset(path, "w") as handle:
        for name, size in zip(("time", "z", "y", "x"), values.shape):
            handle.createDimension(name, size)
        handle.createVariable("density", "f4", ("time", "z", "y", "x"))[:] = values
    runs = {}
    for name, data in (("files", [str(RUN / "*.vti")]), ("netcdf", [str(path), "--time", "all"])):
        assert main(["bench", "series", *data, "--steps", "1", "--out", str(tmp_path / name), *BUDGET]) == 0
        runs[name] = read_rows(tmp_path / name / "series.csv", SeriesStepRow)
    assert "run.nc[t=0]" in runs["netcdf"][0].file and "density" in runs["netcdf"][0].dataset
    for a, b in zip(runs["files"], runs["netcdf"]):
        assert (a.method, a.step) == (b.method, b.step)
        assert a.psnr == pytest.approx(b.psnr, abs=1e-4) and a.file_bytes == pytest.approx(b.file_bytes, rel=0.01)


# Slow tier: three seeds' runs of two models; the benchmark's measurement and its resume are checked in the default
# tier by test_series_benchmark_measures_the_model_files_and_resumes.
@pytest.mark.slow
def test_several_seeds_compare_their_means_and_a_rerun_trains_only_the_new_seed(tmp_path, capsys):
    out = tmp_path / "bench"
    data = str(RUN / "*.vti")
    assert main(["bench", "series", data, "--steps", "0,3", "--seeds", "2", "--out", str(out), *BUDGET]) == 0
    printed = capsys.readouterr().out
    assert printed.count("trained as apmgsrn train does") == 2
    rows = read_rows(out / "series.csv", SeriesStepRow)
    assert sorted({r.seed for r in rows}) == [0, 1]
    files = {(r.method, r.seed): r.model_file for r in rows}
    assert len(set(files.values())) == 4  # every seed its own series and own model files
    psnr = {(r.method, r.seed, r.step): r.psnr for r in rows}
    assert psnr[("series", 0, 1)] != psnr[("series", 1, 1)]  # the seeds train different models

    criteria = series_criteria(rows)
    report = (out / "series.md").read_text()
    for index, t in enumerate((0, 3)):
        own = (psnr[("own", 0, t)] + psnr[("own", 1, t)]) / 2
        series = (psnr[("series", 0, t)] + psnr[("series", 1, t)]) / 2
        assert criteria.differences[index] == pytest.approx(series - own)
        at_least = sum(psnr[("series", s, t)] >= psnr[("own", s, t)] for s in (0, 1))
        assert criteria.pairs[index] == (2, at_least)
        assert f"| {own:.2f} | {series:.2f} |" in report and f"| {at_least} of 2 |" in report
    pairs = sum(at_least for _, at_least in criteria.pairs)
    assert f"seed by seed, {pairs} of 4 pairs" in report and "seeds 0 .. 1" in report
    largest = max(r.file_bytes for r in rows if r.method == "series")
    assert f"| {largest:,} bytes (" in report

    # A third seed: only its models train.
    assert main(["bench", "series", data, "--steps", "0,3", "--seeds", "3", "--out", str(out), *BUDGET]) == 0
    printed = capsys.readouterr().out
    assert re.findall(r"^seed (\d+): series:.*trained as", printed, flags=re.M) == ["2"]
    assert re.findall(r"^seed (\d+): \[\d/2\] own model", printed, flags=re.M) == ["2", "2"]
    assert sorted({r.seed for r in read_rows(out / "series.csv", SeriesStepRow)}) == [0, 1, 2]
    assert "seeds 0 .. 2" in (out / "series.md").read_text()
