"""Headerless binary volumes (``.raw``/``.bin``), memory-mapped.

Dims and dtype come from ``--shape X,Y,Z --dtype TYPE`` or from a file name such as
``richtmyer_meshkov_t20_256x256x256_uint8.raw`` (``NAME_XxYxZ_dtype.raw``, x first).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.memory_map import MemoryMappedVolume
from apmgsrn.data.opener import check_declared_array, check_regular
from apmgsrn.data.volume import parse_shape
from apmgsrn.errors import ApmgsrnError

#: Type names seen in raw file names and on command lines beyond NumPy's own (uint8, float32, ...).
DTYPE_ALIASES = {
    "uchar": "uint8",
    "char": "int8",
    "byte": "uint8",
    "ushort": "uint16",
    "short": "int16",
    "uint": "uint32",
    "int": "int32",
    "float": "float32",
    "double": "float64",
    "half": "float16",
}

_NAME_PATTERN = re.compile(r"(?:^|[_\-.])(\d+)x(\d+)x(\d+)(?:_([A-Za-z0-9<>=|]+))?\.(?:raw|bin)$", re.IGNORECASE)


def parse_dtype(text: str, path: Path | str = "") -> np.dtype:
    """Parse a voxel type name (``uint8``, ``float32``, ``<u2``, ``double``, ...).

    Args:
        text: The type name.
        path: The file it is for, for messages.

    Returns:
        The NumPy dtype (integer or float).

    Raises:
        ApmgsrnError: If the name is not an integer or float type.
    """
    name = DTYPE_ALIASES.get(str(text).lower(), str(text))
    try:
        dtype = np.dtype(name)
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in "uif":
        where = f"{path}: " if path else ""
        raise ApmgsrnError(
            f"{where}unknown voxel type {text!r}; use one of uint8, int8, uint16, int16, uint32, int32, "
            "float16, float32, float64 (e.g. dtype=uint8)", arguments=("dtype",)
        )
    return dtype


def parse_raw_name(path: Path) -> tuple[tuple[int, int, int] | None, str | None]:
    """Read ``X, Y, Z`` and the dtype name out of a file name like ``NAME_XxYxZ_dtype.raw``.

    Args:
        path: The raw file.

    Returns:
        ``((X, Y, Z) or None, dtype name or None)``.
    """
    match = _NAME_PATTERN.search(path.name)
    if match is None:
        return None, None
    dims = (int(match.group(1)), int(match.group(2)), int(match.group(3)))
    return dims, match.group(4)


class RawVolume(MemoryMappedVolume):
    """A headerless C-order (z, y, x) binary volume, x fastest, read through ``np.memmap``.

    Args:
        path: The ``.raw``/``.bin`` file.
        shape: ``(X, Y, Z)`` as typed by users (x first), or ``"X,Y,Z"``; default: from the name.
        dtype: Voxel type name; default: from the name.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
    """

    def __init__(
        self,
        path: Path,
        shape: tuple[int, int, int] | str | None = None,
        dtype: str | None = None,
        fill_nonfinite: float | None = None,
    ) -> None:
        path = Path(path)
        named_dims, named_dtype = parse_raw_name(path)
        if isinstance(shape, str):
            shape = parse_shape(shape)
        xyz = tuple(int(n) for n in shape) if shape is not None else named_dims
        type_name = dtype if dtype is not None else named_dtype
        if xyz is None or type_name is None:
            missing = " and ".join(
                text for text, value in (("shape=X,Y,Z", xyz), ("dtype=TYPE", type_name)) if value is None
            )
            raise ApmgsrnError(
                f"{path}: a raw file has no header; pass {missing}, or name the file NAME_XxYxZ_dtype.raw "
                "(e.g. volume_256x256x256_uint8.raw)", arguments=("shape", "dtype"),
            )
        if len(xyz) != 3 or min(xyz) <= 0:
            raise ApmgsrnError(f"{path}: invalid shape {xyz}; pass shape=X,Y,Z with three positive integers",
                               arguments=("shape",))
        voxel_type = parse_dtype(type_name, path)
        x_size, y_size, z_size = xyz
        expected = x_size * y_size * z_size * voxel_type.itemsize
        actual = check_regular(path).st_size
        if actual != expected:
            voxels = x_size * y_size * z_size
            hint = ""
            if actual and actual % voxels == 0 and actual // voxels in (1, 2, 4, 8):
                hint = f" (the size fits {actual // voxels}-byte voxels: check dtype=)"
            raise ApmgsrnError(
                f"{path}: file is {actual} bytes but {x_size}x{y_size}x{z_size} (x*y*z) {voxel_type} needs "
                f"{expected} bytes{hint}; the file is truncated or shape= or dtype= is wrong",
                arguments=("shape", "dtype"),
            )
        check_declared_array(path, None, (z_size, y_size, x_size), voxel_type, actual)
        super().__init__(path, None, (z_size, y_size, x_size), voxel_type, fill_nonfinite)

    def _open_handle(self) -> Any:
        check_regular(self.path)
        try:
            return np.memmap(self.path, dtype=self.dtype, mode="r", shape=self.shape)
        except (OSError, ValueError) as exc:
            raise ApmgsrnError(f"{self.path}: cannot map the raw file ({exc})") from exc
