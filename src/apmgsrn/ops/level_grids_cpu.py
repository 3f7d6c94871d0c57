"""CPU backend of the multi-level grid encoding: one fused C/OpenMP kernel, built once with the system compiler.

Same semantics as :func:`apmgsrn.ops.level_grids.level_grid_features_reference` (zero-padded trilinear
look-ups, dense or hashed levels, level-major concatenation), with gradients for the table only: the
maps and points are constants here (the adaptive grids' maps learn from the density loss, which does not
sample the grids).

Work per point and level: 12 multiply-adds for the map, the 8 corners' rows (dense index or 32-bit hash)
and weights, then ``F`` gathers of 8 values. Points are processed in tiles of 128 so that every loop runs
over the tile's points and vectorises (AVX2 gathers with ``-march=native``). The backward scatters with
trilinear weights into the table; each extra thread scatters into a private copy of the gradient (the
tables are small: 0.3 MB at the small preset), summed at the end, so there are no atomics.

Every input is defined (the contract of :mod:`apmgsrn.ops`): corner indices are clamped in float, NaN going to
0, before the integer conversion, and a non-finite index coordinate weighs 0; a point with a NaN coordinate
gets NaN features and scatters nothing.

Built and cached like :mod:`apmgsrn.ops.multigrid_cpu` (same compiler choice and flags, through
:mod:`apmgsrn.ops.kernel_cache`);
when it cannot be built the dispatcher falls back to the reference.
"""

from __future__ import annotations

import ctypes
import functools

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.ops.level_layout import LevelLayout

C_SOURCE = r"""
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#else  /* built without OpenMP: one thread, the pragmas are ignored */
static int omp_get_thread_num(void) { return 0; }
static int omp_get_num_threads(void) { return 1; }
#endif

typedef int64_t i64;
typedef uint32_t u32;

#define TILE 128

/* One level's 8 corners of every tile point. */
typedef struct {
    int off[8][TILE];                     /* corner rows times F (float offsets in the level) */
    float wt[8][TILE];                    /* corner weights; 0 for corners outside the lattice */
} Corners;

typedef struct {
    float px[TILE], py[TILE], pz[TILE];   /* the tile's points */
    Corners c;                            /* the level at hand's corners, unless the caller keeps every level's */
    float res[TILE];                      /* one gathered feature */
    int nans;                             /* how many of the tile's points have a NaN coordinate */
} Scratch;

/* Level description: index-space map (A' row-major, then t'), vertices per axis, table rows, storage. */
typedef struct { const float *map; int rx, ry, rz, hashed, features; u32 rows; } Level;

/* Whether a point (x, y, z) has a NaN coordinate: its features are NaN and it adds to no gradient. */
static inline int nan_point(const float *p) { return p[0] != p[0] || p[1] != p[1] || p[2] != p[2]; }

static inline void load_tile(Scratch *s, const float *points, i64 i0, int nt) {
    const float *p = points + 3 * i0;
    int nans = 0;
    for (int i = 0; i < nt; ++i) {
        s->px[i] = p[3 * i]; s->py[i] = p[3 * i + 1]; s->pz[i] = p[3 * i + 2];
        nans += nan_point(p + 3 * i);
    }
    s->nans = nans;
}

static inline int tile_nan(const Scratch *s, int k) { return s->px[k] != s->px[k] || s->py[k] != s->py[k] || s->pz[k] != s->pz[k]; }

/* v clamped to [0, hi] in float, so that the integer conversion after it is defined for every input:
   NaN (from a NaN point, or Inf * 0 and Inf - Inf in the map of an infinite one) goes to 0. */
static inline float clampf(float v, float hi) { return v >= 0.0f ? (v < hi ? v : hi) : 0.0f; }

/* The 8 corners of every tile point in one level into c: rows (times F) and trilinear weights. Corners outside
   the lattice get weight 0 and a clamped, valid row; so does every corner of a non-finite index coordinate
   (its comparisons are false), so no input reads outside the table. Branch-free (ternaries) so that gcc
   vectorises. */
static inline void corners(const Scratch *s, Level lv, int nt, Corners *c) {
    const float *a = lv.map;
    const float a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], a4 = a[4], a5 = a[5];
    const float a6 = a[6], a7 = a[7], a8 = a[8], a9 = a[9], a10 = a[10], a11 = a[11];
    const float rx = (float)lv.rx, ry = (float)lv.ry, rz = (float)lv.rz;
    const u32 mask = lv.rows - 1u, sy = (u32)lv.rx, sz = (u32)lv.rx * (u32)lv.ry;
    const int hashed = lv.hashed, f = lv.features;
    const float *restrict px = s->px, *restrict py = s->py, *restrict pz = s->pz;
    int *restrict o0 = c->off[0], *restrict o1 = c->off[1], *restrict o2 = c->off[2], *restrict o3 = c->off[3];
    int *restrict o4 = c->off[4], *restrict o5 = c->off[5], *restrict o6 = c->off[6], *restrict o7 = c->off[7];
    float *restrict w0 = c->wt[0], *restrict w1 = c->wt[1], *restrict w2 = c->wt[2], *restrict w3 = c->wt[3];
    float *restrict w4 = c->wt[4], *restrict w5 = c->wt[5], *restrict w6 = c->wt[6], *restrict w7 = c->wt[7];
    #pragma omp simd
    for (int k = 0; k < nt; ++k) {
        const float fx = a0 * px[k] + a1 * py[k] + a2 * pz[k] + a9;
        const float fy = a3 * px[k] + a4 * py[k] + a5 * pz[k] + a10;
        const float fz = a6 * px[k] + a7 * py[k] + a8 * pz[k] + a11;
        const float lx = floorf(fx), ly = floorf(fy), lz = floorf(fz);
        const float tx = fx - lx, ty = fy - ly, tz = fz - lz;
        const float wx0 = (lx >= 0.0f && lx < rx) ? 1.0f - tx : 0.0f;
        const float wx1 = (lx >= -1.0f && lx + 1.0f < rx) ? tx : 0.0f;
        const float wy0 = (ly >= 0.0f && ly < ry) ? 1.0f - ty : 0.0f;
        const float wy1 = (ly >= -1.0f && ly + 1.0f < ry) ? ty : 0.0f;
        const float wz0 = (lz >= 0.0f && lz < rz) ? 1.0f - tz : 0.0f;
        const float wz1 = (lz >= -1.0f && lz + 1.0f < rz) ? tz : 0.0f;
        u32 x0 = (u32)clampf(lx, rx - 1.0f), x1 = (u32)clampf(lx + 1.0f, rx - 1.0f);
        u32 y0 = (u32)clampf(ly, ry - 1.0f), y1 = (u32)clampf(ly + 1.0f, ry - 1.0f);
        u32 z0 = (u32)clampf(lz, rz - 1.0f), z1 = (u32)clampf(lz + 1.0f, rz - 1.0f);
        u32 r000, r100, r010, r110, r001, r101, r011, r111;
        if (hashed) {  /* Instant-NGP: x * 1 xor y * 2654435761 xor z * 805459861, mod 2^T (32-bit) */
            y0 *= 2654435761u; y1 *= 2654435761u; z0 *= 805459861u; z1 *= 805459861u;
            r000 = (x0 ^ y0 ^ z0) & mask; r100 = (x1 ^ y0 ^ z0) & mask;
            r010 = (x0 ^ y1 ^ z0) & mask; r110 = (x1 ^ y1 ^ z0) & mask;
            r001 = (x0 ^ y0 ^ z1) & mask; r101 = (x1 ^ y0 ^ z1) & mask;
            r011 = (x0 ^ y1 ^ z1) & mask; r111 = (x1 ^ y1 ^ z1) & mask;
        } else {       /* dense: x + R_x (y + R_y z) */
            y0 *= sy; y1 *= sy; z0 *= sz; z1 *= sz;
            r000 = x0 + y0 + z0; r100 = x1 + y0 + z0; r010 = x0 + y1 + z0; r110 = x1 + y1 + z0;
            r001 = x0 + y0 + z1; r101 = x1 + y0 + z1; r011 = x0 + y1 + z1; r111 = x1 + y1 + z1;
        }
        o0[k] = (int)r000 * f; o1[k] = (int)r100 * f; o2[k] = (int)r010 * f; o3[k] = (int)r110 * f;
        o4[k] = (int)r001 * f; o5[k] = (int)r101 * f; o6[k] = (int)r011 * f; o7[k] = (int)r111 * f;
        const float yz00 = wy0 * wz0, yz10 = wy1 * wz0, yz01 = wy0 * wz1, yz11 = wy1 * wz1;
        w0[k] = wx0 * yz00; w1[k] = wx1 * yz00; w2[k] = wx0 * yz10; w3[k] = wx1 * yz10;
        w4[k] = wx0 * yz01; w5[k] = wx1 * yz01; w6[k] = wx0 * yz11; w7[k] = wx1 * yz11;
    }
}

/* res[k] = sum_j b[off_j[k]] w_j[k] over the corners c (vectorised gathers). */
static inline void gather(const float *restrict b, Scratch *s, const Corners *c, int nt) {
    const int *restrict o0 = c->off[0], *restrict o1 = c->off[1], *restrict o2 = c->off[2], *restrict o3 = c->off[3];
    const int *restrict o4 = c->off[4], *restrict o5 = c->off[5], *restrict o6 = c->off[6], *restrict o7 = c->off[7];
    const float *restrict w0 = c->wt[0], *restrict w1 = c->wt[1], *restrict w2 = c->wt[2], *restrict w3 = c->wt[3];
    const float *restrict w4 = c->wt[4], *restrict w5 = c->wt[5], *restrict w6 = c->wt[6], *restrict w7 = c->wt[7];
    float *restrict res = s->res;
    #pragma omp simd
    for (int k = 0; k < nt; ++k) {
        float acc = b[o0[k]] * w0[k];
        acc += b[o1[k]] * w1[k]; acc += b[o2[k]] * w2[k]; acc += b[o3[k]] * w3[k];
        acc += b[o4[k]] * w4[k]; acc += b[o5[k]] * w5[k]; acc += b[o6[k]] * w6[k]; acc += b[o7[k]] * w7[k];
        res[k] = acc;
    }
}

static inline Level level_at(i64 l, const float *maps, const int *meta, const i64 *rows) {
    const int *m = meta + 6 * l;
    Level lv = {maps + 12 * l, m[0], m[1], m[2], m[3], m[4], (u32)rows[l]};
    return lv;
}

/* The features of the tile's nt points from i0, every level: point k, column c into out[k * sn + c * sc].
   keep: NULL, or room for every level's corners (levels of them), kept there for scatter_tile. */
static void encode_tile(Scratch *s, const float *points, i64 i0, int nt, i64 levels, const float *maps,
                        const int *meta, const i64 *rows, const i64 *offsets, const float *table, float *out,
                        i64 sn, i64 sc, Corners *keep) {
    load_tile(s, points, i0, nt);
    for (i64 l = 0; l < levels; ++l) {
        const Level lv = level_at(l, maps, meta, rows);
        Corners *c = keep != NULL ? keep + l : &s->c;
        corners(s, lv, nt, c);
        for (int f = 0; f < lv.features; ++f) {
            gather(table + offsets[l] + f, s, c, nt);
            float *oc = out + (meta[6 * l + 5] + f) * sc;
            for (int k = 0; k < nt; ++k) oc[(i64)k * sn] = s->res[k];
        }
    }
    if (s->nans == 0 || levels == 0) return;
    const i64 columns = meta[6 * (levels - 1) + 5] + meta[6 * (levels - 1) + 4];
    for (int k = 0; k < nt; ++k)
        if (tile_nan(s, k))
            for (i64 col = 0; col < columns; ++col) out[(i64)k * sn + col * sc] = NAN;
}

/* dst += the trilinear scatter of the gradients of the features of the tile's nt points (loaded; a point with a
   NaN coordinate adds nothing, whatever its gradient): point k,
   column c at g[k * sn + c * sc]. A level of two features (the hybrid's) adds both at each corner in one pass
   over the corners: every table entry still gets its additions in the same order, so the sums are the same to
   the bit, with half the corner loads (a fused training step 5-6 % faster). kept: NULL, or every level's corners
   as encode_tile kept them for these points (else computed again). */
static void scatter_tile(Scratch *s, int nt, i64 levels, const float *maps, const int *meta, const i64 *rows,
                         const i64 *offsets, const float *g, i64 sn, i64 sc, float *dst, const Corners *kept) {
    for (i64 l = 0; l < levels; ++l) {
        const Level lv = level_at(l, maps, meta, rows);
        const Corners *c = kept != NULL ? kept + l : &s->c;
        if (kept == NULL) corners(s, lv, nt, &s->c);
        float *b = dst + offsets[l];
        const float *g0 = g + meta[6 * l + 5] * sc;
        if (lv.features == 2) {
            const float *g1 = g0 + sc;
            for (int k = 0; k < nt; ++k) {
                if (s->nans && tile_nan(s, k)) continue;
                const float v0 = g0[(i64)k * sn], v1 = g1[(i64)k * sn];
                for (int j = 0; j < 8; ++j) {
                    float *p = b + c->off[j][k];
                    const float w = c->wt[j][k];
                    p[0] += w * v0;
                    p[1] += w * v1;
                }
            }
            continue;
        }
        for (int f = 0; f < lv.features; ++f) {
            const float *gc = g0 + f * sc;
            for (int k = 0; k < nt; ++k) {
                if (s->nans && tile_nan(s, k)) continue;
                const float v = gc[(i64)k * sn];
                for (int j = 0; j < 8; ++j) b[c->off[j][k] + f] += c->wt[j][k] * v;
            }
        }
    }
}

/* out[n, col_l + f] = feature f of level l at point n, for every level; element (n, c) of out lives at
   n * sn + c * sc (the caller allocates it column-major, sn = 1: each feature's values are written in order).
   meta: [L, 6] int (R_x, R_y, R_z, hashed, F, first column); rows: [L] table rows;
   offsets: [L] first float of each level in the table. */
void lg_forward(const float *points, i64 n, i64 levels, const float *maps, const int *meta, const i64 *rows,
                const i64 *offsets, const float *table, float *out, i64 sn, i64 sc, int nthreads) {
    const i64 ntiles = (n + TILE - 1) / TILE;
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        /* dynamic: on a shared machine a preempted thread must not hold back a fixed share */
        #pragma omp for schedule(dynamic, 8)
        for (i64 t = 0; t < ntiles; ++t) {
            const i64 i0 = t * TILE;
            const int nt = (int)(n - i0 < TILE ? n - i0 : TILE);
            encode_tile(&s, points, i0, nt, levels, maps, meta, rows, offsets, table, out + i0 * sn, sn, sc, NULL);
        }
    }
}

/* grad_table (zeroed by the caller) += trilinear scatter of grad_out [N, columns], element (n, c) at
   n * sn + c * sc. buffers: (nthreads - 1) zeroed copies of the gradient (size floats each), or NULL with
   one thread. */
void lg_backward(const float *points, i64 n, i64 levels, const float *maps, const int *meta, const i64 *rows,
                 const i64 *offsets, const float *grad_out, i64 sn, i64 sc, float *grad_table, float *buffers,
                 i64 size, int nthreads) {
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        const int th = omp_get_thread_num(), nth = omp_get_num_threads();
        float *dst = th == 0 ? grad_table : buffers + (size_t)(th - 1) * (size_t)size;
        const i64 lo = n * th / nth, hi = n * (th + 1) / nth;
        for (i64 i0 = lo; i0 < hi; i0 += TILE) {
            const int nt = (int)(hi - i0 < TILE ? hi - i0 : TILE);
            load_tile(&s, points, i0, nt);
            scatter_tile(&s, nt, levels, maps, meta, rows, offsets, grad_out + i0 * sn, sn, sc, dst, NULL);
        }
        #pragma omp barrier
        for (int b = 0; b < nth - 1; ++b) {
            const float *src = buffers + (size_t)b * (size_t)size;
            #pragma omp for schedule(static)
            for (i64 e = 0; e < size; ++e) grad_table[e] += src[e];
        }
    }
}
"""

def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.lg_forward.argtypes = [p, i64, i64, p, p, p, p, p, p, i64, i64, i32]
    lib.lg_backward.argtypes = [p, i64, i64, p, p, p, p, p, i64, i64, p, p, i64, i32]
    lib.lg_forward.restype = lib.lg_backward.restype = None


LIBRARY = CompiledLibrary("level_grids_cpu", C_SOURCE, _declare)


def load_error() -> str | None:
    """Why the kernel could not be built or loaded (``None`` when it has not failed)."""
    return LIBRARY.error


def is_available() -> bool:
    """True when the kernel builds and loads on this machine."""
    return LIBRARY.available()


class KernelLayout:
    """A :class:`LevelLayout` as the kernel reads it: ``meta`` ``[L, 6]`` int32, ``rows`` and ``offsets`` int64.

    Built once per layout (:func:`kernel_layout`), not per call.
    """

    def __init__(self, layout: LevelLayout):
        self.layout = layout
        meta = [
            [*res, int(hashed), f, col]
            for res, hashed, f, col in zip(layout.resolutions, layout.hashed, layout.features, layout.columns)
        ]
        self.meta = torch.tensor(meta, dtype=torch.int32).contiguous()  # [L, 6]
        self.rows = torch.tensor(layout.sizes, dtype=torch.int64)  # [L]
        self.offsets = torch.tensor(layout.offsets, dtype=torch.int64)  # [L]


@functools.lru_cache(maxsize=64)
def kernel_layout(layout: LevelLayout) -> KernelLayout:
    """The kernel's view of ``layout`` (cached: layouts are frozen and few)."""
    return KernelLayout(layout)


def kernel_inputs(points: torch.Tensor, maps: torch.Tensor,
                  table: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points ``[N, 3]``, maps ``[L, 12]`` (``A'`` row-major, then ``t'``) and table as the level kernels read
    them: detached, float32, contiguous."""
    m = maps.detach().to(torch.float32)
    flat_maps = torch.cat([m[:, :, :3].reshape(-1, 9), m[:, :, 3]], dim=1).contiguous()
    return points.detach().to(torch.float32).contiguous(), flat_maps, table.detach().to(torch.float32).contiguous()


class _LevelGridFunction(torch.autograd.Function):
    """Autograd wrapper: gradients for the table only."""

    @staticmethod
    def forward(ctx, points, maps, table, kernel_layout):  # type: ignore[override]
        lib = LIBRARY.load_or_raise()
        layout = kernel_layout.layout
        pts, flat_maps, tab = kernel_inputs(points, maps, table)
        n = pts.shape[0]
        # Column-major [N, C] (a transposed [C, N]): each feature's values are stored in order, and the
        # decoder's first matrix product reads a transposed operand at no cost. Every element is written.
        out = torch.empty(layout.out_features, n, dtype=torch.float32).t()
        lib.lg_forward(
            pts.data_ptr(), n, layout.levels, flat_maps.data_ptr(), kernel_layout.meta.data_ptr(),
            kernel_layout.rows.data_ptr(), kernel_layout.offsets.data_ptr(), tab.data_ptr(), out.data_ptr(),
            *out.stride(), torch.get_num_threads(),
        )
        ctx.save_for_backward(pts, flat_maps)
        ctx.kernel_layout = kernel_layout
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        if not ctx.needs_input_grad[2]:
            return None, None, None, None
        lib = LIBRARY.load_or_raise()
        pts, flat_maps = ctx.saved_tensors
        kernel_layout = ctx.kernel_layout
        layout = kernel_layout.layout
        go = grad_out.to(torch.float32)  # read through its strides: no copy
        size = layout.table_size
        grad = torch.zeros(size, dtype=torch.float32)
        threads = torch.get_num_threads()
        buffers = torch.zeros(threads - 1, size, dtype=torch.float32) if threads > 1 else None
        lib.lg_backward(
            pts.data_ptr(), pts.shape[0], layout.levels, flat_maps.data_ptr(), kernel_layout.meta.data_ptr(),
            kernel_layout.rows.data_ptr(), kernel_layout.offsets.data_ptr(), go.data_ptr(), *go.stride(),
            grad.data_ptr(), None if buffers is None else buffers.data_ptr(), size, threads,
        )
        return None, None, grad, None


def level_grid_features_cpu(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout
) -> torch.Tensor:
    """Fused CPU level-grid features with gradients for ``table`` only (float32 CPU tensors).

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps (no gradient flows to them).
        table: ``[T]`` flat parameters.
        layout: the levels.

    Returns:
        ``[N, sum_l F_l]``, as :func:`~apmgsrn.ops.level_grids.level_grid_features_reference`.
    """
    return _LevelGridFunction.apply(points, maps, table, kernel_layout(layout))
