"""CPU kernel of an error guide's draw search: for ascending queries, the first position of a running sum
whose value is not below each, in one merge walk.

Why: a guide draws its voxel points by systematic sampling (:class:`apmgsrn.training.points.ErrorGuide`): a few
thousand ascending positions searched in the running sum of 2^18 voxels' errors (2 MB of float64) at every
iteration of a series' step fine-tunes. Between two fused training steps that array has left the caches, and a
binary search per position paid a miss per probe: NumPy's took 0.37 ms for 6,144 draws, this walk 0.16 (one
thread, caches flushed between calls). It reads the running sum once, in order, and compares exactly as
``torch.searchsorted`` does (``values[i] < query``), so the indices are the same, which
``tests/test_voxel_points.py`` checks. Built and cached like :mod:`apmgsrn.ops.trilinear_cpu`.
"""

from __future__ import annotations

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary

C_SOURCE = r"""
#include <stdint.h>
typedef int64_t i64;

/* out[j] = the first i < n with values[i] >= queries[j], else n; queries ascending, values ascending. */
void ascending_search(const double *values, i64 n, const double *queries, i64 m, i64 *out) {
    i64 i = 0;
    for (i64 j = 0; j < m; ++j) {
        const double q = queries[j];
        while (i < n && values[i] < q) ++i;
        out[j] = i;
    }
}
"""


def _declare(lib) -> None:
    import ctypes

    p, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.ascending_search.argtypes = [p, i64, p, i64, p]
    lib.ascending_search.restype = None


LIBRARY = CompiledLibrary("sorted_search_cpu", C_SOURCE, _declare)


def ascending_search_cpu(values: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """``torch.searchsorted(values, queries)`` for ascending ``queries``, in one merge walk.

    Args:
        values: ``[N]`` float64 CPU, ascending.
        queries: ``[M]`` float64 CPU, ascending (a query out of order gets a wrong index: the walk never goes
            back).

    Returns:
        ``[M]`` int64 positions in ``[0, N]``.
    """
    lib = LIBRARY.load_or_raise()
    values = values.contiguous()
    queries = queries.contiguous()
    out = torch.empty(queries.shape[0], dtype=torch.int64)
    lib.ascending_search(values.data_ptr(), values.shape[0], queries.data_ptr(), queries.shape[0], out.data_ptr())
    return out
