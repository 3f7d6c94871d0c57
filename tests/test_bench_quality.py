"""``bench quality``: runs every combination once, resumes, and writes the Table 1 layout and a chart."""

import csv
import dataclasses
import json
import re

import numpy as np
import pytest
from PIL import Image

from apmgsrn.bench.datasets import parse_data_spec
from apmgsrn.bench.results import QualityRow, read_rows
from apmgsrn.bench.tables import quality_tables
from apmgsrn.cli.main import main
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def crop(hcci_oh, tmp_path_factory):
    """A real 20^3 crop of the hcci OH field (NetCDF), saved as .npy, and its label."""
    volume = open_volume(hcci_oh, variable="oh")
    data = volume.read(slice(80, 100), slice(80, 100), slice(80, 100))
    path = tmp_path_factory.mktemp("quality") / "hcci_crop.npy"
    np.save(path, data)
    return path


def test_quality_benchmark_writes_csv_table_and_chart_and_resumes(crop, tmp_path, capsys):
    out = tmp_path / "results"
    args = ["bench", "quality", str(crop), "--sizes", "small", "--iterations", "4", "--batch-size", "512",
            "--out", str(out), "--device", "cpu"]
    assert main(args + ["--seeds", "2"]) == 0
    printed = capsys.readouterr().out
    assert len(re.findall(r"^\[\d+/8\]", printed, flags=re.M)) == 8  # 4 models x 1 size x 2 seeds

    with open(out / "quality.csv", newline="") as handle:
        records = list(csv.DictReader(handle))
    assert [f.name for f in dataclasses.fields(QualityRow)] == list(records[0])
    assert sorted((r["model"], r["seed"]) for r in records) == [
        (m, s) for m in ("apmgsrn", "fvsrn", "hybrid", "ngp") for s in ("0", "1")
    ]
    for record in records:
        # The default model stores its feature tables in float16, the others every parameter in float32.
        floats = int(record["parameters"]) * 4
        if record["model"] == "hybrid":
            assert floats / 2 < int(record["parameter_bytes"]) < floats
        else:
            assert floats == int(record["parameter_bytes"])
        assert int(record["parameter_bytes"]) < int(record["file_bytes"])
        # The crop is stored as float32: both ratios count 4 bytes a voxel.
        assert record["data_dtype"] == "float32" and int(record["data_bytes"]) == 20**3 * 4
        assert float(record["compression_ratio"]) == pytest.approx(20**3 * 4 / int(record["file_bytes"]))
        assert float(record["compression_ratio_float32"]) == float(record["compression_ratio"])
        assert (out / "models").joinpath(record["model_file"].split("/")[-1]).is_file()
        # The largest voxel error, as eval measures it on the model file.
        evaluation = json.loads(_eval_json(capsys, out / "models" / record["model_file"].split("/")[-1], crop))
        assert float(record["max_abs_error"]) == pytest.approx(evaluation["max_abs_error"], rel=1e-5)

    table = (out / "quality.md").read_text()
    assert "Largest absolute error over every voxel" in table
    header = "| volume | APMGSRN S | fVSRN S | NGP S | hybrid S |"
    assert header in table
    row = next(line for line in table.splitlines() if line.startswith("| hcci_crop.npy"))
    assert row.count("**") == 2 and row.count("±") == 4  # one best cell; mean ± spread of 2 seeds
    assert "| NGP | small | 70,800 |" in table
    with Image.open(out / "quality.png") as chart:
        assert chart.format == "PNG" and chart.width > 300

    # A third seed runs only the four new combinations.
    assert main(args + ["--seeds", "3"]) == 0
    printed = capsys.readouterr().out
    assert len(re.findall(r"^\[\d+/12\]", printed, flags=re.M)) == 4
    assert len(read_rows(out / "quality.csv", QualityRow)) == 12


def _eval_json(capsys, model, data) -> str:
    capsys.readouterr()
    assert main(["eval", str(model), str(data), "--json"]) == 0
    return capsys.readouterr().out


def _row(dataset, model, size, seed, psnr):
    return QualityRow(dataset, "8x8x8", model, size, seed, 10, 64, "cosine", 100, 400, 500, "uint8", 512, 1.024,
                      4.096, psnr, 1.0, 100.0, "cpu", "m.apmgsrn")


def test_table_marks_the_best_per_size_and_leaves_missing_cells_empty():
    rows = [
        _row("a.nc:v", "apmgsrn", "small", 0, 30.0), _row("a.nc:v", "apmgsrn", "small", 1, 32.0),
        _row("a.nc:v", "ngp", "small", 0, 33.5), _row("a.nc:v", "apmgsrn", "medium", 0, 40.0),
        _row("a.nc:v", "fvsrn", "medium", 0, 41.25),
    ]
    table = quality_tables(rows)
    line = next(row for row in table.splitlines() if row.startswith("| a.nc:v"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1:] == ["31.00 ± 1.41 / 40.00", "– / **41.25**", "**33.50** / –"]


def test_data_spec_takes_a_variable_after_the_last_colon(hcci_oh):
    spec = parse_data_spec(f"{hcci_oh}:oh")
    assert spec.variable == "oh" and spec.label == "hcci_oh_187.nc:oh"
    with pytest.raises(ApmgsrnError, match="no such volume file"):
        parse_data_spec(str(hcci_oh.parent / "missing.nc") + ":oh")


def test_quality_benchmark_refuses_a_file_as_results_folder(crop, tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("x")
    assert main(["bench", "quality", str(crop), "--out", str(target), "--iterations", "1"]) == 2
    assert "needs a folder" in capsys.readouterr().err
