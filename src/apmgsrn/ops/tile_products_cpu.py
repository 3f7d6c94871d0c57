"""Small matrix products on x86's AMX tile unit, in bfloat16 pieces that keep float32's accuracy.

The fused training step (:mod:`apmgsrn.ops.field_train_cpu`) multiplies each tile of 128 points' activations
by the decoder's weights, forward and backward. Where the CPU has AMX (Intel Xeon from Sapphire Rapids on)
those products can run on its tile unit, which multiplies bfloat16 matrices many times as fast as the
vector unit multiplies float32 ones (the default decoder's products in a step: about 1 ms against 8, one thread). bfloat16 alone keeps 8 bits of a float's 24 and would cost the fit
accuracy, so each float32 factor is split into two bfloat16 numbers, ``x = hi + lo`` (``hi`` the rounded
value, ``lo`` the rounded remainder: 16 bits in all), and a product is the sum of three tile products,
``hi*hi + hi*lo + lo*hi`` (the ``lo*lo`` term is below float32 rounding of a 16-bit product), added in float32.
The result agrees with float32 to about 1e-5 relative: the size of float32 rounding across a 64-term sum of
the decoder's layers (tests compare it with the reference in forward and backward).

:data:`AMX_SOURCE` is C that a kernel includes: ``amx_ready()`` asks Linux for the tile unit (once per
process; 0 where the CPU, the compiler or the kernel says no), ``amx_split`` makes the two halves of float32
rows, and ``amx_product`` computes ``C = A B`` for an ``A`` of split rows and a ``B`` in the tile unit's pair
layout (:func:`pair_layout`). Built only where the compiler targets AMX (``-march=native`` on such a CPU);
elsewhere the kernel's products stay on the vector unit.
"""

from __future__ import annotations

import torch

#: Rows and bfloat16 columns of an AMX tile: a product's inner dimension must be a multiple of this.
TILE_DEPTH = 32

AMX_SOURCE = r"""
#if defined(__AMX_TILE__) && defined(__AMX_BF16__) && defined(__AVX512BF16__) && defined(__AVX512BW__)
#define HAVE_AMX 1
#include <immintrin.h>
#include <stdint.h>
#include <unistd.h>
#include <sys/syscall.h>

typedef uint16_t bf16;

/* 1 when this process may use the tile unit (asked of Linux once: the tile data state is opt-in). */
int amx_ready(void) {
    static int state = -1;
    if (state < 0) state = syscall(SYS_arch_prctl, 0x1023 /* ARCH_REQ_XCOMP_PERM */, 18 /* XTILEDATA */) == 0;
    return state;
}

/* Every tile 16 rows of 64 bytes (palette 1); each thread that runs products loads it once. */
static void amx_configure(void) {
    struct { uint8_t palette, start; uint8_t reserved[14]; uint16_t colsb[16]; uint8_t rows[16]; } cfg;
    memset(&cfg, 0, sizeof cfg);
    cfg.palette = 1;
    for (int t = 0; t < 8; ++t) { cfg.colsb[t] = 64; cfg.rows[t] = 16; }
    _tile_loadconfig(&cfg);
}

/* hi[i] + lo[i] = x[i] to 16 bits: hi the nearest bfloat16, lo the remainder's; n a multiple of 16. */
static inline void amx_split(const float *x, i64 n, bf16 *hi, bf16 *lo) {
    for (i64 i = 0; i < n; i += 16) {
        const __m512 v = _mm512_loadu_ps(x + i);
        const __m256i h = (__m256i)_mm512_cvtneps_pbh(v);
        const __m512 back = _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(h), 16));
        _mm256_storeu_si256((__m256i *)(hi + i), h);
        _mm256_storeu_si256((__m256i *)(lo + i), (__m256i)_mm512_cvtneps_pbh(_mm512_sub_ps(v, back)));
    }
}

/* Tile J (0..3) += A B for the loaded A halves (tiles 4, 5) and B's pair rows at b (tiles 6, 7). */
#define AMX_TERM(J) do { \
        _tile_loadd(6, bh + boff + (J) * 32, bstride); \
        _tile_loadd(7, bl + boff + (J) * 32, bstride); \
        _tile_dpbf16ps(J, 4, 6); _tile_dpbf16ps(J, 5, 6); _tile_dpbf16ps(J, 4, 7); \
    } while (0)
#define AMX_EACH(MACRO) do { MACRO(0); if (nc > 1) MACRO(1); if (nc > 2) MACRO(2); if (nc > 3) MACRO(3); } while (0)
#define AMX_ZERO(J) _tile_zero(J)
#define AMX_STORE(J) _tile_stored(J, c + m0 * ldc + n0 + (J) * 16, ldc * 4)

#define AMX_LOAD(J) _tile_loadd(J, c + m0 * ldc + n0 + (J) * 16, ldc * 4)

/* c[M][N] (row stride ldc floats) = A B, or += with accumulate: A [M][K] as halves ah, al (row stride lda),
   B [K][N] as halves bh, bl in pair layout ([K / 2][2 N]: row p holds B[2p][n], B[2p + 1][n] side by side for
   every n). M and N multiples of 16, K of 32. */
static void amx_product(const bf16 *ah, const bf16 *al, i64 lda, const bf16 *bh, const bf16 *bl, i64 M, i64 N,
                        i64 K, float *c, i64 ldc, int accumulate) {
    const i64 bstride = 4 * N;  /* bytes of a pair row */
    for (i64 m0 = 0; m0 < M; m0 += 16)
        for (i64 n0 = 0; n0 < N; n0 += 64) {
            const int nc = (int)((N - n0) / 16 < 4 ? (N - n0) / 16 : 4);
            if (accumulate) AMX_EACH(AMX_LOAD);
            else AMX_EACH(AMX_ZERO);
            for (i64 k0 = 0; k0 < K; k0 += 32) {
                _tile_loadd(4, ah + m0 * lda + k0, lda * 2);
                _tile_loadd(5, al + m0 * lda + k0, lda * 2);
                const i64 boff = (k0 / 2) * 2 * N + 2 * n0;
                AMX_EACH(AMX_TERM);
            }
            AMX_EACH(AMX_STORE);
        }
}

/* dst[j][i] = src[i][j] for a 16 x 16 block of floats (row strides ss and ds). */
static inline void transpose16(const float *src, i64 ss, float *dst, i64 ds) {
    __m512 r[16], t[16];
    for (int i = 0; i < 16; ++i) r[i] = _mm512_loadu_ps(src + i * ss);
    for (int i = 0; i < 16; i += 2) {  /* pairs of rows, 32-bit interleave inside each 128-bit lane */
        t[i] = _mm512_unpacklo_ps(r[i], r[i + 1]);
        t[i + 1] = _mm512_unpackhi_ps(r[i], r[i + 1]);
    }
    for (int i = 0; i < 16; i += 4) {  /* fours of rows: lane L of r[i + j] holds rows i..i+3 of column 4L + j */
        r[i] = _mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(t[i]), _mm512_castps_pd(t[i + 2])));
        r[i + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(t[i]), _mm512_castps_pd(t[i + 2])));
        r[i + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(t[i + 1]), _mm512_castps_pd(t[i + 3])));
        r[i + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(t[i + 1]), _mm512_castps_pd(t[i + 3])));
    }
    for (int j = 0; j < 4; ++j) {  /* gather lane L of the four fours into column 4L + j */
        const __m512 v0 = _mm512_shuffle_f32x4(r[j], r[4 + j], 0x88), v1 = _mm512_shuffle_f32x4(r[j], r[4 + j], 0xDD);
        const __m512 w0 = _mm512_shuffle_f32x4(r[8 + j], r[12 + j], 0x88);
        const __m512 w1 = _mm512_shuffle_f32x4(r[8 + j], r[12 + j], 0xDD);
        _mm512_storeu_ps(dst + j * ds, _mm512_shuffle_f32x4(v0, w0, 0x88));
        _mm512_storeu_ps(dst + (8 + j) * ds, _mm512_shuffle_f32x4(v0, w0, 0xDD));
        _mm512_storeu_ps(dst + (4 + j) * ds, _mm512_shuffle_f32x4(v1, w1, 0x88));
        _mm512_storeu_ps(dst + (12 + j) * ds, _mm512_shuffle_f32x4(v1, w1, 0xDD));
    }
}

/* The rows [M][N] of bfloat16 x (M even, N a multiple of 32) in pair layout [M / 2][2 N]. */
static inline void amx_pair_rows(const bf16 *x, i64 M, i64 N, bf16 *out) {
    __m512i low = _mm512_setzero_si512(), high = _mm512_setzero_si512();
    uint16_t lo_idx[32], hi_idx[32];
    for (int i = 0; i < 16; ++i) {
        lo_idx[2 * i] = (uint16_t)i; lo_idx[2 * i + 1] = (uint16_t)(32 + i);
        hi_idx[2 * i] = (uint16_t)(16 + i); hi_idx[2 * i + 1] = (uint16_t)(48 + i);
    }
    low = _mm512_loadu_si512(lo_idx); high = _mm512_loadu_si512(hi_idx);
    for (i64 p = 0; p < M / 2; ++p)
        for (i64 c = 0; c < N; c += 32) {
            const __m512i a = _mm512_loadu_si512(x + 2 * p * N + c), b = _mm512_loadu_si512(x + (2 * p + 1) * N + c);
            _mm512_storeu_si512(out + p * 2 * N + 2 * c, _mm512_permutex2var_epi16(a, low, b));
            _mm512_storeu_si512(out + p * 2 * N + 2 * c + 32, _mm512_permutex2var_epi16(a, high, b));
        }
}
#else
int amx_ready(void) { return 0; }
#endif
"""


def pair_layout(matrix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A float32 matrix ``[K, N]`` (``K`` even) as the tile unit reads a right factor: its bfloat16 halves
    (``hi``, the nearest bfloat16, and ``lo``, the remainder's), each ``[K / 2, 2 N]`` int16 holding rows
    ``2p`` and ``2p + 1`` interleaved (element ``[p, 2 n + b]`` is ``matrix[2 p + b, n]``)."""
    matrix = matrix.to(torch.float32)
    hi = matrix.to(torch.bfloat16)
    lo = (matrix - hi.to(torch.float32)).to(torch.bfloat16)
    k, n = matrix.shape

    def paired(half: torch.Tensor) -> torch.Tensor:
        return half.view(torch.int16).reshape(k // 2, 2, n).transpose(1, 2).reshape(k // 2, 2 * n)

    return paired(hi), paired(lo)
