"""A time budget (training/timing.py, ``train --minutes``): the iterations sized to the machine before training."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.timing import size_for_minutes
from apmgsrn.training.trainer import TrainConfig

NEGHIP = "neghip_32x32x32_uint8.npy"


def test_the_sized_iterations_fill_the_budget_at_the_measured_rate(test_data):
    """The iterations times the measured seconds an iteration fit the minutes, one more would not; the density
    start keeps its share of the budget; the run's field is not the one the probe trained."""
    values = np.load(test_data / NEGHIP).astype(np.float32)
    prepared = prepare_values(values, "none", 0.0, NEGHIP, torch.device("cpu"))
    config = TrainConfig(iterations=1000, batch_size=1024, **training_defaults("hybrid"))
    def field():  # the probe trains it: a fresh one each time
        return NeuralField(preset_config("hybrid", "small"), volume_shape=values.shape,
                           generator=torch.Generator().manual_seed(0))

    for minutes in (0.005, 0.02):
        sized, budget = size_for_minutes(field(), prepared.values, config, minutes, probe_seconds=0.05)
        assert sized.iterations == budget.iterations >= 1
        assert budget.moving_seconds > 0 and budget.frozen_seconds > 0
        low, high = sorted((budget.moving_seconds, budget.frozen_seconds))
        assert low <= budget.seconds_per_iteration <= high
        assert budget.iterations * budget.seconds_per_iteration <= minutes * 60 or budget.iterations == 1
        assert (budget.iterations + 1) * budget.seconds_per_iteration > minutes * 60
        assert sized.density_start == min(sized.iterations, round(config.density_start / 1000 * sized.iterations))
        assert {k: v for k, v in vars(sized).items() if k not in ("iterations", "density_start")} == \
            {k: v for k, v in vars(config).items() if k not in ("iterations", "density_start")}
    with pytest.raises(ApmgsrnError, match="minutes"):
        size_for_minutes(field(), prepared.values, config, 0.0)


def test_train_minutes_records_the_budget_and_trains_that_many_iterations(test_data, tmp_path, capsys):
    out = tmp_path / "m.apmgsrn"
    assert main(["train", str(test_data / NEGHIP), "--out", str(out), "--minutes", "0.02", "--batch-size", "1024",
                 "--device", "cpu", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    training = apmgsrn.load(out).description.training
    budget = training["time_budget"]
    assert budget["minutes"] == 0.02 and summary["iterations"] == budget["iterations"] == training["iterations"]
    assert training["plan"]["minutes"] == 0.02


def test_a_time_budget_is_refused_beside_iterations_and_for_a_series(test_data, tmp_path, capsys):
    base = ["train", "--out", str(tmp_path / "m.apmgsrn"), "--minutes", "1", "--device", "cpu"]
    assert main([*base[:1], str(test_data / NEGHIP), *base[1:], "--iterations", "10"]) == 2
    assert "give one of them" in capsys.readouterr().err
    series = str(test_data / "viscous_fingers_run01" / "*.vti")
    assert main([*base[:1], series, *base[1:]]) == 2
    assert "time series" in capsys.readouterr().err
    for bad in ("0", "-1", "nan", "1e9"):
        assert main([*base[:1], str(test_data / NEGHIP), *base[1:3], "--minutes", bad]) == 2
        assert capsys.readouterr().err.count("\n") == 1


def test_the_dry_run_plan_of_a_budget_is_the_library_plan(test_data, capsys):
    data = str(test_data / NEGHIP)
    assert main(["train", data, "--minutes", "0.5", "--device", "cpu", "--dry-run", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(json.dumps(apmgsrn.plan(data, minutes=0.5, device="cpu").to_dict()))
    assert printed["minutes"] == 0.5


def test_a_resumed_budget_keeps_the_iterations_the_interrupted_run_chose(test_data, tmp_path):
    """Ctrl-C, then --resume: the schedule is the one the first run sized (read from its checkpoint, not
    measured again), so the resumed run ends at the same iteration count."""
    out = tmp_path / "m.apmgsrn"
    command = [sys.executable, "-m", "apmgsrn", "train", str(test_data / NEGHIP), "--out", str(out), "--minutes",
               "0.15", "--batch-size", "1024", "--checkpoint-every", "20", "--device", "cpu"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    checkpoint = Path(str(out) + ".ckpt")
    deadline = time.time() + 120
    while not checkpoint.exists():
        assert process.poll() is None, process.stderr.read().decode()
        assert time.time() < deadline
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    stdout, _ = process.communicate(timeout=60)
    assert process.returncode == 130
    sized = int(stdout.decode().split("iterations\n")[0].rsplit("-> ", 1)[1].replace(",", ""))
    subprocess.run([*command, "--resume"], check=True, capture_output=True)
    training = apmgsrn.load(out).description.training
    assert training["iterations"] == sized and training["time_budget"]["resumed"] is True
