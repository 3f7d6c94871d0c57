"""CPU kernel of the ground-truth sampler: trilinear, corner-aligned, border-clamped, bit for bit ATen's.

Why: ``F.grid_sample`` on a 3-D volume is a scalar loop in ATen, parallel over the batch only, so the
trainer's one batch of 32,768 points ran on one thread however many there were, about 11 ms of a
training step on the 2-core development machine. This kernel splits the points over threads and keeps
several points' cache misses in flight (the volume is far larger than the caches).

Exactness: the arithmetic is ATen's ``grid_sampler_3d_cpu_impl`` for bilinear interpolation, border
padding and ``align_corners=True``, operation for operation: the same unnormalisation
``((x + 1) / 2) * (size - 1)``, the same clamp (in float, before the integer conversion: any finite or
infinite coordinate lands in the volume, NaN on the last voxel, as ``std::min``/``std::max`` do), the same
corner weights multiplied in the same order, the same sum in the same order, with floating-point
contraction off (no fused multiply-adds). So training on it gives the same numbers as before, which
:mod:`tests.test_ops_trilinear` checks bit for bit. A point with a NaN coordinate samples NaN, as
:func:`apmgsrn.ops.trilinear.sample_volume_reference` does (the contract of :mod:`apmgsrn.ops`). Built and cached like
:mod:`apmgsrn.ops.multigrid_cpu` (one C file, no PyTorch headers, called through :mod:`ctypes`).
"""

from __future__ import annotations

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary

C_SOURCE = r"""
#include <math.h>
#include <stdint.h>
typedef int64_t i64;

/* No contraction: ATen computes every product and sum separately, and so must this file. */
#pragma GCC optimize ("fp-contract=off")

#define TILE 64

/* std::min(limit, std::max(v, 0)): NaN passes max and loses to min, so it lands on the limit. */
static inline float clip(float v, float limit) {
    const float low = v < 0.0f ? 0.0f : v;
    return low < limit ? low : limit;
}

/* out[i] = trilinear sample of volume [d, h, w] (C order) at points[i] = (x, y, z) in [-1, 1]^3. */
void trilinear_border(const float *volume, i64 d, i64 h, i64 w, const float *points, i64 n, float *out,
                      int nthreads) {
    const float lx = (float)(w - 1), ly = (float)(h - 1), lz = (float)(d - 1);
    const i64 ntiles = (n + TILE - 1) / TILE;
    #pragma omp parallel for schedule(dynamic, 16) num_threads(nthreads)
    for (i64 t = 0; t < ntiles; ++t) {
        const i64 i0 = t * TILE, i1 = i0 + TILE < n ? i0 + TILE : n;
        i64 base[TILE], dx[TILE], dy[TILE], dz[TILE];
        float ax[TILE], ay[TILE], az[TILE], bx[TILE], by[TILE], bz[TILE];
        /* First the addresses of the whole tile, so its cache misses overlap in the loads below. */
        for (i64 i = i0; i < i1; ++i) {
            const int k = (int)(i - i0);
            const float ix = clip(((points[3 * i] + 1.0f) / 2.0f) * lx, lx);
            const float iy = clip(((points[3 * i + 1] + 1.0f) / 2.0f) * ly, ly);
            const float iz = clip(((points[3 * i + 2] + 1.0f) / 2.0f) * lz, lz);
            const i64 x0 = (i64)floorf(ix), y0 = (i64)floorf(iy), z0 = (i64)floorf(iz);
            /* weights toward the upper (a) and lower (b) corner, as ATen forms them */
            ax[k] = ix - (float)x0; bx[k] = (float)(x0 + 1) - ix;
            ay[k] = iy - (float)y0; by[k] = (float)(y0 + 1) - iy;
            az[k] = iz - (float)z0; bz[k] = (float)(z0 + 1) - iz;
            /* a step to an upper corner outside the volume is 0: its term is skipped below */
            dx[k] = x0 + 1 < w ? 1 : 0;
            dy[k] = y0 + 1 < h ? w : 0;
            dz[k] = z0 + 1 < d ? h * w : 0;
            base[k] = (z0 * h + y0) * w + x0;
            __builtin_prefetch(volume + base[k]);
            __builtin_prefetch(volume + base[k] + dy[k]);
            __builtin_prefetch(volume + base[k] + dz[k]);
            __builtin_prefetch(volume + base[k] + dy[k] + dz[k]);
        }
        for (i64 i = i0; i < i1; ++i) {
            const int k = (int)(i - i0);
            const float *v = volume + base[k];
            const i64 sx = dx[k], sy = dy[k], sz = dz[k];
            const int ux = sx != 0, uy = sy != 0, uz = sz != 0;
            /* ATen's corner order and products: tnw tne tsw tse bnw bne bsw bse */
            float acc = 0.0f;
            acc += v[0] * (bx[k] * by[k] * bz[k]);
            if (ux) acc += v[sx] * (ax[k] * by[k] * bz[k]);
            if (uy) acc += v[sy] * (bx[k] * ay[k] * bz[k]);
            if (ux && uy) acc += v[sx + sy] * (ax[k] * ay[k] * bz[k]);
            if (uz) acc += v[sz] * (bx[k] * by[k] * az[k]);
            if (ux && uz) acc += v[sx + sz] * (ax[k] * by[k] * az[k]);
            if (uy && uz) acc += v[sy + sz] * (bx[k] * ay[k] * az[k]);
            if (ux && uy && uz) acc += v[sx + sy + sz] * (ax[k] * ay[k] * az[k]);
            const float *p = points + 3 * i;
            out[i] = p[0] != p[0] || p[1] != p[1] || p[2] != p[2] ? NAN : acc;  /* a NaN point samples NaN */
        }
    }
}
"""


def _declare(lib) -> None:
    import ctypes

    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.trilinear_border.argtypes = [p, i64, i64, i64, p, i64, p, i32]
    lib.trilinear_border.restype = None


LIBRARY = CompiledLibrary("trilinear_cpu", C_SOURCE, _declare)


def sample_volume_cpu(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Trilinear samples of a float32 CPU volume, exactly as :func:`apmgsrn.ops.trilinear.sample_volume`.

    Args:
        volume: ``[D, H, W]`` float32, C-contiguous.
        points: ``[N, 3]`` float32 ``(x, y, z)``, C-contiguous.

    Returns:
        ``[N]`` float32.
    """
    lib = LIBRARY.load_or_raise()
    d, h, w = volume.shape
    out = torch.empty(points.shape[0], dtype=torch.float32)
    lib.trilinear_border(volume.data_ptr(), d, h, w, points.data_ptr(), points.shape[0], out.data_ptr(),
                         torch.get_num_threads())
    return out
