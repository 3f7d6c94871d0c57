"""What identifies a volume's data: where it really lives and a hash of a sample of its values.

A resumed run must continue on the data it started on. A file name, shape and dtype do not tell two files
apart (``run1/density.nc`` and ``run2/density.nc``); the fingerprint adds the file's real path (links
resolved) and a SHA-256 of a sample of its values: 3 x 3 x 3 small blocks spread evenly over the volume,
corners and centre included. Blocks, not a strided lattice: a chunked file (NetCDF, HDF5, Zarr) then
reads a few chunks, never the whole file.
"""

from __future__ import annotations

import hashlib
import os

from apmgsrn.data.volume import Volume

#: Blocks per axis and their side in voxels: 27 blocks of at most 16^3 values (about 110,000 in all).
BLOCKS_PER_AXIS, BLOCK_SIDE = 3, 16


def volume_fingerprint(volume: Volume) -> dict:
    """A JSON-able identity of a volume's data.

    Args:
        volume: the volume (its values are read as :meth:`Volume.read` returns them, fill value included).

    Returns:
        ``{"path", "variable", "time", "shape", "dtype", "sample_sha256"}``; ``path`` is the real path of
        the file (symbolic links and ``..`` resolved).
    """
    digest = hashlib.sha256(repr(volume.shape).encode())
    for z in _block_slices(volume.shape[0]):
        for y in _block_slices(volume.shape[1]):
            for x in _block_slices(volume.shape[2]):
                digest.update(volume.read(z, y, x).tobytes())  # [<=16, <=16, <=16] float32
    return {
        "path": os.path.realpath(volume.path),
        "variable": volume.variable,
        "time": volume.time,
        "shape": list(volume.shape),
        "dtype": str(volume.dtype),
        "sample_sha256": digest.hexdigest(),
    }


def _block_slices(length: int) -> list[slice]:
    """Where the blocks lie along an axis of ``length`` voxels: evenly spaced, the first at 0 and the last at
    the end."""
    side = min(BLOCK_SIDE, length)
    starts = sorted({round(i * (length - side) / (BLOCKS_PER_AXIS - 1)) for i in range(BLOCKS_PER_AXIS)})
    return [slice(start, start + side) for start in starts]
