"""Anchored grids (TrainConfig.anchored_grids): the first grids keep their starting placement while the
density loss moves the others; the CLI's size targets anchor one; bad counts are refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.cli.main import main
from apmgsrn.data import open_volume
from apmgsrn.errors import InvalidArgument
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.training.trainer import TrainConfig, Trainer, current_names


@pytest.fixture(scope="module")
def channel(test_data) -> torch.Tensor:
    """The real 96x64x48 channel-flow pressure crop, scaled to [0, 1]."""
    values = open_volume(test_data / "channel_pressure_96x64x48.nc", variable="pressure").read()
    values = torch.from_numpy(np.asarray(values, dtype=np.float32))
    return (values - values.min()) / (values.max() - values.min())


def placements_after(channel, anchored: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(matrices and translations before, after) 60 iterations whose grids move from the first one."""
    field = NeuralField(preset_config("apmgsrn", "small", grids=4, resolution=(6, 6, 6)),
                        volume_shape=tuple(channel.shape))
    field.encoder.reset_parameters(torch.Generator().manual_seed(3))
    before = torch.cat([field.encoder.matrices.detach().flatten(1), field.encoder.translations.detach()], 1)
    config = TrainConfig(iterations=60, batch_size=1024, density_start=1, freeze_fraction=1.0,
                         density_tolerance=0.0, anchored_grids=anchored, decoder_precision="float32")
    Trainer(field, channel, config).run()
    after = torch.cat([field.encoder.matrices.detach().flatten(1), field.encoder.translations.detach()], 1)
    return before, after  # [grids, 12]


@pytest.mark.parametrize("anchored", [0, 1, 3])
def test_anchored_grids_keep_their_placement_and_the_others_move(channel, anchored):
    before, after = placements_after(channel, anchored)
    moved = (after - before).abs().amax(1)  # [grids]
    assert torch.all(moved[:anchored] == 0)
    assert torch.all(moved[anchored:] > 1e-3)


def test_more_anchored_grids_than_moving_grids_are_refused(channel):
    field = NeuralField(preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4)),
                        volume_shape=tuple(channel.shape))
    with pytest.raises(InvalidArgument, match="anchored_grids=3: the model has 2 grids"):
        Trainer(field, channel, TrainConfig(iterations=5, batch_size=64, anchored_grids=3))
    fvsrn = NeuralField(preset_config("fvsrn", "small", resolution=(4, 4, 4)), volume_shape=tuple(channel.shape))
    with pytest.raises(InvalidArgument, match="has 0 grids"):
        Trainer(fvsrn, channel, TrainConfig(iterations=5, batch_size=64, anchored_grids=1))
    with pytest.raises(InvalidArgument, match="anchored_grids"):
        TrainConfig(anchored_grids=-1)


def test_the_command_line_names_a_bad_count_in_one_line(tmp_path, neghip_crop, capsys):
    path, _ = neghip_crop
    code = main(["train", str(path), "--out", str(tmp_path / "m.apmgsrn"), "--grids", "2", "--anchored-grids", "3",
                 "--iterations", "5", "--batch-size", "256", "--device", "cpu"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--anchored-grids" in err[0] and not (tmp_path / "m.apmgsrn").exists()


def test_a_small_size_target_anchors_one_grid_unless_told_otherwise(test_data, tmp_path, capsys):
    volume = str(test_data / "neghip_64x64x64_uint8.raw")  # 262,144 bytes
    common = ["--model", "apmgsrn", "--iterations", "5", "--batch-size", "256", "--device", "cpu"]
    assert main(["train", volume, "--out", str(tmp_path / "a.apmgsrn"), *common, "--ratio", "100"]) == 0
    out = capsys.readouterr().out
    assert "4 grids" in out and "one grid anchored over the domain" in out
    assert main(["train", volume, "--out", str(tmp_path / "b.apmgsrn"), *common, "--ratio", "100",
                 "--anchored-grids", "0"]) == 0
    assert "anchored" not in capsys.readouterr().out
    assert main(["train", volume, "--out", str(tmp_path / "c.apmgsrn"), *common, "--ratio", "10"]) == 0
    out = capsys.readouterr().out
    assert "16 grids" in out and "anchored" not in out  # enough grids that none loses its region


def test_info_says_how_many_grids_were_anchored(neghip_crop, tmp_path, capsys):
    path, _ = neghip_crop
    common = ["--grids", "4", "--resolution", "6", "--iterations", "20", "--batch-size", "256", "--device", "cpu"]
    for anchored in ("2", "0"):
        out = tmp_path / f"m{anchored}.apmgsrn"
        assert main(["train", str(path), "--out", str(out), *common, "--anchored-grids", anchored]) == 0
        capsys.readouterr()
        assert main(["info", str(out)]) == 0
        frozen = [line for line in capsys.readouterr().out.splitlines() if line.startswith("grids frozen")]
        assert len(frozen) == 1 and ("(2 anchored over the domain)" in frozen[0]) == (anchored == "2")


@pytest.mark.parametrize(("options", "series", "expected"), [
    ({}, False, 0),  # one volume: the paper's training
    ({"series_training": "joint"}, True, 1),  # a time series of APMGSRN anchors one
    ({"series_training": "joint", "anchored_grids": 0}, True, 0),
    ({"anchored_grids": 2}, False, 2),
])
def test_a_time_series_anchors_one_grid_unless_told_otherwise(test_data, options, series, expected):
    data = str(test_data / "viscous_fingers_run01" / ("*.vti" if series else "030_density_030_064_2.0.vti"))
    assert apmgsrn.plan(data, model="apmgsrn", device="cpu", **options).training.anchored_grids == expected


def test_checkpoints_from_before_the_option_resume_with_every_grid_moving():
    stored = {"iterations": 10, "batch_size": 64, "voxel_fraction": 0.0}
    assert current_names(stored)["anchored_grids"] == 0
