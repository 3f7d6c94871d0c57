"""A time series on bricks (issue 16): one job per (brick, group of steps), each reading only its box of its
steps; a rerun after an interruption trains only the missing pairs and reaches the same model; a step decodes
as a brick model. Real data: the four consecutive viscous-fingering steps of tests/data."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.data.series import open_series
from apmgsrn.decomposition.executor import DaskJobQueue
from apmgsrn.decomposition.planner import DecompositionConfig, plan_bricks
from apmgsrn.decomposition.series_bricks import step_groups, train_series_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.decode import decode_array
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.io import model_kind
from apmgsrn.io.brick_folder import brick_file_name
from apmgsrn.models.registry import preset_config
from apmgsrn.models.series_field import SeriesConfig, SeriesFieldConfig
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
