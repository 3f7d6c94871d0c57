"""Decode several steps of a time-series model into one file with a leading time axis, one step's field at a
time, slab by slab (:func:`apmgsrn.inference.decode.write_field`)."""

from __future__ import annotations

import math
from pathlib import Path

from apmgsrn.data.writers import VolumeWriter
from apmgsrn.inference.decode import Box, write_field
from apmgsrn.progress import Progress
from apmgsrn.recipes import RUNTIME


def decode_series(step_field, out: Path, shape: tuple[int, int, int], indices, time_values=None,
                  batch_size: int = RUNTIME.query_batch, slab_voxels: int = RUNTIME.slab_voxels, progress: bool = False,
                  box: Box | None = None, **writer_options) -> None:
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
        box: the lattice spans this box of ``[-1, 1]^3`` (default: all of it).
        writer_options: as for :func:`decode_volume` (``variable``, ``attributes``, ``axes``...).
    """
    indices = list(indices)
    with VolumeWriter(out, shape, **writer_options, steps=len(indices),
                      time_values=indices if time_values is None else time_values) as writer, \
            Progress(len(indices) * math.prod(shape), unit="voxel", description="decode", enabled=progress) as shown:
        for position, index in enumerate(indices):
            write_field(writer, step_field(index), shape, position, shown, batch_size, slab_voxels, box)
