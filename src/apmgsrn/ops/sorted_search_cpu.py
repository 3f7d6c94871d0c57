"""CPU kernels of an error guide's draws: for ascending queries, the first position of a running sum whose
value is not below each, in one merge walk; and a whole guided draw (search, voxel, position, value) in one pass.

Why: a guide draws its voxel points by systematic sampling (:class:`apmgsrn.training.points.ErrorGuide`): a few
thousand ascending positions searched in the running sum of 2^18 voxels' errors (2 MB of float64) at every
iteration of a series' step fine-tunes. Between two fused training steps that array has left the caches, and a
binary search per position paid a miss per probe: NumPy's took 0.37 ms for 6,144 draws, this walk 0.16 (one
thread, caches flushed between calls). It reads the running sum once, in order, and compares exactly as
``torch.searchsorted`` does (``values[i] < query``), so the indices are the same, which
``tests/test_voxel_points.py`` checks. Built and cached like :mod:`apmgsrn.ops.trilinear_cpu`.

:func:`guided_voxels_cpu` is the rest of a guided draw (:meth:`apmgsrn.training.points.ErrorGuide.draw` and
:func:`apmgsrn.training.points.voxel_points`, and the gather of the voxels' values) in one pass over the draws,
instead of a dozen tensor operations each writing a ``[count]`` array (16,384 draws of a 187^3 volume's guide,
its random numbers included: 0.92 against 1.42 ms). Large draws are split between torch's threads
(:func:`draw_threads`): 16,384 draws of that guide took 0.70 ms on one thread and 0.38 ms on two, random numbers
excluded.
It takes the same random numbers from the caller and rounds every step as PyTorch does (float64 positions;
float32 coordinates ``i * (2 / (n - 1)) - 1``, multiplied and subtracted without a fused multiply-add), so it
gives the same indices, points and values to the bit; the tests compare them.
"""

from __future__ import annotations

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.recipes import RUNTIME

C_SOURCE = r"""
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif
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

/* Coordinate of voxel i of an axis of n: i * step - 1 (step = 2 / (n - 1)), rounded as two float32 operations;
   the middle, 0, for an axis of one voxel. */
__attribute__((optimize("fp-contract=off")))
static inline float axis_coordinate(i64 i, i64 n, float step) { return n == 1 ? 0.0f : (float)i * step - 1.0f; }

/* first i < n with values[i] >= q (else n): the walk's answer for q, by bisection. */
static i64 lower_bound(const double *values, i64 n, double q) {
    i64 lo = 0, hi = n;
    while (lo < hi) { const i64 mid = lo + (hi - lo) / 2; if (values[mid] < q) lo = mid + 1; else hi = mid; }
    return lo;
}

/* count guided draws: draw j's position (j + 1 - offset) / count searched in the running sum cumulative[blocks],
   its block clamped to the last, the voxel at random offsets[0..2][j] (z, y, x; in [0, block)) inside the block
   (clamped to the volume [d][h][w]); out: flat index, point (x, y, z) in [-1, 1] and the voxel's value.
   The draws are cut into one run per thread; each run finds its first block by bisection and walks from there,
   which gives every draw the block the single walk gives it. */
__attribute__((optimize("fp-contract=off")))
void guided_voxels(const double *cumulative, i64 blocks, double offset, i64 count, i64 block, i64 d, i64 h, i64 w,
                   const i64 *offsets, const float *volume, i64 *index, float *points, float *values, int nthreads) {
    const i64 bh = (h + block - 1) / block, bw = (w + block - 1) / block;
    const float sx = w > 1 ? (float)(2.0 / (double)(w - 1)) : 0.0f;
    const float sy = h > 1 ? (float)(2.0 / (double)(h - 1)) : 0.0f;
    const float sz = d > 1 ? (float)(2.0 / (double)(d - 1)) : 0.0f;
    #pragma omp parallel num_threads(nthreads)
    {
        int t = 0, nt = 1;
#ifdef _OPENMP
        t = omp_get_thread_num(); nt = omp_get_num_threads();
#endif
        const i64 first = count * t / nt, last = count * (t + 1) / nt;
        i64 i = first < last ? lower_bound(cumulative, blocks, ((double)(first + 1) - offset) / (double)count) : 0;
        for (i64 j = first; j < last; ++j) {
            const double q = ((double)(j + 1) - offset) / (double)count;
            while (i < blocks && cumulative[i] < q) ++i;
            const i64 b = i < blocks - 1 ? i : blocks - 1;
            i64 z = b / (bh * bw), y = b / bw % bh, x = b % bw;
            if (block > 1) {
                z = z * block + offsets[j]; y = y * block + offsets[count + j]; x = x * block + offsets[2 * count + j];
                z = z < d - 1 ? z : d - 1; y = y < h - 1 ? y : h - 1; x = x < w - 1 ? x : w - 1;
            }
            const i64 flat = (z * h + y) * w + x;
            index[j] = flat;
            points[3 * j] = axis_coordinate(x, w, sx);
            points[3 * j + 1] = axis_coordinate(y, h, sy);
            points[3 * j + 2] = axis_coordinate(z, d, sz);
            values[j] = volume[flat];
        }
    }
}
"""


def _declare(lib) -> None:
    import ctypes

    p, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.ascending_search.argtypes = [p, i64, p, i64, p]
    lib.ascending_search.restype = None
    lib.guided_voxels.argtypes = [p, i64, ctypes.c_double, i64, i64, i64, i64, i64, p, p, p, p, p, ctypes.c_int]
    lib.guided_voxels.restype = None


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


def draw_threads(count: int) -> int:
    """Threads that share ``count`` guided draws: torch's, at most one per ``RUNTIME.draws_per_thread`` draws."""
    return max(1, min(torch.get_num_threads(), count // RUNTIME.draws_per_thread))


def guided_voxels_cpu(cumulative: torch.Tensor, offset: float, count: int, block: int, volume: torch.Tensor,
                      offsets: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` draws of an error guide, whole: as :meth:`~apmgsrn.training.points.ErrorGuide.draw` with the
    random ``offset`` and (blocks of more than one voxel) the random in-block ``offsets``, then the voxels'
    positions and values.

    Args:
        cumulative: ``[P]`` float64 CPU, the blocks' running sum of errors, ascending, ending at 1.
        offset: the draw's random offset in ``[0, 1)``.
        count: draws.
        block: voxels per block edge.
        volume: ``[D, H, W]`` float32 CPU.
        offsets: ``[3, count]`` int64 in ``[0, block)`` (z, y, x), or None when ``block`` is 1.

    Returns:
        ``([count] int64 flat voxel indices, [count, 3] float32 points (x, y, z), [count] float32 values)``.
    """
    lib = LIBRARY.load_or_raise()
    cumulative = cumulative.contiguous()
    volume = volume.contiguous()
    d, h, w = volume.shape
    index = torch.empty(count, dtype=torch.int64)
    points = torch.empty(count, 3, dtype=torch.float32)
    values = torch.empty(count, dtype=torch.float32)
    if block > 1:
        offsets = offsets.to(torch.int64).contiguous()
    lib.guided_voxels(cumulative.data_ptr(), cumulative.shape[0], float(offset), count, block, d, h, w,
                      None if block == 1 else offsets.data_ptr(), volume.data_ptr(), index.data_ptr(),
                      points.data_ptr(), values.data_ptr(), draw_threads(count))
    return index, points, values
