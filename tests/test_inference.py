"""Evaluating a field against a volume: the slab loop, strided subsets, the error figures and the shape check,
on the bundled real crop and the reference model trained on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import apmgsrn
from apmgsrn.data import open_volume
from apmgsrn.errors import ApmgsrnError
from apmgsrn.inference.decode import decode_array
from apmgsrn.inference.evaluate import compare_arrays, evaluate
from apmgsrn.inference.slabs import z_slabs
from apmgsrn.ops.trilinear import voxel_coordinates

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def model_and_truth():
    model = apmgsrn.load(DATA / "reference_field.apmgsrn")
    truth = np.load(DATA / "reference_neghip_24.npy").astype(np.float32)  # [24, 24, 24]
    with torch.no_grad():
        direct = model(voxel_coordinates(truth.shape)).view(truth.shape).double().numpy()  # every voxel at once
    return model, truth, direct


@pytest.mark.parametrize("stride", [1, 2, 5])
def test_slabs_of_a_strided_lattice_tile_it_in_order(stride):
    shape = (23, 7, 9)
    slabs = list(z_slabs(shape, slab_voxels=30, stride=stride))
    assert slabs[0].start == 0 and slabs[-1].stop == 23
    assert all(a.stop == b.start for a, b in zip(slabs, slabs[1:]))
    assert all(s.start % stride == 0 for s in slabs)
    volume = np.arange(np.prod(shape)).reshape(shape)
    pieces = np.concatenate([volume[z][::stride, ::stride, ::stride] for z in slabs])
    np.testing.assert_array_equal(pieces, volume[::stride, ::stride, ::stride])


@pytest.mark.parametrize("slab_voxels", [24 * 24, 5 * 24 * 24, 2**22])
def test_evaluation_over_slabs_matches_a_direct_computation(model_and_truth, slab_voxels):
    model, truth, direct = model_and_truth
    diff = direct - truth
    result = evaluate(model, truth, slab_voxels=slab_voxels)
    mse = float(np.mean(diff**2))
    assert result.mse == pytest.approx(mse, rel=1e-12)
    assert result.max_abs_error == pytest.approx(float(np.abs(diff).max()), rel=1e-12)
    assert (result.data_min, result.data_max) == (0.0, 255.0)
    assert result.psnr == pytest.approx(20 * np.log10(255.0) - 10 * np.log10(mse), abs=1e-9)
    # The file on disk, read one slab at a time, gives the same figures.
    assert evaluate(model, open_volume(DATA / "reference_neghip_24.npy"), slab_voxels=slab_voxels) == result


def test_a_strided_subset_compares_its_voxels_against_the_whole_value_range(model_and_truth):
    model, truth, direct = model_and_truth
    result = evaluate(model, truth, max_voxels=1000, slab_voxels=300)  # stride ceil(13824 / 1000)^(1/3) = 3
    diff = (direct - truth)[::3, ::3, ::3]
    assert result.mse == pytest.approx(float(np.mean(diff**2)), rel=1e-12)
    assert result.max_abs_error == pytest.approx(float(np.abs(diff).max()), rel=1e-12)
    assert (result.data_min, result.data_max) == (float(truth.min()), float(truth.max()))


def test_decoding_to_memory_and_comparing_arrays_agree_with_evaluation(model_and_truth):
    model, truth, _ = model_and_truth
    decoded = decode_array(model, truth.shape, slab_voxels=1000)
    assert compare_arrays(decoded, truth) == evaluate(model, truth)


def test_a_volume_of_another_shape_is_refused_naming_both(model_and_truth):
    model, truth, _ = model_and_truth
    with pytest.raises(ApmgsrnError, match=r"volume is 20x24x24 \(x\*y\*z\) but the model was trained on 24x24x24"):
        evaluate(model, truth[:, :, :20], trained_shape=model.description.volume_shape)


def test_nan_in_the_truth_is_refused(model_and_truth):
    model, truth, _ = model_and_truth
    broken = truth.copy()
    broken[7, 3, 3] = np.nan
    with pytest.raises(ApmgsrnError, match="NaN or Inf"):
        evaluate(model, broken)
