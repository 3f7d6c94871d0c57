"""SZ3, ZFP, SPERR and TTHRESH round trips on real data, ratio matching, and the ``bench compress`` harness output."""

import csv
import math
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from apmgsrn.bench import compressors
from apmgsrn.bench.compress import CompressPlan, run_compress
from apmgsrn.bench.datasets import DataSpec
from apmgsrn.bench.results import CompressRow
from apmgsrn.cli.main import main
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError

REPO = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def c60_block(test_data, tmp_path_factory):
    """A real 40x40x24 block of the C60 field, in memory (float32) and as .npy (uint8, as the field is stored).

    Not one of the NetCDF previews: those were made by ZFP itself, which then restores them exactly.
    The voxels [20:44, 20:60, 20:60] of the 128^3 source; the bundled crop starts at (16, 16, 16).
    """
    volume = open_volume(test_data / "c60_80x64x48_uint8.raw")
    data = volume.read(slice(4, 28), slice(4, 44), slice(4, 44))
    path = tmp_path_factory.mktemp("compress") / "c60_block.npy"
    np.save(path, data.astype(np.uint8))
    return path, data


@pytest.mark.parametrize("name", ["sz3", "zfp"])
def test_compressor_round_trip_honours_the_relative_error_bound(name, c60_block):
    pytest.importorskip({"sz3": "pysz", "zfp": "zfpy"}[name])
    _, data = c60_block
    compressor = compressors.get_compressor(name)
    value_range = float(data.max() - data.min())
    sizes = []
    for bound in (1e-2, 1e-4):
        packed = compressor.compress(data, bound)
        restored = compressor.decompress(packed)
        assert restored.shape == data.shape and restored.dtype == np.float32
        error = float(np.abs(restored.astype(np.float64) - data).max())
        assert error <= bound * value_range * (1 + 1e-6)
        if bound == 1e-2:
            assert error > 0  # lossy at the loose bound
        sizes.append(len(packed.data))
    assert data.nbytes > sizes[1] > sizes[0]  # compresses, and a tighter bound costs bytes


def test_zfp_fixed_precision_trades_bit_planes_for_bytes_and_refuses_other_settings(c60_block):
    pytest.importorskip("zfpy")
    _, data = c60_block
    compressor = compressors.get_compressor("zfp-precision")
    assert compressor.setting == "precision"
    sizes, errors = [], []
    for precision in (2, 6, 12):
        packed = compressor.compress(data, precision)
        restored = compressor.decompress(packed)
        assert restored.shape == data.shape and restored.dtype == np.float32
        sizes.append(len(packed.data))
        errors.append(float(np.abs(restored.astype(np.float64) - data).max()))
    assert sizes[0] < sizes[1] < sizes[2] < data.nbytes
    assert errors[0] > errors[1] > errors[2]
    for bad in (0, 33, 2.5):
        with pytest.raises(ApmgsrnError, match="precision"):
            compressor.compress(data, bad)


def test_compress_benchmark_writes_rows_table_and_rate_distortion_chart(c60_block, tmp_path, capsys):
    pytest.importorskip("pysz")
    pytest.importorskip("zfpy")
    path, data = c60_block
    out = tmp_path / "results"
    code = main(["bench", "compress", str(path), "--models", "apmgsrn", "ngp", "--iterations", "5",
                 "--compressors", "sz3", "zfp", "zfp-precision",
                 "--batch-size", "512", "--bounds", "0.01", "0.001", "--precisions", "2", "6", "--query-points", "5000",
                 "--out", str(out),
                 "--device", "cpu"])
    assert code == 0
    with open(out / "compress_c60_block.csv", newline="") as handle:
        records = list(csv.DictReader(handle))
    assert list(records[0]) == [f.name for f in dataclasses.fields(CompressRow)]
    assert [(r["method"], r["setting"]) for r in records] == [
        ("sz3", "0.01"), ("sz3", "0.001"), ("zfp", "0.01"), ("zfp", "0.001"), ("zfp-precision", "2"),
        ("zfp-precision", "6"), ("apmgsrn", "small"), ("ngp", "small"),
    ]
    for r in records:
        # c60 is stored as uint8: its ratio counts 1 byte a voxel, the float32 ratio 4.
        assert float(r["compression_ratio"]) == pytest.approx(data.size / int(r["compressed_bytes"]))
        assert float(r["compression_ratio_float32"]) == pytest.approx(data.nbytes / int(r["compressed_bytes"]))
        assert int(r["query_points"]) == 5000 and float(r["query_points_per_second"]) > 0
        assert float(r["decompress_voxels_per_second"]) > 0 and float(r["psnr"]) > 0
    # The networks were trained through bench quality into the same folder.
    assert (out / "quality.csv").is_file()
    with Image.open(out / "compress_c60_block.png") as chart:
        assert chart.format == "PNG"
    assert "| c60_block.npy | SZ3 | 0.01 |" in (out / "compress_c60_block.md").read_text()


def test_a_missing_compressor_package_is_skipped_with_the_install_hint(c60_block, tmp_path, monkeypatch):
    path, _ = c60_block

    def missing(self):
        raise ImportError("no module")

    monkeypatch.setattr(compressors.SZ3Compressor, "_module", missing)
    monkeypatch.setattr(compressors.ZFPCompressor, "_module", missing)
    monkeypatch.setattr(compressors.WasmCodecCompressor, "_module", missing)
    lines = []
    plan = CompressPlan(DataSpec(path), models=("fvsrn",), iterations=3, batch_size=256, query_points=100)
    report = run_compress(plan, tmp_path / "r", torch.device("cpu"), log=lines.append)
    assert [r.method for r in report.rows] == ["fvsrn"]
    assert len(report.skipped) == 6 and all("apmgsrn[baselines]" in s for s in report.skipped)
    assert any(line.startswith("skipped sz3: the 'pysz' package is not installed") for line in lines)
    assert any(line.startswith("skipped tthresh: the 'numcodecs-wasm-tthresh' package") for line in lines)


def test_packed_and_bounded_models_are_their_own_methods(test_data, tmp_path):
    import numpy as np
    import torch

    import apmgsrn
    from apmgsrn.bench.compress import measure_model
    from apmgsrn.training.packing import PackConfig, pack_field, write_packed

    model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    truth = np.load(test_data / "reference_neghip_24.npy").astype(np.float32)
    points = torch.rand(1000, 3) * 2 - 1
    rows = {}
    for name, config in {"packed": PackConfig(bits=8), "bounded": PackConfig(bits=8, max_error=5.0)}.items():
        path = tmp_path / f"{name}.apmgsrn"
        write_packed(path, pack_field(apmgsrn.load(test_data / "reference_field.apmgsrn").field, truth, config,
                                      model.description.source, {}))
        rows[name] = measure_model(path, truth, points, "neghip24", torch.device("cpu"), truth.size)
    assert rows["packed"].method == "apmgsrn packed" and rows["bounded"].method == "apmgsrn packed bounded"
    assert rows["bounded"].max_abs_error <= 5.0 < rows["packed"].max_abs_error
    assert rows["packed"].compressed_bytes == (tmp_path / "packed.apmgsrn").stat().st_size


def _row(method: str, setting: str, ratio: float, psnr: float, dataset: str = "v.nc:x") -> CompressRow:
    return CompressRow(dataset=dataset, method=method, setting=setting, compressed_bytes=int(1e6 / ratio),
                       compression_ratio=ratio, compression_ratio_float32=ratio, psnr=psnr, max_abs_error=1.0,
                       compress_seconds=1.0, decompress_seconds=1.0, decompress_voxels_per_second=1.0,
                       query_points=1, query_seconds=1.0, query_points_per_second=1.0)


def test_the_compressor_at_a_networks_ratio_is_interpolated_in_log_ratio_on_measured_hcci_rows():
    from apmgsrn.bench.results import read_rows
    from apmgsrn.bench.tables import compressor_psnr_at, network_frontier

    rows = read_rows(REPO / "benchmarks" / "results" / "compress_packed_hcci.csv", CompressRow)
    sz3 = sorted((r.compression_ratio, r.psnr) for r in rows if r.method == "sz3")
    ratios, values = np.log([r for r, _ in sz3]), np.array([p for _, p in sz3])
    networks = network_frontier(rows)
    assert networks and all(r.method not in ("sz3", "zfp") for r in networks)
    for row in networks:
        value, how = compressor_psnr_at(sz3, row.compression_ratio)
        assert how == "interpolated"  # SZ3 spans 88:1 to 13,244:1 here, every network lies inside
        assert value == pytest.approx(np.interp(np.log(row.compression_ratio), ratios, values))


def test_a_network_beyond_a_compressors_reach_is_ahead_only_above_its_last_point():
    from apmgsrn.bench.tables import crossover_lines, network_frontier

    rows = [_row("sz3", "0.1", 100.0, 34.0), _row("sz3", "0.2", 400.0, 26.0),
            _row("apmgsrn", "small", 200.0, 29.0),  # behind SZ3 (30 dB at 200:1)
            _row("apmgsrn packed", "small", 1000.0, 28.0),  # above SZ3's best at 400:1: ahead
            _row("apmgsrn packed", "custom", 900.0, 27.0),  # a network at a higher ratio does better
            _row("apmgsrn packed", "custom", 3000.0, 20.0),  # below 26 dB beyond 400:1: not decided
            _row("apmgsrn packed", "small", 3010.0, 15.0)]  # within 1 % of 3,000:1 and worse: not a choice
    assert [r.compression_ratio for r in network_frontier(rows)] == [200.0, 1000.0, 3000.0]
    text = "\n".join(crossover_lines(rows))
    assert "| 200 | 29.00 | SZ3 | 30.00 | -1.00 |" in text
    assert "| 1,000 | 28.00 | SZ3 | ≤ 26.00 | +2.00 |" in text
    assert "| 3,000 | 20.00 | SZ3 | not reached (at most 400:1 measured) | |" in text
    assert "networks ahead of SZ3 from 1,000:1 up; ahead at 1,000:1; behind at 200:1" in text
    assert "ZFP" not in text  # no ZFP rows, no ZFP comparison


def test_zfp_is_compared_in_whichever_of_its_modes_is_best_at_the_networks_ratio():
    from apmgsrn.bench.tables import compressor_curve, crossover_lines

    rows = [_row("zfp", "0.01", 20.0, 50.0), _row("zfp", "0.5", 30.0, 45.0),  # accuracy mode: exact-ish, 30:1 at most
            _row("zfp-precision", "8", 25.0, 30.0),  # beaten by the accuracy mode at a higher ratio: not ZFP's best
            _row("zfp-precision", "2", 100.0, 25.0), _row("zfp-precision", "1", 200.0, 10.0),
            _row("hybrid", "small", 150.0, 20.0)]
    assert compressor_curve(rows, ("zfp", "zfp-precision")) == [(20.0, 50.0), (30.0, 45.0), (100.0, 25.0),
                                                                (200.0, 10.0)]
    text = "\n".join(crossover_lines(rows))
    zfp_at_150 = 25.0 + (10.0 - 25.0) * math.log(1.5) / math.log(2.0)
    assert f"| 150 | 20.00 | ZFP | {zfp_at_150:.2f} | {20.0 - zfp_at_150:+.2f} |" in text
    assert "networks ahead of ZFP at every ratio compared, from 150:1 up" in text
    assert "ZFP-PRECISION" not in text  # one comparison per compressor, not per mode


def test_no_models_runs_the_compressors_alone(c60_block, tmp_path):
    pytest.importorskip("zfpy")
    path, _ = c60_block
    out = tmp_path / "r"
    code = main(["bench", "compress", str(path), "--models", "--compressors", "zfp-precision", "--precisions", "3",
                 "--query-points", "100", "--out", str(out), "--device", "cpu"])
    assert code == 0
    with open(out / "compress_c60_block.csv", newline="") as handle:
        assert [(r["method"], r["setting"]) for r in csv.DictReader(handle)] == [("zfp-precision", "3")]
    assert not (out / "quality.csv").exists()  # nothing was trained


WASM_PACKAGES = {"sperr": "numcodecs_wasm_sperr", "sperr-pwe": "numcodecs_wasm_sperr",
                 "tthresh": "numcodecs_wasm_tthresh"}
MATCHABLE = {"sz3": "pysz", "zfp-precision": "zfpy", **WASM_PACKAGES}


@pytest.fixture(scope="module")
def turbulence(test_data):
    """The 48^3 vorticity magnitude of the project's own turbulence run (tests/data/README.md): no compressor
    made it."""
    return np.load(test_data / "turbulence_vorticity_48.npy")


def _max_error(restored: np.ndarray, data: np.ndarray) -> float:
    return float(np.abs(restored.astype(np.float64) - data).max())


@pytest.mark.parametrize("volume", ["c60", "turbulence"])
def test_sperr_point_wise_mode_honours_the_relative_error_bound(volume, c60_block, turbulence):
    pytest.importorskip("numcodecs_wasm_sperr")
    data = c60_block[1] if volume == "c60" else turbulence
    compressor = compressors.get_compressor("sperr-pwe")
    value_range = float(data.max() - data.min())
    sizes = []
    for bound in (1e-2, 1e-4):
        packed = compressor.compress(data, bound)
        restored = compressor.decompress(packed)
        assert restored.shape == data.shape and restored.dtype == np.float32
        error = _max_error(restored, data)
        assert 0 < error <= bound * value_range * (1 + 1e-6)
        sizes.append(len(packed.data))
    assert data.nbytes > sizes[1] > sizes[0]


def test_sperr_fixed_rate_spends_the_bits_it_is_given(turbulence):
    pytest.importorskip("numcodecs_wasm_sperr")
    compressor = compressors.get_compressor("sperr")
    assert compressor.setting == "rate"
    sizes, errors = [], []
    for rate in (0.05, 0.5, 4.0):
        packed = compressor.compress(turbulence, rate)
        restored = compressor.decompress(packed)
        assert restored.shape == turbulence.shape and restored.dtype == np.float32
        assert len(packed.data) * 8 >= rate * turbulence.size  # the budget is spent, a header on top
        sizes.append(len(packed.data))
        errors.append(_max_error(restored, turbulence))
    assert sizes[0] < sizes[1] < sizes[2] < turbulence.nbytes
    assert errors[0] > errors[1] > errors[2]
    for bad in (0.0, -1.0, 65.0, 1e-9):  # 1e-9: under a bit for the whole volume
        with pytest.raises(ApmgsrnError, match="sperr rate"):
            compressor.compress(turbulence, bad)


def test_tthresh_reaches_its_psnr_target(turbulence):
    pytest.importorskip("numcodecs_wasm_tthresh")
    from apmgsrn.inference.evaluate import compare_arrays

    compressor = compressors.get_compressor("tthresh")
    assert compressor.setting == "psnr"
    sizes = []
    for target in (30.0, 50.0):
        packed = compressor.compress(turbulence, target)
        restored = compressor.decompress(packed)
        assert restored.shape == turbulence.shape and restored.dtype == np.float32
        assert compare_arrays(restored, turbulence).psnr >= target
        sizes.append(len(packed.data))
    assert sizes[0] < sizes[1] < turbulence.nbytes
    with pytest.raises(ApmgsrnError, match="tthresh PSNR"):
        compressor.compress(turbulence, 0.0)


def test_tthresh_prints_nothing(turbulence, capfd):
    pytest.importorskip("numcodecs_wasm_tthresh")
    compressor = compressors.get_compressor("tthresh")
    compressor.decompress(compressor.compress(turbulence[:16, :16, :16], 40.0))
    out, _ = capfd.readouterr()
    assert out == ""


@pytest.mark.parametrize("name", sorted(MATCHABLE))
def test_a_matched_ratio_lands_within_the_tolerance_and_round_trips_within_its_reported_error(name, turbulence):
    pytest.importorskip(MATCHABLE[name])
    from apmgsrn.bench.compress import measure_compressor

    compressor = compressors.get_compressor(name)
    target = 20.0 if name == "zfp-precision" else 60.0
    accept = 0.2 if name == "zfp-precision" else compressors.RATIO_ACCEPT  # whole bit planes: coarse steps
    match = compressors.match_ratio(compressor, turbulence, target, turbulence.nbytes, accept=accept)
    assert abs(match.ratio / target - 1) <= accept
    if name == "sperr":  # its rate sets its bytes: the search lands within the tolerance it aims at
        assert abs(match.ratio / target - 1) <= compressors.RATIO_TOLERANCE
    assert match.ratio == pytest.approx(turbulence.nbytes / len(match.compressed.data))
    assert 2 <= match.trials <= compressors.MAX_TRIALS
    # The row measured at the matched setting: the same bytes, and the errors it reports are the real ones.
    points = torch.rand(100, 3) * 2 - 1
    row = measure_compressor(compressor, turbulence, match.setting, points, "turbulence", turbulence.nbytes)
    assert row.compressed_bytes == len(match.compressed.data)
    restored = compressor.decompress(match.compressed)
    assert row.max_abs_error == pytest.approx(_max_error(restored, turbulence), rel=1e-6)
    if compressor.setting == "bound":
        assert row.max_abs_error <= match.setting * float(turbulence.max() - turbulence.min()) * (1 + 1e-6)


def test_a_ratio_out_of_reach_is_refused_with_what_the_compressor_can_do(turbulence):
    pytest.importorskip("numcodecs_wasm_sperr")
    pytest.importorskip("zfpy")
    with pytest.raises(compressors.RatioNotReached, match=r"sperr: 1e\+09:1 is out of reach; its settings give"):
        compressors.match_ratio(compressors.get_compressor("sperr"), turbulence, 1e9, turbulence.nbytes)
    with pytest.raises(compressors.RatioNotReached, match="zfp-precision: no setting gives 9.9:1 within 0.0001 %"):
        # Between two whole bit-plane counts: neither lands within a millionth of the ratio.
        compressors.match_ratio(compressors.get_compressor("zfp-precision"), turbulence, 9.9, turbulence.nbytes,
                                tolerance=1e-6, accept=1e-6)


def test_bench_compress_at_ratios_runs_every_compressor_it_can_at_each(tmp_path, test_data):
    for package in ("pysz", "zfpy", "numcodecs_wasm_sperr", "numcodecs_wasm_tthresh"):
        pytest.importorskip(package)
    path = test_data / "turbulence_vorticity_48.npy"
    out = tmp_path / "r"
    lines = []
    plan = CompressPlan(DataSpec(path), models=(), ratios=(50.0, 400.0), query_points=100)
    report = run_compress(plan, out, torch.device("cpu"), log=lines.append)
    for row in report.rows:
        assert min(abs(row.compression_ratio / r - 1) for r in plan.ratios) <= compressors.RATIO_ACCEPT
    methods = {row.method for row in report.rows}
    assert {"sz3", "sperr", "sperr-pwe", "tthresh"} <= methods
    # Every compressor at every ratio is a row or a skip with the reason.
    assert len(report.rows) + len(report.skipped) == len(plan.compressors) * len(plan.ratios)
    assert all("out of reach" in reason or "no setting gives" in reason for reason in report.skipped)
    table = report.markdown.read_text()
    assert "| turbulence_vorticity_48.npy | SPERR |" in table and "| TTHRESH |" in table
    with Image.open(report.chart) as chart:
        assert chart.format == "PNG"


def test_bench_compress_cli_takes_ratios_rates_and_psnrs(tmp_path, test_data, capsys):
    pytest.importorskip("numcodecs_wasm_sperr")
    pytest.importorskip("numcodecs_wasm_tthresh")
    path = test_data / "turbulence_vorticity_48.npy"
    out = tmp_path / "r"
    assert main(["bench", "compress", str(path), "--models", "--compressors", "sperr", "tthresh", "--rates", "0.5",
                 "--psnrs", "40", "--query-points", "100", "--out", str(out), "--device", "cpu"]) == 0
    with open(out / "compress_turbulence_vorticity_48.csv", newline="") as handle:
        assert [(r["method"], r["setting"]) for r in csv.DictReader(handle)] == [("sperr", "0.5"), ("tthresh", "40")]
    assert main(["bench", "compress", str(path), "--models", "--compressors", "sperr", "--ratios", "100",
                 "--query-points", "100", "--out", str(out), "--device", "cpu"]) == 0
    with open(out / "compress_turbulence_vorticity_48.csv", newline="") as handle:
        (row,) = csv.DictReader(handle)
    assert row["method"] == "sperr" and abs(float(row["compression_ratio"]) / 100 - 1) <= 0.01
    assert main(["bench", "compress", str(path), "--models", "--compressors", "sperr", "--ratios", "100",
                 "--ratio-tolerance", "0.9", "--out", str(out), "--device", "cpu"]) == 2
    assert "error: --ratio-tolerance 0.9: must be" in capsys.readouterr().err


@pytest.mark.parametrize("field, value", [("ratios", (1.0,)), ("rates", (0.0,)), ("psnrs", (-3.0,)),
                                          ("ratio_tolerance", 0.0)])
def test_bad_ratio_rate_and_psnr_settings_are_refused(field, value, test_data):
    with pytest.raises(ApmgsrnError, match=field):
        CompressPlan(DataSpec(test_data / "turbulence_vorticity_48.npy"), **{field: value})


def test_spectral_families_are_compared_as_one_compressor_each():
    from apmgsrn.bench.tables import crossover_lines

    rows = [_row("sperr", "0.1", 300.0, 50.0), _row("sperr-pwe", "0.01", 100.0, 60.0),
            _row("tthresh", "40", 300.0, 45.0), _row("apmgsrn packed", "small", 300.0, 48.0)]
    text = "\n".join(crossover_lines(rows))
    assert "| 300 | 48.00 | SPERR | 50.00 | -2.00 |" in text
    assert "| 300 | 48.00 | TTHRESH | 45.00 | +3.00 |" in text
    assert "SPERR-PWE" not in text


def test_a_codec_that_fails_is_skipped_with_the_reason_and_the_rest_goes_on(tmp_path, test_data, monkeypatch):
    pytest.importorskip("numcodecs_wasm_tthresh")
    pytest.importorskip("numcodecs_wasm_sperr")

    class Broken:
        def decode(self, stream):
            raise Exception("wasm trap: unreachable\nbacktrace")  # what the WebAssembly runtime raises

    monkeypatch.setattr(compressors.TTHRESHCompressor, "_decoder", lambda self: Broken())
    plan = CompressPlan(DataSpec(test_data / "turbulence_vorticity_48.npy"), models=(),
                        compressors=("tthresh", "sperr"), psnrs=(40.0,), rates=(1.0,), query_points=100)
    report = run_compress(plan, tmp_path / "r", torch.device("cpu"), log=lambda line: None)
    assert [r.method for r in report.rows] == ["sperr"]
    assert report.skipped == ["tthresh: its decoder failed: wasm trap: unreachable (at psnr 40)"]
