"""Fused CPU inference of a field: encoder and decoder MLP in one pass per tile, for the adaptive multi-grid
encoder (APMGSRN's, :func:`multigrid_decoder_cpu`) and for level grids (the hybrid's, :func:`level_grid_decoder_cpu`).

Why: decoding through PyTorch runs the encoder kernel, writes ``[N, M * C]`` features, then three matrix
products whose ``[N, 64]`` activations go through memory (and, for each fresh multi-megabyte buffer,
through page faults). Here a tile of 128 points is encoded into a buffer that stays in cache and the MLP
runs point by point on it, so nothing but the points and the ``[N]`` output touches memory.

Sparsity: a point's features are zero for every grid that does not cover it, and ReLU zeroes about half
of each hidden layer (57 % and 69 % in a trained small model), so each layer adds up only the weight rows
of its input's non-zero entries: ``y = sum_{k: x_k != 0} x_k W^T[k, :]``, a broadcast and a fused
multiply-add per 8 (AVX2) or 16 (AVX-512) outputs. Dense matrix products cannot skip those zeros. The
output layer is a dense dot product with the last hidden layer, taken while it is still in registers.

The sums run in another order than PyTorch's matrix products (and with fused multiply-adds), so results
agree with the reference ``decoder(multigrid_features_reference(...))`` to float32 rounding, not bit for
bit; tests compare them. A point with a NaN coordinate decodes to NaN (the contract of :mod:`apmgsrn.ops`).
Inference only: no gradients. The MLP's C source (:data:`MLP_SOURCE`) follows a tile
encoder: :data:`apmgsrn.ops.multigrid_cpu.C_SOURCE`'s in :data:`LIBRARY`, :data:`apmgsrn.ops.level_grids_cpu.C_SOURCE`'s
in :data:`LEVEL_LIBRARY`, each built and cached as a library of its own. A hybrid small model's pass over every
voxel of a 64^3 volume (what ``eval`` and the training's error guide run; a model of a viscous-finger step)
took 76 ms against 103 through the level kernel and PyTorch's matrix products in chunks of 8,192 points, and
223 in one batch (1 thread; random points on c60 models: docs/benchmarks_decode.md).
"""

from __future__ import annotations

import ctypes

import torch

from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.ops.level_grids_cpu import C_SOURCE as LEVEL_SOURCE
from apmgsrn.ops.level_grids_cpu import kernel_inputs, kernel_layout
from apmgsrn.ops.level_layout import LevelLayout
from apmgsrn.ops.multigrid_cpu import C_SOURCE as MULTIGRID_SOURCE
from apmgsrn.ops.multigrid_cpu import LANE_LUT_SOURCE
from apmgsrn.ops.multigrid_cpu import _sampling_layout, index_space_affine

#: Largest encoder output (``M * C``) and decoder width the fused kernel takes; larger models use the
#: reference (their per-thread buffers would not fit in cache anyway).
MAX_FEATURES, MAX_WIDTH = 4096, 4096

MLP_SOURCE = r"""
#include <stdlib.h>
#include <string.h>

#if defined(__AVX512F__)
#define VL 16
#else
#define VL 8
#endif
/* GCC vector of VL floats; aligned(4) makes every load and store through it an unaligned one. */
typedef float vec __attribute__((vector_size(VL * 4), aligned(4)));
typedef int veci __attribute__((vector_size(VL * 4), aligned(4)));

int field_vector_width(void) { return VL; }

/* Positions k < K where x[k] != 0 (NaN included), in order, into idx (room for K + 8); returns the count. */
static inline int nonzero(const float *x, int K, int *idx) {
    int n = 0, k = 0;
#if defined(__AVX2__)
    const __m256 zero = _mm256_setzero_ps();
    for (; k + 8 <= K; k += 8) {
        const int mask = _mm256_movemask_ps(_mm256_cmp_ps(_mm256_loadu_ps(x + k), zero, _CMP_NEQ_UQ));
        const __m256i lanes = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)lane_lut[mask]));
        _mm256_storeu_si256((__m256i *)(idx + n), _mm256_add_epi32(lanes, _mm256_set1_epi32(k)));
        n += __builtin_popcount(mask);
    }
#endif
    for (; k < K; ++k) { idx[n] = k; n += x[k] != 0.0f; }
    return n;
}

/* acc[0..nv) = sum over the listed inputs of x[k] * wt[k, 0 .. nv*VL) (row stride wp). With few vectors
   per row the rows alternate between two sets of accumulators, so the adds of one row do not wait for
   the previous row's (fused multiply-add latency). */
static inline __attribute__((always_inline)) void weighted_rows(
        const float *x, const int *idx, int nnz, const float *wt, long wp, const int nv, vec *acc) {
    vec a[8], b[8];
    for (int v = 0; v < nv; ++v) { a[v] = (vec){0}; b[v] = (vec){0}; }
    int j = 0;
    if (nv <= 4) {
        for (; j + 1 < nnz; j += 2) {
            const float s0 = x[idx[j]], s1 = x[idx[j + 1]];
            const float *r0 = wt + (long)idx[j] * wp, *r1 = wt + (long)idx[j + 1] * wp;
            for (int v = 0; v < nv; ++v) {
                a[v] += s0 * *(const vec *)(r0 + v * VL);
                b[v] += s1 * *(const vec *)(r1 + v * VL);
            }
        }
    }
    for (; j < nnz; ++j) {
        const float s = x[idx[j]];
        const float *r = wt + (long)idx[j] * wp;
        for (int v = 0; v < nv; ++v) a[v] += s * *(const vec *)(r + v * VL);
    }
    for (int v = 0; v < nv; ++v) acc[v] = a[v] + b[v];
}

/* weighted_rows for the block of nv = min(8, (wp - ob) / VL) vectors starting at column ob; returns nv. */
static inline __attribute__((always_inline)) int row_block(
        const float *x, const int *idx, int nnz, const float *wt, long wp, long ob, vec *acc) {
    const int nv = (int)((wp - ob) / VL < 8 ? (wp - ob) / VL : 8);
    switch (nv) {  /* constant vector counts, so the accumulators live in registers */
        case 8: weighted_rows(x, idx, nnz, wt + ob, wp, 8, acc); break;
        case 7: weighted_rows(x, idx, nnz, wt + ob, wp, 7, acc); break;
        case 6: weighted_rows(x, idx, nnz, wt + ob, wp, 6, acc); break;
        case 5: weighted_rows(x, idx, nnz, wt + ob, wp, 5, acc); break;
        case 4: weighted_rows(x, idx, nnz, wt + ob, wp, 4, acc); break;
        case 3: weighted_rows(x, idx, nnz, wt + ob, wp, 3, acc); break;
        case 2: weighted_rows(x, idx, nnz, wt + ob, wp, 2, acc); break;
        default: weighted_rows(x, idx, nnz, wt + ob, wp, 1, acc); break;
    }
    return nv;
}

/* relu keeping NaN, as torch.relu does */
static inline vec relu(vec a) { return (vec)((veci)a & ~(veci)(a < (vec){0})); }

/* One hidden layer: y = relu(x W^T) for the listed inputs, or, when last != NULL, the output
   sum_o relu(x W^T)_o last[o] without storing y. wp: padded width (a multiple of VL). */
static float hidden_layer(const float *x, const int *idx, int nnz, const float *wt, long wp, float *y,
                          const float *last) {
    vec total = (vec){0};
    for (long ob = 0; ob < wp; ob += 8 * VL) {
        vec acc[8];
        const int nv = row_block(x, idx, nnz, wt, wp, ob, acc);
        if (last != NULL) {
            for (int v = 0; v < nv; ++v) total += relu(acc[v]) * *(const vec *)(last + ob + v * VL);
        } else {
            for (int v = 0; v < nv; ++v) *(vec *)(y + ob + v * VL) = relu(acc[v]);
        }
    }
    float sum = 0.0f;
    for (int l = 0; l < VL; ++l) sum += total[l];
    return sum;
}

/* One thread's decoder: the MLP (f inputs, then `layers` hidden widths padded to pad[l], weights as
   field_decode's) and its buffers: a tile's features feature-major (feat[j * TILE + k]), two of the widest
   layer and the non-zero list (room for it plus 8). */
typedef struct { i64 f; int layers; const i64 *pad; const float *weights; float *feat, *x, *y; int *idx; } Mlp;

static Mlp mlp_open(i64 f, int layers, const i64 *pad, const float *weights) {
    i64 widest = f;
    for (int l = 0; l < layers; ++l) widest = pad[l] > widest ? pad[l] : widest;
    Mlp m = {f, layers, pad, weights, malloc(sizeof(float) * (size_t)(TILE * f)),
             malloc(sizeof(float) * (size_t)widest), malloc(sizeof(float) * (size_t)widest),
             malloc(sizeof(int) * (size_t)(widest + 8))};
    return m;
}

static void mlp_close(Mlp *m) { free(m->feat); free(m->x); free(m->y); free(m->idx); }

/* out[k] = NaN for the tile's points (nt from i0) with a NaN coordinate, whatever the decoder made of them. */
static void nan_outputs(const float *points, i64 i0, int nt, float *out) {
    for (int k = 0; k < nt; ++k)
        if (nan_point(points + 3 * (i0 + k))) out[k] = NAN;
}

/* out[k] = decoder(features of point k) for the nt points of the tile in m->feat. */
static void decode_tile(Mlp *m, int nt, float *out) {
    float *x = m->x, *y = m->y;
    for (int k = 0; k < nt; ++k) {
        for (i64 j = 0; j < m->f; ++j) x[j] = m->feat[j * TILE + k];  /* the point's features */
        const float *in = x;
        i64 width = m->f;
        const float *wt = m->weights;
        float value = 0.0f;
        for (int l = 0; l < m->layers; ++l) {
            const int nnz = nonzero(in, (int)width, m->idx);
            const float *next = wt + width * m->pad[l];
            if (l == m->layers - 1) {
                value = hidden_layer(in, m->idx, nnz, wt, m->pad[l], NULL, next);
            } else {
                float *h = in == x ? y : x;
                hidden_layer(in, m->idx, nnz, wt, m->pad[l], h, NULL);
                in = h;
            }
            width = m->pad[l];
            wt = next;
        }
        out[k] = value;
    }
}
"""

MULTIGRID_DECODE_SOURCE = r"""
/* The features of the tile's nt points starting at i0, feature-major: ft[(g * C + c) * TILE + k], so
   each grid's samples land in one contiguous row (written straight there when the grid covers the whole
   tile). */
static void encode_tile_t(Scratch *s, const float *points, i64 i0, int nt, const float *aff, i64 m,
                          const float *grids, i64 c, i64 sm, i64 sc, Shape shape, float *ft) {
    load_tile(s, points, i0, nt);
    for (i64 g = 0; g < m; ++g) {
        const int cnt = select_and_weigh(s, aff + 12 * g, nt, shape);
        for (i64 ch = 0; ch < c; ++ch) {
            float *row = ft + (g * c + ch) * TILE;
            if (cnt == nt) {
                gather_tile(grids + g * sm + ch * sc, s, cnt, row);
                continue;
            }
            memset(row, 0, sizeof(float) * (size_t)nt);  /* points the grid misses get 0 */
            if (cnt == 0) continue;
            gather_tile(grids + g * sm + ch * sc, s, cnt, s->res);
            for (int k = 0; k < cnt; ++k) row[s->idx[k]] = s->res[k];
        }
    }
}

/* out[i] = decoder(features(points[i])) for an MLP of `layers` hidden ReLU layers and one linear output.
   weights: layer 0 as [F][pad[0]] (transposed, zero columns up to the padded width), layer l > 0 as
   [pad[l-1]][pad[l]], then the output weights [pad[layers-1]]; zero padding gives zero activations,
   which the non-zero lists skip. */
void field_decode(const float *points, i64 n, const float *aff, i64 m, const float *grids,
                  i64 c, i64 d, i64 h, i64 w, i64 sm, i64 sc, i64 sz, i64 sy, i64 sx,
                  int layers, const i64 *pad, const float *weights, float *out, int nthreads) {
    const i64 ntiles = (n + TILE - 1) / TILE;
    const Shape shape = {(int)d, (int)h, (int)w, (int)sz, (int)sy, (int)sx};
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        Mlp mlp = mlp_open(m * c, layers, pad, weights);
        #pragma omp for schedule(dynamic, 4)
        for (i64 t = 0; t < ntiles; ++t) {
            const i64 i0 = t * TILE;
            const int nt = (int)(n - i0 < TILE ? n - i0 : TILE);
            encode_tile_t(&s, points, i0, nt, aff, m, grids, c, sm, sc, shape, mlp.feat);
            decode_tile(&mlp, nt, out + i0);
            if (s.nans) nan_outputs(points, i0, nt, out + i0);
        }
        mlp_close(&mlp);
    }
}
"""

LEVEL_DECODE_SOURCE = r"""
/* out[i] = decoder(level-grid features(points[i])): lg_forward's levels (same arguments) into a tile buffer
   (encode_tile), then field_decode's MLP (layers, pad, weights) on it. */
void level_decode(const float *points, i64 n, i64 levels, const float *maps, const int *meta, const i64 *rows,
                  const i64 *offsets, const float *table, i64 f, int layers, const i64 *pad, const float *weights,
                  float *out, int nthreads) {
    const i64 ntiles = (n + TILE - 1) / TILE;
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch s;
        Mlp mlp = mlp_open(f, layers, pad, weights);
        #pragma omp for schedule(dynamic, 4)
        for (i64 t = 0; t < ntiles; ++t) {
            const i64 i0 = t * TILE;
            const int nt = (int)(n - i0 < TILE ? n - i0 : TILE);
            encode_tile(&s, points, i0, nt, levels, maps, meta, rows, offsets, table, mlp.feat, 1, TILE, NULL);
            decode_tile(&mlp, nt, out + i0);
            if (s.nans) nan_outputs(points, i0, nt, out + i0);
        }
        mlp_close(&mlp);
    }
}
"""


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.field_decode.argtypes = [p, i64, p, i64, p, *[i64] * 9, i32, p, p, p, i32]
    lib.field_decode.restype = None
    lib.field_vector_width.argtypes = []
    lib.field_vector_width.restype = i32


def _declare_levels(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.level_decode.argtypes = [p, i64, i64, p, p, p, p, p, i64, i32, p, p, p, i32]
    lib.level_decode.restype = None
    lib.field_vector_width.argtypes = []
    lib.field_vector_width.restype = i32


LIBRARY = CompiledLibrary("field_cpu", MULTIGRID_SOURCE + MLP_SOURCE + MULTIGRID_DECODE_SOURCE, _declare)
#: The fused decoder of level-grid encoders (the hybrid's): the level kernel's tile encoder, then the same MLP.
LEVEL_LIBRARY = CompiledLibrary("field_levels_cpu", LEVEL_SOURCE + LANE_LUT_SOURCE + MLP_SOURCE + LEVEL_DECODE_SOURCE,
                                _declare_levels)


def fusable(features: int, widths: list[int], library: CompiledLibrary = LIBRARY) -> bool:
    """Whether the fused kernel (``library``: :data:`LIBRARY` for the multi-grid encoder, :data:`LEVEL_LIBRARY`
    for level grids) takes an encoder of ``features`` outputs and hidden layers of ``widths`` (and builds here)."""
    return (
        0 < features <= MAX_FEATURES
        and len(widths) >= 1
        and all(0 < w <= MAX_WIDTH for w in widths)
        and library.available()
    )


def pack_decoder(weights: list[torch.Tensor], vector_width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The decoder's weights as the kernel reads them.

    Args:
        weights: ``nn.Linear`` weights in order, ``[out, in]``; hidden layers, then the ``[1, in]`` output.
        vector_width: floats per vector of the built kernel.

    Returns:
        ``(packed float32 weights, int64 padded widths of the hidden layers)``.
    """
    hidden, last = weights[:-1], weights[-1]
    padded = [-(-w.shape[0] // vector_width) * vector_width for w in hidden]
    parts = []
    rows = hidden[0].shape[1]  # the encoder's features, unpadded
    for w, width in zip(hidden, padded):
        block = torch.zeros(rows, width, dtype=torch.float32)  # [in (padded), out (padded)]
        block[: w.shape[1], : w.shape[0]] = w.detach().t()
        parts.append(block.reshape(-1))
        rows = width
    output = torch.zeros(rows, dtype=torch.float32)
    output[: last.shape[1]] = last.detach()[0]
    parts.append(output)
    return torch.cat(parts).contiguous(), torch.tensor(padded, dtype=torch.int64)


def multigrid_decoder_cpu(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
    weights: list[torch.Tensor],
) -> torch.Tensor:
    """``decoder(multigrid_features(points, ...))`` in one fused pass, without gradients (float32 CPU).

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]``.
        weights: the decoder's bias-free linear layers ``[out, in]``, ReLU between them, the last ``[1, in]``.

    Returns:
        ``[N]`` decoder outputs.
    """
    lib = LIBRARY.load_or_raise()
    m, c, d, h, w = grids.shape
    pts = points.detach().to(torch.float32).contiguous()
    n = pts.shape[0]
    aff = index_space_affine(matrices, translations, (d, h, w))
    g = _sampling_layout(grids.detach().to(torch.float32), n * m * c)
    packed, padded = pack_decoder(weights, lib.field_vector_width())
    out = torch.empty(n, dtype=torch.float32)
    lib.field_decode(
        pts.data_ptr(), n, aff.data_ptr(), m, g.data_ptr(), c, d, h, w, *g.stride(),
        len(padded), padded.data_ptr(), packed.data_ptr(), out.data_ptr(), torch.get_num_threads(),
    )
    return out


def level_grid_decoder_cpu(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor]
) -> torch.Tensor:
    """``decoder(level_grid_features(points, ...))`` in one fused pass, without gradients (float32 CPU).

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps.
        table: ``[T]`` flat parameters.
        layout: the levels.
        weights: the decoder's bias-free linear layers ``[out, in]``, ReLU between them, the last ``[1, in]``.

    Returns:
        ``[N]`` decoder outputs.
    """
    lib = LEVEL_LIBRARY.load_or_raise()
    kernel = kernel_layout(layout)
    pts, flat_maps, tab = kernel_inputs(points, maps, table)
    n = pts.shape[0]
    packed, padded = pack_decoder(weights, lib.field_vector_width())
    out = torch.empty(n, dtype=torch.float32)
    lib.level_decode(
        pts.data_ptr(), n, layout.levels, flat_maps.data_ptr(), kernel.meta.data_ptr(), kernel.rows.data_ptr(),
        kernel.offsets.data_ptr(), tab.data_ptr(), layout.out_features, len(padded), padded.data_ptr(),
        packed.data_ptr(), out.data_ptr(), torch.get_num_threads(),
    )
    return out
