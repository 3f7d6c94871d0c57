"""glibc's allocator told to keep the memory PyTorch frees, so that the next step's tensors land in pages already
mapped.

PyTorch's CPU tensors come from ``malloc`` and go back with ``free``; nothing caches them. glibc serves a
block above its *mmap threshold* from a fresh mapping, unmapped again on ``free``, and hands the top of its heap
back to the kernel once more than its *trim threshold* lies free there. Its thresholds start low (128 KB) and
follow the blocks freed, which the mixed sizes of a training step or a decoding pass defeat: the activations of
a step (``[16384, 64]`` float32 hidden layers: 4 MB) keep landing in pages the kernel must find and zero on first
touch. Measured with glibc's own settings (``benchmarks/bench_allocator.py``, docs/benchmarks_allocator.md): a
training iteration 1.26-1.36x slower (5,000-6,500 page faults against 0-21); the fused kernels allocate nothing
of size, so they do not care.

:func:`keep_freed_memory` fixes both thresholds (``RUNTIME.mmap_threshold`` and ``RUNTIME.trim_threshold``,
:mod:`apmgsrn.recipes`): blocks up to the first come from the heap, and up to the second of free memory at its top
is kept for the next step. Larger blocks (a whole volume, a
decoded grid) are mapped and unmapped as before, so a process holds at most about that much more than it uses.
It runs on ``import apmgsrn``, so the series' quantisation-aware fine-tune of ``pack``, a user's own training
loop, and evaluation, decoding and rendering of models without a fused kernel get it too; only where the C
library is glibc, and not where the user set
either threshold (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, ``GLIBC_TUNABLES``): theirs stands.
Importing this module imports nothing but the standard library and :mod:`apmgsrn.recipes`.
"""

from __future__ import annotations

import ctypes
import os

from apmgsrn.recipes import RUNTIME

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: Settings by which a user chooses the allocator's thresholds; when any is set, theirs stands.
ALLOCATOR_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds (module docstring), once per process.

    Returns:
        True when they are set (now or before), False where the C library is not glibc or the user chose.
    """
    global _applied
    if _applied is None:
        _applied = False
        if _is_glibc() and not any(name in os.environ for name in ALLOCATOR_VARIABLES):
            try:
                mallopt = ctypes.CDLL(None).mallopt
            except (OSError, AttributeError):
                return False
            mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
            _applied = (bool(mallopt(M_MMAP_THRESHOLD, RUNTIME.mmap_threshold))
                        and bool(mallopt(M_TRIM_THRESHOLD, RUNTIME.trim_threshold)))
    return _applied


def _is_glibc() -> bool:
    """Whether this process runs on glibc (asked of the C library itself: no file is read)."""
    try:
        return (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")
    except (AttributeError, ValueError, OSError):
        return False
