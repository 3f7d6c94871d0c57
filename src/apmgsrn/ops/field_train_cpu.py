"""Fused CPU training step of level-grid features under a frozen decoder (the hybrid's fine-tunes).

When only the encoder's table learns (a time series' steps, their quantisation-aware fine-tune) one
reconstruction step needs the prediction at every point and the gradient of the mean squared error with
respect to the flat table. This kernel computes both in one pass over tiles of 128 points: the level kernel's
look-ups (``encode_tile`` of :data:`apmgsrn.ops.level_grids_cpu.C_SOURCE`), the decoder's layers point by
point with every hidden layer's activations kept (:data:`apmgsrn.ops.field_cpu.MLP_SOURCE`), the error's
gradient back through them (the ReLU masks, then the weights' rows of the outputs still active), and the level
kernel's trilinear scatter of the features' gradients into the table (``scatter_tile``), on the corners the
look-ups found (every level's corners of the tile are kept, 8 KB a level, instead of computed again: the step
5.6 % faster on one thread, the same sums). No ``[N, width]`` activation goes to memory and no autograd graph is
built. On 16,384 points of a hybrid small model (one
thread) it takes 10.4 ms where the level kernel, PyTorch's matrix products and autograd take 14.3
(docs/models.md).

Each extra thread scatters into a private copy of the gradient, summed at the end (as the level kernel's
backward does), so the sum's rounding depends on the thread count. The reference is
:func:`apmgsrn.ops.level_grids.level_grid_mse_step_reference`; tests compare the two in prediction and
gradient.
"""

from __future__ import annotations

import ctypes

import torch

from apmgsrn.ops.field_cpu import MLP_SOURCE, fusable, pack_decoder
from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.ops.level_grids_cpu import C_SOURCE as LEVEL_SOURCE
from apmgsrn.ops.level_grids_cpu import kernel_inputs, kernel_layout
from apmgsrn.ops.level_layout import LevelLayout
from apmgsrn.ops.multigrid_cpu import LANE_LUT_SOURCE

#: Most hidden layers the kernel's per-thread offsets hold (the decoder's own limit).
MAX_LAYERS = 64

TRAIN_SOURCE = f"#define MAX_LAYERS {MAX_LAYERS}\n" + r"""
/* One thread's buffers: the decoder (f inputs padded to fpad, `layers` hidden widths padded to pad[l]; the
   forward weights as field_decode's, the backward's as rows: layer l [pad[l]][in_pad] at roff[l]), one
   point's input and hidden activations (layer l at aoff[l]), two gradient vectors, the non-zero list, and the
   tile's features and their gradients feature-major (feat[j * TILE + k]). */
typedef struct {
    i64 f, fpad; int layers; const i64 *pad; const float *weights, *rows;
    i64 aoff[MAX_LAYERS], roff[MAX_LAYERS];
    float *x, *acts, *g, *gi, *feat, *gfeat; int *idx;
} Step;

static Step step_open(i64 f, int layers, const i64 *pad, const float *weights, const float *rows) {
    Step s = {0};
    s.f = f; s.fpad = (f + VL - 1) / VL * VL; s.layers = layers; s.pad = pad; s.weights = weights; s.rows = rows;
    i64 widest = s.fpad, acts = 0, offset = 0;
    for (int l = 0; l < layers; ++l) {
        s.aoff[l] = acts; acts += pad[l];
        s.roff[l] = offset; offset += pad[l] * (l ? pad[l - 1] : s.fpad);
        widest = pad[l] > widest ? pad[l] : widest;
    }
    s.x = calloc((size_t)s.fpad, sizeof(float));
    s.acts = malloc(sizeof(float) * (size_t)acts);
    s.g = malloc(sizeof(float) * (size_t)widest);
    s.gi = malloc(sizeof(float) * (size_t)widest);
    s.idx = malloc(sizeof(int) * (size_t)(widest + 8));
    s.feat = malloc(sizeof(float) * (size_t)(TILE * f));
    s.gfeat = malloc(sizeof(float) * (size_t)(TILE * f));
    return s;
}

static void step_close(Step *s) {
    free(s->x); free(s->acts); free(s->g); free(s->gi); free(s->idx); free(s->feat); free(s->gfeat);
}

/* y[0..wp) = sum over the listed o of g[o] * rows[o, 0..wp) (rows of stride wp, a multiple of VL). */
static void combine_rows(const float *g, const int *idx, int nnz, const float *rows, long wp, float *y) {
    for (long ob = 0; ob < wp; ob += 8 * VL) {
        vec acc[8];
        const int nv = row_block(g, idx, nnz, rows, wp, ob, acc);
        for (int v = 0; v < nv; ++v) *(vec *)(y + ob + v * VL) = acc[v];
    }
}

/* For the nt points of the tile in s->feat: pred[k] = decoder(features), and s->gfeat the gradient of
   scale * sum_k (pred[k] - target[k])^2 / 2 with respect to the features (scale = 2 / N: the mean). */
static void train_tile(Step *s, int nt, const float *target, float scale, float *pred) {
    for (int k = 0; k < nt; ++k) {
        float *x = s->x;
        for (i64 j = 0; j < s->f; ++j) x[j] = s->feat[j * TILE + k];
        /* forward, every hidden layer kept */
        const float *in = x, *wt = s->weights;
        i64 width = s->f;
        for (int l = 0; l < s->layers; ++l) {
            float *h = s->acts + s->aoff[l];
            const int nnz = nonzero(in, (int)width, s->idx);
            hidden_layer(in, s->idx, nnz, wt, s->pad[l], h, NULL);
            wt += width * s->pad[l];
            in = h;
            width = s->pad[l];
        }
        vec total = (vec){0};  /* wt: the output weights */
        for (i64 o = 0; o < width; o += VL) total += *(const vec *)(in + o) * *(const vec *)(wt + o);
        float y = 0.0f;
        for (int l = 0; l < VL; ++l) y += total[l];
        pred[k] = y;
        const float dy = scale * (y - target[k]);
        /* backward: the output layer, then every hidden layer's rows for its active outputs */
        float *g = s->g, *gi = s->gi;
        for (i64 o = 0; o < width; ++o) g[o] = in[o] > 0.0f ? dy * wt[o] : 0.0f;
        for (int l = s->layers - 1; l >= 0; --l) {
            const i64 in_w = l ? s->pad[l - 1] : s->fpad;
            const int nnz = nonzero(g, (int)s->pad[l], s->idx);
            combine_rows(g, s->idx, nnz, s->rows + s->roff[l], in_w, gi);
            if (l) {
                const float *a = s->acts + s->aoff[l - 1];
                for (i64 j = 0; j < in_w; ++j) gi[j] = a[j] > 0.0f ? gi[j] : 0.0f;
            }
            float *swap = g; g = gi; gi = swap;
        }
        for (i64 j = 0; j < s->f; ++j) s->gfeat[j * TILE + k] = g[j];
    }
}

/* pred[i] = decoder(level-grid features(points[i])) (lg_forward's levels, field_decode's MLP), and
   grad_table (zeroed by the caller) += the gradient of mean_i (pred[i] - target[i])^2 with respect to the
   table. rows: the weights as the backward reads them (see Step). buffers: (nthreads - 1) zeroed copies of the
   gradient (size floats each), or NULL with one thread. */
void level_train(const float *points, i64 n, i64 levels, const float *maps, const int *meta, const i64 *rows_of,
                 const i64 *offsets, const float *table, i64 f, int layers, const i64 *pad, const float *weights,
                 const float *rows, const float *target, float *pred, float *grad_table, float *buffers, i64 size,
                 int nthreads) {
    const float scale = n > 0 ? 2.0f / (float)n : 0.0f;
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch sc;
        Step st = step_open(f, layers, pad, weights, rows);
        /* every level's corners of the tile, computed once for the look-ups and the scatter (NULL if the
           memory cannot be had: computed twice) */
        Corners *kept = malloc(sizeof(Corners) * (size_t)levels);
        const int th = omp_get_thread_num(), nth = omp_get_num_threads();
        float *dst = th == 0 ? grad_table : buffers + (size_t)(th - 1) * (size_t)size;
        const i64 lo = n * th / nth, hi = n * (th + 1) / nth;
        for (i64 i0 = lo; i0 < hi; i0 += TILE) {
            const int nt = (int)(hi - i0 < TILE ? hi - i0 : TILE);
            encode_tile(&sc, points, i0, nt, levels, maps, meta, rows_of, offsets, table, st.feat, 1, TILE, kept);
            train_tile(&st, nt, target + i0, scale, pred + i0);
            scatter_tile(&sc, nt, levels, maps, meta, rows_of, offsets, st.gfeat, 1, TILE, dst, kept);
        }
        free(kept);
        step_close(&st);
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
    lib.level_train.argtypes = [p, i64, i64, p, p, p, p, p, i64, i32, p, p, p, p, p, p, p, i64, i32]
    lib.level_train.restype = None
    lib.field_vector_width.argtypes = []
    lib.field_vector_width.restype = i32


LIBRARY = CompiledLibrary("field_train_cpu", LEVEL_SOURCE + LANE_LUT_SOURCE + MLP_SOURCE + TRAIN_SOURCE, _declare)


def pack_decoder_rows(weights: list[torch.Tensor], vector_width: int) -> torch.Tensor:
    """The hidden layers' weights as the kernel's backward reads them: layer ``l`` as ``[pad_l][in_l]``, its
    rows (one per output) padded with zeros to a multiple of ``vector_width`` in both directions (``in_0``: the
    encoder's features rounded up).

    Args:
        weights: ``nn.Linear`` weights in order, ``[out, in]``; hidden layers, then the ``[1, in]`` output.
        vector_width: the kernel's floats per vector.
    """
    parts = []
    for w in weights[:-1]:
        out = -(-w.shape[0] // vector_width) * vector_width
        inp = -(-w.shape[1] // vector_width) * vector_width
        block = torch.zeros(out, inp, dtype=torch.float32)
        block[: w.shape[0], : w.shape[1]] = w.detach()
        parts.append(block.reshape(-1))
    return torch.cat(parts).contiguous()


def trainable(features: int, widths: list[int]) -> bool:
    """Whether the kernel takes an encoder of ``features`` outputs and hidden layers of ``widths`` (the fused
    inference kernel's limits, at most :data:`MAX_LAYERS` layers) and builds here."""
    return len(widths) <= MAX_LAYERS and fusable(features, widths, LIBRARY)


def level_grid_mse_step_cpu(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout,
    weights: list[torch.Tensor], target: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The prediction of ``decoder(level_grid_features(points))`` and the gradient of its mean squared error to
    ``target`` with respect to ``table``, in one fused pass (float32 CPU tensors; nothing else gets a gradient).

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps.
        table: ``[T]`` flat parameters.
        layout: the levels.
        weights: the decoder's bias-free linear layers ``[out, in]``, ReLU between them, the last ``[1, in]``.
        target: ``[N]`` the values to fit.

    Returns:
        ``([N] prediction, [T] gradient of mean((prediction - target)^2))``.
    """
    lib = LIBRARY.load_or_raise()
    kernel = kernel_layout(layout)
    pts, flat_maps, tab = kernel_inputs(points, maps, table)
    n = pts.shape[0]
    goal = target.detach().to(torch.float32).reshape(-1).contiguous()
    width = lib.field_vector_width()
    packed, padded = pack_decoder(weights, width)
    rows = pack_decoder_rows(weights, width)
    prediction = torch.empty(n, dtype=torch.float32)
    size = layout.table_size
    grad = torch.zeros(size, dtype=torch.float32)
    threads = torch.get_num_threads()
    buffers = torch.zeros(threads - 1, size, dtype=torch.float32) if threads > 1 else None
    lib.level_train(
        pts.data_ptr(), n, layout.levels, flat_maps.data_ptr(), kernel.meta.data_ptr(), kernel.rows.data_ptr(),
        kernel.offsets.data_ptr(), tab.data_ptr(), layout.out_features, len(padded), padded.data_ptr(),
        packed.data_ptr(), rows.data_ptr(), goal.data_ptr(), prediction.data_ptr(), grad.data_ptr(),
        None if buffers is None else buffers.data_ptr(), size, threads,
    )
    return prediction, grad
