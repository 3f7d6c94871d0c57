"""Hard limits: the most any file may declare or any caller may ask for, in one place (docs/security.md).

These are not tuned (the tuned numbers are in :mod:`apmgsrn.recipes`): each bounds what a hostile or
mistaken input could make the library allocate, read or write, far above what real data needs. A value over a
limit is refused in one line before anything is allocated.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    """Every hard limit, one line of why each."""

    #: bytes of a model file's JSON header and of a brick folder's manifest
    header_bytes: int = 64 << 20
    #: bytes of a packed file's description once decompressed
    description_bytes: int = 1 << 20
    #: parameters a packed file may declare (1 GiB of float32: 64 times the large preset)
    packed_parameters: int = 1 << 28
    #: corrected voxels a file may declare (gaps are stored in at most 4 bytes, so indices stay inside int64)
    corrections: int = 1 << 31
    #: voxels of a volume that carries a correction: flat indices ``(z * H + y) * W + x`` stay inside int64
    corrected_voxels: int = 1 << 62
    #: voxels a model may describe along one axis (larger shapes are refused as corrupt)
    volume_axis: int = 1 << 24
    #: attributes of a source's recorded metadata (more is a way to bloat a file, not a description)
    attributes: int = 256
    #: characters of one recorded text
    text: int = 65536
    #: entries of one recorded list
    list_entries: int = 4096
    #: values of one recorded coordinate array
    coordinates: int = 1 << 24
    #: bricks of a brick grid (a hostile manifest could ask for billions of modules)
    bricks: int = 1_000_000
    #: bricks an ONNX export evaluates at every point (tracing takes about 14 s a small hybrid brick)
    export_bricks: int = 8
    #: bytes of a ``.pvd`` collection (a list of file names; megabytes of it are not one)
    pvd_bytes: int = 16 << 20
    #: bytes of one Zarr metadata file (``zarr.json``, ``.zarray``, ...), which zarr reads whole
    zarr_metadata_bytes: int = 64 << 20
    #: bytes read of a file to tell whether it is an apmgsrn manifest
    manifest_head_bytes: int = 1 << 16
    #: expansion of stored bytes a codec gives real data (zlib's bound is 1032:1): a volume beyond the memory
    #: budget must be stored in at least this share of its declared bytes
    expansion: float = 1100.0
    #: bytes a container may declare beyond that bound (headers, a few fill chunks)
    declared_slack: int = 1 << 20
    #: samples along one side of a decoded lattice (no volume read comes near a million voxels a side)
    lattice_side: int = 1 << 20
    #: pixels along an image side (an 8192 x 8192 frame already needs about 1 GB of buffers)
    image_side: int = 8192
    #: frames of a turntable (every frame is held in memory until the animation is written)
    frames: int = 3600
    #: minutes a training budget may state (a week)
    minutes: float = 7 * 24 * 60.0


LIMITS = Limits()
