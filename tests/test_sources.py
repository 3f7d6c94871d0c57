"""The render source both ``apmgsrn render`` and the viewer open: a model file, a brick-model folder or a
volume, with what a render needs beside the field; and its user errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import VolumeField, extent_from_shape, make_transfer_function
from apmgsrn.sources import SourceOptions, is_model_path, open_source, routing_boxes

DATA = Path(__file__).resolve().parent / "data"
VOLUME = DATA / "neghip_32x32x32_uint8.npy"
MODEL = DATA / "render_reference_model.apmgsrn"
BRICKS = DATA / "render_reference_bricks"


def test_a_volume_opens_with_its_voxels_range_and_histogram():
    voxels = np.load(VOLUME)
    source = open_source(VOLUME, options=SourceOptions(histogram_bins=16))
    assert source.kind == "volume" and source.name == str(VOLUME)
    assert source.value_range == (float(voxels.min()), float(voxels.max()))
    assert source.volume_shape == voxels.shape and source.extent == extent_from_shape(voxels.shape)
    assert isinstance(source.field, VolumeField) and torch.equal(source.field.volume, torch.from_numpy(voxels).float())
    assert source.grid_boxes is None and source.brick_boxes is None
    counts = np.histogram(voxels, bins=16, range=source.value_range)[0]
    np.testing.assert_allclose(source.histogram, np.log1p(counts) / np.log1p(counts).max(), atol=1e-4)
    renderer = source.renderer(make_transfer_function("viridis", source.value_range))
    assert renderer.bounds is not None and renderer.bounds.exact  # pooled from the voxels, not sampled


def test_a_model_opens_with_its_metadata_and_grid_boxes():
    source = open_source(MODEL)
    loaded = apmgsrn.load(MODEL)
    assert source.kind == "model" and source.histogram == []
    assert source.value_range == loaded.description.value_range
    assert source.volume_shape == (32, 32, 32)
    assert source.grid_boxes.shape == (2, 8, 3) and source.brick_boxes is None
    points = torch.rand(100, 3) * 2 - 1
    torch.testing.assert_close(source.field(points), loaded(points), atol=0, rtol=0)
    renderer = source.renderer(make_transfer_function("viridis", source.value_range))
    assert renderer.bounds is None and not renderer.ensure_bounds().exact  # sampled from the network


def test_a_brick_model_brings_its_bricks_and_every_bricks_grids():
    source = open_source(BRICKS, options=SourceOptions(histogram_bins=8))
    assert source.kind == "brick model" and "2 bricks (2x1x1)" in source.description
    assert torch.equal(source.brick_boxes, routing_boxes((2, 1, 1)))
    assert source.grid_boxes.shape == (4, 8, 3)  # two grids per brick, in global coordinates
    assert len(source.histogram) == 8 and max(source.histogram) == 1.0


def test_models_are_told_from_volumes(tmp_path):
    assert is_model_path(MODEL) and is_model_path(BRICKS)
    assert not is_model_path(VOLUME) and not is_model_path(DATA)
    renamed = tmp_path / "model.bin"
    renamed.write_bytes(MODEL.read_bytes())
    assert is_model_path(renamed)  # by its header, whatever its name
    broken = tmp_path / "broken.apmgsrn"
    broken.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not a model at all")
    assert is_model_path(broken)  # by its name, so it is refused as a model
    with pytest.raises(ApmgsrnError, match="broken.apmgsrn: not an apmgsrn model file"):
        open_source(broken)


def test_user_errors_name_the_file(tmp_path):
    with pytest.raises(ApmgsrnError, match="none.nc: no such file"):
        open_source(tmp_path / "none.nc")
    with pytest.raises(ApmgsrnError, match="32,768 voxels is more than"):
        open_source(VOLUME, options=SourceOptions(max_volume_voxels=1000))
    holes = np.load(VOLUME).astype(np.float32)
    holes[3, 4, 5] = np.nan
    path = tmp_path / "holes.npy"
    np.save(path, holes)
    with pytest.raises(ApmgsrnError, match="NaN or Inf"):
        open_source(path)
    filled = open_source(path, options=SourceOptions(volume={"fill_nonfinite": -1.0}))
    assert filled.value_range[0] == -1.0


def test_a_series_placed_per_step_shows_each_steps_own_grids(tmp_path):
    """A stepwise series whose steps placed their grids apart: the source at a step carries that step's grid
    boxes (what the viewer's overlay and render draw), not step 0's."""
    from apmgsrn.io import SeriesStepInfo, SourceInfo
    from apmgsrn.series.file import save_series
    from apmgsrn.models.registry import preset_config
    from apmgsrn.series.field import SeriesConfig, SeriesField, SeriesFieldConfig

    config = SeriesFieldConfig(preset_config("apmgsrn", "small", grids=3, resolution=(4, 4, 4), width=8),
                               SeriesConfig(3, 3, "keyframes", placement="per_step"))
    field = SeriesField(config, volume_shape=(8, 8, 8), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        field.encoder.translations[2].add_(0.3)  # step 2's grids sit elsewhere
    path = tmp_path / "placed.apmgsrn"
    save_series(path, field, SourceInfo(), {}, [SeriesStepInfo(float(t), f"s{t}", (0.0, 1.0)) for t in range(3)])
    source = open_source(path)
    torch.testing.assert_close(source.grid_boxes, field.encoder.grid_boxes(0))
    later = source.at_step(2)
    torch.testing.assert_close(later.grid_boxes, field.encoder.grid_boxes(2))
    assert not torch.allclose(later.grid_boxes, source.grid_boxes)
