"""A time series on bricks (issue 16): one job per (brick, group of steps), each reading only its box of its
steps, joint or (the default) stepwise and packed; a rerun after an interruption trains only the missing pairs
and reaches the same model; a step decodes as a brick model. Real data: the four consecutive
viscous-fingering steps of tests/data."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.series.data import open_series
from apmgsrn.decomposition.executor import DaskJobQueue
from apmgsrn.decomposition.planner import DecompositionConfig, plan_bricks
from apmgsrn.series.bricks import step_groups, train_series_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.decode import decode_array
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.io import model_kind
from apmgsrn.io.brick_folder import brick_file_name
from apmgsrn.models.registry import preset_config
from apmgsrn.series.field import SeriesConfig, SeriesFieldConfig
from apmgsrn.series.packing import SeriesPacking
from apmgsrn.series.steps import StepwiseConfig, stepwise_config
from apmgsrn.training.trainer import TrainConfig

pytest.importorskip("distributed")

CONFIG = SeriesFieldConfig(preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), width=32),
                           SeriesConfig(4, 2, "learned", residual=3))
TRAIN = TrainConfig(iterations=80, batch_size=2048, checkpoint_every=40)
GRID = DecompositionConfig((2, 1, 1), ghost_cells=1)


@pytest.fixture(scope="module")
def series(test_data):
    return open_series(str(test_data / "viscous_fingers_run01" / "*.vti")).absolute()


@pytest.fixture(scope="module")
def reference(series, client, tmp_path_factory):
    out = tmp_path_factory.mktemp("reference") / "series_bricks"
    summary = train_series_bricks(series, GRID, CONFIG, TRAIN, out, DaskJobQueue(client, threads_per_job=1),
                                  group_steps=3)
    return out, summary


def test_step_groups_cover_the_series():
    assert step_groups(7, 3) == [range(0, 3), range(3, 6), range(6, 7)]
    assert step_groups(4, None) == [range(0, 4)]


def test_every_brick_and_group_is_a_job_and_a_step_decodes_as_a_brick_model(reference, series):
    out, summary = reference
    assert summary.complete and not summary.failed
    # Groups of 3 steps over 4: steps 0-2 and step 3, two bricks each, four jobs.
    assert [len(g.trained) for g in summary.groups] == [2, 2]
    assert sorted(p.name for p in out.iterdir()) == ["series.json", "steps_000000_000003", "steps_000003_000004"]
    assert model_kind(out) == "series-bricks"
    model = apmgsrn.load(out)
    layout = model.description.series
    assert [s.label for s in layout.steps] == [30, 31, 32, 33]
    truth = series.to_numpy()
    assert layout.steps[3].value_range == (float(truth[3].min()), float(truth[3].max()))
    plan = plan_bricks(series.shape, GRID)
    for step in (1, 3):
        field = model.field.step_field(step)
        group_folder = out / ("steps_000000_000003" if step < 3 else "steps_000003_000004")
        local = step if step < 3 else 0
        decoded = decode_array(field, series.shape)
        # Each brick's own box decodes as that brick's series model at the step, in the brick's coordinates.
        for brick in plan.bricks:
            brick_model = apmgsrn.load(group_folder / brick_file_name(brick.name)).field.step_field(local)
            core = tuple(slice(a, b) for a, b in zip(brick.core_start, brick.core_stop))
            box = decode_array(brick_model, brick.shape)
            offset = tuple(slice(a - s, b - s) for a, b, s in zip(brick.core_start, brick.core_stop, brick.start))
            np.testing.assert_allclose(decoded[core], box[offset], atol=1e-4)
        assert evaluate(field, truth[step]).psnr > 25.0


def test_a_rerun_trains_only_the_missing_pairs_and_reaches_the_same_model(reference, series, client, tmp_path):
    out, _ = reference
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "steps_000003_000004" / brick_file_name("brick_001_000_000")).unlink()
    summary = train_series_bricks(series, GRID, CONFIG, TRAIN, copy, DaskJobQueue(client, threads_per_job=1),
                                  group_steps=3)
    assert [len(g.trained) for g in summary.groups] == [0, 1] and summary.complete
    a, b = apmgsrn.load(out), apmgsrn.load(copy)
    wa, wb = a.field.state_dict(), b.field.state_dict()
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def test_a_folder_of_another_run_is_refused(reference, series, client):
    out, _ = reference
    with pytest.raises(ApmgsrnError, match="other settings"):
        train_series_bricks(series, GRID, CONFIG, TRAIN, out, DaskJobQueue(client, threads_per_job=1), group_steps=2)


# ------------------------------------------------------------------------------- stepwise bricks (the default)
TINY = preset_config("apmgsrn", "small", grids=4, resolution=(8, 8, 8), width=32)
STEPWISE = StepwiseConfig(step_iterations=60)
STEPWISE_TRAIN = replace(TRAIN, iterations=300, voxel_fraction=0.5, anchored_grids=1)


@pytest.fixture(scope="module")
def stepwise_reference(series, client, tmp_path_factory):
    out = tmp_path_factory.mktemp("stepwise") / "series_bricks"
    summary = train_series_bricks(series, GRID, stepwise_config(TINY, 4), STEPWISE_TRAIN, out,
                                  DaskJobQueue(client, threads_per_job=1), group_steps=3, stepwise=STEPWISE,
                                  packing=SeriesPacking(10))
    return out, summary


def test_stepwise_bricks_train_every_group_from_its_own_start_and_pack_every_brick(stepwise_reference, series):
    out, summary = stepwise_reference
    assert summary.complete and [len(g.trained) for g in summary.groups] == [2, 2]
    model = apmgsrn.load(out)
    truth = series.to_numpy()
    plan = plan_bricks(series.shape, GRID)
    for folder, steps in (("steps_000000_000003", range(0, 3)), ("steps_000003_000004", range(3, 4))):
        for brick in plan.bricks:
            brick_model = apmgsrn.load(out / folder / brick_file_name(brick.name))
            assert brick_model.description.kind == "packed-series"
            assert brick_model.field.config.series.placement == "per_step"
            stepwise = brick_model.description.training["stepwise"]
            assert stepwise["start"] in range(len(steps)) and stepwise["step_iterations"][stepwise["start"]] == 0
            # Every step of the brick's box fits its own data better than the neighbouring step's grids do.
            box = tuple(slice(a, b) for a, b in zip(brick.start, brick.stop))
            for local in range(1, len(steps)):
                own = evaluate(brick_model.field.step_field(local), truth[steps[local]][box]).psnr
                assert own > evaluate(brick_model.field.step_field(local - 1), truth[steps[local]][box]).psnr
    for step in range(4):
        assert evaluate(model.field.step_field(step), truth[step]).psnr > 30.0


def test_a_stepwise_brick_rerun_trains_only_the_missing_pairs_and_reaches_the_same_model(
        stepwise_reference, series, client, tmp_path):
    out, _ = stepwise_reference
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "steps_000000_000003" / brick_file_name("brick_000_000_000")).unlink()
    summary = train_series_bricks(series, GRID, stepwise_config(TINY, 4), STEPWISE_TRAIN, copy,
                                  DaskJobQueue(client, threads_per_job=1), group_steps=3, stepwise=STEPWISE,
                                  packing=SeriesPacking(10))
    assert [len(g.trained) for g in summary.groups] == [1, 0] and summary.complete
    wa, wb = apmgsrn.load(out).field.state_dict(), apmgsrn.load(copy).field.state_dict()
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    # The same folder asked for a joint model is another run's.
    with pytest.raises(ApmgsrnError, match="other settings"):
        train_series_bricks(series, GRID, CONFIG, TRAIN, copy, DaskJobQueue(client, threads_per_job=1), group_steps=3)


# Slow tier: the command line on two worker processes; stepwise bricks (every group from its own start, every
# brick packed) are checked in the default tier in process.
@pytest.mark.slow
def test_train_with_bricks_is_stepwise_by_default(test_data, tmp_path, capsys):
    from apmgsrn.cli.main import main

    out = tmp_path / "bricks"
    argv = ["train", str(test_data / "viscous_fingers_run01" / "*.vti"), "--out", str(out), "--bricks", "2,1,1",
            "--group-steps", "2", "--workers", "2", "--iterations", "60", "--batch-size", "1024", "--resolution", "8",
            "--width", "16", "--step-iterations", "10", "--device", "cpu", "--json"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["complete"] and result["groups"] == 2
    assert "2x1x1 = 2 in each of 2 step groups (ghost cells 1); 4 to train, 0 already done" in captured.err
    assert "finished    steps_000002_000004: 2 of 2 bricks" in captured.err
    brick = apmgsrn.load(out / "steps_000000_000002" / brick_file_name("brick_000_000_000"))
    assert brick.description.kind == "packed-series" and "stepwise" in brick.description.training
    assert main(["eval", str(out), str(test_data / "viscous_fingers_run01" / "*.vti"), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["per_step"]
    assert len(rows) == 4 and all(row["psnr"] > 20 for row in rows)
    assert main(["info", str(out)]) == 0
    assert "4 steps, each with its own grids and placement: trained stepwise" in capsys.readouterr().out
