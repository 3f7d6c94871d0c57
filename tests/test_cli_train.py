"""End to end through the command line on real volumes: train, eval, decode, info, resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import apmgsrn
from apmgsrn.cli.main import main

NEGHIP = "neghip_64x64x64_uint8.raw"
FAST = ["--iterations", "200", "--batch-size", "4096", "--device", "cpu"]


def run_json(capsys, argv):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def neghip_model(tmp_path_factory, test_data):
    out = tmp_path_factory.mktemp("neghip") / "neghip.apmgsrn"
    # The paper's model: the figures below are its; the default model has its own (tests/test_hybrid_grid.py).
    assert main(["train", str(test_data / NEGHIP), "--out", str(out), "--model", "apmgsrn", *FAST]) == 0
    return out


def test_train_reaches_psnr_bar_on_real_volume(neghip_model, test_data, capsys):
    # Electron density of a protein, 64^3 uint8: 200 iterations of 4096 points reach ~32 dB (bar: 30).
    result = run_json(capsys, ["eval", str(neghip_model), str(test_data / NEGHIP), "--json"])
    assert set(result) == {"psnr", "mse", "max_abs_error", "data_min", "data_max", "model_bytes", "data_dtype",
                           "data_bytes", "float32_bytes", "compression_ratio", "compression_ratio_float32"}
    assert result["psnr"] > 30.0
    assert result["data_min"] == 0 and result["data_max"] == 255
    assert result["model_bytes"] == neghip_model.stat().st_size
    # A uint8 volume is 1 byte a voxel as stored (SPEC section 8), 4 as float32.
    assert result["data_dtype"] == "uint8" and result["data_bytes"] == 64**3 and result["float32_bytes"] == 64**3 * 4
    assert result["compression_ratio"] == pytest.approx(64**3 / neghip_model.stat().st_size)
    assert result["compression_ratio_float32"] == pytest.approx(64**3 * 4 / neghip_model.stat().st_size)


def test_eval_matches_a_direct_computation(neghip_model, test_data, capsys):
    model = apmgsrn.load(neghip_model)
    data = np.fromfile(test_data / NEGHIP, dtype=np.uint8).reshape(64, 64, 64).astype(np.float64)
    axis = torch.linspace(-1, 1, 64)
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    points = torch.stack([x, y, z], -1).reshape(-1, 3)
    with torch.no_grad():
        pred = model(points).view(64, 64, 64).double().numpy()
    mse = np.mean((pred - data) ** 2)
    expected = 20 * np.log10(255.0) - 10 * np.log10(mse)
    result = run_json(capsys, ["eval", str(neghip_model), str(test_data / NEGHIP), "--json"])
    assert result["psnr"] == pytest.approx(expected, abs=1e-6)
    # linspace and the evaluator's lattice round the coordinates differently: 1e-5 absorbs that.
    assert result["max_abs_error"] == pytest.approx(np.abs(pred - data).max(), rel=1e-5)
    # The training summary measured the same figures right after training, on the same lattice (bit for bit
    # on a CPU; a GPU's summation order may move the last digits of the mean).
    summary = model.description.training
    assert summary["psnr"] == pytest.approx(result["psnr"], abs=1e-6)
    assert summary["max_abs_error"] == pytest.approx(result["max_abs_error"], rel=1e-6)
    assert main(["eval", str(neghip_model), str(test_data / NEGHIP)]) == 0
    text = capsys.readouterr().out
    largest = result["max_abs_error"]
    assert f"max abs error     {largest:.6g} ({100 * largest / 255:.2g} % of the value range)" in text
    assert result["max_abs_error"] == pytest.approx(np.abs(pred - data).max(), rel=1e-6)


def test_decode_writes_the_model_values_at_any_resolution(neghip_model, tmp_path):
    out = tmp_path / "decoded.npy"
    assert main(["decode", str(neghip_model), "--out", str(out), "--shape", "20,10,5"]) == 0
    decoded = np.load(out)
    assert decoded.shape == (5, 10, 20)  # (z, y, x) for X,Y,Z = 20,10,5
    model = apmgsrn.load(neghip_model)
    point = torch.tensor([[-1.0 + 2 * 7 / 19, -1.0 + 2 * 3 / 9, -1.0 + 2 * 2 / 4]])
    with torch.no_grad():
        assert float(model(point)) == pytest.approx(float(decoded[2, 3, 7]), rel=1e-5, abs=1e-4)


def test_decode_to_netcdf_round_trips_through_the_reader(neghip_model, tmp_path, capsys):
    out = tmp_path / "decoded.nc"
    assert main(["decode", str(neghip_model), "--out", str(out)]) == 0
    # The decoded volume evaluated against the model's own output is exact.
    result = run_json(capsys, ["eval", str(neghip_model), str(out), "--json"])
    assert result["max_abs_error"] < 1e-3


def test_info_reports_architecture_training_and_grids(neghip_model, capsys, tmp_path):
    info = run_json(capsys, ["info", str(neghip_model), "--json"])
    assert info["parameters"] == 70_912 and info["parameter_bytes"] == 70_912 * 4
    assert info["volume_shape_xyz"] == [64, 64, 64]
    assert info["training"]["iterations"] == 200 and info["training"]["frozen_at"] == 100
    assert len(info["grids"]) == 16 and info["value_range"] == [0.0, 255.0]
    assert main(["info", str(neghip_model)]) == 0
    text = capsys.readouterr().out
    assert "grids frozen at iteration 100" in text and "70,912" in text
    plot = tmp_path / "curves.png"
    assert main(["info", str(neghip_model), "--plot", str(plot)]) == 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_log10_transform_fits_cosmology_density_in_data_units(test_data, tmp_path, capsys):
    # Dark-matter density spans 0.23 .. 2.8e5: fitted in log10, decoded in data units.
    out = tmp_path / "dm.apmgsrn"
    result = run_json(capsys, ["train", str(test_data / "darkmatter_density_64.h5"), "--out", str(out),
                               "--transform", "log10", *FAST, "--json"])
    model = apmgsrn.load(out)
    assert model.field.transform.kind == "log10" and model.description.transform == "log10"
    with torch.no_grad():
        values = model(torch.rand(4096, 3) * 2 - 1)
    assert float(values.min()) > 0.1 and float(values.max()) < 3e5  # data units, positive
    assert result["psnr"] > 20


def _train_command(data, out, *extra):
    return [sys.executable, "-m", "apmgsrn", "train", str(data), "--out", str(out), "--iterations", "120",
            "--batch-size", "1024", "--checkpoint-every", "20", "--device", "cpu", *extra]


def _same_weights(a: Path, b: Path) -> bool:
    ta, tb = load_file(str(a)), load_file(str(b))
    return ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, test_data):
    out = tmp_path_factory.mktemp("full") / "full.apmgsrn"
    subprocess.run(_train_command(test_data / NEGHIP, out), check=True, capture_output=True)
    return out


def _wait_for(path: Path, process: subprocess.Popen, seconds: float = 120) -> None:
    deadline = time.time() + seconds
    while not path.exists():
        assert process.poll() is None, process.stderr.read().decode()
        assert time.time() < deadline, "no checkpoint appeared"
        time.sleep(0.05)


# Slow tier: a real kill of a training process; the checkpoint and --resume are checked in the default tier by
# test_ctrl_c_saves_then_resume_reaches_the_same_model.
@pytest.mark.slow
def test_resume_after_kill_reaches_the_same_model(test_data, tmp_path, uninterrupted):
    out = tmp_path / "killed.apmgsrn"
    checkpoint = Path(str(out) + ".ckpt")
    process = subprocess.Popen(_train_command(test_data / NEGHIP, out), stderr=subprocess.PIPE,
                               stdout=subprocess.PIPE)
    _wait_for(checkpoint, process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not out.exists() and checkpoint.exists()
    # Without --resume the leftover checkpoint is not silently overwritten.
    refused = subprocess.run(_train_command(test_data / NEGHIP, out), capture_output=True, text=True)
    assert refused.returncode == 2 and "--resume" in refused.stderr
    subprocess.run(_train_command(test_data / NEGHIP, out, "--resume"), check=True, capture_output=True)
    assert _same_weights(out, uninterrupted)
    assert not checkpoint.exists()


def test_ctrl_c_saves_then_resume_reaches_the_same_model(test_data, tmp_path, uninterrupted):
    out = tmp_path / "interrupted.apmgsrn"
    checkpoint = Path(str(out) + ".ckpt")
    process = subprocess.Popen(_train_command(test_data / NEGHIP, out), stderr=subprocess.PIPE,
                               stdout=subprocess.PIPE)
    _wait_for(checkpoint, process)
    process.send_signal(signal.SIGINT)
    stdout, _ = process.communicate(timeout=60)
    assert process.returncode == 130 and b"--resume" in stdout
    assert checkpoint.exists() and not out.exists()
    subprocess.run(_train_command(test_data / NEGHIP, out, "--resume"), check=True, capture_output=True)
    assert _same_weights(out, uninterrupted)


def test_resume_with_other_settings_is_refused(test_data, tmp_path):
    out = tmp_path / "m.apmgsrn"
    process = subprocess.Popen(_train_command(test_data / NEGHIP, out), stderr=subprocess.PIPE,
                               stdout=subprocess.PIPE)
    _wait_for(Path(str(out) + ".ckpt"), process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    other = subprocess.run(_train_command(test_data / NEGHIP, out, "--resume", "--lr", "0.02"),
                           capture_output=True, text=True)
    assert other.returncode == 2 and "other data or settings" in other.stderr
    assert os.path.exists(str(out) + ".ckpt")  # nothing lost
