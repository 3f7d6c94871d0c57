"""Reconstruct a whole volume from a model, chunk by chunk, at its own or another resolution."""

from __future__ import annotations

from pathlib import Path

from apmgsrn.inference.query import query
from apmgsrn.ops.trilinear import voxel_coordinates


def decode_volume(field, out: Path, shape: tuple[int, int, int], batch_size: int = 2**18,
                  slab_voxels: int = 2**22, progress: bool = False, attributes: dict | None = None) -> None:
    """Write the field sampled on a corner-aligned ``(D, H, W)`` grid to ``out`` (.nc, .raw or .npy).

    Only one z-slab of the output is in memory at a time; the file appears atomically when complete.
    """
    from apmgsrn.data.writers import VolumeWriter

    d, h, w = shape
    step = max(1, slab_voxels // (h * w))
    chunks = range(0, d, step)
    if progress:
        import sys

        from tqdm import tqdm

        chunks = tqdm(chunks, unit="slab", desc="decode", disable=not sys.stderr.isatty())
    with VolumeWriter(out, shape, attributes=attributes) as writer:
        for z0 in chunks:
            z = slice(z0, min(z0 + step, d))
            values = query(field, voxel_coordinates(shape, z), batch_size)
            writer.write(z, values.numpy().reshape(z.stop - z.start, h, w))
