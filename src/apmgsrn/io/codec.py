"""Lossless coding of quantised integers: a predictor, a compact byte layout, then LZMA.

1. Predictor (chosen per tensor by the packer: whichever codes smallest): ``none``; ``delta`` (each value
   minus the previous one along the last axis); ``lorenzo`` (the 3-D Lorenzo predictor over the last three
   axes, as SZ uses on volumes: exact on trilinear fields, so smooth feature grids leave small residuals);
   ``time`` (each value minus the one before it along the first axis: for the per-step grids of a time
   series, ``[T, M, C, D, H, W]``, whose consecutive steps are close; offered only by
   :func:`series_predictors_for`, so single fields code as before).
2. Residuals are zigzag-mapped to unsigned integers (``0, -1, 1, -2, ...`` -> ``0, 1, 2, 3, ...``) and
   stored in the fewest whole bytes that hold the largest; wider values are split into byte planes (all low
   bytes, then all high bytes) so that the mostly-zero high bytes compress to almost nothing.
3. LZMA (Python's standard ``lzma``, raw format, no container header) with literal contexts off
   (``lc=lp=pb=0``): quantised parameters are close to independent draws from one distribution, which the
   adaptive range coder of LZMA's literals codes near its entropy. Why LZMA rather than zstandard (through
   numcodecs, which zarr brings): it is in the standard library, its decoder stops at a caller's
   ``max_length`` (so a hostile section can never make it allocate more than the description allows), and
   on the integer sections of real models it codes 1.5-2.5 % smaller than zstandard at level 22
   (docs/packing.md gives the figures and the command).

A packed file's description (JSON text) is coded apart: raw deflate primed with a typical description
(:func:`compress_description`), since LZMA has no preset dictionary and a small model's description would
otherwise take a quarter of its file.

Decoding is bounded: the caller says how many bytes a section must decompress to (from the validated
model config, never from the file), and decompression stops there.
"""

from __future__ import annotations

import lzma
import zlib

import numpy as np

from apmgsrn.errors import ApmgsrnError
from apmgsrn.recipes import RUNTIME
from apmgsrn.threads import map_in_threads, work_threads

PREDICTORS = ("none", "delta", "lorenzo", "time")
#: LZMA settings: for parameter integers no literal context (values are close to independent), for text
#: (the JSON description) the default contexts.
CODECS = {"numbers": {"lc": 0, "lp": 0, "pb": 0}, "text": {}}
MIN_DICTIONARY, MAX_DICTIONARY = 1 << 12, 1 << 24


def _dictionary(size: int) -> int:
    """LZMA's dictionary for ``size`` bytes: the power of two just large enough, within the bounds."""
    return min(max(MIN_DICTIONARY, 1 << max(size - 1, 1).bit_length()), MAX_DICTIONARY)


def _filters(kind: str, size: int) -> list[dict]:
    """LZMA1 at preset 9 with a dictionary just large enough for ``size`` bytes: a larger one only costs
    time (the match finder allocates about ten times it), and the decoder, which knows ``size`` from the
    description, allocates the same."""
    return [{"id": lzma.FILTER_LZMA1, "preset": 9, "dict_size": _dictionary(size), **CODECS[kind]}]


def coding_memory(values: int) -> int:
    """About the most one :func:`encode_levels` of ``values`` integers allocates: LZMA's match finder, about 11
    times its dictionary (:func:`_filters`, for up to 4 bytes a value), and the residuals and their bytes."""
    return 11 * _dictionary(4 * values) + 20 * values


def coding_threads(values: list[int]) -> int:
    """How many compressions of tensors of ``values`` integers :func:`best_encodings` runs at once: as many as
    the process has threads (:func:`~apmgsrn.threads.work_threads`), fewer where the largest would together
    take more than ``RUNTIME.parallel_coding_memory`` (a series of many steps on a machine of many cores)."""
    largest = max((coding_memory(n) for n in values), default=1)
    return max(1, min(work_threads(), RUNTIME.parallel_coding_memory // largest))


def compress(data: bytes, kind: str = "numbers") -> bytes:
    """LZMA raw stream of ``data`` (``kind``: ``numbers`` or ``text``)."""
    return lzma.compress(data, format=lzma.FORMAT_RAW, filters=_filters(kind, len(data)))


def decompress(data: bytes, expected: int, what: str, kind: str = "numbers") -> bytes:
    """Decompress a raw stream that must hold exactly ``expected`` bytes; never allocates more.

    Args:
        data: the compressed section.
        expected: its decompressed size, known from the validated description.
        what: the section, for the message.
        kind: the settings it was compressed with.

    Raises:
        ApmgsrnError: corrupt, shorter or longer than ``expected``.
    """
    out = _inflate(data, expected, what, kind, f"does not hold the {expected} bytes its description declares")
    if len(out) != expected:
        raise ApmgsrnError(f"{what}: compressed data is corrupt or does not hold the {expected} bytes "
                           "its description declares")
    return out


def decompress_bounded(data: bytes, limit: int, what: str, kind: str = "numbers") -> bytes:
    """Decompress a raw stream of unknown size that may hold at most ``limit`` bytes.

    Raises:
        ApmgsrnError: corrupt, unterminated, or longer than ``limit``.
    """
    return _inflate(data, limit, what, kind, f"longer than {limit} bytes")


def _inflate(data: bytes, limit: int, what: str, kind: str, too_long: str) -> bytes:
    """At most ``limit`` bytes of a raw stream that must end there (one byte more, a missing end or bytes
    after it are damage)."""
    decoder = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_filters(kind, limit))
    try:
        out = decoder.decompress(data, max_length=limit)
        extra = b"" if decoder.eof else decoder.decompress(b"", max_length=1)
    except (lzma.LZMAError, EOFError):
        raise ApmgsrnError(f"{what}: compressed data is corrupt") from None
    if extra or not decoder.eof or decoder.unused_data:
        raise ApmgsrnError(f"{what}: compressed data is corrupt or {too_long}")
    return out


# ------------------------------------------------------------------------------------------ description
#: The preset dictionary of a packed file's description (format version 2 on): raw deflate (RFC 1951, the
#: standard library's ``zlib``) primed with a typical description, so the keys and common values that every
#: description repeats cost a few bits each instead of being spelled out. The description of a 2.6 KB model
#: codes to about 230 bytes instead of LZMA's 670 (a quarter of the file at 10,000:1). Fixed forever: files
#: depend on every byte of it; a different primer needs a new name in the header.
DESCRIPTION_PRIMER = (
    b'{"field":{"model":"fvsrn","encoder":{"features":2,"resolution":[32,32,32],"frequencies":6},'
    b'"decoder":{"hidden_layers":2,"width":64}}}{"field":{"model":"ngp","encoder":{"levels":16,"features":2,'
    b'"log2_table_size":12,"base_resolution":16,"finest_resolution":512},"decoder":{"hidden_layers":1,'
    b'"width":32}}}{"field":{"model":"hybrid","encoder":{"levels":15,"features":2,"log2_table_size":10,'
    b'"coarsest":8,"grids":8,"grid_features":1,"grid_resolution":16,"grid_init":"volume","level_lr_scale":3.0,'
    b'"grid_lr_scale":1.0,"lattice":[0,0,0]},"decoder":{"hidden_layers":2,"width":64}},'
    b'"source":{"path":"volume.raw","variable":null,"description":"volume.raw 256x256x256 (x*y*z) uint8",'
    b'"dtype":"uint8"},"training":{"iterations":50000,"batch_size":100000,"seconds":100.0,"frozen_at":40000,'
    b'"stopped_early":true,"device":"cuda"},"transform":{"kind":"log10","offset":1.0,"mean":0.0,"std":1.0},'
    b'"correction":{"max_error":0.01,"step":0.02,"count":1000,"gap_width":2,"level_width":1}}'
    b'{"field":{"model":"apmgsrn","encoder":{"grids":16,"features":1,"resolution":[16,16,16],"init":"default"},'
    b'"decoder":{"hidden_layers":2,"width":64}},"fit_min":0.0,"fit_max":1.0,"value_min":0.0,"value_max":1.0,'
    b'"transform":{"kind":"none","offset":0.0,"mean":0.0,"std":1.0},"volume_shape":[256,256,256],'
    b'"source":{"path":"volume.nc","variable":"density","description":"volume.nc:density 256x256x256 (x*y*z) '
    b'float32","dtype":"float32","attributes":{"long_name":"density","units":""},"dimensions":["z","y","x"],'
    b'"compression":{"zlib":true,"complevel":4,"shuffle":true}},"training":{"iterations":2000,'
    b'"batch_size":32768,"seconds":60.0,"frozen_at":1000,"stopped_early":false,"device":"cpu"},'
    b'"tensors":[["quantized",1024,"lorenzo",1],["quantized",144,"none",1],["quantized",48,"none",1],'
    b'["quantized",512,"delta",1],["quantized",4096,"none",1],["quantized",64,"none",2],["float32"]],'
    b'"packing":{"mode":"size","bits":null,"target_bytes":10000,"float32_psnr":40.0,'
    b'"float32_max_abs_error":1.0,"float32_parameter_bytes":100000,"qat_iterations":0,"scale":0.001,'
    b'"psnr":39.9,"max_abs_error":1.0,"psnr_cost":0.1},"correction":null}'
)
#: The name a packed file's header gives its description coding; files without it use LZMA (version 1).
DESCRIPTION_CODING = "deflate-primer-1"


def compress_description(data: bytes) -> bytes:
    """Raw deflate of a description's JSON, primed with :data:`DESCRIPTION_PRIMER`."""
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zlib.Z_DEFAULT_STRATEGY, zdict=DESCRIPTION_PRIMER)
    return compressor.compress(data) + compressor.flush()


def decompress_description(data: bytes, limit: int, what: str) -> bytes:
    """Inverse of :func:`compress_description`; never more than ``limit`` bytes.

    Raises:
        ApmgsrnError: corrupt, unterminated, followed by other bytes, or longer than ``limit``.
    """
    decoder = zlib.decompressobj(-15, zdict=DESCRIPTION_PRIMER)
    try:
        out = decoder.decompress(data, limit)
    except zlib.error:
        raise ApmgsrnError(f"{what}: compressed data is corrupt") from None
    if decoder.unconsumed_tail or not decoder.eof or decoder.unused_data:
        raise ApmgsrnError(f"{what}: compressed data is corrupt or longer than {limit} bytes")
    return out


# ------------------------------------------------------------------------------------------ predictors
def predict(levels: np.ndarray, shape: tuple[int, ...], predictor: str) -> np.ndarray:
    """Residuals ``[numel]`` int64 of integers ``levels`` (C order of ``shape``) under ``predictor``."""
    values = levels.astype(np.int64).reshape(shape)
    if predictor == "none" or not values.size:
        return values.reshape(-1)
    if predictor == "delta":
        return np.diff(values, axis=-1, prepend=0).reshape(-1)
    if predictor == "lorenzo":
        out = values
        for axis in (-1, -2, -3):
            out = np.diff(out, axis=axis, prepend=0)
        return out.reshape(-1)
    if predictor == "time":
        return np.diff(values, axis=0, prepend=0).reshape(-1)
    raise ValueError(f"unknown predictor {predictor!r}")


def reconstruct(residuals: np.ndarray, shape: tuple[int, ...], predictor: str) -> np.ndarray:
    """Inverse of :func:`predict`: integers ``[numel]`` int64."""
    values = residuals.astype(np.int64).reshape(shape)
    if predictor == "delta":
        values = np.cumsum(values, axis=-1)
    elif predictor == "lorenzo":
        for axis in (-3, -2, -1):
            values = np.cumsum(values, axis=axis)
    elif predictor == "time":
        values = np.cumsum(values, axis=0)
    elif predictor != "none":
        raise ValueError(f"unknown predictor {predictor!r}")
    return values.reshape(-1)


def predictors_for(shape: tuple[int, ...]) -> tuple[str, ...]:
    """Predictors that make sense for ``shape`` (Lorenzo needs three axes of at least two values)."""
    names = ["none"]
    if len(shape) >= 1 and shape[-1] > 1:
        names.append("delta")
    if len(shape) >= 3 and min(shape[-3:]) > 1:
        names.append("lorenzo")
    return tuple(names)


def series_predictors_for(shape: tuple[int, ...]) -> tuple[str, ...]:
    """Predictors that make sense for a tensor with a leading time axis (a series' grids ``[T, M, C, D, H, W]``
    or residuals, a hybrid's level tables ``[T, P]``): those of :func:`predictors_for`, plus ``time`` where there
    are two steps or more."""
    names = predictors_for(shape)
    if len(shape) >= 2 and shape[0] > 1:
        names += ("time",)
    return names


# ------------------------------------------------------------------------------------------ byte layout
def zigzag(values: np.ndarray) -> np.ndarray:
    """Signed -> unsigned: ``0, -1, 1, -2`` -> ``0, 1, 2, 3`` (uint64)."""
    values = values.astype(np.int64)
    return ((values << 1) ^ (values >> 63)).astype(np.uint64)


def unzigzag(values: np.ndarray) -> np.ndarray:
    """Inverse of :func:`zigzag` (int64)."""
    values = values.astype(np.uint64)
    return ((values >> np.uint64(1)).astype(np.int64)) ^ -((values & np.uint64(1)).astype(np.int64))


def width_of(residuals: np.ndarray) -> int:
    """Bytes per value (1, 2 or 4) that hold every zigzag-mapped residual."""
    top = int(zigzag(residuals).max()) if residuals.size else 0
    return 1 if top < 1 << 8 else 2 if top < 1 << 16 else 4


def to_bytes(residuals: np.ndarray, width: int) -> bytes:
    """Zigzag-mapped residuals as ``width``-byte little-endian values, byte planes one after another."""
    unsigned = zigzag(residuals).astype({1: "<u1", 2: "<u2", 4: "<u4"}[width])
    planes = unsigned.view(np.uint8).reshape(-1, width).T  # [width, numel]: low bytes first
    return np.ascontiguousarray(planes).tobytes()


def from_bytes(data: bytes, count: int, width: int) -> np.ndarray:
    """Inverse of :func:`to_bytes`: ``count`` int64 residuals."""
    planes = np.frombuffer(data, dtype=np.uint8).reshape(width, count)
    unsigned = np.ascontiguousarray(planes.T).view({1: "<u1", 2: "<u2", 4: "<u4"}[width]).reshape(count)
    return unzigzag(unsigned.astype(np.uint64))


def encode_levels(levels: np.ndarray, shape: tuple[int, ...], predictor: str) -> tuple[bytes, int]:
    """Predict, lay out and compress integers.

    Returns:
        (compressed bytes, width in bytes per value).
    """
    residuals = predict(levels, shape, predictor)
    width = width_of(residuals)
    return compress(to_bytes(residuals, width)), width


def best_encoding(levels: np.ndarray, shape: tuple[int, ...], predictors: tuple[str, ...] | None = None
                  ) -> tuple[bytes, int, str]:
    """The smallest of :func:`encode_levels` over ``predictors`` (default: :func:`predictors_for` ``shape``).

    Returns:
        (compressed bytes, width, predictor).
    """
    return best_encodings([(levels, shape, predictors)])[0]


def best_encodings(jobs: list[tuple[np.ndarray, tuple[int, ...], tuple[str, ...] | None]]
                   ) -> list[tuple[bytes, int, str]]:
    """:func:`best_encoding` of every ``(levels, shape, predictors)``, all their compressions run side by side on
    the threads the process may use (:func:`~apmgsrn.threads.map_in_threads`: LZMA releases the GIL; as many as
    memory allows, :func:`coding_threads`); the same bytes as one after another, the first predictor kept where
    two code alike."""
    tasks = [(index, predictor) for index, (_, shape, predictors) in enumerate(jobs)
             for predictor in predictors or predictors_for(shape)]
    coded = map_in_threads(lambda task: encode_levels(jobs[task[0]][0], jobs[task[0]][1], task[1]), tasks,
                           coding_threads([jobs[index][0].size for index, _ in tasks]))
    best: list[tuple[bytes, int, str] | None] = [None] * len(jobs)
    for (index, predictor), (data, width) in zip(tasks, coded):
        if best[index] is None or len(data) < len(best[index][0]):
            best[index] = (data, width, predictor)
    return best
