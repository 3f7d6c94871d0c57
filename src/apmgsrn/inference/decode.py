"""Reconstruct a whole volume from a field, slab by slab, at its own or another resolution."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from apmgsrn.data.writers import VolumeWriter
from apmgsrn.inference.slabs import QUERY_BATCH, SLAB_VOXELS, field_slabs
from apmgsrn.progress import Progress


def decode_volume(field, out: Path, shape: tuple[int, int, int], batch_size: int = QUERY_BATCH,
                  slab_voxels: int = SLAB_VOXELS, progress: bool = False, attributes: dict | None = None) -> None:
    """Write the field sampled on a corner-aligned ``(D, H, W)`` grid to ``out`` (.nc, .raw or .npy).

    Only one z-slab of the output is in memory at a time; the file appears atomically when complete.

    Args:
        field: module ``[N, 3] -> [N, 1]`` in data units.
        out: the volume file to write.
        shape: ``(D, H, W)`` of the output.
        batch_size: points per forward pass.
        slab_voxels: voxels per slab.
        progress: show progress (see :mod:`apmgsrn.progress`).
        attributes: global attributes of a NetCDF output.
    """
    with VolumeWriter(out, shape, attributes=attributes) as writer, \
            Progress(math.prod(shape), unit="voxel", description="decode", enabled=progress) as shown:
        for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size):
            writer.write(z, values.numpy())
            shown.update(values.numel())


def decode_array(field, shape: tuple[int, int, int], batch_size: int = QUERY_BATCH,
                 slab_voxels: int = SLAB_VOXELS) -> np.ndarray:
    """The field sampled on a corner-aligned ``(D, H, W)`` grid, as one float32 array in memory."""
    decoded = np.empty(shape, dtype=np.float32)
    for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size):
        decoded[z] = values.numpy()
    return decoded
