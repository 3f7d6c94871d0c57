"""CPU backend of the multi-grid encoder: one fused C/OpenMP kernel, built once with the system compiler.

Why a hand-written kernel: the reference materialises the ``[M, N, 3]`` local coordinates, runs ``M`` zero
padded ``grid_sample`` look-ups and, in backward, ``grid_sampler_3d_backward`` (the bulk of a training
step). The kernel here does transform, bounds test, trilinear weights, gather and concatenation in one
pass per point and grid, in registers, and skips grids that do not cover the point. Its backward scatters
into the feature grids with one thread per grid (no atomics, no per-thread copies of the grids) when there
are at least as many grids as threads, and with per-thread gradient buffers otherwise.

Vectorisation: points are processed in tiles of 128; for each grid the tile is mapped, tested, compacted
to the points that touch the grid, weighed and gathered by loops that gcc vectorises (AVX2 gathers with
``-march=native``), and the gathered values are written into the output rows.

Build: plain C (no PyTorch headers, so it compiles in one to two seconds), called through :mod:`ctypes`
(which releases the GIL), linked with ``-fopenmp``. PyTorch ships ``libgomp.so.1`` under the same soname
and loads it first, so the kernel runs on PyTorch's own OpenMP thread pool and honours
``torch.set_num_threads``. The shared object is cached by :mod:`apmgsrn.ops.kernel_cache` under
``$APMGSRN_CACHE/kernels`` (default ``~/.cache/apmgsrn/kernels``; only a folder this user owns and nobody
else can write is trusted, else it is built into a private temporary folder) keyed by the hash of the
source, the flags, the compiler and the CPU, so it compiles once per machine. ``$CC`` picks the compiler
(default gcc, then cc). If it cannot be built (no compiler, no OpenMP is fine: it then runs on one thread),
:func:`load_library` returns ``None`` and the dispatcher falls back to the reference.

Semantics are those of :func:`apmgsrn.ops.multigrid.multigrid_features_reference`: corner-aligned,
zero-padded trilinear sampling (a corner outside the grid contributes zero), grid-major concatenation, at every
input (the contract of :mod:`apmgsrn.ops`): only finite index coordinates inside the grid pass the bounds test
that comes before any integer conversion, and a point with a NaN coordinate gets NaN features and density and
adds to no gradient.
"""

from __future__ import annotations

import ctypes

import torch

from apmgsrn.ops.contract import FAR, finite_stand_in
from apmgsrn.ops.kernel_cache import CompiledLibrary

#: AVX2 compaction table, shared by every kernel that lists the non-zero lanes of a mask (here, and the fused
#: decoders of :mod:`apmgsrn.ops.field_cpu`).
LANE_LUT_SOURCE = r"""
#if defined(__AVX2__)
#include <immintrin.h>
/* lane_lut[mask]: positions of the set bits of an 8-bit mask, in order (zero-filled), for compaction. */
static unsigned char lane_lut[256][8];
__attribute__((constructor)) static void init_lane_lut(void) {
    for (int mask = 0; mask < 256; ++mask) {
        int n = 0;
        for (int b = 0; b < 8; ++b) if (mask >> b & 1) lane_lut[mask][n++] = (unsigned char)b;
        for (; n < 8; ++n) lane_lut[mask][n] = 0;
    }
}
#endif
"""
# The C source. Coordinates are folded into index space once per grid: ``f = A' p + t'`` with
# ``A' = A (size - 1) / 2`` and ``t' = (t + 1) (size - 1) / 2`` (corner-aligned unnormalisation), so a
# point costs 9 multiply-adds per grid before the bounds test.
C_SOURCE = f"#define FAR {FAR!r}f\n" + r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#else  /* built without OpenMP (a compiler that lacks it): one thread, the pragmas are ignored */
static int omp_get_thread_num(void) { return 0; }
static int omp_get_num_threads(void) { return 1; }
#endif

typedef int64_t i64;
""" + LANE_LUT_SOURCE + r"""
/* Points are processed in tiles: every loop below runs over the points of one tile for one grid, so
   the compiler vectorises it (8 points per AVX2 instruction), and the tile's scratch stays in L1. */
#define TILE 128

typedef struct {
    float px[TILE], py[TILE], pz[TILE];   /* the tile's points */
    float fx[TILE], fy[TILE], fz[TILE];   /* index-space coordinates in the current grid */
    float cx[TILE], cy[TILE], cz[TILE];   /* the same, compacted to the points that touch the grid */
    int inside[TILE];                     /* 1 where the point touches the grid */
    int idx[TILE];                        /* tile position of each compacted point */
    int off[8][TILE];                     /* corner offsets (elements), compacted */
    float wt[8][TILE];                    /* corner weights, compacted; 0 for corners outside */
    float res[TILE];                      /* gathered feature of one channel, compacted */
    int nans;                             /* how many of the tile's points have a NaN coordinate */
} Scratch;

typedef struct { int d, h, w, sz, sy, sx; } Shape;

/* A coordinate as the references map it (apmgsrn.ops.contract.finite_stand_in): NaN as 0, beyond +-FAR
   (inf included) as +-FAR. */
static inline float stand_in(float v) { return v != v ? 0.0f : (v > FAR ? FAR : (v < -FAR ? -FAR : v)); }

/* Whether a point (x, y, z) has a NaN coordinate: its features are NaN and it adds to no gradient (it touches no
   grid: NaN fails the bounds test of select_and_weigh). */
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

/* Map the tile into one grid (index units), keep the points that touch it, and compute their eight
   corners. Only finite index coordinates strictly inside (-1, size) pass the bounds test (NaN and Inf, from
   non-finite or huge points, compare false), so the integer conversions below are defined and every
   address is inside the grid. Returns how many points touch the grid; s->idx maps compacted slots back to the tile
   (identity when all do). Branch-free forms throughout (ternaries, float masks), since gcc vectorises
   neither && chains nor fminf/fmaxf without fast-math. */
static inline int select_and_weigh(Scratch *s, const float *a, int nt, Shape g) {
    const float fw = (float)g.w, fh = (float)g.h, fd = (float)g.d;
    const float a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], a4 = a[4], a5 = a[5];
    const float a6 = a[6], a7 = a[7], a8 = a[8], a9 = a[9], a10 = a[10], a11 = a[11];
    const float *restrict px = s->px, *restrict py = s->py, *restrict pz = s->pz;
    float *restrict fxs = s->fx, *restrict fys = s->fy, *restrict fzs = s->fz;
    int *restrict inside = s->inside, *restrict idx = s->idx;
    int total = 0;
    #pragma omp simd reduction(+:total)
    for (int i = 0; i < nt; ++i) {
        const float fx = a0 * px[i] + a1 * py[i] + a2 * pz[i] + a9;
        const float fy = a3 * px[i] + a4 * py[i] + a5 * pz[i] + a10;
        const float fz = a6 * px[i] + a7 * py[i] + a8 * pz[i] + a11;
        /* some corner is inside iff floor(f) is in [-1, size - 1] on every axis; NaN compares false */
        const float in = (fx > -1.0f ? 1.0f : 0.0f) * (fx < fw ? 1.0f : 0.0f) * (fy > -1.0f ? 1.0f : 0.0f)
                       * (fy < fh ? 1.0f : 0.0f) * (fz > -1.0f ? 1.0f : 0.0f) * (fz < fd ? 1.0f : 0.0f);
        inside[i] = (int)in;
        total += (int)in;
        fxs[i] = fx; fys[i] = fy; fzs[i] = fz;
    }
    const float *cx = fxs, *cy = fys, *cz = fzs;
    int cnt = nt;
    if (total == 0) return 0;
    if (total < nt) {
        /* skip the points this grid does not cover: branch-free compaction (always write, advance
           only for inside points) */
        float *restrict ox = s->cx, *restrict oy = s->cy, *restrict oz = s->cz;
        cnt = 0;
        int i = 0;
#if defined(__AVX2__)
        /* eight at a time: the inside lanes' positions from a table, one permute per array */
        for (; i + 8 <= nt; i += 8) {
            const __m256i in8 = _mm256_loadu_si256((const __m256i *)(inside + i));
            const int mask = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(in8, _mm256_setzero_si256())));
            const __m256i lanes = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)lane_lut[mask]));
            _mm256_storeu_ps(ox + cnt, _mm256_permutevar8x32_ps(_mm256_loadu_ps(fxs + i), lanes));
            _mm256_storeu_ps(oy + cnt, _mm256_permutevar8x32_ps(_mm256_loadu_ps(fys + i), lanes));
            _mm256_storeu_ps(oz + cnt, _mm256_permutevar8x32_ps(_mm256_loadu_ps(fzs + i), lanes));
            _mm256_storeu_si256((__m256i *)(idx + cnt), _mm256_add_epi32(lanes, _mm256_set1_epi32(i)));
            cnt += __builtin_popcount(mask);
        }
#endif
        for (; i < nt; ++i) {
            idx[cnt] = i; ox[cnt] = fxs[i]; oy[cnt] = fys[i]; oz[cnt] = fzs[i];
            cnt += inside[i];
        }
        cx = ox; cy = oy; cz = oz;
    } else {
        for (int i = 0; i < nt; ++i) idx[i] = i;
    }
    int *restrict o0 = s->off[0], *restrict o1 = s->off[1], *restrict o2 = s->off[2], *restrict o3 = s->off[3];
    int *restrict o4 = s->off[4], *restrict o5 = s->off[5], *restrict o6 = s->off[6], *restrict o7 = s->off[7];
    float *restrict w0 = s->wt[0], *restrict w1 = s->wt[1], *restrict w2 = s->wt[2], *restrict w3 = s->wt[3];
    float *restrict w4 = s->wt[4], *restrict w5 = s->wt[5], *restrict w6 = s->wt[6], *restrict w7 = s->wt[7];
    #pragma omp simd
    for (int k = 0; k < cnt; ++k) {
        const float fx = cx[k], fy = cy[k], fz = cz[k];
        const float flx = floorf(fx), fly = floorf(fy), flz = floorf(fz);
        const float tx = fx - flx, ty = fy - fly, tz = fz - flz;
        /* zero padding: a corner outside the grid gets weight 0 and a clamped, valid address */
        const float wx0 = flx >= 0.0f ? 1.0f - tx : 0.0f, wx1 = flx + 1.0f < fw ? tx : 0.0f;
        const float wy0 = fly >= 0.0f ? 1.0f - ty : 0.0f, wy1 = fly + 1.0f < fh ? ty : 0.0f;
        const float wz0 = flz >= 0.0f ? 1.0f - tz : 0.0f, wz1 = flz + 1.0f < fd ? tz : 0.0f;
        const int ox0 = (int)(flx > 0.0f ? flx : 0.0f) * g.sx;
        const int ox1 = (int)(flx + 1.0f < fw ? flx + 1.0f : fw - 1.0f) * g.sx;
        const int oy0 = (int)(fly > 0.0f ? fly : 0.0f) * g.sy;
        const int oy1 = (int)(fly + 1.0f < fh ? fly + 1.0f : fh - 1.0f) * g.sy;
        const int oz0 = (int)(flz > 0.0f ? flz : 0.0f) * g.sz;
        const int oz1 = (int)(flz + 1.0f < fd ? flz + 1.0f : fd - 1.0f) * g.sz;
        const float wyz00 = wy0 * wz0, wyz10 = wy1 * wz0, wyz01 = wy0 * wz1, wyz11 = wy1 * wz1;
        /* corner order of grid_sample: x fastest, then y, then z */
        w0[k] = wx0 * wyz00; o0[k] = oz0 + oy0 + ox0;
        w1[k] = wx1 * wyz00; o1[k] = oz0 + oy0 + ox1;
        w2[k] = wx0 * wyz10; o2[k] = oz0 + oy1 + ox0;
        w3[k] = wx1 * wyz10; o3[k] = oz0 + oy1 + ox1;
        w4[k] = wx0 * wyz01; o4[k] = oz1 + oy0 + ox0;
        w5[k] = wx1 * wyz01; o5[k] = oz1 + oy0 + ox1;
        w6[k] = wx0 * wyz11; o6[k] = oz1 + oy1 + ox0;
        w7[k] = wx1 * wyz11; o7[k] = oz1 + oy1 + ox1;
    }
    return cnt;
}

/* res[k] = sum_j b[off_j[k]] w_j[k] for the compacted points (vectorised gathers). */
static inline void gather_tile(const float *restrict b, Scratch *s, int cnt, float *restrict res) {
    const int *restrict o0 = s->off[0], *restrict o1 = s->off[1], *restrict o2 = s->off[2], *restrict o3 = s->off[3];
    const int *restrict o4 = s->off[4], *restrict o5 = s->off[5], *restrict o6 = s->off[6], *restrict o7 = s->off[7];
    const float *restrict w0 = s->wt[0], *restrict w1 = s->wt[1], *restrict w2 = s->wt[2], *restrict w3 = s->wt[3];
    const float *restrict w4 = s->wt[4], *restrict w5 = s->wt[5], *restrict w6 = s->wt[6], *restrict w7 = s->wt[7];
    #pragma omp simd
    for (int k = 0; k < cnt; ++k) {
        float acc = b[o0[k]] * w0[k];
        acc += b[o1[k]] * w1[k];
        acc += b[o2[k]] * w2[k];
        acc += b[o3[k]] * w3[k];
        acc += b[o4[k]] * w4[k];
        acc += b[o5[k]] * w5[k];
        acc += b[o6[k]] * w6[k];
        acc += b[o7[k]] * w7[k];
        res[k] = acc;
    }
}

/* The features of the tile's nt points starting at i0 into rows o[k * M * C + g * C + c]. */
static void encode_tile(Scratch *s, const float *points, i64 i0, int nt, const float *aff, i64 m,
                        const float *grids, i64 c, i64 sm, i64 sc, Shape shape, float *o) {
    const i64 mc = m * c;
    load_tile(s, points, i0, nt);
    memset(o, 0, sizeof(float) * (size_t)nt * (size_t)mc);  /* grids missing a point give 0 */
    for (i64 g = 0; g < m; ++g) {
        const int cnt = select_and_weigh(s, aff + 12 * g, nt, shape);
        for (i64 ch = 0; ch < c; ++ch) {
            gather_tile(grids + g * sm + ch * sc, s, cnt, s->res);
            float *oc = o + g * c + ch;
            for (int k = 0; k < cnt; ++k) oc[(i64)s->idx[k] * mc] = s->res[k];
        }
    }
    if (s->nans == 0) return;
    for (int k = 0; k < nt; ++k)
        if (nan_point(points + 3 * (i0 + k)))
            for (i64 e = 0; e < mc; ++e) o[(i64)k * mc + e] = NAN;
}

/* out[n, g*C + c] = zero-padded trilinear sample of grid g, channel c, at A'_g p_n + t'_g.
   aff: [M, 12] index-space maps; grid strides (elements) sm, sc, sz, sy, sx, so channel-first and
   channel-last grids both work. Points are split over threads; every output element is written. */
void mg_forward(const float *points, i64 n, const float *aff, i64 m, const float *grids,
                i64 c, i64 d, i64 h, i64 w, i64 sm, i64 sc, i64 sz, i64 sy, i64 sx,
                float *out, int nthreads) {
    const i64 mc = m * c;
    const i64 ntiles = (n + TILE - 1) / TILE;
    const Shape shape = {(int)d, (int)h, (int)w, (int)sz, (int)sy, (int)sx};
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        /* dynamic: on a shared machine a preempted thread must not hold back a fixed half of the work */
        #pragma omp for schedule(dynamic, 8)
        for (i64 t = 0; t < ntiles; ++t) {
            const i64 i0 = t * TILE;
            const int nt = (int)(n - i0 < TILE ? n - i0 : TILE);
            encode_tile(&s, points, i0, nt, aff, m, grids, c, sm, sc, shape, out + i0 * mc);
        }
    }
}

/* gg (one grid's gradient) += trilinear scatter of grad_out's columns of grid g over points [lo, hi). */
static void scatter_range(const float *points, i64 lo, i64 hi, const float *aff_g, const float *grad_out,
                          i64 mc, i64 g, i64 c, i64 sc, Shape shape, float *gg, Scratch *s) {
    for (i64 i0 = lo; i0 < hi; i0 += TILE) {
        const int nt = (int)(hi - i0 < TILE ? hi - i0 : TILE);
        load_tile(s, points, i0, nt);
        const int cnt = select_and_weigh(s, aff_g, nt, shape);
        for (i64 ch = 0; ch < c; ++ch) {
            float *b = gg + ch * sc;
            const float *go = grad_out + i0 * mc + g * c + ch;
            for (int k = 0; k < cnt; ++k) {
                const float v = go[(i64)s->idx[k] * mc];
                for (int j = 0; j < 8; ++j) b[s->off[j][k]] += s->wt[j][k] * v;
            }
        }
    }
}

/* grad_grids (zeroed by the caller, strides sm..sx) += scatter of grad_out [N, M*C].
   buffers: NULL when m >= nthreads, else (nthreads - 1) zeroed dense copies of the gradient. */
void mg_backward(const float *points, i64 n, const float *aff, i64 m, const float *grad_out,
                 i64 c, i64 d, i64 h, i64 w, i64 sm, i64 sc, i64 sz, i64 sy, i64 sx,
                 float *grad_grids, float *buffers, int nthreads) {
    const i64 mc = m * c;
    const Shape shape = {(int)d, (int)h, (int)w, (int)sz, (int)sy, (int)sx};
    if (buffers == NULL || nthreads <= 1) {
        /* Each grid belongs to one thread: no races, no atomics, no copies. Dynamic, since grids
           cover different numbers of points once they have moved. */
        #pragma omp parallel num_threads(nthreads)
        {
            Scratch s;
            #pragma omp for schedule(dynamic, 1)
            for (i64 g = 0; g < m; ++g)
                scatter_range(points, 0, n, aff + 12 * g, grad_out, mc, g, c, sc, shape, grad_grids + g * sm, &s);
        }
        return;
    }
    /* Fewer grids than threads: split the points, one private gradient per extra thread, then sum. */
    const i64 total = m * sm;
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        const int t = omp_get_thread_num(), nt = omp_get_num_threads();
        const i64 lo = n * t / nt, hi = n * (t + 1) / nt;
        float *dst = t == 0 ? grad_grids : buffers + (size_t)(t - 1) * (size_t)total;
        for (i64 g = 0; g < m; ++g)
            scatter_range(points, lo, hi, aff + 12 * g, grad_out, mc, g, c, sc, shape, dst + g * sm, &s);
        #pragma omp barrier
        for (int b = 0; b < nt - 1; ++b) {
            const float *src = buffers + (size_t)b * (size_t)total;
            #pragma omp for schedule(static)
            for (i64 e = 0; e < total; ++e) grad_grids[e] += src[e];
        }
    }
}

/* ---- Gradient w.r.t. the placement: d loss / d f (index-space coordinates) of every point in every grid ----
   gf[(g * n + i) * 3 + k] = sum_c grad_out[i, g * C + c] * d feature_gc / d f_k at point i, axis k = x, y, z;
   0 where the grid misses the point. The derivative of zero-padded trilinear sampling: along x, the
   bilinear (y, z) mix of the differences between the corner values at floor(fx) + 1 and floor(fx) (a corner
   outside the grid reads 0), as grid_sample's backward computes it. One thread per grid (no races). */
void mg_backward_coords(const float *points, i64 n, const float *aff, i64 m, const float *grad_out,
                        const float *grids, i64 c, i64 d, i64 h, i64 w, i64 sm, i64 sc, i64 sz, i64 sy, i64 sx,
                        float *gf, int nthreads) {
    const i64 mc = m * c;
    const float fw = (float)w, fh = (float)h, fd = (float)d;
    #pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (i64 g = 0; g < m; ++g) {
        const float *a = aff + 12 * g;
        const float *grid = grids + g * sm;
        float *out = gf + g * n * 3;
        for (i64 i = 0; i < n; ++i) {
            const float px = points[3 * i], py = points[3 * i + 1], pz = points[3 * i + 2];
            const float fx = a[0] * px + a[1] * py + a[2] * pz + a[9];
            const float fy = a[3] * px + a[4] * py + a[5] * pz + a[10];
            const float fz = a[6] * px + a[7] * py + a[8] * pz + a[11];
            float gx = 0.0f, gy = 0.0f, gz = 0.0f;
            if (fx > -1.0f && fx < fw && fy > -1.0f && fy < fh && fz > -1.0f && fz < fd) {
                const float flx = floorf(fx), fly = floorf(fy), flz = floorf(fz);
                const float tx = fx - flx, ty = fy - fly, tz = fz - flz;
                const int x0 = (int)flx, y0 = (int)fly, z0 = (int)flz;
                const int vx0 = x0 >= 0, vx1 = x0 + 1 < w, vy0 = y0 >= 0, vy1 = y0 + 1 < h;
                const int vz0 = z0 >= 0, vz1 = z0 + 1 < d;
                const i64 ox0 = (i64)(vx0 ? x0 : 0) * sx, ox1 = (i64)(vx1 ? x0 + 1 : 0) * sx;
                const i64 oy0 = (i64)(vy0 ? y0 : 0) * sy, oy1 = (i64)(vy1 ? y0 + 1 : 0) * sy;
                const i64 oz0 = (i64)(vz0 ? z0 : 0) * sz, oz1 = (i64)(vz1 ? z0 + 1 : 0) * sz;
                const float *go = grad_out + i * mc + g * c;
                for (i64 ch = 0; ch < c; ++ch) {
                    const float *b = grid + ch * sc;
                    /* v[z][y][x], 0 outside */
                    const float v000 = vz0 && vy0 && vx0 ? b[oz0 + oy0 + ox0] : 0.0f;
                    const float v001 = vz0 && vy0 && vx1 ? b[oz0 + oy0 + ox1] : 0.0f;
                    const float v010 = vz0 && vy1 && vx0 ? b[oz0 + oy1 + ox0] : 0.0f;
                    const float v011 = vz0 && vy1 && vx1 ? b[oz0 + oy1 + ox1] : 0.0f;
                    const float v100 = vz1 && vy0 && vx0 ? b[oz1 + oy0 + ox0] : 0.0f;
                    const float v101 = vz1 && vy0 && vx1 ? b[oz1 + oy0 + ox1] : 0.0f;
                    const float v110 = vz1 && vy1 && vx0 ? b[oz1 + oy1 + ox0] : 0.0f;
                    const float v111 = vz1 && vy1 && vx1 ? b[oz1 + oy1 + ox1] : 0.0f;
                    const float up = go[ch];
                    gx += up * ((1.0f - ty) * (1.0f - tz) * (v001 - v000) + ty * (1.0f - tz) * (v011 - v010)
                              + (1.0f - ty) * tz * (v101 - v100) + ty * tz * (v111 - v110));
                    gy += up * ((1.0f - tx) * (1.0f - tz) * (v010 - v000) + tx * (1.0f - tz) * (v011 - v001)
                              + (1.0f - tx) * tz * (v110 - v100) + tx * tz * (v111 - v101));
                    gz += up * ((1.0f - tx) * (1.0f - ty) * (v100 - v000) + tx * (1.0f - ty) * (v101 - v001)
                              + (1.0f - tx) * ty * (v110 - v010) + tx * ty * (v111 - v011));
                }
            }
            out[3 * i] = gx; out[3 * i + 1] = gy; out[3 * i + 2] = gz;
        }
    }
}

/* ---- Feature density (docs/method.md §3): rho[n] = sum_g det[g] exp(-sum_d G_g(p_n)_d^(2P)) ---- */

/* exp(x) for x <= 0, vectorisable (glibc's expf is not, without fast-math): 2^k e^r with
   |r| <= ln2/2 and a degree-6 polynomial (the classic single-precision minimax coefficients);
   within 2 ulp of expf, and exactly 0 below -87 where expf underflows to denormals. */
static inline float exp_nonpositive(float x) {
    const float xc = x > -87.0f ? x : -87.0f;
    const float k = floorf(xc * 1.44269504088896341f + 0.5f);
    float r = xc - k * 0.693359375f;  /* ln 2 split in two for an exact first product */
    r = r + k * 2.12194440e-4f;
    float y = 1.9875691500e-4f;
    y = y * r + 1.3981999507e-3f;
    y = y * r + 8.3334519073e-3f;
    y = y * r + 4.1665795894e-2f;
    y = y * r + 1.6666665459e-1f;
    y = y * r + 5.0000001201e-1f;
    y = y * r * r + r + 1.0f;
    const int32_t bits = ((int32_t)k + 127) << 23;  /* 2^k, k in [-126, 0] */
    float scale;
    memcpy(&scale, &bits, sizeof scale);
    return x > -87.0f ? y * scale : 0.0f;
}

/* x^e for 0 <= e < 128 by squaring, with a fixed trip count and selects instead of branches, so the
   loops that call it vectorise whatever e is (the caller checks the range). */
static inline float pow_int(float x, int e) {
    float r = 1.0f;
    for (int bit = 0; bit < 7; ++bit) {
        r = (e >> bit) & 1 ? r * x : r;
        x = x * x;
    }
    return r;
}

#define DTILE 256

/* rho for the points [i0, i0 + nt) of one tile. Inlined with a literal two_p (2P = 20, the paper's),
   the powers fold to a few multiplies; OpenMP regions stay outside, since gcc does not propagate
   constants into the functions it outlines for them. */
static inline __attribute__((always_inline)) void density_tile(
        const float *points, i64 i0, int nt, const float *aff, const float *det, i64 m, const int two_p,
        float *rho) {
    float px[DTILE], py[DTILE], pz[DTILE], acc[DTILE];
    for (int i = 0; i < nt; ++i) {
        px[i] = points[3 * (i0 + i)]; py[i] = points[3 * (i0 + i) + 1]; pz[i] = points[3 * (i0 + i) + 2];
        acc[i] = 0.0f;
    }
    for (i64 g = 0; g < m; ++g) {
        const float *a = aff + 12 * g;
        const float a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], a4 = a[4], a5 = a[5];
        const float a6 = a[6], a7 = a[7], a8 = a[8], a9 = a[9], a10 = a[10], a11 = a[11];
        const float dg = det[g];
        #pragma omp simd
        for (int i = 0; i < nt; ++i) {
            const float lx = a0 * px[i] + a1 * py[i] + a2 * pz[i] + a9;
            const float ly = a3 * px[i] + a4 * py[i] + a5 * pz[i] + a10;
            const float lz = a6 * px[i] + a7 * py[i] + a8 * pz[i] + a11;
            const float sum = pow_int(lx, two_p) + pow_int(ly, two_p) + pow_int(lz, two_p);
            acc[i] += dg * exp_nonpositive(-sum);
        }
    }
    /* NaN at a point with a NaN coordinate; a point whose map gives NaN from Inf * 0 or Inf - Inf got 0 from
       exp_nonpositive, as any point far outside */
    for (int i = 0; i < nt; ++i) rho[i0 + i] = px[i] != px[i] || py[i] != py[i] || pz[i] != pz[i] ? NAN : acc[i];
}

/* Adds this tile's d rho / d (det, A, t) of every grid into own [M, 13] (det, A row-major, t). */
static inline __attribute__((always_inline)) void density_backward_tile(
        const float *points, i64 i0, int nt, const float *aff, const float *det, i64 m, const int two_p,
        const float *grad_rho, double *own) {
    float px[DTILE], py[DTILE], pz[DTILE], gr[DTILE];
    for (int i = 0; i < nt; ++i) {
        /* finite stand-ins (the references' finite_stand_in): a point's zero gradient times its coordinate
           must stay 0; a NaN point (its density is NaN) adds nothing, whatever its gradient */
        const float *p = points + 3 * (i0 + i);
        px[i] = stand_in(p[0]); py[i] = stand_in(p[1]); pz[i] = stand_in(p[2]);
        gr[i] = nan_point(p) ? 0.0f : grad_rho[i0 + i];
    }
    for (i64 g = 0; g < m; ++g) {
        const float *a = aff + 12 * g;
        const float a0 = a[0], a1 = a[1], a2 = a[2], a3 = a[3], a4 = a[4], a5 = a[5];
        const float a6 = a[6], a7 = a[7], a8 = a[8], a9 = a[9], a10 = a[10], a11 = a[11];
        const float scale = -(float)two_p * det[g];
        float r0 = 0, rxx = 0, rxy = 0, rxz = 0, ryx = 0, ryy = 0, ryz = 0;
        float rzx = 0, rzy = 0, rzz = 0, rx = 0, ry = 0, rz = 0;
        #pragma omp simd reduction(+:r0, rxx, rxy, rxz, ryx, ryy, ryz, rzx, rzy, rzz, rx, ry, rz)
        for (int i = 0; i < nt; ++i) {
            const float lx = a0 * px[i] + a1 * py[i] + a2 * pz[i] + a9;
            const float ly = a3 * px[i] + a4 * py[i] + a5 * pz[i] + a10;
            const float lz = a6 * px[i] + a7 * py[i] + a8 * pz[i] + a11;
            const float qx = pow_int(lx, two_p - 1), qy = pow_int(ly, two_p - 1), qz = pow_int(lz, two_p - 1);
            const float e = exp_nonpositive(-(qx * lx + qy * ly + qz * lz));
            /* d rho / d det = e; d rho / d l_k = -2P det e l_k^(2P-1); zero where e is 0, so a far-away
               point cannot give 0 * inf */
            const float ge = e > 0.0f ? gr[i] * e : 0.0f;  /* a NaN point's NaN gradient adds nothing */
            const float sg = e > 0.0f ? scale * ge : 0.0f;
            const float sx = e > 0.0f ? sg * qx : 0.0f;
            const float sy = e > 0.0f ? sg * qy : 0.0f;
            const float sz = e > 0.0f ? sg * qz : 0.0f;
            r0 += ge;
            rxx += sx * px[i]; rxy += sx * py[i]; rxz += sx * pz[i]; rx += sx;
            ryx += sy * px[i]; ryy += sy * py[i]; ryz += sy * pz[i]; ry += sy;
            rzx += sz * px[i]; rzy += sz * py[i]; rzz += sz * pz[i]; rz += sz;
        }
        double *r = own + 13 * g;  /* dl_k / dA_kj = p_j, dl_k / dt_k = 1 */
        r[0] += r0;
        r[1] += rxx; r[2] += rxy; r[3] += rxz;
        r[4] += ryx; r[5] += ryy; r[6] += ryz;
        r[7] += rzx; r[8] += rzy; r[9] += rzz;
        r[10] += rx; r[11] += ry; r[12] += rz;
    }
}

/* aff: [M, 12] plain maps (A row-major, then t), local units; 1 <= power <= 63. */
void mg_density(const float *points, i64 n, const float *aff, const float *det, i64 m, int power,
                float *rho, int nthreads) {
    const i64 ntiles = (n + DTILE - 1) / DTILE;
    #pragma omp parallel for schedule(dynamic, 4) num_threads(nthreads)
    for (i64 t = 0; t < ntiles; ++t) {
        const i64 i0 = t * DTILE;
        const int nt = (int)(n - i0 < DTILE ? n - i0 : DTILE);
        if (power == 10)
            density_tile(points, i0, nt, aff, det, m, 20, rho);
        else
            density_tile(points, i0, nt, aff, det, m, 2 * power, rho);
    }
}

/* Flush denormal float results to zero and read denormal inputs as zero (x86's FTZ and DAZ bits) on the
   calling thread; returns the previous control word for denormals_restore. A density's gradient is made of
   products of tiny factors (rho_s, e far from a grid) whose denormal results each cost a microcode assist,
   on a trained model's batch four times the whole backward; a term below 2^-126 changes no sum that Adam
   can tell from zero. */
#if defined(__SSE2__)
#include <xmmintrin.h>
#endif
static inline unsigned denormals_flush(void) {
#if defined(__SSE2__)
    const unsigned csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040u);
    return csr;
#else
    return 0;
#endif
}

static inline void denormals_restore(unsigned csr) {
#if defined(__SSE2__)
    _mm_setcsr(csr);
#else
    (void)csr;
#endif
}

/* partial: [blocks, M, 13] zeroed doubles, sums: [M, 13]. The tiles are cut into `blocks` runs fixed by n
   alone; each run is summed by one thread into its own partial, and the partials are added in order, so
   the result is the same on any number of threads (a thread-count change never changes training).
   Denormal terms count as zero (denormals_flush). */
void mg_density_backward(const float *points, i64 n, const float *aff, const float *det, i64 m,
                         int power, const float *grad_rho, double *partial, i64 blocks, double *sums,
                         int nthreads) {
    const i64 ntiles = (n + DTILE - 1) / DTILE;
    const i64 per_block = (ntiles + blocks - 1) / blocks;
    #pragma omp parallel num_threads(nthreads)
    {
    const unsigned csr = denormals_flush();
    #pragma omp for schedule(dynamic, 1)
    for (i64 b = 0; b < blocks; ++b) {
        double *own = partial + (size_t)b * (size_t)(13 * m);
        for (i64 t = b * per_block; t < ntiles && t < (b + 1) * per_block; ++t) {
            const i64 i0 = t * DTILE;
            const int nt = (int)(n - i0 < DTILE ? n - i0 : DTILE);
            if (power == 10)
                density_backward_tile(points, i0, nt, aff, det, m, 20, grad_rho, own);
            else
                density_backward_tile(points, i0, nt, aff, det, m, 2 * power, grad_rho, own);
        }
    }
    denormals_restore(csr);
    }
    for (i64 e = 0; e < 13 * m; ++e) {
        double total = 0.0;
        for (i64 b = 0; b < blocks; ++b) total += partial[(size_t)b * (size_t)(13 * m) + e];
        sums[e] = total;
    }
}
"""


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    sizes = [i64] * 9  # c, d, h, w, then strides sm, sc, sz, sy, sx
    lib.mg_forward.argtypes = [p, i64, p, i64, p, *sizes, p, i32]
    lib.mg_backward.argtypes = [p, i64, p, i64, p, *sizes, p, p, i32]
    lib.mg_backward_coords.argtypes = [p, i64, p, i64, p, p, *sizes, p, i32]
    lib.mg_density.argtypes = [p, i64, p, p, i64, i32, p, i32]
    lib.mg_density_backward.argtypes = [p, i64, p, p, i64, i32, p, p, i64, p, i32]
    for fn in (lib.mg_forward, lib.mg_backward, lib.mg_backward_coords, lib.mg_density, lib.mg_density_backward):
        fn.restype = None


LIBRARY = CompiledLibrary("multigrid_cpu", C_SOURCE, _declare)


def load_library() -> ctypes.CDLL | None:
    """Build (once per machine) and load the kernel library.

    Returns:
        The loaded library, or ``None`` when it cannot be built here (see :func:`load_error`).
    """
    return LIBRARY.load()


def load_error() -> str | None:
    """Why :func:`load_library` returned ``None`` (``None`` when it has not failed)."""
    return LIBRARY.error


def is_available() -> bool:
    """True when the kernel library builds and loads on this machine."""
    return LIBRARY.available()


def index_space_affine(
    matrices: torch.Tensor, translations: torch.Tensor, size: tuple[int, int, int]
) -> torch.Tensor:
    """Fold corner-aligned unnormalisation into the maps: rows (x, y, z) in voxel index units.

    Args:
        matrices: ``[M, 3, 3]`` the ``A_i`` (row ``k`` gives local coordinate ``k`` = x, y, z).
        translations: ``[M, 3]`` the ``t_i``.
        size: grid ``(D, H, W)``.

    Returns:
        ``[M, 12]`` float32 contiguous: ``A'`` row-major then ``t'``, ``f = A' p + t'`` in index units.
    """
    d, h, w = size
    # Folded in float64 so the only float32 rounding is the kernel's own.
    half = torch.tensor([(w - 1) / 2, (h - 1) / 2, (d - 1) / 2], dtype=torch.float64)  # x, y, z
    a = matrices.detach().cpu().double() * half[None, :, None]  # [M, 3, 3]
    t = (translations.detach().cpu().double() + 1) * half[None, :]  # [M, 3]
    return torch.cat([a.reshape(-1, 9), t], dim=1).float().contiguous()  # [M, 12]


def forward_features(points: torch.Tensor, aff: torch.Tensor, grids: torch.Tensor) -> torch.Tensor:
    """Fused forward pass on float32 CPU tensors.

    Args:
        points: ``[N, 3]`` contiguous.
        aff: ``[M, 12]`` from :func:`index_space_affine`.
        grids: ``[M, C, D, H, W]``, any strides (channel-first or a channel-last view).

    Returns:
        ``[N, M * C]`` features, as the reference.
    """
    lib = LIBRARY.load_or_raise()
    m, c, d, h, w = grids.shape
    n = points.shape[0]
    out = torch.empty(n, m * c, dtype=torch.float32)  # every element is written by the kernel
    lib.mg_forward(
        points.data_ptr(), n, aff.data_ptr(), m, grids.data_ptr(), c, d, h, w, *grids.stride(),
        out.data_ptr(), torch.get_num_threads(),
    )
    return out


def backward_grids(
    points: torch.Tensor,
    aff: torch.Tensor,
    grad_out: torch.Tensor,
    shape: tuple[int, ...],
    stride: tuple[int, ...] | None = None,
) -> torch.Tensor:
    """Gradient of the features w.r.t. the grids: a scatter of ``grad_out`` with trilinear weights.

    Args:
        points: ``[N, 3]`` contiguous float32.
        aff: ``[M, 12]`` from :func:`index_space_affine`.
        grad_out: ``[N, M * C]``.
        shape: the grids' shape ``(M, C, D, H, W)``.
        stride: the grids' strides when dense (the gradient gets the same layout), else ``None``
            (contiguous).

    Returns:
        ``[M, C, D, H, W]`` float32 gradient.
    """
    lib = LIBRARY.load_or_raise()
    m, c, d, h, w = shape
    go = grad_out.to(torch.float32).contiguous()
    if stride is None:
        grad = torch.zeros(shape, dtype=torch.float32)
    else:
        grad = torch.empty_strided(shape, stride, dtype=torch.float32).zero_()
    threads = torch.get_num_threads()
    buffers = None
    if m < threads:
        # Fewer grids than threads: per-thread private copies of the gradient, reduced in the kernel.
        buffers = torch.zeros(threads - 1, grad.numel(), dtype=torch.float32)
    lib.mg_backward(
        points.data_ptr(), points.shape[0], aff.data_ptr(), m, go.data_ptr(), c, d, h, w,
        *grad.stride(), grad.data_ptr(), None if buffers is None else buffers.data_ptr(), threads,
    )
    return grad


def _grid_major_dense(t: torch.Tensor) -> bool:
    """True when ``t`` fills its memory without gaps and grid ``i`` occupies block ``i`` (any order
    inside a grid), the layouts the backward kernel writes to directly."""
    if t.stride(0) * t.shape[0] != t.numel() and t.shape[0] > 1:
        return False
    expected = 1
    for i in sorted(range(1, t.dim()), key=lambda i: t.stride(i)):
        if t.shape[i] == 1:
            continue
        if t.stride(i) != expected:
            return False
        expected *= t.shape[i]
    return t.shape[0] == 1 or expected == t.stride(0)


def channel_last(grids: torch.Tensor) -> torch.Tensor:
    """A channel-last copy of ``grids`` viewed as ``[M, C, D, H, W]`` (the kernels read any strides).

    Args:
        grids: ``[M, C, D, H, W]``.

    Returns:
        The same values, stored ``[M, D, H, W, C]``: a corner's ``C`` features share a cache line.
    """
    return grids.permute(0, 2, 3, 4, 1).contiguous().permute(0, 4, 1, 2, 3)  # [M, C, D, H, W] view


def _sampling_layout(grids: torch.Tensor, samples: int) -> torch.Tensor:
    """The grids as the forward kernel should read them.

    Channel-first grids with ``C > 1`` put a corner's channels ``D H W`` elements apart, one cache miss
    each; a channel-last copy costs one pass over the grids, so it is made when there are at least as
    many samples (points x grids x channels) as grid elements (decoding; medium training batches).
    """
    c = grids.shape[1]
    if c > 1 and grids.stride(1) != 1 and samples >= grids.numel():
        return channel_last(grids)
    return grids


def backward_placement(
    points: torch.Tensor,
    aff: torch.Tensor,
    grad_out: torch.Tensor,
    grids: torch.Tensor,
    matrices: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradient of the features w.r.t. the placement (the reconstruction error moving the grids).

    Args:
        points: ``[N, 3]`` contiguous float32.
        aff: ``[M, 12]`` from :func:`index_space_affine`.
        grad_out: ``[N, M * C]``.
        grids: ``[M, C, D, H, W]`` float32, any strides.
        matrices: ``[M, 3, 3]`` (their dtype and device for the result).

    Returns:
        ``(d/dA [M, 3, 3], d/dt [M, 3])``: the kernel's gradient in index space, scaled back to the local
        ``[-1, 1]`` coordinates ``l = A p + t`` (``f = (l + 1) (size - 1) / 2``), then chained through ``l``.
    """
    lib = LIBRARY.load_or_raise()
    m, c, d, h, w = grids.shape
    n = points.shape[0]
    go = grad_out.to(torch.float32).contiguous()
    index_grad = torch.empty(m, n, 3, dtype=torch.float32)  # every element is written by the kernel
    lib.mg_backward_coords(
        points.data_ptr(), n, aff.data_ptr(), m, go.data_ptr(), grids.data_ptr(), c, d, h, w, *grids.stride(),
        index_grad.data_ptr(), torch.get_num_threads(),
    )
    half = torch.tensor([(w - 1) / 2, (h - 1) / 2, (d - 1) / 2], dtype=torch.float32)  # x, y, z
    local_grad = index_grad * half  # [M, N, 3]; 0 where a grid misses a point (every grid misses a non-finite one)
    grad_matrices = torch.einsum("mnk,nj->mkj", local_grad, finite_stand_in(points))  # [M, 3, 3]: no 0 * inf
    return grad_matrices.to(matrices.dtype), local_grad.sum(1).to(matrices.dtype)  # [M, 3, 3], [M, 3]


class _MultigridFunction(torch.autograd.Function):
    """Autograd wrapper: gradients for the grids and the placement (the points are constants here)."""

    @staticmethod
    def forward(ctx, points, matrices, translations, grids):  # type: ignore[override]
        m, c, d, h, w = grids.shape
        pts = points.detach().to(torch.float32).contiguous()
        aff = index_space_affine(matrices, translations, (d, h, w))
        g = grids.detach()
        layout = _sampling_layout(g, pts.shape[0] * m * c)
        out = forward_features(pts, aff, layout)
        placed = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        # Only the layout is kept for the grids' gradient (scattered straight into it); the placement's
        # gradient reads the grids' values.
        ctx.save_for_backward(pts, aff, *((layout, matrices) if placed else ()))
        ctx.grid_layout = (tuple(g.shape), tuple(g.stride()) if _grid_major_dense(g) else None)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        pts, aff, *placement = ctx.saved_tensors
        grad_grids = grad_matrices = grad_translations = None
        if ctx.needs_input_grad[3]:
            grad_grids = backward_grids(pts, aff, grad_out, *ctx.grid_layout)
        if placement:
            grad_matrices, grad_translations = backward_placement(pts, aff, grad_out, *placement)
        return None, grad_matrices, grad_translations, grad_grids


def multigrid_features_cpu(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor, grids: torch.Tensor
) -> torch.Tensor:
    """Fused CPU multi-grid features with gradients for ``grids``, ``matrices`` and ``translations`` (float32
    CPU tensors).

    Args:
        points: ``[N, 3]`` (no gradient flows to them).
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]``.

    Returns:
        ``[N, M * C]`` features, as :func:`~apmgsrn.ops.multigrid.multigrid_features_reference`.
    """
    return _MultigridFunction.apply(points, matrices, translations, grids)


class _DensityFunction(torch.autograd.Function):
    """Feature density with gradients for ``det`` and the maps (``points`` are constants)."""

    @staticmethod
    def forward(ctx, points, matrices, translations, det, power):  # type: ignore[override]
        lib = LIBRARY.load_or_raise()
        pts = points.detach().to(torch.float32).contiguous()
        m = matrices.shape[0]
        aff = torch.cat(
            [matrices.detach().reshape(m, 9), translations.detach().reshape(m, 3)], dim=1
        ).to(torch.float32).contiguous()  # [M, 12]: A row-major, then t
        det_c = det.detach().to(torch.float32).contiguous()
        rho = torch.empty(pts.shape[0], dtype=torch.float32)
        lib.mg_density(
            pts.data_ptr(), pts.shape[0], aff.data_ptr(), det_c.data_ptr(), m, int(power),
            rho.data_ptr(), torch.get_num_threads(),
        )
        ctx.save_for_backward(pts, aff, det_c)
        ctx.power = int(power)
        return rho

    @staticmethod
    def backward(ctx, grad_rho):  # type: ignore[override]
        pts, aff, det_c = ctx.saved_tensors
        lib = LIBRARY.load_or_raise()
        m = aff.shape[0]
        g = grad_rho.to(torch.float32).contiguous()
        tiles = -(-pts.shape[0] // 256)  # DTILE points per tile in the C source
        # at most 64 runs of tiles summed apart (blocks * M * 13 doubles), a function of the point count alone
        blocks = max(1, min(64, tiles))
        partial = torch.zeros(blocks, m, 13, dtype=torch.float64)  # one per run of tiles, no races
        sums = torch.empty(m, 13, dtype=torch.float64)
        lib.mg_density_backward(
            pts.data_ptr(), pts.shape[0], aff.data_ptr(), det_c.data_ptr(), m, ctx.power,
            g.data_ptr(), partial.data_ptr(), blocks, sums.data_ptr(), torch.get_num_threads(),
        )
        sums = sums.to(torch.float32)  # [M, 13]
        grad_det = sums[:, 0]
        grad_a = sums[:, 1:10].reshape(m, 3, 3)  # [M, 3, 3]
        grad_t = sums[:, 10:]  # [M, 3]
        return None, grad_a, grad_t, grad_det, None


def feature_density_cpu(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor, power: int = 10
) -> torch.Tensor:
    """Fused CPU feature density with gradients for ``matrices`` and ``translations``.

    Args:
        points: ``[N, 3]`` float32.
        matrices: ``[M, 3, 3]`` float32.
        translations: ``[M, 3]`` float32.
        power: super-Gaussian power ``P``.

    Returns:
        ``[N]`` density, as :func:`~apmgsrn.ops.multigrid.feature_density`.
    """
    det = torch.linalg.det(matrices)  # [M]; autograd takes d det / d A from here
    return _DensityFunction.apply(points, matrices, translations, det, power)
