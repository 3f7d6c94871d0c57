"""Volumes backed by a NumPy memory map (raw and ``.npy`` files): regions are paged in lazily."""

from __future__ import annotations

from typing import Any

import numpy as np

from apmgsrn.data.volume import Volume


class MemoryMappedVolume(Volume):
    """Base of raw and ``.npy`` volumes: `_open_handle` returns a read-only ``np.memmap``.

    Only the pages of the requested region are read from disk, so bricks of volumes larger
    than memory work; the map is reopened after ``fork`` or unpickling instead of being copied.
    """

    def _read_stored(self, z: slice, y: slice, x: slice) -> np.ndarray:
        # Copy into a fresh float32 array: the result must not keep the map (or file) alive.
        stored = self._get_handle()[z, y, x]
        self._check_float32_range(stored)
        return np.array(stored, dtype=np.float32, order="C")

    def _close_handle(self, handle: Any) -> None:
        # np.memmap has no close(); the mapping is released when the last reference goes.
        return None

    def _may_hold_nonfinite(self) -> bool:
        return self.dtype.kind == "f"
