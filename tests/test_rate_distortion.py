"""``apmgsrn bench rd``: the rate-distortion page on a real (simulated, never compressed) volume, the crossover
of two curves, the reuse of what a results folder holds, and bad input."""

import math

import pytest
from PIL import Image

from apmgsrn.bench import rate_distortion
from apmgsrn.bench.rate_distortion import (
    Crossing,
    VolumeResult,
    classical_wins,
    crossover_text,
    crossovers,
    failure_reason,
    psnr_at,
)
from apmgsrn.bench.results import CompressRow
from apmgsrn.cli.main import main

pytestmark = pytest.mark.usefixtures("one_thread")


def _bench_rd(test_data, out, page, *extra):
    return main(["bench", "rd", str(test_data / "turbulence_vorticity_48.npy"), "--quick", "--ratios", "30", "100",
                 "--models", "apmgsrn", "--compressors", "sz3", "sperr", "--iterations", "20", "--batch-size", "2048",
                 "--query-points", "2048", "--region", "16", "--device", "cpu", "--out", str(out), "--page",
                 str(page), *extra])


def test_the_page_chart_and_a_rerun_that_measures_nothing_again(test_data, tmp_path, monkeypatch, capsys):
    pytest.importorskip("pysz")
    pytest.importorskip("numcodecs_wasm_sperr")
    out, page = tmp_path / "results", tmp_path / "docs" / "rd.md"
    assert _bench_rd(test_data, out, page) == 0
    text = page.read_text()
    chart = tmp_path / "docs" / "images" / "rate_distortion_turbulence_vorticity_48.png"
    assert "](images/rate_distortion_turbulence_vorticity_48.png)" in text
    with Image.open(chart) as image:
        assert image.size[0] > 300 and image.size[1] > 200
    assert "## Where the classical compressors still win" in text
    assert "**turbulence_vorticity_48.npy** (48x48x48)" in text
    assert "| method | 30:1 | 100:1 |" in text
    for method in ("SZ3", "SPERR", "APMGSRN"):
        row = next(line for line in text.splitlines() if line.startswith(f"| {method} |"))
        cells = row.strip("|").split("|")[1:]
        assert len(cells) == 2
    assert "| network | SZ3 | ZFP | SPERR | TTHRESH |" in text
    assert "| method | query Mpoints/s | region s | whole volume s |" in text
    models = sorted((out / "models").glob("rd_*.apmgsrn"))
    assert len(models) == 2  # apmgsrn at 30:1 and 100:1
    rows = (out / "compress_turbulence_vorticity_48.csv").read_text().splitlines()
    assert len(rows) == 1 + 6  # header, two compressors and one network at two ratios
    # Every point landed near its ratio (against float32: the volume is float32 here, so stored = float32).
    header = rows[0].split(",")
    for line in rows[1:]:
        record = dict(zip(header, line.split(",")))
        assert float(record["compression_ratio_float32"]) == pytest.approx(float(record["compression_ratio"]))
    stamps = {path: path.stat().st_mtime_ns for path in models}
    capsys.readouterr()

    def refuse(*args, **kwargs):
        raise AssertionError("a rerun trained or compressed again")

    monkeypatch.setattr(rate_distortion.subprocess, "run", refuse)
    monkeypatch.setattr(rate_distortion, "match_ratio", refuse)
    monkeypatch.setattr(rate_distortion, "measure_model", refuse)
    page.unlink()
    assert _bench_rd(test_data, out, page) == 0
    log = capsys.readouterr().out
    assert log.count("reused") == 6
    assert page.exists() and "| APMGSRN |" in page.read_text()
    assert {path: path.stat().st_mtime_ns for path in models} == stamps
    assert len((out / "compress_turbulence_vorticity_48.csv").read_text().splitlines()) == 7


def test_a_network_file_far_from_its_ratio_is_not_measured_there(test_data, tmp_path, monkeypatch, capsys):
    """A model file at a point's path that does not give the point's ratio (a float32 model left where packing
    failed, a file of other settings) is listed as not measured, naming the file, not drawn at that ratio."""
    pytest.importorskip("pysz")
    pytest.importorskip("numcodecs_wasm_sperr")
    out, page = tmp_path / "results", tmp_path / "rd.md"
    assert _bench_rd(test_data, out, page) == 0
    at_30, at_100 = sorted((out / "models").glob("rd_*.apmgsrn"), key=lambda p: p.stat().st_size, reverse=True)
    fresh = tmp_path / "fresh"
    (fresh / "models").mkdir(parents=True)
    (fresh / "models" / at_30.name).write_bytes(at_100.read_bytes())  # the 100:1 file where 30:1's belongs
    (fresh / "models" / at_100.name).write_bytes(at_100.read_bytes())
    capsys.readouterr()
    assert _bench_rd(test_data, fresh, page) == 0
    log = capsys.readouterr().out
    assert "apmgsrn 30:1: not measured" in log and "not within 5% of 30:1" in log
    assert "not within 5% of 30:1" in page.read_text()
    row = next(line for line in page.read_text().splitlines() if line.startswith("| APMGSRN |"))
    assert row.strip("|").split("|")[1].strip() == "–"


def test_curves_that_cross_once_meet_where_their_log_ratio_lines_do():
    network = [(100.0, 40.0), (1000.0, 38.0), (10000.0, 30.0)]
    compressor = [(100.0, 50.0), (1000.0, 36.0), (10000.0, 25.0)]
    (crossing,) = crossovers(network, compressor)
    # Gap -10 dB at 100:1 and +2 dB at 1,000:1: zero at 10/12 of the decade.
    assert crossing.ratio == pytest.approx(100 * 10 ** (10 / 12))
    assert crossing.ahead_above == "network"
    assert "(network ahead above)" in crossover_text(network, compressor)


def test_curves_sampled_at_other_ratios_are_compared_where_both_are_defined():
    network = [(95.0, 40.0), (1040.0, 38.0)]
    compressor = [(100.0, 44.0), (300.0, 40.0), (1000.0, 34.0), (3000.0, 30.0)]
    (crossing,) = crossovers(network, compressor)
    assert 100 < crossing.ratio < 1000 and crossing.ahead_above == "network"
    back = crossovers(compressor, network)
    assert back[0].ratio == pytest.approx(crossing.ratio) and back[0].ahead_above == "compressor"


def test_curves_that_never_cross_say_none_in_range_and_who_leads():
    network = [(100.0, 30.0), (1000.0, 28.0), (10000.0, 20.0)]
    compressor = [(100.0, 50.0), (1000.0, 36.0), (10000.0, 25.0)]
    assert crossovers(network, compressor) == []
    text = crossover_text(network, compressor)
    assert text.startswith("none in range 100-10,000:1: compressor ahead throughout")
    assert "20.0 dB at 100:1" in text and "5.0 dB at 10,000:1" in text
    assert crossover_text(network, [(30000.0, 20.0), (90000.0, 10.0)]).startswith("not compared")


def test_curves_that_meet_at_the_edge_of_the_range_cross_there():
    last = crossovers([(100.0, 30.0), (1000.0, 36.0)], [(100.0, 40.0), (1000.0, 36.0)])
    assert last == [Crossing(1000.0, "network")]
    first = crossovers([(100.0, 40.0), (1000.0, 38.0)], [(100.0, 40.0), (1000.0, 30.0)])
    assert first == [Crossing(100.0, "network")]
    lead_lost = crossovers([(100.0, 40.0), (1000.0, 30.0)], [(100.0, 40.0), (1000.0, 38.0)])
    assert lead_lost == [Crossing(100.0, "compressor")]


def test_a_curve_at_an_asked_ratio_interpolates_or_takes_a_point_within_five_per_cent():
    curve = [(98.0, 40.0), (1030.0, 30.0)]
    assert psnr_at(curve, 100.0) == pytest.approx(40.0 - 10.0 * math.log(100 / 98) / math.log(1030 / 98))
    assert psnr_at(curve, 1000.0) == pytest.approx(30.0 + 10.0 * math.log(1030 / 1000) / math.log(1030 / 98))
    assert psnr_at(curve, 1050.0) == 30.0  # beyond the last point by 2 %
    assert psnr_at(curve, 1200.0) is None  # beyond it by 17 %
    assert psnr_at([(29.0, math.inf), (100.0, 50.0)], 30.0) == math.inf  # exact there


@pytest.mark.parametrize("ratio", ["0", "-5"])
def test_a_ratio_of_zero_or_less_is_one_line_and_exit_2(ratio, test_data, tmp_path, capsys):
    code = main(["bench", "rd", str(test_data / "turbulence_vorticity_48.npy"), "--ratios", "100", ratio,
                 "--out", str(tmp_path / "out")])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "--ratios" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_a_missing_volume_is_one_line_and_exit_2(tmp_path, capsys):
    code = main(["bench", "rd", str(tmp_path / "no_such_volume.raw"), "--out", str(tmp_path / "out")])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "no_such_volume.raw" in err and len(err.splitlines()) == 1


def _row(method, ratio, psnr):
    return CompressRow(dataset="v", method=method, setting="s", compressed_bytes=int(4e6 / ratio),
                       compression_ratio=ratio, compression_ratio_float32=ratio, psnr=psnr, max_abs_error=1.0,
                       compress_seconds=1.0, decompress_seconds=0.1, decompress_voxels_per_second=1e7,
                       query_points=1000, query_seconds=0.1, query_points_per_second=1e4)


def test_the_paragraph_says_where_each_compressor_wins_by_how_much_and_where_a_network_leads():
    ratios = (100.0, 1000.0, 3000.0)
    points = {("sperr", 100.0): 50.0, ("sperr", 1000.0): 40.0, ("sperr", 3000.0): 33.0,
              ("tthresh", 100.0): 47.5, ("sz3", 100.0): 45.0, ("sz3", 1000.0): 30.0,
              ("apmgsrn", 100.0): 46.0, ("apmgsrn", 1000.0): 41.5, ("apmgsrn", 3000.0): 36.0}
    rows = {key: _row(key[0], key[1] * 1.01, psnr) for key, psnr in points.items()}
    result = VolumeResult("v", "8x8x8", "float32", "v", ratios, rows, {key: 0.1 for key in rows}, {},
                          ("sz3", "sperr", "tthresh", "apmgsrn"), "8x8x8")
    text = classical_wins(result, ("apmgsrn",))
    assert text.startswith("**v** (8x8x8): ")
    assert "SPERR beats every network at 100:1 by 4.0 dB" in text
    assert "TTHRESH beats every network at 100:1 by 1.5 dB" in text
    assert "SZ3 never does" in text
    assert "A network leads every compressor measured from 1,000:1 up to 3,000:1" in text
    # The network behind again at the highest ratio: no lead claimed.
    rows[("apmgsrn", 3000.0)] = _row("apmgsrn", 3030.0, 30.0)
    assert "At the highest ratio compared (3,000:1) a compressor still leads" in classical_wins(result, ("apmgsrn",))


def test_a_failed_training_is_reported_by_its_error_or_its_exception_not_by_its_progress():
    progress = "model size  4 grids of 4^3, decoder 1 x 16, chosen to pack into 838 bytes\n"
    traceback = "Traceback (most recent call last):\n  File \"x.py\", line 1\nIndexError: index -1 is out of bounds\n"
    assert failure_reason(traceback, progress, 1) == "IndexError: index -1 is out of bounds"
    assert failure_reason("error: --size 10: too small\n", progress, 2) == "--size 10: too small"
    assert failure_reason("", progress, 1) == progress.strip()
    assert failure_reason("", "", -9) == "exit status -9"
