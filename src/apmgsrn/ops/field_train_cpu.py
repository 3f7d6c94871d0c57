"""Fused CPU reconstruction step of level-grid features and the decoder (the hybrid's training step).

One reconstruction step needs the prediction at every point and the gradients of the mean squared error with
respect to the flat table (the level tables and the adaptive grids) and, when the decoder learns (a volume's
training), to every decoder weight; under a frozen decoder (a time series' steps, their quantisation-aware
fine-tune) the table's alone. This kernel computes them in one pass over tiles of 128 points: the level
kernel's look-ups (``encode_tile`` of :data:`apmgsrn.ops.level_grids_cpu.C_SOURCE`); the decoder's layers as
small matrix products of the tile's ``[128, width]`` block with the layer's weights, register-blocked, their
ReLU taken as the sums are stored (every block stays in the core's caches: no ``[N, width]`` activation goes to
memory and no autograd graph is built); the error's gradient back through them (masked by the kept
activations); the weights' gradients as the tile's sums of outer products ``G_l^T A_(l-1)``, added to a
per-thread float32 sum; and the level kernel's trilinear scatter of the features' gradients into the table
(``scatter_tile``), on the corners the look-ups found (every level's corners of the tile are kept, 8 KB a
level, instead of computed again). On the default model's batch of 32,768 points it replaces the level
kernel's forward and backward, the decoder's nine matrix products, two ReLUs and their backward, and the
autograd graph between them (docs/benchmarks.md, "The default model's training step").

Where the CPU has AMX (:mod:`apmgsrn.ops.tile_products_cpu`) and every width is a multiple of its depth (the
default model's are), the layers' forward products, the backward's products with the weights and the weights'
gradients run on the tile unit in bfloat16 halves that keep 16 bits of every factor: 11 % less time for the
whole kernel on the default model (32,768 points, 1 and 2 threads; docs/benchmarks_train_step.md). Its
prediction matches float32 to about 1e-5 of its scale; a hidden activation within about 1e-5 of zero can take
the other side of its ReLU, and that point's gradient then takes or skips the unit, so gradients can differ
from the vector unit's by a few 1e-3 of their largest entry where a trained model has such activations (the
fits do not: tests/test_ops_tile_products_cpu.py). ``tile_unit=False`` keeps the vector unit.

Each extra thread scatters into a private copy of the table's gradient and sums its own weights' gradients,
added at the end in thread order, so the sums' rounding depends on the thread count (not on the run). The
references are :func:`apmgsrn.ops.level_grids.level_grid_train_step_reference` and
:func:`apmgsrn.ops.level_grids.level_grid_mse_step_reference`; tests compare them in prediction and gradients.
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
from apmgsrn.ops.tile_products_cpu import AMX_SOURCE, TILE_DEPTH, pair_layout

#: Most hidden layers the kernel's per-thread offsets hold (the decoder's own limit).
MAX_LAYERS = 64
#: Most hidden units in all (the padded widths' sum) the kernel takes: a thread keeps two tile-wide arrays of
#: them (activations and gradients, 8 MB at this bound); wider decoders train through autograd.
MAX_HIDDEN_UNITS = 8192

TRAIN_SOURCE = f"#define MAX_LAYERS {MAX_LAYERS}\n" + r"""
/* One thread's buffers, every tile-wide array point-major ([TILE][width]): the decoder (f inputs padded to
   fpad, `layers` hidden widths padded to pad[l]; the forward weights as field_decode's, the backward's as
   rows: layer l [pad[l]][in_pad] at roff[l]); the tile's inputs (x: [TILE][fpad], its padding 0), hidden
   activations (layer l [TILE][pad[l]] at TILE * aoff[l]), the gradients of those layers' inputs to ReLU (tg,
   laid out as the activations), of the outputs (dy) and of the inputs (gx); the tile's features and their
   gradients feature-major (feat[j * TILE + k]), as the level kernel reads and writes them; and, when the
   decoder learns, the thread's sum of the weights' gradients gw (the hidden layers as `rows`, then the
   output weights at out_off; NULL when the decoder is frozen). */
typedef struct {
    i64 f, fpad; int layers; const i64 *pad; const float *weights, *rows;
    i64 aoff[MAX_LAYERS], roff[MAX_LAYERS], out_off;
    float *x, *acts, *tg, *dy, *gx, *feat, *gfeat, *gw;
#ifdef HAVE_AMX
    /* With the tile unit (amx != NULL): the weights' bfloat16 halves in pair layout, layer l's forward factor
       W_l^T at amx + foff[l] and its backward factor W_l at amx + boff[l] (hi, then lo, each [in][out]
       numbers), the split rows of a product's left factor (hi, lo: [TILE][widest]), a right factor's halves in
       pair layout (pair_hi, pair_lo: as many) and a layer's gradient transposed (gt: [widest][TILE]). */
    const bf16 *amx; i64 foff[MAX_LAYERS], boff[MAX_LAYERS]; bf16 *hi, *lo, *pair_hi, *pair_lo; float *gt;
#endif
} Step;

/* Opens a thread's buffers (learning: with the decoder's gradient); returns 0, or -1 when memory could not
   be had (step_close still frees what was). */
static int step_open(Step *s, i64 f, int layers, const i64 *pad, const float *weights, const float *rows,
                     const void *amx, int learning) {
    memset(s, 0, sizeof *s);
    s->f = f; s->fpad = (f + VL - 1) / VL * VL; s->layers = layers; s->pad = pad; s->weights = weights;
    s->rows = rows;
    i64 acts = 0, offset = 0;
    for (int l = 0; l < layers; ++l) {
        s->aoff[l] = acts; acts += pad[l];
        s->roff[l] = offset; offset += pad[l] * (l ? pad[l - 1] : s->fpad);
    }
    s->out_off = offset;
    s->x = calloc((size_t)(TILE * s->fpad), sizeof(float));  /* the padding stays 0 */
    s->acts = malloc(sizeof(float) * (size_t)(TILE * acts));
    s->tg = malloc(sizeof(float) * (size_t)(TILE * acts));
    s->dy = malloc(sizeof(float) * TILE);
    s->gx = malloc(sizeof(float) * (size_t)(TILE * s->fpad));
    s->feat = malloc(sizeof(float) * (size_t)(TILE * f));
    s->gfeat = malloc(sizeof(float) * (size_t)(TILE * f));
    int ok = s->x && s->acts && s->tg && s->dy && s->gx && s->feat && s->gfeat;
#ifdef HAVE_AMX
    if (amx && amx_ready()) {
        i64 widest = s->fpad, forward = 0;
        for (int l = 0; l < layers; ++l) {
            const i64 in = l ? pad[l - 1] : s->fpad;
            widest = pad[l] > widest ? pad[l] : widest;
            s->foff[l] = forward; forward += 2 * in * pad[l];
        }
        for (int l = 0; l < layers; ++l) s->boff[l] = forward + s->foff[l];
        s->amx = amx;
        s->hi = malloc(sizeof(bf16) * (size_t)(TILE * widest));
        s->lo = malloc(sizeof(bf16) * (size_t)(TILE * widest));
        s->pair_hi = malloc(sizeof(bf16) * (size_t)(TILE * widest));
        s->pair_lo = malloc(sizeof(bf16) * (size_t)(TILE * widest));
        s->gt = malloc(sizeof(float) * (size_t)(TILE * widest));
        ok = ok && s->hi && s->lo && s->pair_hi && s->pair_lo && s->gt;
    }
#else
    (void)amx;
#endif
    if (learning) {
        s->gw = calloc((size_t)(offset + pad[layers - 1]), sizeof(float));
        ok = ok && s->gw;
    }
    return ok ? 0 : -1;
}

/* Size in floats of a decoder's weight gradient as gw holds it. */
static i64 step_weight_floats(const Step *s) { return s->out_off + s->pad[s->layers - 1]; }

static void step_close(Step *s) {
    free(s->x); free(s->acts); free(s->tg); free(s->dy); free(s->gx); free(s->feat); free(s->gfeat);
    free(s->gw);
#ifdef HAVE_AMX
    free(s->hi); free(s->lo); free(s->pair_hi); free(s->pair_lo); free(s->gt);
#endif
}

/* Rows of a product's register block: with 32 vector registers (AVX-512) 4 rows of 4 vectors, else 2. */
#if VL == 16
#define BLOCK_ROWS 6
#else
#define BLOCK_ROWS 2
#endif

enum { PUT, ADD, RELU, MASK };  /* what a product block does with its sums */

/* One register block of a small matrix product: for the R rows r and the nv vectors of columns,
   sum_q g[q * gq + r * gr] * b[q * bs + (columns)] over q < K, then c (row stride cs) gets it as `mode`
   says: PUT stores it, ADD adds it, RELU stores relu(sum), MASK stores it where mask (stride cs) > 0, else 0.
   The strides let one kernel take a row-major left factor (gq = 1, gr = its row stride) or a transposed one
   (gq = its row stride, gr = 1). */
static inline __attribute__((always_inline)) void product_block(
        const float *g, i64 gq, i64 gr, const float *b, i64 bs, i64 K, const int R, const int nv, float *c,
        i64 cs, const int mode, const float *mask) {
    vec acc[BLOCK_ROWS][4];
    for (int r = 0; r < R; ++r)
        for (int v = 0; v < nv; ++v) acc[r][v] = (vec){0};
    for (i64 q = 0; q < K; ++q) {
        vec bv[4];
        for (int v = 0; v < nv; ++v) bv[v] = *(const vec *)(b + q * bs + v * VL);
        for (int r = 0; r < R; ++r) {
            const vec gv = (vec){0} + g[q * gq + r * gr];
            for (int v = 0; v < nv; ++v) acc[r][v] += gv * bv[v];
        }
    }
    for (int r = 0; r < R; ++r)
        for (int v = 0; v < nv; ++v) {
            vec *out = (vec *)(c + r * cs + v * VL);
            if (mode == PUT) *out = acc[r][v];
            else if (mode == ADD) *out += acc[r][v];
            else if (mode == RELU) *out = relu(acc[r][v]);
            else *out = (vec)((veci)acc[r][v] & (veci)(*(const vec *)(mask + r * cs + v * VL) > (vec){0}));
        }
}

/* product_block over column blocks of up to 4 vectors (cols a multiple of VL) for R rows. */
static inline __attribute__((always_inline)) void product_rows(
        const float *g, i64 gq, i64 gr, const float *b, i64 bs, i64 K, const int R, i64 cols, float *c, i64 cs,
        const int mode, const float *mask) {
    for (i64 cb = 0; cb < cols; cb += 4 * VL) {
        const int nv = (int)((cols - cb) / VL < 4 ? (cols - cb) / VL : 4);
        const float *m = mask ? mask + cb : NULL;
        switch (nv) {  /* constant vector counts, so the sums live in registers */
            case 4: product_block(g, gq, gr, b + cb, bs, K, R, 4, c + cb, cs, mode, m); break;
            case 3: product_block(g, gq, gr, b + cb, bs, K, R, 3, c + cb, cs, mode, m); break;
            case 2: product_block(g, gq, gr, b + cb, bs, K, R, 2, c + cb, cs, mode, m); break;
            default: product_block(g, gq, gr, b + cb, bs, K, R, 1, c + cb, cs, mode, m); break;
        }
    }
}

/* c[rows][cols] (mode) sum_q g[q * gq + r * gr] b[q][cols] for every row r, BLOCK_ROWS at a time. */
static inline __attribute__((always_inline)) void product(
        const float *g, i64 gq, i64 gr, const float *b, i64 bs, i64 K, i64 rows, i64 cols, float *c, i64 cs,
        const int mode, const float *mask) {
    i64 r = 0;
    for (; r + BLOCK_ROWS <= rows; r += BLOCK_ROWS)
        product_rows(g + r * gr, gq, gr, b, bs, K, BLOCK_ROWS, cols, c + r * cs, cs, mode,
                     mask ? mask + r * cs : NULL);
    for (; r + 2 <= rows; r += 2)
        product_rows(g + r * gr, gq, gr, b, bs, K, 2, cols, c + r * cs, cs, mode, mask ? mask + r * cs : NULL);
    for (; r < rows; ++r)
        product_rows(g + r * gr, gq, gr, b, bs, K, 1, cols, c + r * cs, cs, mode, mask ? mask + r * cs : NULL);
}

/* For the nt points of the tile in s->feat: pred[k] = decoder(features), and s->gfeat the gradient of
   scale * sum_k (pred[k] - target[k])^2 / 2 with respect to the features (scale = 2 / N: the mean); with
   s->gw, the gradient with respect to the decoder's weights added there. Every layer, forward and backward,
   is a product of the tile's [nt][width] block with the layer's weights, in cache; the weights' gradients are
   the tile's sums of outer products G_l^T A_(l-1). */
static void train_tile(Step *s, int nt, const float *target, float scale, float *pred) {
    const int last = s->layers - 1;
    const i64 fpad = s->fpad, plast = s->pad[last];
    for (int k = 0; k < nt; ++k)
        for (i64 j = 0; j < s->f; ++j) s->x[k * fpad + j] = s->feat[j * TILE + k];
#ifdef HAVE_AMX
    /* the tile unit's rows: a multiple of its depth, those past nt zero so that they add nothing to a sum over
       the points (the weights' gradients) */
    const i64 rows = (nt + 31) / 32 * 32;
    if (s->amx) memset(s->x + nt * fpad, 0, sizeof(float) * (size_t)((rows - nt) * fpad));
#endif
    /* forward: H_l = relu(A_(l-1) W_l^T), every layer kept */
    const float *in = s->x, *wt = s->weights;
    i64 stride = fpad, width = s->f;
    for (int l = 0; l < s->layers; ++l) {
        float *h = s->acts + TILE * s->aoff[l];
#ifdef HAVE_AMX
        if (s->amx) {
            const bf16 *wh = s->amx + s->foff[l];
            amx_split(in, rows * stride, s->hi, s->lo);
            amx_product(s->hi, s->lo, stride, wh, wh + stride * s->pad[l], rows, s->pad[l], stride, h, s->pad[l], 0);
            for (i64 e = 0; e < rows * s->pad[l]; e += VL) *(vec *)(h + e) = relu(*(const vec *)(h + e));
        } else
#endif
        product(in, 1, stride, wt, s->pad[l], width, nt, s->pad[l], h, s->pad[l], RELU, NULL);
        wt += width * s->pad[l];
        in = h;
        stride = width = s->pad[l];
    }
    const float *hl = s->acts + TILE * s->aoff[last];  /* wt: the output weights */
    float *gl = s->tg + TILE * s->aoff[last];
    for (int k = 0; k < nt; ++k) {
        vec total = (vec){0};
        for (i64 o = 0; o < plast; o += VL) total += *(const vec *)(hl + k * plast + o) * *(const vec *)(wt + o);
        float y = 0.0f;
        for (int l = 0; l < VL; ++l) y += total[l];
        pred[k] = y;
        const float dy = scale * (y - target[k]);
        s->dy[k] = dy;
        /* backward through the output layer and the last ReLU */
        for (i64 o = 0; o < plast; o += VL) {
            const vec h = *(const vec *)(hl + k * plast + o);
            *(vec *)(gl + k * plast + o) = (vec)((veci)(dy * *(const vec *)(wt + o)) & (veci)(h > (vec){0}));
        }
    }
    /* backward: G_(l-1) = (G_l W_l) masked by ReLU, then the inputs' gradient G_0 W_0 */
#ifdef HAVE_AMX
    if (s->amx) {
        for (int k = nt; k < rows; ++k)
            for (i64 o = 0; o < plast; ++o) gl[k * plast + o] = 0.0f;
        for (int l = last; l >= 0; --l) {
            const i64 pl = s->pad[l], pin = l ? s->pad[l - 1] : fpad;
            const bf16 *wh = s->amx + s->boff[l];
            float *g = l ? s->tg + TILE * s->aoff[l - 1] : s->gx;
            amx_split(s->tg + TILE * s->aoff[l], rows * pl, s->hi, s->lo);
            amx_product(s->hi, s->lo, pl, wh, wh + pl * pin, rows, pin, pl, g, pin, 0);
            if (!l) break;
            const float *a = s->acts + TILE * s->aoff[l - 1];
            for (i64 e = 0; e < rows * pin; e += VL)
                *(vec *)(g + e) = (vec)((veci)*(const vec *)(g + e) & (veci)(*(const vec *)(a + e) > (vec){0}));
        }
    } else
#endif
    {
        for (int l = last; l >= 1; --l) {
            const i64 pl = s->pad[l], pin = s->pad[l - 1];
            product(s->tg + TILE * s->aoff[l], 1, pl, s->rows + s->roff[l], pin, pl, nt, pin,
                    s->tg + TILE * s->aoff[l - 1], pin, MASK, s->acts + TILE * s->aoff[l - 1]);
        }
        product(s->tg, 1, s->pad[0], s->rows, fpad, s->pad[0], nt, fpad, s->gx, fpad, PUT, NULL);
    }
    for (int k = 0; k < nt; ++k)
        for (i64 j = 0; j < s->f; ++j) s->gfeat[j * TILE + k] = s->gx[k * fpad + j];
    if (!s->gw) return;
    for (int l = 0; l < s->layers; ++l) {  /* dW_l += G_l^T A_(l-1) over the tile */
        const float *a = l ? s->acts + TILE * s->aoff[l - 1] : s->x;
        const i64 pl = s->pad[l], cols = l ? s->pad[l - 1] : fpad;
#ifdef HAVE_AMX
        if (s->amx) {  /* the points are the sum's index: G_l transposed, A_(l-1) in pair layout */
            const float *g = s->tg + TILE * s->aoff[l];
            amx_split(a, rows * cols, s->hi, s->lo);
            amx_pair_rows(s->hi, rows, cols, s->pair_hi);
            amx_pair_rows(s->lo, rows, cols, s->pair_lo);
            for (i64 p0 = 0; p0 < rows; p0 += 16)
                for (i64 u0 = 0; u0 < pl; u0 += 16) transpose16(g + p0 * pl + u0, pl, s->gt + u0 * rows + p0, rows);
            amx_split(s->gt, pl * rows, s->hi, s->lo);
            amx_product(s->hi, s->lo, rows, s->pair_hi, s->pair_lo, pl, cols, rows, s->gw + s->roff[l], cols, 1);
            continue;
        }
#endif
        product(s->tg + TILE * s->aoff[l], pl, 1, a, cols, nt, pl, cols, s->gw + s->roff[l], cols, ADD, NULL);
    }
    float *go = s->gw + s->out_off;  /* d loss / d w_out += sum_k dy[k] H_last[k] */
    for (i64 o = 0; o < plast; o += VL) {
        vec acc = (vec){0};
        for (int k = 0; k < nt; ++k) acc += s->dy[k] * *(const vec *)(hl + k * plast + o);
        *(vec *)(go + o) += acc;
    }
}

/* pred[i] = decoder(level-grid features(points[i])) (lg_forward's levels, field_decode's MLP), and
   grad_table (zeroed by the caller) += the gradient of mean_i (pred[i] - target[i])^2 with respect to the
   table. rows: the weights as the backward reads them (see Step). buffers: (nthreads - 1) zeroed copies of the
   gradient (size floats each), or NULL with one thread. grad_weights: NULL (a frozen decoder), or where the
   gradient with respect to the decoder's weights goes, laid out as Step's gw (written, not added to): each
   thread sums its points' in float32, and the threads' sums are added in thread order. Returns 0, or -1 when
   a thread could not have its buffers (nothing is then valid). */
int level_train(const float *points, i64 n, i64 levels, const float *maps, const int *meta, const i64 *rows_of,
                const i64 *offsets, const float *table, i64 f, int layers, const i64 *pad, const float *weights,
                const float *rows, const void *amx, const float *target, float *pred, float *grad_table,
                float *buffers, i64 size, float *grad_weights, int nthreads) {
    const float scale = n > 0 ? 2.0f / (float)n : 0.0f;
    float **parts = grad_weights ? calloc((size_t)nthreads, sizeof(float *)) : NULL;
    int failed = grad_weights && !parts;
    if (failed) return -1;
    #pragma omp parallel num_threads(nthreads)
    {
        Scratch sc;
        Step st;
        const int opened = step_open(&st, f, layers, pad, weights, rows, amx, grad_weights != NULL);
#ifdef HAVE_AMX
        if (st.amx) amx_configure();
#endif
        const i64 wsize = step_weight_floats(&st);
        if (grad_weights) parts[omp_get_thread_num()] = st.gw;
        if (opened != 0) {
            #pragma omp atomic write
            failed = 1;
        }
        /* every level's corners of the tile, computed once for the look-ups and the scatter (NULL if the
           memory cannot be had: computed twice) */
        Corners *kept = malloc(sizeof(Corners) * (size_t)levels);
        const int th = omp_get_thread_num(), nth = omp_get_num_threads();
        float *dst = th == 0 ? grad_table : buffers + (size_t)(th - 1) * (size_t)size;
        const i64 lo = n * th / nth, hi = n * (th + 1) / nth;
        #pragma omp barrier
        if (!failed) {
            for (i64 i0 = lo; i0 < hi; i0 += TILE) {
                const int nt = (int)(hi - i0 < TILE ? hi - i0 : TILE);
                encode_tile(&sc, points, i0, nt, levels, maps, meta, rows_of, offsets, table, st.feat, 1, TILE, kept);
                train_tile(&st, nt, target + i0, scale, pred + i0);
                scatter_tile(&sc, nt, levels, maps, meta, rows_of, offsets, st.gfeat, 1, TILE, dst, kept);
            }
        }
        free(kept);
        #pragma omp barrier
        if (!failed) {
            for (int b = 0; b < nth - 1; ++b) {
                const float *src = buffers + (size_t)b * (size_t)size;
                #pragma omp for schedule(static)
                for (i64 e = 0; e < size; ++e) grad_table[e] += src[e];
            }
            if (grad_weights) {
                #pragma omp for schedule(static)
                for (i64 e = 0; e < wsize; ++e) {
                    float total = parts[0][e];
                    for (int t = 1; t < nth; ++t) total += parts[t][e];
                    grad_weights[e] = total;
                }
            }
        }
        #pragma omp barrier
#ifdef HAVE_AMX
        if (st.amx) _tile_release();
#endif
        step_close(&st);  /* frees gw, which the sum above read */
    }
    free(parts);
    return failed ? -1 : 0;
}
"""


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.level_train.argtypes = [p, i64, i64, p, p, p, p, p, i64, i32, p, p, p, p, p, p, p, p, i64, p, i32]
    lib.level_train.restype = i32
    lib.field_vector_width.argtypes = []
    lib.field_vector_width.restype = i32
    lib.amx_ready.argtypes = []
    lib.amx_ready.restype = i32


LIBRARY = CompiledLibrary("field_train_cpu", LEVEL_SOURCE + LANE_LUT_SOURCE + MLP_SOURCE + AMX_SOURCE + TRAIN_SOURCE,
                          _declare)


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
    inference kernel's limits, at most :data:`MAX_LAYERS` layers of :data:`MAX_HIDDEN_UNITS` units in all)
    and builds here."""
    return len(widths) <= MAX_LAYERS and sum(widths) <= MAX_HIDDEN_UNITS and fusable(features, widths, LIBRARY)


def unpack_weight_grads(flat: torch.Tensor, weights: list[torch.Tensor], vector_width: int) -> list[torch.Tensor]:
    """The kernel's decoder-weight gradient (laid out as :func:`pack_decoder_rows`, then the padded output
    weights) as one tensor per weight, each shaped as it."""
    grads, start = [], 0
    for w in weights[:-1]:
        out = -(-w.shape[0] // vector_width) * vector_width
        inp = -(-w.shape[1] // vector_width) * vector_width
        block = flat[start : start + out * inp].view(out, inp)
        grads.append(block[: w.shape[0], : w.shape[1]].contiguous())
        start += out * inp
    grads.append(flat[start : start + weights[-1].shape[1]].view_as(weights[-1]).clone())
    return grads


def tile_unit_factors(weights: list[torch.Tensor], features: int, padded: list[int]) -> torch.Tensor:
    """The hidden layers' weights as the tile unit's products read them (:mod:`apmgsrn.ops.tile_products_cpu`):
    every layer's forward factor ``W_l^T`` (``[in, out]``, the encoder's features padded to ``features``), then
    every layer's backward factor ``W_l`` (``[out, in]``), each padded with zeros and given as its two bfloat16
    halves in pair layout (hi, then lo), flat int16."""
    forward, backward = [], []
    inputs = features
    for w, out in zip(weights[:-1], padded):
        block = torch.zeros(out, inputs, dtype=torch.float32)
        block[: w.shape[0], : w.shape[1]] = w.detach()
        forward.extend(half.reshape(-1) for half in pair_layout(block.t().contiguous()))
        backward.extend(half.reshape(-1) for half in pair_layout(block))
        inputs = out
    return torch.cat(forward + backward).contiguous()


def tile_unit_takes(features: int, padded: list[int], lib) -> bool:
    """Whether the fused step's products run on the tile unit: it is there (built for, and granted by Linux)
    and every product's inner width (the padded features, every hidden layer) is a multiple of its depth."""
    return bool(lib.amx_ready()) and all(width % TILE_DEPTH == 0 for width in (features, *padded))


def level_grid_train_step_cpu(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout,
    weights: list[torch.Tensor], target: torch.Tensor, decoder_learns: bool = True, tile_unit: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor] | None]:
    """The prediction of ``decoder(level_grid_features(points))`` and the gradients of its mean squared error
    to ``target`` with respect to ``table`` and, when ``decoder_learns``, every decoder weight, in one fused
    pass (float32 CPU tensors; the points and maps are constants).

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps.
        table: ``[T]`` flat parameters.
        layout: the levels.
        weights: the decoder's bias-free linear layers ``[out, in]``, ReLU between them, the last ``[1, in]``.
        target: ``[N]`` the values to fit.
        decoder_learns: whether to compute the weights' gradients.
        tile_unit: run the decoder's forward and backward products on AMX where the CPU has it
            (:func:`tile_unit_takes`); False: on the vector unit in float32.

    Returns:
        ``([N] prediction, [T] table gradient, the weights' gradients shaped as them or None)``.

    Raises:
        MemoryError: the kernel's per-thread buffers could not be had.
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
    flat_w = torch.empty(rows.numel() + int(padded[-1]), dtype=torch.float32) if decoder_learns else None
    features = -(-layout.out_features // width) * width
    factors = None
    if tile_unit and tile_unit_takes(features, padded.tolist(), lib):
        factors = tile_unit_factors(weights, features, padded.tolist())
    status = lib.level_train(
        pts.data_ptr(), n, layout.levels, flat_maps.data_ptr(), kernel.meta.data_ptr(), kernel.rows.data_ptr(),
        kernel.offsets.data_ptr(), tab.data_ptr(), layout.out_features, len(padded), padded.data_ptr(),
        packed.data_ptr(), rows.data_ptr(), None if factors is None else factors.data_ptr(), goal.data_ptr(),
        prediction.data_ptr(), grad.data_ptr(),
        None if buffers is None else buffers.data_ptr(), size, None if flat_w is None else flat_w.data_ptr(), threads,
    )
    if status != 0:
        raise MemoryError("the fused training step could not allocate its per-thread buffers")
    return prediction, grad, None if flat_w is None else unpack_weight_grads(flat_w, weights, width)


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
    prediction, grad, _ = level_grid_train_step_cpu(points, maps, table, layout, weights, target, False)
    return prediction, grad
