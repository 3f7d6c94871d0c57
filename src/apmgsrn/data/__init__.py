"""Volumes on disk: lazy readers for NetCDF, HDF5, Zarr, raw, npy and VTK XML, and writers.

`open_volume` picks the reader by suffix; every reader returns a `Volume` whose `Volume.read`
fetches only the requested region as float32 ``[d, h, w]`` in C order (z, y, x), x fastest.
Readers of optional formats (vtk) import their library only when such a file is opened.
"""

from apmgsrn.data.readers import SUPPORTED_SUFFIXES, open_volume, supported_formats
from apmgsrn.data.volume import ArrayVolume, Volume, VolumeStats, check_finite, format_xyz, parse_shape
from apmgsrn.data.writers import WRITABLE_SUFFIXES, VolumeWriter

__all__ = [
    "ArrayVolume",
    "SUPPORTED_SUFFIXES",
    "Volume",
    "VolumeStats",
    "VolumeWriter",
    "WRITABLE_SUFFIXES",
    "check_finite",
    "format_xyz",
    "open_volume",
    "parse_shape",
    "supported_formats",
]
