"""The container every model file uses: one safetensors file whose header metadata says what it holds.

The header's ``__metadata__`` holds ``format = "apmgsrn"``, a ``format_version``, a ``kind`` (``field``,
``training-state``, ...) and a ``description`` JSON. Reading validates the whole header as plain JSON before
any tensor is touched: the declared dtype and shape of every tensor must match its byte extent, extents must
lie inside the file and not overlap, and the sizes must stay under a bound. Nothing in a file is ever
executed (safetensors holds raw numbers; no pickle anywhere).
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save as save_safetensors_bytes

from apmgsrn.errors import ApmgsrnError
from apmgsrn.atomic import atomic_write

FORMAT = "apmgsrn"
#: Version 1: the first format. Version 2: a packed file's description is coded with deflate and a primer
#: (:mod:`apmgsrn.io.packed`; the layout of every other kind is unchanged). Files of every version up to this
#: one load.
FORMAT_VERSION = 2
#: Largest JSON header of a model file (and of a brick folder's manifest).
MAX_HEADER_BYTES = 64 * 1024 * 1024
#: Kinds of single-file models: a float32 field (:mod:`apmgsrn.io.field_file`) and a packed one
#: (:mod:`apmgsrn.io.packed`). A model of either kind may replace a model file of the other.
FIELD_KIND, PACKED_KIND = "field", "packed-field"
MODEL_FILE_KINDS = (FIELD_KIND, PACKED_KIND)
#: Kinds of time-series model files: float32 (:mod:`apmgsrn.series.file`) and packed
#: (:mod:`apmgsrn.series.packed_file`). Either may replace a file of the other, never a single-volume model.
SERIES_KIND, PACKED_SERIES_KIND = "series", "packed-series"
SERIES_FILE_KINDS = (SERIES_KIND, PACKED_SERIES_KIND)
#: Element sizes of the dtypes a model file may hold.
DTYPE_BYTES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}


@dataclass(frozen=True)
class TensorEntry:
    """A tensor as the header declares it (checked against its byte extent)."""

    dtype: str
    shape: tuple[int, ...]
    nbytes: int


@dataclass(frozen=True)
class Header:
    """A validated header: what the file holds, before any tensor is read.

    Attributes:
        kind: ``"field"``, ``"training-state"``, ...
        version: format version of the file.
        description: the parsed ``description`` JSON (an object).
        tensors: name -> declared dtype and shape.
    """

    kind: str
    version: int
    description: dict
    tensors: dict[str, TensorEntry]


def parse_json(text: str | bytes, fail: str):
    """``json.loads`` that turns every way a hostile text can fail into ``ApmgsrnError(fail)``.

    Deep nesting (RecursionError), invalid UTF-8 and invalid JSON are all refused with the same message.
    """
    try:
        return json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError):
        raise ApmgsrnError(fail) from None


def read_header(path: str | os.PathLike) -> Header:
    """Validate a file's safetensors header and return what it declares.

    Raises:
        ApmgsrnError: missing, unreadable, not a model file, corrupt, or from a newer format version.
    """
    path = Path(path)
    if not path.exists():
        raise ApmgsrnError(f"{path}: no such model file")
    if not path.is_file():
        raise ApmgsrnError(f"{path}: is not a model file (a folder?); pass the file written by 'apmgsrn train'")
    not_ours = f"{path}: not an apmgsrn model file (corrupt, truncated or another format)"
    try:
        with open(path, "rb") as f:
            # The size of the file opened, not of the path: a writer may atomically replace the path meanwhile.
            size = os.fstat(f.fileno()).st_size
            prefix = f.read(8)
            if len(prefix) < 8:
                raise ApmgsrnError(not_ours)
            (length,) = struct.unpack("<Q", prefix)
            if length > min(size - 8, MAX_HEADER_BYTES):
                raise ApmgsrnError(not_ours)
            raw = f.read(length)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    header = parse_json(raw, not_ours)
    meta = header.get("__metadata__") if isinstance(header, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ApmgsrnError(not_ours)
    try:
        version = int(meta.get("format_version", ""))
    except (TypeError, ValueError):
        raise ApmgsrnError(not_ours) from None
    if version > FORMAT_VERSION:
        raise ApmgsrnError(
            f"{path}: written by a newer apmgsrn (model format {version}, this one reads up to "
            f"{FORMAT_VERSION}); upgrade apmgsrn to load it"
        )
    description = parse_json(meta.get("description", "{}"), not_ours)
    if not isinstance(description, dict) or not isinstance(meta.get("kind", ""), str):
        raise ApmgsrnError(not_ours)
    tensors = _tensor_entries(header, size - 8 - length, not_ours)
    return Header(meta.get("kind", ""), version, description, tensors)


def header_of_kind(path: str | os.PathLike, kind: str, what: str, header: Header | None = None) -> Header:
    """``header`` (read from ``path`` when None), checked to declare ``kind``.

    Args:
        what: the file wanted, for the message (``"a packed model"``).

    Raises:
        ApmgsrnError: unreadable, or a file of another kind.
    """
    header = header or read_header(path)
    if header.kind != kind:
        raise ApmgsrnError(f"{path}: is a {header.kind or 'unknown'} file, not {what}")
    return header


def _tensor_entries(header: dict, body: int, not_ours: str) -> dict[str, TensorEntry]:
    """Every tensor's dtype and shape, checked against its extent; extents inside the body, disjoint."""
    entries: dict[str, TensorEntry] = {}
    extents = []
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        if not isinstance(entry, dict):
            raise ApmgsrnError(not_ours)
        offsets, dtype, shape = entry.get("data_offsets"), entry.get("dtype"), entry.get("shape")
        if not (
            isinstance(offsets, list) and len(offsets) == 2 and all(_is_int(v) for v in offsets)
            and 0 <= offsets[0] <= offsets[1] <= body
            and dtype in DTYPE_BYTES
            and isinstance(shape, list) and len(shape) <= 8 and all(_is_int(v) and v >= 0 for v in shape)
            and math.prod(shape) * DTYPE_BYTES[dtype] == offsets[1] - offsets[0]
        ):
            raise ApmgsrnError(not_ours)
        entries[name] = TensorEntry(dtype, tuple(shape), offsets[1] - offsets[0])
        extents.append(tuple(offsets))
    extents.sort()
    for (_, end), (start, _) in zip(extents, extents[1:]):
        if start < end:
            raise ApmgsrnError(not_ours)
    return entries


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def load_tensors(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """All tensors of a file whose header :func:`read_header` accepted (safetensors parsing only)."""
    try:
        data = Path(path).read_bytes()
        return load_safetensors_bytes(data)
    except (SafetensorError, ValueError) as exc:
        raise ApmgsrnError(f"{path}: not an apmgsrn model file (corrupt: {exc})") from None
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None


def check_replaceable(path: str | os.PathLike, kind: str, what: str = "model file") -> None:
    """Refuse to write a file of ``kind`` where anything but an older file of the same kind lies.

    A model replaces an older model of any single-file kind (:data:`MODEL_FILE_KINDS`; atomically, once the
    new one is complete), a time-series model an older one of either series kind (:data:`SERIES_FILE_KINDS`)
    and a training checkpoint an older checkpoint; a volume, an image, a file of another kind or one this
    version cannot read is never overwritten by one.

    Raises:
        ApmgsrnError: ``path`` exists and is not a readable apmgsrn file of ``kind``.
    """
    path = Path(path)
    if not path.exists() or path.is_dir():
        return  # nothing to lose; a folder is refused by the writer
    replaceable = next((kinds for kinds in (MODEL_FILE_KINDS, SERIES_FILE_KINDS) if kind in kinds), (kind,))
    try:
        same_kind = read_header(path).kind in replaceable
    except ApmgsrnError:
        same_kind = False
    if not same_kind:
        raise ApmgsrnError(
            f"{path}: exists and is not an apmgsrn {what}; it is never overwritten by one: delete it yourself "
            "or pass another out=", arguments=("out",),
        )


def file_bytes(tensors: dict[str, torch.Tensor], kind: str, description: dict) -> bytes:
    """The bytes of a container file holding ``tensors`` and a JSON ``description`` (nothing written)."""
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    metadata = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "kind": kind,
        "description": json.dumps(description, separators=(",", ":"), allow_nan=True),
    }
    return save_safetensors_bytes(tensors, metadata=metadata)


def save_tensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor], kind: str, description: dict,
                 what: str = "model file") -> int:
    """Write tensors and a JSON description atomically as one safetensors file.

    The file is serialised in memory and written with plain file I/O, so a full disk is an ``OSError`` that
    :func:`~apmgsrn.atomic.atomic_write` turns into one clear message. An existing file is replaced only
    when it is an older file of the same kind (:func:`check_replaceable`).

    Returns:
        The file's size in bytes.
    """
    return write_file_bytes(path, file_bytes(tensors, kind, description), kind, what)


def write_file_bytes(path: str | os.PathLike, data: bytes, kind: str, what: str = "model file") -> int:
    """Write a container file's bytes (from :func:`file_bytes`) atomically, after :func:`check_replaceable`.

    Returns:
        The file's size in bytes.
    """
    check_replaceable(path, kind, what)
    atomic_write(path, lambda temp: Path(temp).write_bytes(data), what)
    return len(data)
