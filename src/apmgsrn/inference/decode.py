"""Reconstruct a whole volume (or the steps of a time-series model) from a field, slab by slab, at its own or
another resolution."""

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
        _write_field(writer, field, shape, None, shown, batch_size, slab_voxels)


def decode_series(step_field, out: Path, shape: tuple[int, int, int], indices, time_values=None,
                  batch_size: int = QUERY_BATCH, slab_voxels: int = SLAB_VOXELS, progress: bool = False,
                  attributes: dict | None = None) -> None:
    """Write several steps of a time-series model to one file with a leading time dimension.

    One step's field is materialised at a time and written slab by slab; the file appears atomically when
    every step is complete.

    Args:
        step_field: ``step index -> field`` (``[N, 3] -> [N, 1]`` in data units).
        out: the file to write (.nc with dims ``(time, z, y, x)``, or .raw/.npy with the steps in order).
        shape: ``(D, H, W)`` of every step.
        indices: the steps to write, in order.
        time_values: the NetCDF ``time`` coordinate of those steps (default: their indices).
        batch_size: points per forward pass.
        slab_voxels: voxels per slab.
        progress: show progress (see :mod:`apmgsrn.progress`).
        attributes: global attributes of a NetCDF output.
    """
    indices = list(indices)
    with VolumeWriter(out, shape, attributes=attributes, steps=len(indices),
                      time_values=indices if time_values is None else time_values) as writer, \
            Progress(len(indices) * math.prod(shape), unit="voxel", description="decode", enabled=progress) as shown:
        for position, index in enumerate(indices):
            _write_field(writer, step_field(index), shape, position, shown, batch_size, slab_voxels)


def _write_field(writer: VolumeWriter, field, shape, step: int | None, shown: Progress, batch_size: int,
                 slab_voxels: int) -> None:
    for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size):
        writer.write(z, values.numpy(), step=step)
        shown.update(values.numel())


def decode_array(field, shape: tuple[int, int, int], batch_size: int = QUERY_BATCH,
                 slab_voxels: int = SLAB_VOXELS) -> np.ndarray:
    """The field sampled on a corner-aligned ``(D, H, W)`` grid, as one float32 array in memory."""
    decoded = np.empty(shape, dtype=np.float32)
    for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size):
        decoded[z] = values.numpy()
    return decoded
