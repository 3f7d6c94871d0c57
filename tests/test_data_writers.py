"""VolumeWriter round trips and its atomic, all-or-nothing behaviour."""

from __future__ import annotations

from pathlib import Path

import netCDF4
import numpy as np
import pytest

from apmgsrn.data import VolumeWriter, open_volume
from apmgsrn.errors import ApmgsrnError


@pytest.fixture(scope="module")
def block(test_data: Path) -> np.ndarray:
    """A real non-cubic float32 block (z, y, x) = (21, 33, 45) of the channel-flow pressure.

    The voxels [10:31, 100:133, 300:345] of the 640x240x48 source; the bundled crop starts at (0, 96, 288).
    """
    return open_volume(test_data / "channel_pressure_96x64x48.nc").read(
        slice(10, 31), slice(4, 37), slice(12, 57)
    )


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.mark.parametrize("name", ["out.nc", "out_45x33x21_float32.raw", "out_45x33x21_float32.bin", "out.npy"])
def test_round_trip_written_out_of_order(tmp_path: Path, block: np.ndarray, name: str) -> None:
    path = tmp_path / name
    slabs = [slice(8, 16), slice(0, 8), slice(16, 21)]  # any order, uneven last slab
    with VolumeWriter(path, block.shape, variable="pressure", attributes={"source": "test"}) as writer:
        for z in slabs:
            writer.write(z, block[z])
            assert not path.exists()  # nothing under the real name until close
    assert _leftovers(tmp_path) == []
    volume = open_volume(path)
    assert volume.shape == block.shape and volume.dtype == np.float32
    np.testing.assert_array_equal(volume.to_numpy(), block)


def test_netcdf_output_has_dims_variable_and_attributes(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "decoded.nc"
    attributes = {"model": "apmgsrn", "psnr_db": 41.5, "iterations": 500, "shape_xyz": [45, 33, 21],
                  "converged": True, "config": {"grids": 16}, "note": None}
    with VolumeWriter(path, block.shape, variable="pressure", attributes=attributes) as writer:
        writer.write(slice(0, 21), block)
    with netCDF4.Dataset(path) as handle:
        assert handle["pressure"].dimensions == ("z", "y", "x")
        assert handle["pressure"].dtype == np.float32
        assert handle.model == "apmgsrn" and handle.psnr_db == 41.5 and handle.iterations == 500
        assert list(handle.shape_xyz) == [45, 33, 21] and handle.converged == 1
        assert handle.config == '{"grids": 16}' and handle.note == "null"
    assert open_volume(path).variable == "pressure"


def test_raw_output_is_little_endian_x_fastest(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "plain.raw"
    with VolumeWriter(path, block.shape) as writer:
        writer.write(slice(0, 21), block)
    np.testing.assert_array_equal(np.fromfile(path, dtype="<f4").reshape(21, 33, 45), block)


def test_error_inside_the_block_leaves_no_file_and_keeps_the_old_one(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "kept.npy"
    np.save(path, np.zeros((2, 2, 2), np.float32))
    with pytest.raises(KeyboardInterrupt):
        with VolumeWriter(path, block.shape) as writer:
            writer.write(slice(0, 5), block[0:5])
            raise KeyboardInterrupt
    assert _leftovers(tmp_path) == []
    assert np.load(path).shape == (2, 2, 2)


@pytest.mark.parametrize("name", ["partial.nc", "partial.raw", "partial.npy"])
def test_unfinished_volume_is_not_saved(tmp_path: Path, block: np.ndarray, name: str) -> None:
    writer = VolumeWriter(tmp_path / name, block.shape)
    writer.write(slice(0, 20), block[0:20])
    with pytest.raises(ValueError, match="1 z-slices were never written"):
        writer.close()
    assert list(tmp_path.iterdir()) == []


def test_block_of_the_wrong_shape_is_refused(tmp_path: Path, block: np.ndarray) -> None:
    with VolumeWriter(tmp_path / "x.npy", block.shape) as writer:
        with pytest.raises(ValueError, match="does not match"):
            writer.write(slice(0, 4), block[0:3])
        with pytest.raises(ValueError, match="step 1"):
            writer.write(slice(0, 4, 2), block[0:4:2])
        writer.write(slice(0, 21), block)


def test_missing_output_folder(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "no" / "such" / "folder" / "out.nc"
    with pytest.raises(ApmgsrnError) as caught:
        VolumeWriter(path, block.shape)
    assert str(path) in str(caught.value) and "does not exist" in str(caught.value)


def test_unknown_output_suffix(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "out.tiff"
    with pytest.raises(ApmgsrnError) as caught:
        VolumeWriter(path, block.shape)
    message = str(caught.value)
    assert str(path) in message and "'.tiff'" in message and ".nc" in message and ".npy" in message


def test_invalid_netcdf_variable_name(tmp_path: Path, block: np.ndarray) -> None:
    path = tmp_path / "bad.nc"
    with pytest.raises(ApmgsrnError) as caught:
        VolumeWriter(path, block.shape, variable=" leading space")
    assert str(path) in str(caught.value)
    assert list(tmp_path.iterdir()) == []
