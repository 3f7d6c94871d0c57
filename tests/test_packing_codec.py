"""Quantisation and lossless coding of a real model's parameters (io/quantization.py, io/codec.py): what is
stored is restored exactly, steps bound the rounding error, and decompression never goes past what the
description declares."""

from __future__ import annotations

import json
import lzma

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import codec
from apmgsrn.io.quantization import (
    MAX_GROUPS,
    MIN_GROUP,
    group_count,
    group_size,
    quantize,
    round_steps,
    steps_for_bits,
)
from apmgsrn.recipes import RUNTIME
from apmgsrn.threads import map_in_threads


@pytest.fixture(scope="module")
def parameters(test_data) -> dict[str, np.ndarray]:
    """The float32 parameters of the committed reference model (trained on a crop of neghip)."""
    model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    return {name: p.detach().numpy().copy() for name, p in model.field.state_dict().items()}


def test_groups_follow_the_trailing_axes_and_stay_few():
    assert group_size((16, 4, 16, 16, 16)) == 16**3  # one group per grid and feature channel
    assert group_size((4, 1, 8, 8, 8)) == 2 * 8**3  # a grid of 512 is too small: two whole grids
    assert group_size((64, 16)) == 64 * 16  # weight matrix of 1,024: one group
    assert group_size((300, 16)) == 64 * 16  # rows of 16: blocks of whole rows reaching MIN_GROUP
    assert group_size((3, 4)) == 12
    huge = (1 << 26, 2)
    assert group_count(2 << 26, group_size(huge)) <= MAX_GROUPS
    for shape in [(16, 4, 16, 16, 16), (300, 16), (1 << 20,), (5, 3, 7)]:
        size = group_size(shape)
        assert size >= min(MIN_GROUP, int(np.prod(shape)))


@pytest.mark.parametrize("bits", [2, 4, 8, 12, 16])
def test_quantised_parameters_are_within_half_a_step_and_fit_their_bits(parameters, bits):
    for name, values in parameters.items():
        size = group_size(values.shape)
        quantized = quantize(values, steps_for_bits(values, size, bits), size)
        assert np.abs(quantized.levels).max() <= (1 << (bits - 1)) - 1
        restored = quantized.dequantize().numpy()
        step = quantized.steps.astype(np.float32)[np.arange(values.size) // size].reshape(values.shape)
        # Half a step, plus float32 rounding of the product.
        assert (np.abs(restored - values) <= step * (0.5 + 1e-3)).all(), name


def test_steps_are_stored_as_positive_finite_float16():
    steps = round_steps(np.array([0.0, 1e-30, np.nan, np.inf, 0.25, 1e9]))
    assert steps.dtype == np.float16 and np.isfinite(steps).all() and (steps > 0).all()
    assert steps[4] == np.float16(0.25)


@pytest.mark.parametrize("bits", [4, 8, 16])
def test_every_predictor_and_byte_layout_restores_the_integers_exactly(parameters, bits):
    for name, values in parameters.items():
        size = group_size(values.shape)
        levels = quantize(values, steps_for_bits(values, size, bits), size).levels
        for predictor in codec.predictors_for(values.shape):
            data, width = codec.encode_levels(levels, values.shape, predictor)
            raw = codec.decompress(data, levels.size * width, name)
            residuals = codec.from_bytes(raw, levels.size, width)
            assert np.array_equal(codec.reconstruct(residuals, values.shape, predictor), levels), (name, predictor)


def test_the_smallest_encoding_is_chosen(parameters):
    grids = parameters["encoder.grids"]  # [M, C, D, H, W]: all three predictors apply
    size = group_size(grids.shape)
    levels = quantize(grids, steps_for_bits(grids, size, 10), size).levels
    assert codec.predictors_for(grids.shape) == ("none", "delta", "lorenzo")
    data, _, predictor = codec.best_encoding(levels, grids.shape)
    assert len(data) == min(len(codec.encode_levels(levels, grids.shape, p)[0]) for p in codec.PREDICTORS)
    assert predictor in codec.PREDICTORS


def test_parameters_coded_side_by_side_are_the_bytes_coded_one_after_another(parameters):
    """best_encodings runs every (parameter, predictor) compression on the process's threads: the same bytes,
    widths and choices as one at a time, in the parameters' order, on one thread or two."""
    jobs = []
    for name in ("encoder.grids", "decoder.0.weight", "encoder.translations"):
        values = parameters[name]
        size = group_size(values.shape)
        jobs.append((quantize(values, steps_for_bits(values, size, 9), size).levels, values.shape, None))
    jobs.append((jobs[0][0], jobs[0][1], ("delta",)))  # a predictor imposed
    one_at_a_time = []
    for levels, shape, predictors in jobs:  # each predictor in turn, the first of the smallest kept
        coded = [(*codec.encode_levels(levels, shape, p), p) for p in predictors or codec.predictors_for(shape)]
        one_at_a_time.append(min(coded, key=lambda c: len(c[0])))
    threads = torch.get_num_threads()
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            assert codec.best_encodings(jobs) == one_at_a_time
    finally:
        torch.set_num_threads(threads)
    assert one_at_a_time[3][2] == "delta"
    assert map_in_threads(lambda x: x * x, range(7), 3) == [x * x for x in range(7)]


def test_fewer_compressions_run_side_by_side_where_each_would_take_much_memory(monkeypatch):
    """LZMA's match finder takes about ten times its dictionary: a small model's tensors code on every thread,
    the tensors of a long series on as many as fit the memory set aside, and one at least."""
    monkeypatch.setattr(codec, "work_threads", lambda: 64)
    small = [10_000] * 12
    assert codec.coding_threads(small) == 64
    long_series = [300 * 42_000, 1_000]  # 300 steps of a small hybrid's level table, and a decoder
    fitting = codec.coding_threads(long_series)
    assert 1 < fitting < 64 and fitting * codec.coding_memory(long_series[0]) <= RUNTIME.parallel_coding_memory
    assert codec.coding_threads([10 ** 9]) == 1


def test_zigzag_and_byte_planes_round_trip_signed_values():
    values = np.array([0, -1, 1, -2, 2, 127, -128, 40_000, -(1 << 30)], dtype=np.int64)
    assert codec.zigzag(values[:5]).tolist() == [0, 1, 2, 3, 4]
    assert np.array_equal(codec.unzigzag(codec.zigzag(values)), values)
    for width in (4,):
        assert np.array_equal(codec.from_bytes(codec.to_bytes(values, width), values.size, width), values)
    assert codec.width_of(values[:6]) == 1 and codec.width_of(values[:8]) == 4
    assert codec.width_of(np.array([300, -300])) == 2


def test_decompression_refuses_wrong_sizes_corruption_and_bombs():
    data = np.arange(5000, dtype=np.uint16).tobytes()
    packed = codec.compress(data)
    assert codec.decompress(packed, len(data), "t") == data
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(packed, len(data) - 1, "t")  # holds more than declared
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(packed, len(data) + 1, "t")  # holds less
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(packed[: len(packed) // 2], len(data), "t")  # truncated
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(packed + b"\0", len(data), "t")  # bytes after the end
    damaged = bytearray(packed)
    damaged[len(damaged) // 2] ^= 0xFF
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(bytes(damaged), len(data), "t")
    # A bomb: 64 MiB of zeros in a few KB; declared small, it stops at the declared size and is refused.
    bomb = lzma.compress(bytes(64 << 20), format=lzma.FORMAT_RAW, filters=codec._filters("numbers", 1 << 24))
    assert len(bomb) < 64 << 10
    with pytest.raises(ApmgsrnError, match="corrupt"):
        codec.decompress(bomb, 1 << 20, "t")
    text = b'{"a": 1}' * 100
    assert codec.decompress_bounded(codec.compress(text, "text"), 1 << 20, "t", "text") == text
    with pytest.raises(ApmgsrnError, match="longer than 100 bytes"):
        codec.decompress_bounded(codec.compress(text, "text"), 100, "t", "text")


def test_the_primed_description_coding_round_trips_shrinks_and_refuses_damage(parameters, test_data):
    """A real packed description: restored exactly, smaller than LZMA's, and bounded like every section."""
    from apmgsrn.io.field_file import field_description
    from apmgsrn.training.packing import bits_quantizer, encode_field

    model = apmgsrn.load(test_data / "reference_field.apmgsrn")
    tensors, _ = encode_field(model.field, bits_quantizer(model.field, 8))
    text = json.dumps({**field_description(model.field, model.description.source, {"iterations": 300}),
                       "tensors": [t.entry() for t in tensors], "packing": {"mode": "bits", "bits": 8}},
                      separators=(",", ":")).encode()
    coded = codec.compress_description(text)
    assert codec.decompress_description(coded, 1 << 20, "d") == text
    assert len(coded) < 0.6 * len(codec.compress(text, "text"))
    with pytest.raises(ApmgsrnError, match="longer than 100 bytes"):
        codec.decompress_description(coded, 100, "d")
    for damaged in (coded[: len(coded) // 2], coded + b"\0", bytes(len(coded))):
        with pytest.raises(ApmgsrnError, match="corrupt"):
            codec.decompress_description(damaged, 1 << 20, "d")
    # A bomb: 64 MiB of spaces in about 64 KB; it stops at the limit and is refused.
    bomb = codec.compress_description(b" " * (64 << 20))
    assert len(bomb) < 128 << 10
    with pytest.raises(ApmgsrnError, match="longer than"):
        codec.decompress_description(bomb, 1 << 20, "d")
