"""Choosing which variable of a multi-array file to read, and which time step.

NetCDF, HDF5, Zarr and VTK files can hold several arrays; the rules for picking one, and the
messages when the choice is ambiguous or impossible, are the same for all of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apmgsrn.errors import ApmgsrnError


@dataclass(frozen=True)
class ArrayInfo:
    """What a reader found in a file before reading any voxels.

    Attributes:
        name: Variable name, HDF5 dataset path, Zarr array path or VTK array name.
        shape: Stored shape, C order.
        dtype: Stored dtype, or ``None`` when the array is not numeric (strings, compounds).
        dims: Dimension names, where the format has them (NetCDF).
    """

    name: str
    shape: tuple[int, ...]
    dtype: np.dtype | None
    dims: tuple[str, ...] | None = None

    @property
    def numeric(self) -> bool:
        """Whether the voxels are integers or floats."""
        return self.dtype is not None and self.dtype.kind in "uifb"

    def summary(self) -> str:
        """E.g. ``"density (3-D z=256 y=256 x=256, float32)"`` for error messages."""
        if self.dims is not None and len(self.dims) == len(self.shape):
            extent = " ".join(f"{d}={n}" for d, n in zip(self.dims, self.shape))
        else:
            extent = "x".join(str(n) for n in self.shape) or "scalar"
        kind = str(self.dtype) if self.dtype is not None else "non-numeric"
        return f"{self.name} ({len(self.shape)}-D {extent}, {kind})"


def _listing(arrays: list[ArrayInfo]) -> str:
    return "; ".join(a.summary() for a in arrays) if arrays else "nothing"


def choose_array(
    path: Path,
    arrays: list[ArrayInfo],
    requested: str | None,
    kind: str = "variable",
    default_ndims: tuple[int, ...] = (3,),
) -> ArrayInfo:
    """Pick the array to read: the one named, else the only numeric one of `default_ndims` dims.

    Args:
        path: The file, for messages.
        arrays: Everything the file holds.
        requested: Name the user passed as ``variable`` (``None`` for the default).
        kind: What the format calls its arrays ("variable", "dataset", "array"), for messages.
        default_ndims: Dimension counts eligible as the default (``(3, 4)`` where a leading time
            axis is conventional, as in NetCDF).

    Returns:
        The chosen `ArrayInfo`.

    Raises:
        ApmgsrnError: If the named array is missing, or the default is absent or ambiguous.
    """
    if requested is not None:
        for info in arrays:
            if info.name == requested or info.name.lstrip("/") == requested.lstrip("/"):
                return info
        raise ApmgsrnError(
            f"{path}: no {kind} named {requested!r}; available: {_listing(arrays)}; "
            "pass variable= with one of these names", arguments=("variable",),
        )
    eligible = [a for a in arrays if a.numeric and len(a.shape) in default_ndims]
    if len(eligible) == 1:
        return eligible[0]
    if not eligible:
        raise ApmgsrnError(
            f"{path}: no 3-D {kind} found (found: {_listing(arrays)}); "
            "apmgsrn needs a 3-D volume (z, y, x); pass variable=NAME if one of these is it", arguments=("variable",),
        )
    raise ApmgsrnError(
        f"{path}: several 3-D {kind}s: {', '.join(repr(a.name) for a in eligible)}; "
        "pass variable=NAME to choose one", arguments=("variable",),
    )


def select_time(
    path: Path, info: ArrayInfo, time: int | None, kind: str = "variable"
) -> tuple[int | None, tuple[int, int, int]]:
    """Resolve the time index of a 3-D or (time, z, y, x) array.

    Args:
        path: The file, for messages.
        info: The chosen array.
        time: Index the user passed as ``time`` (``None`` for the default).
        kind: What the format calls its arrays, for messages.

    Returns:
        ``(time_index or None, (D, H, W))``: ``None`` when the array has no time axis.

    Raises:
        ApmgsrnError: If the array is not numeric, not 3-D/4-D, has several time steps and no
            ``time``, or ``time`` is out of range or given for data without a time axis.
    """
    if not info.numeric:
        raise ApmgsrnError(
            f"{path}: {kind} {info.summary()} is not numeric; pass variable= with a numeric 3-D {kind}",
            arguments=("variable",),
        )
    ndim = len(info.shape)
    if ndim == 3:
        if time is not None:
            raise ApmgsrnError(f"{path}: {kind} {info.summary()} has no time dimension; drop time=",
                               arguments=("time",))
        return None, (info.shape[0], info.shape[1], info.shape[2])
    if ndim == 4:
        steps = info.shape[0]
        if time is None:
            if steps == 1:
                time = 0
            else:
                raise ApmgsrnError(
                    f"{path}: {kind} {info.summary()} has a time dimension of length {steps}; "
                    f"pass time=INDEX (0..{steps - 1})", arguments=("time",),
                )
        if not isinstance(time, (int, np.integer)) or not 0 <= int(time) < steps:
            raise ApmgsrnError(
                f"{path}: time={time} is out of range: {kind} {info.name!r} has {steps} time steps "
                f"(pass time=0..{steps - 1})", arguments=("time",),
            )
        return int(time), (info.shape[1], info.shape[2], info.shape[3])
    raise ApmgsrnError(
        f"{path}: {kind} {info.summary()} is {ndim}-D; apmgsrn needs 3-D data (z, y, x) "
        "or 4-D with a leading time dimension"
    )
