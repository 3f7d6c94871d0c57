"""Training batches on voxels (TrainConfig.voxel_fraction): where the points land, what the targets are, and
that the trainer, the command line, the API and the benchmark use the option."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from apmgsrn.bench.results import QualityRow, read_rows
import apmgsrn
from apmgsrn.data import open_volume
from apmgsrn.errors import InvalidArgument
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.trilinear import sample_volume
from apmgsrn.training.points import draw_batch, spatially_ordered, voxel_count
from apmgsrn.training.trainer import TrainConfig, Trainer


@pytest.fixture(scope="module")
def channel(test_data) -> torch.Tensor:
    """The real 96x64x48 channel-flow pressure crop, scaled to [0, 1] (non-cubic: catches swapped axes)."""
    values = open_volume(test_data / "channel_pressure_96x64x48.nc", variable="pressure").read()
    values = torch.from_numpy(np.asarray(values, dtype=np.float32))
    return (values - values.min()) / (values.max() - values.min())


def test_no_voxel_points_draws_what_the_trainer_always_drew(channel):
    points, targets = draw_batch(channel, 1000, 0.0, torch.Generator().manual_seed(3))
    expected = torch.rand(1000, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1
    assert torch.equal(points, expected)
    assert torch.equal(targets, sample_volume(channel, expected))


def test_voxel_points_sit_on_voxels_and_carry_their_values(channel):
    d, h, w = channel.shape
    points, targets = draw_batch(channel, 4000, 1.0, torch.Generator().manual_seed(0))
    # back to indices: every coordinate is a lattice position
    index = (points + 1) / 2 * torch.tensor([w - 1, h - 1, d - 1])
    assert torch.allclose(index, index.round(), atol=1e-4)
    x, y, z = index.round().long().unbind(1)
    assert torch.equal(targets, channel[z, y, x])
    # interpolating the volume there gives the voxel back (same convention as sample_volume)
    assert torch.allclose(sample_volume(channel, points), targets, atol=1e-6)
    # drawn over the whole volume, not one corner of it
    assert {int(x.max() > w * 0.9), int(y.max() > h * 0.9), int(z.max() > d * 0.9)} == {1}


def test_a_mix_keeps_its_share_and_trilinear_targets_for_the_rest(channel):
    points, targets = draw_batch(channel, 1001, 0.5, torch.Generator().manual_seed(1))
    on_voxels = voxel_count(1001, 0.5)
    assert points.shape == (1001, 3) and targets.shape == (1001,) and on_voxels in (500, 501)
    rest = points[on_voxels:]
    assert torch.equal(targets[on_voxels:], sample_volume(channel, rest))
    d, h, w = channel.shape
    index = (rest + 1) / 2 * torch.tensor([w - 1, h - 1, d - 1])
    assert (index - index.round()).abs().max() > 0.1  # uniform points, not voxels


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), "half", None])
def test_the_share_must_be_a_number_in_0_1(bad):
    with pytest.raises(InvalidArgument, match="voxel_fraction"):
        TrainConfig(voxel_fraction=bad)


def test_the_trainer_fits_the_batch_the_option_draws(channel):
    field = NeuralField(preset_config("apmgsrn", "small", grids=2), volume_shape=tuple(channel.shape))
    config = TrainConfig(iterations=10, batch_size=512, voxel_fraction=0.75, seed=5)
    before = copy.deepcopy(field)
    losses = Trainer(field, channel, config).step()
    points, targets = draw_batch(channel, 512, 0.75, torch.Generator().manual_seed(5))
    with torch.no_grad():
        expected = (before.normalized(points).view(-1) - targets).square().mean()
    assert float(losses.reconstruction) == pytest.approx(float(expected), rel=1e-5)


def test_a_series_draws_each_group_on_its_own_step(channel):
    from apmgsrn.series.field import SeriesConfig, SeriesField, SeriesFieldConfig

    series = torch.stack([channel, 1 - channel, channel.flip(0)])  # [T, D, H, W]
    tiny = preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4))
    field = SeriesField(SeriesFieldConfig(tiny, SeriesConfig(3, 2)))
    trainer = Trainer(field, series, TrainConfig(iterations=10, batch_size=300, voxel_fraction=1.0,
                                                 steps_per_iteration=3))
    steps = trainer.batch_steps(0)
    points, targets = trainer._draw_series_batch(steps)
    for group, (p, t) in enumerate(zip(points.view(3, -1, 3), targets.view(3, -1))):
        assert torch.allclose(sample_volume(series[steps[group]], p), t, atol=1e-6)


@pytest.mark.parametrize(("argv", "expected"), [
    (["--model", "hybrid"], 0.5),
    (["--model", "apmgsrn"], 0.0),
    (["--model", "ngp"], 0.0),
    (["--model", "apmgsrn", "--voxel-fraction", "0.25"], 0.25),
    (["--model", "hybrid", "--voxel-fraction", "0"], 0.0),
])
def test_each_model_kind_has_its_default_and_the_flag_overrides_it(test_data, argv, expected):
    assert _dry_run(test_data, argv)["training"]["voxel_fraction"] == expected


@pytest.mark.parametrize(("argv", "expected"), [
    (["--model", "hybrid"], 1.0),
    (["--model", "apmgsrn"], 0.0),
    (["--model", "hybrid", "--error-sampling", "0"], 0.0),
    (["--model", "apmgsrn", "--voxel-fraction", "0.5", "--error-sampling", "0.5"], 0.5),
])
def test_the_hybrid_draws_its_voxel_points_where_it_is_wrong_unless_told_otherwise(test_data, argv, expected):
    assert _dry_run(test_data, argv)["training"]["error_sampling"] == expected


def _dry_run(test_data, argv: list[str]) -> dict:
    """The plan ``train --dry-run --json`` prints for the bundled neghip volume."""
    import contextlib
    import io
    import json

    from apmgsrn.cli.main import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["train", str(test_data / "neghip_32x32x32_uint8.npy"), "--device", "cpu", "--dry-run",
                     "--json", *argv]) == 0
    return json.loads(out.getvalue())


def test_the_command_line_names_a_bad_share(tmp_path, neghip_crop, capsys):
    from apmgsrn.cli.main import main

    path, _ = neghip_crop
    code = main(["train", str(path), "--out", str(tmp_path / "m.apmgsrn"), "--voxel-fraction", "2"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--voxel-fraction" in err[0]


def test_benchmark_results_from_before_the_option_read_as_uniform_points(tmp_path):
    import csv
    import dataclasses

    from apmgsrn.bench.results import write_rows

    names = [f.name for f in dataclasses.fields(QualityRow)
             if f.name not in ("voxel_fraction", "max_abs_error", "error_sampling")]
    row = dict(dataset="hcci_oh_187.nc:oh", shape="187x187x187", model="hybrid", size="small", seed=0,
               iterations=2000, batch_size=32768, lr_schedule="cosine", parameters=69104, parameter_bytes=276416,
               file_bytes=290112, data_dtype="float32", data_bytes=26156812, compression_ratio=90.2,
               compression_ratio_float32=90.2, psnr=53.33, train_seconds=112.3, ms_per_iteration=56.1,
               device="cpu", model_file="m.apmgsrn")
    older = tmp_path / "quality.csv"
    with open(older, "w", newline="") as handle:  # a results file written before the column existed
        writer = csv.writer(handle)
        writer.writerow(names)
        writer.writerow([row[name] for name in names])
    (read,) = read_rows(older, QualityRow)
    assert read.voxel_fraction == 0.0 and read.psnr == 53.33 and math.isnan(read.max_abs_error)
    assert read.error_sampling == 0.0
    assert read.key() != dataclasses.replace(read, voxel_fraction=0.5).key()
    assert read.key() != dataclasses.replace(read, error_sampling=1.0).key()
    write_rows(older, [read], QualityRow)  # today's columns; read back unchanged (the missing error stays NaN)
    (again,) = read_rows(older, QualityRow)
    assert dataclasses.replace(again, max_abs_error=0.0) == dataclasses.replace(read, max_abs_error=0.0)
    assert math.isnan(again.max_abs_error)
    extra = tmp_path / "other.csv"
    extra.write_text(older.read_text().replace("voxel_fraction", "unknown_column"))
    with pytest.raises(Exception, match="other columns"):
        read_rows(extra, QualityRow)


def test_the_python_api_trains_with_the_model_kinds_default_unless_given(neghip_crop):
    import apmgsrn

    _, data = neghip_crop
    budget = dict(iterations=5, batch_size=256, device="cpu")
    hybrid = apmgsrn.fit(data, model="hybrid", **budget)
    given = apmgsrn.fit(data, model="apmgsrn", voxel_fraction=0.3, **budget)
    assert hybrid.description.training["config"]["voxel_fraction"] == 0.5
    assert hybrid.description.training["config"]["error_sampling"] == 1.0
    assert given.description.training["config"]["voxel_fraction"] == 0.3
    assert given.description.training["config"]["error_sampling"] == 0.0


def test_info_says_how_much_of_each_batch_was_on_voxels(neghip_crop, tmp_path, capsys):
    import apmgsrn
    from apmgsrn.cli.main import main

    _, data = neghip_crop
    budget = dict(iterations=5, batch_size=256, device="cpu")
    apmgsrn.fit(data, model="hybrid", **budget).save(tmp_path / "hybrid.apmgsrn")
    apmgsrn.fit(data, model="apmgsrn", **budget).save(tmp_path / "paper.apmgsrn")
    assert main(["info", str(tmp_path / "hybrid.apmgsrn")]) == 0
    assert "256 points (0.5 of each on voxels, 1 of those where the error was)" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "paper.apmgsrn")]) == 0
    assert "on voxels" not in capsys.readouterr().out


def test_an_ordered_batch_keeps_every_point_with_its_target_and_runs_through_the_lattice(channel):
    points, targets = draw_batch(channel, 3000, 0.5, torch.Generator().manual_seed(4))
    ordered, ordered_targets = spatially_ordered(points, targets, cells=16)
    # a permutation of the same (point, target) pairs
    pairs = torch.cat([points, targets[:, None]], 1)
    reordered = torch.cat([ordered, ordered_targets[:, None]], 1)
    assert sorted(map(tuple, pairs.tolist())) == sorted(map(tuple, reordered.tolist()))
    assert torch.allclose(sample_volume(channel, ordered), ordered_targets, atol=1e-6)
    # z slowest, x fastest over a 16^3 lattice of cells; the unordered draw was not
    cell = ((ordered + 1) * 7.5).round().long()
    key = (cell[:, 2] * 16 + cell[:, 1]) * 16 + cell[:, 0]
    assert bool((key[1:] >= key[:-1]).all())
    assert not bool((((points + 1) * 7.5).round().long() == cell).all())


def test_the_hybrid_orders_cpu_batches_only_once_its_tables_outgrow_the_caches(channel):
    def trainer(model: str, size: str) -> Trainer:
        field = NeuralField(preset_config(model, size), volume_shape=channel.shape,
                            generator=torch.Generator().manual_seed(0))
        return Trainer(field, channel, TrainConfig(iterations=10, batch_size=2048, seed=5, voxel_fraction=0.5))

    assert not trainer("hybrid", "small").order_batches
    assert not trainer("apmgsrn", "medium").order_batches  # the paper's model trains as it always did
    ordered, plain = trainer("hybrid", "medium"), trainer("hybrid", "medium")
    assert ordered.order_batches
    plain.order_batches = False
    losses = [run.step().reconstruction for run in (ordered, plain)]
    # the same batch in another order: the same loss and the same step, up to the order of the sums
    assert torch.allclose(losses[0], losses[1], rtol=1e-5)
    for (name, a), (_, b) in zip(ordered.field.state_dict().items(), plain.field.state_dict().items()):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6), name


# ------------------------------------------------------------------------------- error-guided voxel points
def _with_error_in(channel: torch.Tensor, box: tuple[slice, slice, slice], error: torch.Tensor | float):
    """A predictor of voxel positions that returns the channel's own values, off by ``error`` inside ``box``
    (exactly right elsewhere)."""
    wrong = channel.clone()
    wrong[box] += error
    d, h, w = channel.shape

    def predict(points):
        x, y, z = (((points[:, axis] + 1) * (n - 1) / 2).round().long() for axis, n in enumerate((w, h, d)))
        return wrong.reshape(-1)[(z * h + y) * w + x]

    return predict


def test_error_guided_voxels_land_where_the_model_is_wrong_in_proportion_to_the_error(channel):
    """Voxels are drawn as often as their share of the total absolute error says: none where the prediction is
    exact, twice as many where it is twice as far off."""
    from apmgsrn.training.points import ErrorGuide

    box = (slice(10, 30), slice(5, 25), slice(0, 48))
    error = torch.zeros(20, 20, 48)
    error[:, :, :24] = 0.01
    error[:, :, 24:] = 0.02  # twice as far off in the far half of the box
    guide = ErrorGuide(channel, pool=channel.numel())  # every voxel measured
    generator = torch.Generator().manual_seed(0)
    guide.measure(_with_error_in(channel, box, error), generator)
    index = guide.draw(30000, generator)
    assert index.shape == (30000,)
    d, h, w = channel.shape
    z, y, x = index // (h * w), index // w % h, index % w
    assert bool(((z >= 10) & (z < 30) & (y >= 5) & (y < 25)).all())
    far = int((x >= 24).sum())
    assert far / (30000 - far) == pytest.approx(2.0, rel=0.02)
    # Voxels of equal error are drawn equally often (systematic sampling: within one of each other).
    counts = torch.bincount(index, minlength=channel.numel())
    near = counts.view(d, h, w)[10:30, 5:25, :24]
    assert int(near.max()) - int(near.min()) <= 1


def test_the_draws_search_finds_what_torch_searchsorted_finds(channel):
    """The guide's search (NumPy's on a CPU) against ``torch.searchsorted``: a real volume's absolute
    values as errors (zeros among them, so runs of equal sums), queries as a draw makes them, and ties at
    exactly a running sum's value."""
    from apmgsrn.training.points import search_sorted

    errors = channel.reshape(-1).double().abs()
    errors[::7] = 0.0
    cumulative = errors.cumsum(0) / errors.sum()
    for count, offset in ((8192, 0.3), (100, 0.999), (30000, 0.0)):
        queries = (torch.arange(1, count + 1, dtype=torch.float64) - offset) / count
        queries = torch.cat([queries, cumulative[::997]])  # exact ties too
        found = search_sorted(cumulative, queries)
        assert found.dtype == torch.int64 and torch.equal(found, torch.searchsorted(cumulative, queries))


def test_the_draws_merge_walk_finds_what_torch_searchsorted_finds(channel):
    """The guide's search for ascending draws (a merge walk in C on a CPU) against ``torch.searchsorted``: a
    real volume's absolute values as errors (zeros among them, so runs of equal sums), queries as a draw makes
    them, exact ties at a running sum's value, queries before the first sum and past the last, and none."""
    from apmgsrn.ops.sorted_search_cpu import LIBRARY, ascending_search_cpu
    from apmgsrn.training.points import search_ascending

    assert LIBRARY.available(), LIBRARY.error
    errors = channel.reshape(-1).double().abs()
    errors[::7] = 0.0
    cumulative = errors.cumsum(0) / errors.sum()
    for count, offset in ((8192, 0.3), (100, 0.999), (30000, 0.0), (1, 0.5)):
        queries = (torch.arange(1, count + 1, dtype=torch.float64) - offset) / count
        queries, _ = torch.cat([queries, cumulative[::997], torch.tensor([-1.0, 0.0, 2.0], dtype=torch.float64)]
                               ).sort()
        expected = torch.searchsorted(cumulative, queries)
        assert torch.equal(ascending_search_cpu(cumulative, queries), expected)
        assert torch.equal(search_ascending(cumulative, queries), expected)
    assert ascending_search_cpu(cumulative, torch.empty(0, dtype=torch.float64)).shape == (0,)


@pytest.mark.parametrize("shape,pool", [((48, 64, 96), None), ((48, 64, 96), 3000), ((1, 40, 33), 200),
                                        ((50, 1, 7), 40), ((5, 6, 1), None)])
def test_a_guided_draw_in_one_pass_gives_what_the_tensor_path_gives_bit_for_bit(channel, shape, pool):
    """The CPU's one-pass guided draw (search, block, voxel, position, value) against the tensor operations it
    replaces, from the same random draws: the same indices, points and values to the bit, on a real volume
    measured voxel by voxel and in blocks (voxels clamped at a block that the volume's edge cuts), and on
    lattices with an axis of one voxel; on one thread and with the draws split between threads."""
    from apmgsrn.ops.sorted_search_cpu import LIBRARY
    from apmgsrn.training.points import ErrorGuide

    assert LIBRARY.available(), LIBRARY.error
    d, h, w = shape
    volume = channel[:d, :h, :w].contiguous() if shape[0] <= channel.shape[0] else None
    volume = volume if volume is not None and volume.shape == shape else torch.rand(shape)
    guide = ErrorGuide(volume, pool=pool) if pool else ErrorGuide(volume)
    guide.measure(lambda points: torch.zeros(len(points)), torch.Generator())  # errors = |values|
    threads = torch.get_num_threads()
    try:
        for workers in (1, 2, 3):  # 20,000 draws run on one thread, then split between two and three
            torch.set_num_threads(workers)
            for seed, count in ((1, 777), (2, 1), (3, 20000)):
                index, points, values = guide.draw_voxels(count, torch.Generator().manual_seed(seed))
                expected = guide.draw(count, torch.Generator().manual_seed(seed))
                assert torch.equal(index, expected)
                assert torch.equal(points, guide.voxel_points(expected))
                assert torch.equal(values, volume.reshape(-1)[expected])
    finally:
        torch.set_num_threads(threads)


def test_error_guided_points_sit_on_voxels_with_their_values_and_keep_the_uniform_share(channel):
    from apmgsrn.training.points import ErrorGuide

    guide = ErrorGuide(channel)
    guide.measure(_with_error_in(channel, (slice(0, 8), slice(None), slice(None)), 0.05), torch.Generator())
    points, targets = draw_batch(channel, 4000, 0.5, torch.Generator().manual_seed(1), guide, 0.5)
    assert torch.allclose(sample_volume(channel, points), targets, atol=1e-6)
    on_voxels = points[:2000]
    d = channel.shape[0]
    z = ((on_voxels[:, 2] + 1) * (d - 1) / 2).round()
    assert int((z < 8).sum()) >= 1000  # the guided half, in the wrong slab, and some of the uniform half
    assert int((z >= 8).sum()) > 700  # the uniform half of the voxel points lands all over


@pytest.mark.parametrize("depth", [40, 48])
def test_a_guides_voxel_positions_are_those_voxel_points_computes_bit_for_bit(channel, depth):
    """The guide's table of every voxel's position (made by its measurement of every voxel) gives the positions
    the batch's voxel points always had, before a measurement (a resumed run) and after; a volume measured in
    blocks (48 x 64 x 96) has no table and computes them."""
    from apmgsrn.recipes import VOLUME
    from apmgsrn.training.points import ErrorGuide, voxel_points

    channel = channel[:depth].contiguous()
    guide = ErrorGuide(channel)
    index = torch.randint(0, channel.numel(), (5000,), generator=torch.Generator().manual_seed(2))
    index[:2] = torch.tensor([0, channel.numel() - 1])
    expected = voxel_points(index, tuple(channel.shape))
    assert torch.equal(guide.voxel_points(index), expected)  # no table yet: computed
    guide.measure(_with_error_in(channel, (slice(0, 8), slice(None), slice(None)), 0.05), torch.Generator())
    assert (guide._every_voxel is not None) == (channel.numel() <= VOLUME.error_pool)
    assert torch.equal(guide.voxel_points(index), expected)  # from the table where there is one
    points, targets = draw_batch(channel, 4000, 1.0, torch.Generator().manual_seed(1), guide, 0.5)
    drawn = ((points + 1) / 2 * torch.tensor([channel.shape[2] - 1, channel.shape[1] - 1, channel.shape[0] - 1])
             ).round().long()
    flat = (drawn[:, 2] * channel.shape[1] + drawn[:, 1]) * channel.shape[2] + drawn[:, 0]
    assert torch.equal(points, voxel_points(flat, tuple(channel.shape)))
    assert torch.equal(targets, channel.reshape(-1)[flat])


def test_a_large_volume_is_measured_once_per_block_and_drawn_anywhere_in_the_blocks_that_are_wrong(channel):
    """Above its pool of voxels the guide measures one random voxel of every block of b^3 and draws the batch's
    voxels anywhere inside the blocks it picks: all of a wrong region gets fitted, not only the voxels measured."""
    from apmgsrn.training.points import ErrorGuide

    guide = ErrorGuide(channel, pool=5000)  # 48 x 64 x 96: blocks of 4^3, 12 x 16 x 24 = 4,608 of them
    assert guide.block == 4 and guide.blocks == (12, 16, 24)
    generator = torch.Generator().manual_seed(0)
    guide.measure(_with_error_in(channel, (slice(8, 16), slice(None), slice(None)), 0.01), generator)
    index = guide.draw(20000, generator)
    z = index // (64 * 96)
    assert bool(((z >= 8) & (z < 16)).all())
    assert len(torch.unique(index)) > 4 * 2 * 16 * 24  # many voxels of each of the 768 wrong blocks


def test_a_model_exact_at_every_voxel_gets_uniform_voxel_draws(channel):
    from apmgsrn.training.points import ErrorGuide

    guide = ErrorGuide(channel, pool=channel.numel())
    guide.measure(_with_error_in(channel, (slice(0, 0),) * 3, 0.0), torch.Generator())
    counts = torch.bincount(guide.draw(channel.numel(), torch.Generator()), minlength=channel.numel())
    assert bool((counts == 1).all())


def test_error_sampling_guides_only_voxel_points_of_a_single_volume(channel):
    """The share must be in [0, 1]; without voxel points there is nothing to guide (the trainer keeps its
    uniform draws, so a hybrid's default share is harmless with ``voxel_fraction=0``); a joint series model's
    batches are not guided, and asking for it is refused."""
    with pytest.raises(InvalidArgument, match="error_sampling"):
        TrainConfig(error_sampling=1.5, voxel_fraction=0.5)
    field = NeuralField(preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4), width=8),
                        volume_shape=tuple(channel.shape), generator=torch.Generator().manual_seed(0))
    assert Trainer(field, channel, TrainConfig(iterations=1, error_sampling=1.0)).error_guide is None
    assert Trainer(field, channel, TrainConfig(iterations=1, voxel_fraction=0.5, error_sampling=1.0)).error_guide
    with pytest.raises(InvalidArgument, match="single volume"):
        Trainer(field, channel.unsqueeze(0).expand(2, -1, -1, -1),
                TrainConfig(iterations=1, voxel_fraction=0.5, error_sampling=1.0))


@pytest.mark.parametrize("iterations, measurements, expected", [(40, 20, 20), (40, 5, 5), (50, 25, 25), (10, 25, 10)])
def test_a_guided_run_measures_the_error_as_often_as_it_is_told(channel, monkeypatch, iterations, measurements,
                                                               expected):
    """``error_measurements`` evenly spaced measurements, the first before the first iteration (at most one per
    iteration); 0 is refused."""
    from apmgsrn.training.points import ErrorGuide

    calls = []
    measure = ErrorGuide.measure
    monkeypatch.setattr(ErrorGuide, "measure", lambda self, *a: (calls.append(1), measure(self, *a))[1])
    field = NeuralField(preset_config("hybrid", "small", levels=4, log2_table_size=8, grids=2, resolution=4, width=8),
                        volume_shape=tuple(channel.shape), generator=torch.Generator().manual_seed(0))
    config = TrainConfig(iterations=iterations, batch_size=256, voxel_fraction=0.5, error_sampling=1.0,
                         error_measurements=measurements)
    Trainer(field, channel, config).run()
    assert len(calls) == expected
    with pytest.raises(InvalidArgument, match="error_measurements"):
        TrainConfig(error_measurements=0)


def test_error_guided_fine_tune_of_a_neighbour_fits_a_real_step_better(test_data):
    """A model of one viscous-finger step fine-tuned on the next step: drawing its voxel points where it is wrong
    fits the next step better in the same iterations than drawing them uniformly (the series' step fine-tune):
    47.1 against 46.3 dB here. (From a start fitted worse, 41 dB after 150 iterations, the guide loses 0.6 dB:
    it pays where the error is where the data changed, not everywhere.)"""
    from apmgsrn.series.data import open_series
    from apmgsrn.inference.evaluate import evaluate

    from apmgsrn.training.fit import build_field, prepare_values

    steps = open_series(str(test_data / "viscous_fingers_run01" / "*.vti")).to_numpy()[[0, 1]]
    config = preset_config("hybrid", "small", levels=6, log2_table_size=10, grids=4, resolution=8, width=16)
    single = prepare_values(steps[0], "none", 0.0, "viscous fingers", torch.device("cpu"))
    start = build_field(single, config, (32, 32, 32), 0)
    Trainer(start, single.values, TrainConfig(iterations=600, batch_size=2048, voxel_fraction=0.5)).run()
    target = (steps[1] - start.fit_min) / (start.fit_max - start.fit_min)  # the next step in the start's units
    results = {}
    for share in (0.0, 1.0):
        field = copy.deepcopy(start)
        field.decoder.requires_grad_(False)
        fine_tune = TrainConfig(iterations=200, batch_size=1024, voxel_fraction=0.5, error_sampling=share,
                                density_start=201)
        Trainer(field, torch.from_numpy(target).float(), fine_tune, warm=True).run()
        results[share] = evaluate(field.eval(), steps[1]).psnr
    assert results[1.0] > results[0.0] + 0.3


def _guided_run(volume, checkpoint, iterations=40, parts=1):
    field = NeuralField(preset_config("hybrid", "small", levels=4, log2_table_size=9, grids=2, resolution=4, width=16),
                        volume_shape=tuple(volume.shape), generator=torch.Generator().manual_seed(0))
    config = TrainConfig(iterations=iterations, batch_size=512, voxel_fraction=0.5, error_sampling=1.0,
                         checkpoint_every=25, error_parts=parts)
    return Trainer(field, volume, config, checkpoint, {"run": "guided"})


@pytest.mark.parametrize("parts", [1, 2])
def test_a_checkpoint_keeps_the_error_measurement_so_a_resumed_run_repeats_the_uninterrupted_one(test_data,
                                                                                                  tmp_path, parts):
    """Checkpointed at iteration 25 with the error last measured at 24 (every 2 of 40): the resumed run draws
    from the saved measurement, not a new one at 25, and ends with exactly the uninterrupted run's weights
    (measured in two parts, the errors of both parts are kept too)."""
    from apmgsrn.errors import ApmgsrnError
    from apmgsrn.io.container import load_tensors, read_header, save_tensors

    values = np.load(test_data / "neghip_32x32x32_uint8.npy").astype(np.float32) / 255
    volume = torch.from_numpy(values)
    checkpoint = tmp_path / "run.ckpt"
    whole = _guided_run(volume, checkpoint, parts=parts)
    whole.run()  # leaves the checkpoint of iteration 25
    resumed = _guided_run(volume, checkpoint, parts=parts)
    resumed.load_checkpoint(checkpoint)
    assert resumed.state.iteration == 25
    saved = load_tensors(checkpoint)
    assert torch.equal(resumed.error_guide.cumulative, saved["error_guide"])
    assert ("error_guide_errors" in saved) == (parts > 1)
    resumed.run()
    assert all(torch.equal(a, b) for a, b in zip(whole.field.state_dict().values(), resumed.field.state_dict().values()))

    tensors, header = load_tensors(checkpoint), read_header(checkpoint)
    tensors["error_guide"] = tensors["error_guide"].flip(0)  # not a running sum any more
    save_tensors(tmp_path / "tampered.ckpt", tensors, header.kind, header.description)
    with pytest.raises(ApmgsrnError, match="damaged.*error_guide"):
        _guided_run(volume, tmp_path / "tampered.ckpt", parts=parts).load_checkpoint(tmp_path / "tampered.ckpt")
    if parts > 1:
        tensors = load_tensors(checkpoint)
        tensors["error_guide_errors"][3] = -1.0  # an error below 0
        save_tensors(tmp_path / "negative.ckpt", tensors, header.kind, header.description)
        with pytest.raises(ApmgsrnError, match="damaged.*error_guide_errors"):
            _guided_run(volume, tmp_path / "negative.ckpt", parts=parts).load_checkpoint(tmp_path / "negative.ckpt")


def test_a_guide_measured_in_parts_refreshes_one_part_at_a_time(channel):
    """With two parts the first measurement takes every voxel, each later one every second voxel in turn
    (even, then odd, ...), the other half keeping its errors; the draws follow the merged errors."""
    from apmgsrn.training.points import ErrorGuide

    volume = channel[:64, :64, :64].contiguous()  # at most VOLUME.error_pool voxels: measured one by one, not by blocks
    guide = ErrorGuide(volume, parts=2)
    assert guide.block == 1
    count = volume.numel()
    flat = volume.reshape(-1)
    guide.measure(lambda p: torch.zeros(len(p)), torch.Generator())  # error = the value itself
    assert torch.equal(guide.errors, flat.double())
    guide.measure(lambda p: torch.ones(len(p)) * 2, torch.Generator(), turn=3)  # odd voxels: |2 - value|
    odd = torch.arange(count) % 2 == 1
    assert torch.equal(guide.errors[odd], (2 - flat[odd]).double())
    assert torch.equal(guide.errors[~odd], flat[~odd].double())
    expected = guide.errors.cumsum(0)
    assert torch.allclose(guide.cumulative, expected / expected[-1])
    whole = ErrorGuide(volume)
    whole.measure(lambda p: torch.zeros(len(p)), torch.Generator())
    whole.measure(lambda p: torch.ones(len(p)) * 2, torch.Generator(), turn=3)  # one part: every voxel
    assert torch.equal(whole.errors, (2 - flat).double())
