"""Every bad input a user can give gets one line on stderr, exit code 2, and loses nothing."""

from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest

from apmgsrn.cli.main import main
from apmgsrn.io import SourceInfo, save_field

FAST = ["--iterations", "30", "--batch-size", "1024", "--device", "cpu"]


def fails_cleanly(capsys, argv, *needles):
    """Run the CLI in-process; assert exit 2 and a one-line 'error:' message naming what went wrong."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


def test_missing_data_file(capsys, tmp_path):
    fails_cleanly(capsys, ["train", str(tmp_path / "nope.nc"), "--out", str(tmp_path / "m")], "nope.nc")


def test_unknown_format(capsys, tmp_path):
    path = tmp_path / "volume.xyz"
    path.write_bytes(b"1234")
    fails_cleanly(capsys, ["train", str(path), "--out", str(tmp_path / "m")], "volume.xyz")


def test_garbage_netcdf(capsys, tmp_path):
    path = tmp_path / "broken.nc"
    path.write_bytes(b"CDF\x01" + b"\xff" * 300)
    fails_cleanly(capsys, ["train", str(path), "--out", str(tmp_path / "m")], "broken.nc")


def test_truncated_raw_and_wrong_shape(capsys, tmp_path, test_data):
    data = (test_data / "neghip_64x64x64_uint8.raw").read_bytes()
    truncated = tmp_path / "cut_64x64x64_uint8.raw"
    truncated.write_bytes(data[: len(data) - 1000])
    fails_cleanly(capsys, ["train", str(truncated), "--out", str(tmp_path / "m")], "cut_64x64x64_uint8.raw")
    fails_cleanly(capsys, ["train", str(test_data / "neghip_64x64x64_uint8.raw"), "--shape", "64,64,65",
                           "--out", str(tmp_path / "m")], "neghip")


def test_missing_variable_lists_the_available_ones(capsys, tmp_path, test_data):
    fails_cleanly(capsys, ["train", str(test_data / "miranda_density_80x64x48.nc"), "--variable", "pressure",
                           "--out", str(tmp_path / "m")], "pressure", "density")


def test_nan_volume_is_refused_with_a_count_then_trains_with_fill(capsys, tmp_path, test_data):
    volume = np.fromfile(test_data / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    volume = volume[:32, :32, :32].astype(np.float32)
    volume[0, 0, :5] = np.nan
    volume[1, 1, 1] = np.inf
    path = tmp_path / "holes.npy"
    np.save(path, volume)
    fails_cleanly(capsys, ["train", str(path), "--out", str(tmp_path / "m")], "6", "--fill-nonfinite")
    assert main(["train", str(path), "--out", str(tmp_path / "m"), "--fill-nonfinite", "0", *FAST]) == 0


def test_constant_volume_trains_without_dividing_by_zero(capsys, tmp_path):
    path = tmp_path / "flat.npy"
    np.save(path, np.full((8, 9, 10), 3.5, dtype=np.float32))
    model = tmp_path / "flat.apmgsrn"
    assert main(["train", str(path), "--out", str(model), *FAST]) == 0
    capsys.readouterr()
    assert main(["eval", str(model), str(path), "--json"]) == 0
    out = capsys.readouterr().out
    assert '"mse": 0.0' in out and '"max_abs_error": 0.0' in out


def test_log10_of_non_positive_data_is_refused(capsys, tmp_path, test_data):
    fails_cleanly(capsys, ["train", str(test_data / "neghip_64x64x64_uint8.raw"), "--transform", "log10",
                           "--out", str(tmp_path / "m")], "--log-offset")


def test_unwritable_output(capsys, tmp_path, test_data):
    fails_cleanly(capsys, ["train", str(test_data / "neghip_64x64x64_uint8.raw"),
                           "--out", str(tmp_path / "no" / "such" / "dir" / "m.apmgsrn"), *FAST], "does not exist")


def test_cuda_asked_for_without_a_gpu(capsys, tmp_path, test_data):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    fails_cleanly(capsys, ["train", str(test_data / "neghip_64x64x64_uint8.raw"), "--device", "cuda",
                           "--out", str(tmp_path / "m")], "--device cpu")


@pytest.fixture()
def model_file(tmp_path):
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import preset_config

    path = tmp_path / "ok.apmgsrn"
    save_field(path, NeuralField(preset_config("apmgsrn", "small"), volume_shape=(64, 64, 64)), SourceInfo(), {})
    return path


class _Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("command", ["info", "eval", "decode"])
def test_bad_model_files(capsys, tmp_path, model_file, test_data, command):
    marker = tmp_path / "executed"
    bad = {
        "missing.apmgsrn": None,
        "corrupt.apmgsrn": model_file.read_bytes()[:200],
        "evil.apmgsrn": pickle.dumps(_Exploit(str(marker))),
    }
    for name, content in bad.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        argv = {
            "info": ["info", str(path)],
            "eval": ["eval", str(path), str(test_data / "neghip_64x64x64_uint8.raw")],
            "decode": ["decode", str(path), "--out", str(tmp_path / "d.npy")],
        }[command]
        fails_cleanly(capsys, argv, name)
    assert not marker.exists()
    assert not (tmp_path / "d.npy").exists()


def test_eval_against_the_wrong_volume(capsys, model_file, test_data):
    fails_cleanly(capsys, ["eval", str(model_file), str(test_data / "c60_80x64x48_uint8.raw")],
                  "trained on 64x64x64")


def test_decode_to_an_unknown_suffix_or_missing_folder(capsys, tmp_path, model_file):
    fails_cleanly(capsys, ["decode", str(model_file), "--out", str(tmp_path / "x.tiff")], "x.tiff")
    fails_cleanly(capsys, ["decode", str(model_file), "--out", str(tmp_path / "no" / "x.npy")], "x.npy")


def test_the_installed_command_exits_2_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "apmgsrn", "info", str(tmp_path / "none.apmgsrn")],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and result.stderr.startswith("error: ")


def test_a_reader_that_stops_early_gets_no_traceback(test_data, monkeypatch):
    """`apmgsrn info MODEL | head -1`: writing to a pipe whose reader has gone ends the command quietly with the
    status a tool killed by SIGPIPE has (141), not with a traceback."""
    import io
    import os

    read_end, write_end = os.pipe()
    os.close(read_end)
    stdout = io.TextIOWrapper(os.fdopen(write_end, "wb"), line_buffering=True)
    monkeypatch.setattr(sys, "stdout", stdout)
    try:
        assert main(["info", str(test_data / "reference_field.apmgsrn")]) == 141
    finally:
        monkeypatch.undo()
        try:
            stdout.close()
        except OSError:
            pass


def test_a_packing_that_fails_after_training_says_where_the_trained_model_is(test_data, tmp_path, capsys):
    """A bound too tight for float32 is found only after training: the one-line error says so and that the
    trained model is at --out, unpacked, and that file loads."""
    import apmgsrn

    out = tmp_path / "m.apmgsrn"
    fails_cleanly(capsys, ["train", str(test_data / "turbulence_vorticity_48.npy"), "--iterations", "5",
                           "--batch-size", "1024", "--device", "cpu", "--max-error", "1e-9", "--json",
                           "--out", str(out)],
                  "--max-error", f"the trained model is kept, not packed, at {out}", "apmgsrn pack")
    assert apmgsrn.load(out).description.packing is None
