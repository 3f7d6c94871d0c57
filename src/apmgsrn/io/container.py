"""The container every model file uses: one safetensors file whose header metadata says what it holds.

The header's ``__metadata__`` holds ``format = "apmgsrn"``, a ``format_version``, a ``kind`` (``field``,
``training-state``, ...), a ``description`` JSON and ``checksums``: a crc32c of every tensor (its name, dtype,
shape and bytes) and one of the description (format, version, kind, description text and the tensors'
checksums), so that the description checksum alone identifies the whole file. Reading validates the whole
header as plain JSON before any tensor is touched: the description checksum must match, the declared dtype
and shape of every tensor must match its byte extent, extents must lie inside the file and not overlap, and
the sizes must stay under a bound; every tensor's checksum is verified when its bytes are read, before use.
Files written before checksums existed (format version 2 and older) still load, with a note
(:class:`~apmgsrn.errors.ApmgsrnNote`). Nothing in a file is ever executed (safetensors holds raw numbers; no
pickle anywhere).
"""

from __future__ import annotations

import json
import math
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import crc32c
import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save as save_safetensors_bytes

from apmgsrn.limits import LIMITS
from apmgsrn.errors import ApmgsrnError, ApmgsrnNote
from apmgsrn.atomic import atomic_write

FORMAT = "apmgsrn"
#: Version 1: the first format. Version 2: a packed file's description is coded with deflate and a primer
#: (:mod:`apmgsrn.io.packed`; the layout of every other kind is unchanged). Version 3: the metadata records
#: crc32c checksums of the description and of every tensor, verified on load. Files of every version from 1 up
#: to this one load.
FORMAT_VERSION = 3
#: The first version whose files must hold ``checksums``.
CHECKSUMS_VERSION = 3
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
#: The safetensors name of each torch dtype (what a tensor's checksum covers).
TORCH_DTYPES = {torch.float64: "F64", torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16",
                torch.int64: "I64", torch.int32: "I32", torch.int16: "I16", torch.int8: "I8", torch.uint8: "U8",
                torch.bool: "BOOL"}


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
        checksums: name -> the crc32c its tensor must have (None in files older than
            :data:`CHECKSUMS_VERSION`).
        digest: the description's checksum, which covers every tensor's (None in older files).
    """

    kind: str
    version: int
    description: dict
    tensors: dict[str, TensorEntry]
    checksums: dict[str, str] | None = None
    digest: str | None = None


def parse_json(text: str | bytes, fail: str):
    """``json.loads`` that turns every way a hostile text can fail into ``ApmgsrnError(fail)``.

    Deep nesting (RecursionError), invalid UTF-8 and invalid JSON are all refused with the same message.
    """
    try:
        return json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError):
        raise ApmgsrnError(fail) from None


def read_header(path: str | os.PathLike) -> Header:
    """Validate a file's safetensors header and its description checksum, and return what it declares.

    Raises:
        ApmgsrnError: missing, unreadable, not a model file, corrupt, damaged, or from a newer format version.
    """
    path = Path(path)
    if not path.exists():
        raise ApmgsrnError(f"{path}: no such model file")
    if not path.is_file():
        raise ApmgsrnError(f"{path}: is not a model file (a folder?); pass the file written by 'apmgsrn train'")
    try:
        with open(path, "rb") as f:
            # The size of the file opened, not of the path: a writer may atomically replace the path meanwhile.
            size = os.fstat(f.fileno()).st_size
            prefix = f.read(8)
            length = _header_length(path, prefix, size)
            raw = f.read(length)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    return _parse_header(path, raw, size - 8 - length)


def _not_ours(path) -> str:
    return f"{path}: not an apmgsrn model file (corrupt, truncated or another format)"


def _damaged(path, part: str) -> ApmgsrnError:
    return ApmgsrnError(f"{path}: damaged: checksum of {part} does not match (the file was changed after it "
                        "was written)")


def _header_length(path, prefix: bytes, size: int) -> int:
    """The header length an 8-byte prefix declares, checked against the file's size."""
    if len(prefix) < 8:
        raise ApmgsrnError(_not_ours(path))
    (length,) = struct.unpack("<Q", prefix)
    if length > min(size - 8, LIMITS.header_bytes):
        raise ApmgsrnError(_not_ours(path))
    return length


def _parse_header(path, raw: bytes, body: int) -> Header:
    """The validated header of ``raw`` (the header's JSON bytes; ``body``: the bytes after it)."""
    not_ours = _not_ours(path)
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
    if version < 1:
        raise ApmgsrnError(f"{path}: not an apmgsrn model file (model format {version} does not exist)")
    tensors = _tensor_entries(header, body, not_ours)
    checksums, digest = _checked_metadata(path, meta, version, set(tensors))
    description = parse_json(meta.get("description", "{}"), not_ours)
    if not isinstance(description, dict) or not isinstance(meta.get("kind", ""), str):
        raise ApmgsrnError(not_ours)
    return Header(meta.get("kind", ""), version, description, tensors, checksums, digest)


def _checked_metadata(path, meta: dict, version: int, names: set[str]) -> tuple[dict[str, str] | None, str | None]:
    """The tensors' checksums and the description's, the latter verified against the metadata.

    Checksums are verified whenever the file holds them (a bit flip in the version cannot turn them off) and
    required from :data:`CHECKSUMS_VERSION` on; an older file without them is noted once.
    """
    if "checksums" not in meta:
        if version >= CHECKSUMS_VERSION:
            raise ApmgsrnError(f"{path}: damaged: the checksums that model format {version} records are missing")
        note_unchecked(path, f"model format {version}, written before checksums: damage to it cannot be detected")
        return None, None
    damaged = _damaged(path, "the description")
    stored = parse_json(meta["checksums"], str(damaged)) if isinstance(meta["checksums"], str) else None
    table = stored.get("tensors") if isinstance(stored, dict) else None
    digest = stored.get("description") if isinstance(stored, dict) else None
    if not (isinstance(table, dict) and isinstance(digest, str) and all(isinstance(v, str) for v in table.values())):
        raise damaged
    if digest != _description_checksum(meta, table):
        raise damaged
    if set(table) != names:
        raise _damaged(path, "the tensor list")
    return table, digest


def _description_checksum(meta: dict, table: dict[str, str]) -> str:
    """crc32c of what the metadata says: format, version, kind and description as stored, and the tensors'
    checksums (so a changed tensor checksum is a changed description too)."""
    covered = [meta.get("format"), meta.get("format_version"), meta.get("kind", ""), meta.get("description", "{}"),
               table]
    return _crc([json.dumps(covered, sort_keys=True, separators=(",", ":")).encode()])


def tensor_checksum(name: str, tensor: torch.Tensor) -> str:
    """crc32c of a tensor's name, dtype, shape and bytes (as a file stores them: little-endian, C order)."""
    dtype = TORCH_DTYPES.get(tensor.dtype)
    if dtype is None:
        raise ValueError(f"tensor {name!r} has dtype {tensor.dtype}, which model files do not store")
    data = tensor.detach().contiguous().cpu().reshape(-1).view(torch.uint8).numpy()
    label = json.dumps([name, dtype, list(tensor.shape)], separators=(",", ":")).encode()
    return _crc([label, memoryview(data)])


def _crc(parts) -> str:
    value = 0
    for part in parts:
        value = crc32c.crc32c(part, value=value)
    return f"{value:08x}"


def file_checksum(path: str | os.PathLike) -> str:
    """crc32c of a whole file's bytes (a brick folder's manifest records its bricks' this way).

    Raises:
        ApmgsrnError: unreadable.
    """
    value = 0
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 22):
                value = crc32c.crc32c(chunk, value=value)
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    return f"{value:08x}"


#: The key under which a folder's JSON manifest (a brick or time-series brick folder) holds its own checksum.
MANIFEST_CHECKSUM = "manifest_checksum"


def manifest_checksum(manifest: dict) -> str:
    """crc32c of a folder manifest's canonical JSON (keys sorted, no spaces), its own checksum left out."""
    body = {key: value for key, value in manifest.items() if key != MANIFEST_CHECKSUM}
    return _crc([json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=True).encode()])


def sealed_manifest_text(manifest: dict) -> str:
    """A folder manifest's JSON text with its own checksum (:data:`MANIFEST_CHECKSUM`), verified on reading."""
    body = {key: value for key, value in manifest.items() if key != MANIFEST_CHECKSUM}
    return json.dumps({**body, MANIFEST_CHECKSUM: manifest_checksum(body)}, indent=1, allow_nan=True)


#: Files already noted as written without checksums (each is noted once per process).
_NOTED: set[str] = set()


def note_unchecked(path: str | os.PathLike, why: str) -> None:
    """Note, once per file, that ``path`` was written before checksums (``why``: which format, what follows)."""
    key = os.path.abspath(path)
    if key in _NOTED:
        return
    _NOTED.add(key)
    warnings.warn(f"{path}: {why}", ApmgsrnNote, stacklevel=3)


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
    """All tensors of a file, each verified against its checksum before it is returned.

    The header is read again from the same bytes as the tensors (a file replaced since :func:`read_header`
    cannot slip through).

    Raises:
        ApmgsrnError: unreadable, not a model file, corrupt or damaged.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    length = _header_length(path, data[:8], len(data))
    header = _parse_header(path, data[8:8 + length], len(data) - 8 - length)
    try:
        tensors = load_safetensors_bytes(data)
    except (SafetensorError, ValueError) as exc:
        raise ApmgsrnError(f"{path}: not an apmgsrn model file (corrupt: {exc})") from None
    if set(tensors) != set(header.tensors):
        raise ApmgsrnError(_not_ours(path))
    if header.checksums is not None:
        for name, tensor in tensors.items():
            if tensor_checksum(name, tensor) != header.checksums[name]:
                raise _damaged(path, f"tensor {name!r}")
    return tensors


def verify_file(path: str | os.PathLike) -> Header:
    """Check a container file of any kind without building anything: its header, the description checksum and
    every tensor's checksum.

    Returns:
        The header.

    Raises:
        ApmgsrnError: unreadable, not a model file, corrupt, damaged or from a newer format version.
    """
    header = read_header(path)
    load_tensors(path)
    return header


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
    """The bytes of a container file holding ``tensors`` and a JSON ``description``, with the checksums of both
    (nothing written)."""
    metadata = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "kind": kind,
        "description": json.dumps(description, separators=(",", ":"), allow_nan=True),
    }
    return sealed_file_bytes(tensors, metadata)


def sealed_file_bytes(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> bytes:
    """The bytes of a safetensors file of ``tensors`` whose metadata is ``metadata`` plus the checksums of it
    and of every tensor (any ``checksums`` entry in ``metadata`` is replaced)."""
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    metadata = {k: v for k, v in metadata.items() if k != "checksums"}
    table = {name: tensor_checksum(name, tensor) for name, tensor in tensors.items()}
    checksums = {"description": _description_checksum(metadata, table), "tensors": table}
    metadata["checksums"] = json.dumps(checksums, separators=(",", ":"))
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
    # A model writer may write into a brick folder (its bricks, their checkpoints); commands and the API refuse a
    # model output inside another model's folder before any work (cli/paths.py, api.py).
    atomic_write(path, lambda temp: Path(temp).write_bytes(data), what, model_part=True)
    return len(data)
