"""NumPy ``.npy`` volumes, memory-mapped (``np.load(mmap_mode="r")``)."""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from apmgsrn.data.memory_map import MemoryMappedVolume
from apmgsrn.data.opener import check_declared_array, check_regular
from apmgsrn.errors import ApmgsrnError

#: The first bytes of every .npy file (numpy.lib.format).
NPY_MAGIC = b"\x93NUMPY"


def _map_npy(path: Path) -> np.ndarray:
    size = check_regular(path).st_size
    try:
        with open(path, "rb") as f:
            magic = f.read(len(NPY_MAGIC))
    except OSError as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc.strerror})") from None
    if magic != NPY_MAGIC and not magic.startswith(b"PK"):  # numpy reads a .npz (a zip) and says so below
        raise ApmgsrnError(f"{path}: not a .npy array (it lacks numpy's header); save the volume with numpy.save")
    try:
        # allow_pickle=False: an .npy of Python objects could run code when loaded.
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError, TypeError, pickle.UnpicklingError) as exc:
        raise ApmgsrnError(
            f"{path}: not a readable .npy array ({exc}); check that it was written by numpy.save and is not truncated"
        ) from exc
    if not isinstance(array, np.ndarray):
        raise ApmgsrnError(f"{path}: holds no single array; save one 3-D array with numpy.save")
    check_declared_array(path, None, array.shape, array.dtype, size)
    return array


class NumpyVolume(MemoryMappedVolume):
    """A 3-D array in a ``.npy`` file, C order (z, y, x), memory-mapped.

    Args:
        path: The ``.npy`` file.
        fill_nonfinite: If set, reads replace NaN/Inf by this value.
    """

    def __init__(self, path: Path, fill_nonfinite: float | None = None) -> None:
        path = Path(path)
        array = _map_npy(path)
        if array.ndim != 3:
            raise ApmgsrnError(
                f"{path}: array is {array.ndim}-D with shape {array.shape}; apmgsrn needs a 3-D array (z, y, x)"
            )
        if array.dtype.kind not in "uifb":
            raise ApmgsrnError(f"{path}: array type {array.dtype} is not numeric; save integers or floats")
        super().__init__(path, None, array.shape, array.dtype, fill_nonfinite)
        self._handle, self._handle_pid = array, os.getpid()

    def _open_handle(self) -> Any:
        return _map_npy(self.path)
