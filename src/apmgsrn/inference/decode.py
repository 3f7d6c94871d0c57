"""Reconstruct a volume from a field, slab by slab, at its own or another resolution, whole or a region (the steps
of a time-series model: :mod:`apmgsrn.series.decode`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from apmgsrn.data.writers import VolumeWriter
from apmgsrn.inference.slabs import field_slabs
from apmgsrn.progress import Progress
from apmgsrn.recipes import RUNTIME

#: A box in the field's ``[-1, 1]^3``, ``((x0, x1), (y0, y1), (z0, z1))``.
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]


def decode_volume(field, out: Path, shape: tuple[int, int, int], batch_size: int = RUNTIME.query_batch,
                  slab_voxels: int = RUNTIME.slab_voxels, progress: bool = False, box: Box | None = None,
                  **writer_options) -> None:
    """Write the field sampled on a corner-aligned ``(D, H, W)`` lattice to ``out`` (.nc, .vti, .raw, .npy).

    Only one z-slab of the output is in memory at a time; the file appears atomically when complete.

    Args:
        field: module ``[N, 3] -> [N, 1]`` in data units.
        out: the volume file to write.
        shape: ``(D, H, W)`` of the output.
        batch_size: points per forward pass.
        slab_voxels: voxels per slab.
        progress: show progress (see :mod:`apmgsrn.progress`).
        box: the lattice spans this box of ``[-1, 1]^3`` (default: all of it).
        writer_options: keyword arguments of :class:`~apmgsrn.data.writers.VolumeWriter` (``variable``,
            ``attributes``, ``variable_attributes``, ``axes``, ``compression``).
    """
    with VolumeWriter(out, shape, **writer_options) as writer, \
            Progress(math.prod(shape), unit="voxel", description="decode", enabled=progress) as shown:
        write_field(writer, field, shape, None, shown, batch_size, slab_voxels, box)


def write_field(writer: VolumeWriter, field, shape, step: int | None, shown: Progress, batch_size: int,
                slab_voxels: int, box: Box | None = None) -> None:
    """Write ``field`` sampled on ``shape`` slab by slab into ``writer`` (at time step ``step`` of a file with a
    time axis; None: none), counting the voxels on ``shown``."""
    for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size, box=box):
        writer.write(z, values.numpy(), step=step)
        shown.update(values.numel())


def decode_array(field, shape: tuple[int, int, int], batch_size: int = RUNTIME.query_batch,
                 slab_voxels: int = RUNTIME.slab_voxels, box: Box | None = None) -> np.ndarray:
    """The field sampled on a corner-aligned ``(D, H, W)`` lattice over ``box`` (default ``[-1, 1]^3``), as one
    float32 array in memory."""
    decoded = np.empty(shape, dtype=np.float32)
    for z, values in field_slabs(field, shape, slab_voxels, batch_size=batch_size, box=box):
        decoded[z] = values.numpy()
    return decoded
