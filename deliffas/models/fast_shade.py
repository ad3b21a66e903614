"""Inference-only shading of many rays: sampling and encoding fused into the MLP's GEMM operands, in fp32 or bf16.

:class:`FastShader` computes what ``DeliffasModel.shade`` computes, outside autograd on CPU:

* one C pass per ray (``deliffas/native.py``) writes the positional encodings of the ray's uvs and
  the bilinearly sampled features (``sample_uv``'s convention: texel centres, border clamp) from
  the channels_last feature maps straight into two row-major GEMM operands, in the MLP's dtype.
  The encodings take one sin/cos per coordinate and the double-angle recurrence in float64 for
  the higher frequencies (the same float32 arguments ``positional_encoding`` rounds to, within
  1e-7 of its values);
* the MLP runs as a chain of ``torch.addmm`` into reused row-chunk buffers; the layer after the
  feature concatenation is split into its feature and hidden columns (two products summed), so
  nothing is concatenated.

``dtype=torch.bfloat16`` keeps bf16 copies of the weights (refreshed when a parameter changes) and
runs every product in bf16 with fp32 output (colours in fp32). Use it where the CPU has native
bf16 (:func:`native_bf16`); elsewhere bf16 is several times slower than fp32.

:meth:`FastShader.shade_fused` does all of it in one C pass instead (a tile of rays in the vector lanes: 16
with AVX-512, 8 elsewhere; each colour written straight to its pixel); the engine's fast path uses it by
default. Its hidden layers run in bf16 with native bf16 dot products (AVX512-BF16's ``vdpbf16ps``, fp32
sums) when the shader's dtype is bf16 and the kernel was built with them for this CPU
(:meth:`FastShader.fused_bf16`), else in fp32; encodings, samples, the output layer and its sigmoid are
fp32 either way. With ``pe_table=True`` its fp32 pass takes the first hidden layer's encoded part from
per-coordinate tables (:meth:`FastShader.encoding_table`: four table rows per coordinate instead of the
sin/cos and 2 L + 1 products; about 1e-4 from the exact pass, whose tiles it keeps where a uv lies outside
[0, 1]); the engine's fast path turns it on (``FastRender.pe_table``). With ``project_features=True`` the fp32 pass
samples the feature layer's feature part from maps projected once per frame's features (:meth:`FastShader.projected_maps`:
bilinear sampling commutes with the layer's product, so each ray reads N projected columns instead of sampling F
features and multiplying them by an (F, N) block; within 1e-6 of the sampled features); the engine's fast path turns
it on (``FastRender.project_features``).

Supported variants: no view direction and one inner U-Net (``two_surface``, ``single_surface``);
:func:`supports` says so, and callers use ``DeliffasModel.shade`` otherwise. Without the C kernel
(``DELIFFAS_NATIVE=0``, no compiler) the inputs come from ``DeliffasModel.gather_inputs``.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
import threading

import torch

from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.ray_query import RayQuery
from deliffas.native import LazyLibrary

__all__ = ["FastShader", "supports", "native_bf16", "ROW_CHUNK", "TABLE_NODES", "PROJECTED_MAX_BYTES"]

logger = logging.getLogger(__name__)

TABLE_NODES = 2048
"""Intervals of :meth:`FastShader.encoding_table` on [0, 1] (a power of 2: x * TABLE_NODES is exact in fp32)."""

PROJECTED_MAX_BYTES = 64 * 2**20
"""The most :meth:`FastShader.projected_maps` projects (all maps together); larger ones (the paper preset's 1024^2
texels of 256 columns) sample the features instead."""

ROW_CHUNK = 16384
"""Rays per MLP chunk (realtime preset, bf16, 197 k rays, CPU time under load: 2048 / 4096 / 8192 /
16384 / 65536 rows took 37.5 / 31.8 / 28.4 / 26.3 / 26.7 ms)."""

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>

static inline uint16_t to_bf16(float f) {
    uint32_t u;
    memcpy(&u, &f, 4);
    u += 0x7FFFu + ((u >> 16) & 1u);
    return (uint16_t)(u >> 16);
}

/* sin and cos of a (|a| up to a few pi) to ~1e-12: reduction by the nearest multiple of pi, Taylor to degree 16
   (error (pi/2)^17/17! < 1e-11); libm's sincos took ~4x longer per ray than the rest of this pass. */
static inline void sin_cos(double a, double *s, double *c) {
    const double pi = 3.14159265358979323846;
    double k = nearbyint(a * (1.0 / pi)), r = a - k * pi, r2 = r * r;
    double sn = r * (1.0 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880 + r2 * (-1.0 / 39916800
                  + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0))))))));
    double cs = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800
                  + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0 + r2 * (1.0 / 20922789888000.0))))))));
    double sign = ((int64_t)k & 1) ? -1.0 : 1.0;
    *s = sign * sn;
    *c = sign * cs;
}

#define PUT_F32(out, i, v) ((out)[i] = (v))
#define PUT_BF16(out, i, v) ((out)[i] = to_bf16(v))

/* One variant per output type T with store PUT:
   encode: positional encoding of one uv into out[i0 ..]: u v, then per k: sin(a_k u) sin(a_k v) cos(a_k u)
   cos(a_k v), a_k x = 2^k float(x * float(pi)) (what torch rounds x * float(2^k pi) to), by the double-angle
   recurrence in float64.
   sample: bilinear lookup of a channels_last (S, S, C) map at uv (grid_sample, align_corners False, border).
   rows: rows [start, stop) of enc (n, E): PE(uv_outer) if outer_encoded, then PE(uv_inner); and of
   feats (n, F): the outer map at uv_outer if map_out is given, then the inner feature (the outer map at
   uv_inner where from_outer). */
#define VARIANT(NAME, T, PUT)                                                                                  \
static void encode_##NAME(const float *uv, int L, int include_input, T *out) {                                 \
    int64_t i = 0;                                                                                             \
    if (include_input) { PUT(out, i, uv[0]); i++; PUT(out, i, uv[1]); i++; }                                  \
    if (L == 0) return;                                                                                        \
    const float pi = (float)3.14159265358979323846;                                                            \
    double s0, c0, s1, c1;                                                                                     \
    sin_cos((double)(uv[0] * pi), &s0, &c0);                                                                   \
    sin_cos((double)(uv[1] * pi), &s1, &c1);                                                                    \
    for (int k = 0; k < L; k++) {                                                                              \
        PUT(out, i, (float)s0); PUT(out, i + 1, (float)s1); PUT(out, i + 2, (float)c0); PUT(out, i + 3, (float)c1); \
        i += 4;                                                                                                \
        double t0 = 2.0 * s0 * c0, t1 = 2.0 * s1 * c1;                                                        \
        c0 = c0 * c0 - s0 * s0; c1 = c1 * c1 - s1 * s1; s0 = t0; s1 = t1;                                    \
    }                                                                                                          \
}                                                                                                              \
static void sample_##NAME(const float *map, int64_t S, int64_t C, const float *uv, T *out) {                  \
    float gx = 2.0f * uv[0] - 1.0f, gy = 1.0f - 2.0f * uv[1];                                                  \
    float ix = ((gx + 1.0f) * (float)S - 1.0f) / 2.0f, iy = ((gy + 1.0f) * (float)S - 1.0f) / 2.0f;            \
    float hi = (float)(S - 1);                                                                                 \
    ix = ix < 0.0f ? 0.0f : (ix > hi ? hi : ix);                                                               \
    iy = iy < 0.0f ? 0.0f : (iy > hi ? hi : iy);                                                               \
    if (ix != ix) ix = 0.0f;                                                                                   \
    if (iy != iy) iy = 0.0f;                                                                                   \
    int64_t x0 = (int64_t)floorf(ix), y0 = (int64_t)floorf(iy);                                                \
    float fx = ix - (float)x0, fy = iy - (float)y0;                                                            \
    int64_t x1 = x0 + 1 < S ? x0 + 1 : x0, y1 = y0 + 1 < S ? y0 + 1 : y0;                                      \
    float w00 = (1.0f - fx) * (1.0f - fy), w01 = fx * (1.0f - fy), w10 = (1.0f - fx) * fy, w11 = fx * fy;      \
    const float *p00 = map + (y0 * S + x0) * C, *p01 = map + (y0 * S + x1) * C;                                \
    const float *p10 = map + (y1 * S + x0) * C, *p11 = map + (y1 * S + x1) * C;                                \
    for (int64_t c = 0; c < C; c++) PUT(out, c, w00 * p00[c] + w01 * p01[c] + w10 * p10[c] + w11 * p11[c]);   \
}                                                                                                              \
static void rows_##NAME(int64_t start, int64_t stop, const float *uv_in, const uint8_t *from_outer,           \
                        const float *uv_out, int outer_encoded, int L, int include_input, const float *map_in,\
                        const float *map_out, int64_t S, int64_t C, T *enc, int64_t E, T *feats, int64_t F) { \
    int64_t per_uv = (include_input ? 2 : 0) + 4 * (int64_t)L;                                                 \
    for (int64_t r = start; r < stop; r++) {                                                                   \
        T *e = enc + r * E, *f = feats + r * F;                                                                \
        if (outer_encoded) { encode_##NAME(uv_out + 2 * r, L, include_input, e); e += per_uv; }                \
        encode_##NAME(uv_in + 2 * r, L, include_input, e);                                                    \
        if (map_out) { sample_##NAME(map_out, S, C, uv_out + 2 * r, f); f += C; }                              \
        const float *m = (from_outer && from_outer[r] && map_out) ? map_out : map_in;                          \
        sample_##NAME(m, S, C, uv_in + 2 * r, f);                                                              \
    }                                                                                                          \
}

VARIANT(f32, float, PUT_F32)
VARIANT(bf16, uint16_t, PUT_BF16)

/* exp(x) for x in [-88, 88] to ~2 ulp, branch-free so the compiler vectorises the loop around it:
   x = k ln2 + r, |r| <= ln2 / 2, exp(r) by a degree-7 polynomial, 2^k through the exponent bits. */
static inline float exp_approx(float x) {
    x = x < -87.0f ? -87.0f : (x > 88.0f ? 88.0f : x);
    float k = nearbyintf(x * 1.44269504088896341f);
    float r = x - k * 0.693145751953125f - k * 1.428606765330187e-06f;
    float p = 1.0f + r * (1.0f + r * (0.5f + r * (1.6666667163e-01f + r * (4.1666667908e-02f + r * (8.3333337680e-03f
              + r * (1.3888889225e-03f + r * 1.9841270114e-04f))))));
    int32_t e = ((int32_t)k + 127) << 23;
    float scale;
    memcpy(&scale, &e, 4);
    return p * scale;
}

static inline float bf16_to_f32(uint16_t v) {
    uint32_t u = (uint32_t)v << 16;
    float f;
    memcpy(&f, &u, 4);
    return f;
}

/* The MLP's output layer and its sigmoid: rgb = sigmoid(h W^T + b) in fp32 for rows [0, n) of h (n, K)
   (leading dimension ld, bf16 or fp32), W (3, K) and b (3,) fp32. Row r goes to out[3 pixels[r] ..]
   when pixels is given (the image canvas), else to out[3 r ..]. 16 partial sums per output so the
   K loop vectorises without reassociating one sum. */
void deliffas_rgb_out(int64_t n, const void *h, int64_t ld, int bf16, int64_t K, const float *w, const float *b,
                      const int64_t *pixels, float *out) {
    enum { B = 64 };
    float logit[3 * B];
    for (int64_t r0 = 0; r0 < n; r0 += B) {
        int64_t m = n - r0 < B ? n - r0 : B;
        for (int64_t i = 0; i < m; i++) {
            float x[16];
            float acc[3][16];
            for (int j = 0; j < 3; j++) for (int l = 0; l < 16; l++) acc[j][l] = 0.0f;
            int64_t k = 0;
            for (; k + 16 <= K; k += 16) {
                if (bf16) { const uint16_t *hr = (const uint16_t *)h + (r0 + i) * ld + k;
                            for (int l = 0; l < 16; l++) x[l] = bf16_to_f32(hr[l]); }
                else { const float *hr = (const float *)h + (r0 + i) * ld + k;
                       for (int l = 0; l < 16; l++) x[l] = hr[l]; }
                for (int j = 0; j < 3; j++) for (int l = 0; l < 16; l++) acc[j][l] += x[l] * w[j * K + k + l];
            }
            for (int j = 0; j < 3; j++) {
                float s = b[j];
                for (int l = 0; l < 16; l++) s += acc[j][l];
                for (int64_t kk = k; kk < K; kk++) {
                    float v = bf16 ? bf16_to_f32(((const uint16_t *)h)[(r0 + i) * ld + kk]) : ((const float *)h)[(r0 + i) * ld + kk];
                    s += v * w[j * K + kk];
                }
                logit[3 * i + j] = s;
            }
        }
        for (int64_t i = 0; i < 3 * m; i++) logit[i] = 1.0f / (1.0f + exp_approx(-logit[i]));
        for (int64_t i = 0; i < m; i++) {
            float *o = out + 3 * (pixels ? pixels[r0 + i] : r0 + i);
            o[0] = logit[3 * i]; o[1] = logit[3 * i + 1]; o[2] = logit[3 * i + 2];
        }
    }
}

void deliffas_ray_inputs(int64_t start, int64_t stop, const float *uv_in, const uint8_t *from_outer,
                         const float *uv_out, int outer_encoded, int L, int include_input, const float *map_in,
                         const float *map_out, int64_t S, int64_t C, int bf16, void *enc, int64_t E, void *feats,
                         int64_t F) {
    if (bf16)
        rows_bf16(start, stop, uv_in, from_outer, uv_out, outer_encoded, L, include_input, map_in, map_out, S, C,
                  (uint16_t *)enc, E, (uint16_t *)feats, F);
    else
        rows_f32(start, stop, uv_in, from_outer, uv_out, outer_encoded, L, include_input, map_in, map_out, S, C,
                 (float *)enc, E, (float *)feats, F);
}
"""


# The whole shading of a ray in one pass, a tile of rays at a time with the rays in the vector lanes (GCC/clang
# vector extensions: 16 rays in AVX-512 registers, 8 in AVX2's under -march=native): encodings and samples (the
# pass above, into a transposed tile), every hidden layer (bias, products, ReLU) in fp32 from tile to tile in L1,
# the output layer, its sigmoid and the write into the canvas. Nothing per ray reaches memory but its colour. FMA
# contraction is on here (a separate build), so values differ from torch's fp32 in the last bits.
_FUSED_SOURCE = _SOURCE + r"""
#include <stdlib.h>

/* Rays per tile = float lanes of the widest vector registers: 16 with AVX-512, else 8. A 16-lane tile on AVX2 is
   emulated with register pairs, and the dense layers' accumulators then spill: the fp32 pass ran 5 x slower. */
#ifdef __AVX512F__
#define TILE 16
#else
#define TILE 8
#endif
typedef float vtile __attribute__((vector_size(4 * TILE)));  /* one tile row: TILE floats */
typedef float v8 __attribute__((vector_size(32)));
typedef int32_t vtilei __attribute__((vector_size(4 * TILE)));

/* The positional encoding of uvs [0, m) of a tile into xt (features, TILE), as encode_f32 per ray (a partial
   tile repeats its last uv): sin and cos by the same reduction and series, written so the compiler vectorises
   over the tile (rounding to the nearest multiple of pi by the 1.5 2^52 shift instead of nearbyint). */
static void encode_tile(const float *uv, int64_t m, int L, int include_input, float *xt) {
    const float pi = (float)3.14159265358979323846;
    const double dpi = 3.14159265358979323846, shift = 6755399441055744.0;
    double s[2][TILE], c[2][TILE];
    float u[2][TILE];
    for (int64_t i = 0; i < TILE; i++)
        for (int d = 0; d < 2; d++) u[d][i] = uv[2 * (i < m ? i : m - 1) + d];
    for (int d = 0; d < 2; d++) {
        if (include_input)
            for (int64_t i = 0; i < TILE; i++) xt[d * TILE + i] = u[d][i];
        for (int64_t i = 0; i < TILE; i++) {
            float x = u[d][i];
            double a = (double)(x * pi);
            double k = (a * (1.0 / dpi) + shift) - shift, r = a - k * dpi, r2 = r * r;
            double sn = r * (1.0 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880
                          + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0))))))));
            double cs = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800
                          + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0 + r2 * (1.0 / 20922789888000.0))))))));
            double sign = 1.0 - 2.0 * (double)((int64_t)k & 1);
            s[d][i] = sign * sn;
            c[d][i] = sign * cs;
        }
    }
    float *o = xt + (include_input ? 2 : 0) * TILE;
    for (int k = 0; k < L; k++, o += 4 * TILE) {
        for (int64_t i = 0; i < TILE; i++) {
            o[i] = (float)s[0][i]; o[TILE + i] = (float)s[1][i];
            o[2 * TILE + i] = (float)c[0][i]; o[3 * TILE + i] = (float)c[1][i];
        }
        for (int d = 0; d < 2; d++)
            for (int64_t i = 0; i < TILE; i++) {
                double t = 2.0 * s[d][i] * c[d][i];
                c[d][i] = c[d][i] * c[d][i] - s[d][i] * s[d][i];
                s[d][i] = t;
            }
    }
}

/* A tile's uvs (the last ray repeated past m) and sin/cos of pi * uv in float32: Cody-Waite reduction by pi, then
   odd/even polynomials on [-pi/2, pi/2]; the base frequency of both fp32 encoders (the others follow by doubling). */
static inline void base_sin_cos(const float *uv, int64_t m, float u[2][TILE], float s[2][TILE], float c[2][TILE]) {
    const float pi = (float)3.14159265358979323846, pi_hi = 3.140625f, pi_lo = 9.67653589793e-4f,
                shift = 12582912.0f;  /* 1.5 2^23: adding and subtracting it rounds to an integer */
    for (int64_t i = 0; i < TILE; i++)
        for (int d = 0; d < 2; d++) u[d][i] = uv[2 * (i < m ? i : m - 1) + d];
    for (int d = 0; d < 2; d++)
        for (int64_t i = 0; i < TILE; i++) {
            float a = u[d][i] * pi;
            float k = (a * (1.0f / pi) + shift) - shift;
            float r = (a - k * pi_hi) - k * pi_lo, r2 = r * r;
            float sn = r * (1.0f + r2 * (-1.0f / 6 + r2 * (1.0f / 120 + r2 * (-1.0f / 5040 + r2 * (1.0f / 362880
                         + r2 * (-1.0f / 39916800))))));
            float cs = 1.0f + r2 * (-0.5f + r2 * (1.0f / 24 + r2 * (-1.0f / 720 + r2 * (1.0f / 40320
                         + r2 * (-1.0f / 3628800 + r2 * (1.0f / 479001600))))));
            float sign = 1.0f - 2.0f * (float)((int32_t)k & 1);
            s[d][i] = sign * sn;
            c[d][i] = sign * cs;
        }
}

/* encode_tile in float32 for the bf16 hidden layers, whose inputs are rounded to bf16 (8 bits) anyway: sin and cos
   of a = float(x pi) by a two-part pi reduction and Taylor series to degree 11 / 12 (error < 1e-7), the higher
   frequencies by the double-angle recurrence in float32 (its error doubles per step: about 3e-5 at the 10th
   frequency, against bf16's 2e-3), 16 lanes a vector instead of 8 in float64. */
static void encode_tile_f32(const float *uv, int64_t m, int L, int include_input, float *xt) {
    float s[2][TILE], c[2][TILE], u[2][TILE];
    base_sin_cos(uv, m, u, s, c);
    for (int d = 0; d < 2; d++)
        if (include_input)
            for (int64_t i = 0; i < TILE; i++) xt[d * TILE + i] = u[d][i];
    float *o = xt + (include_input ? 2 : 0) * TILE;
    for (int k = 0; k < L; k++, o += 4 * TILE) {
        for (int64_t i = 0; i < TILE; i++) {
            o[i] = s[0][i]; o[TILE + i] = s[1][i];
            o[2 * TILE + i] = c[0][i]; o[3 * TILE + i] = c[1][i];
        }
        for (int d = 0; d < 2; d++)
            for (int64_t i = 0; i < TILE; i++) {
                float t = 2.0f * s[d][i] * c[d][i];
                c[d][i] = c[d][i] * c[d][i] - s[d][i] * s[d][i];
                s[d][i] = t;
            }
    }
}

/* The bilinear taps of a tile's uvs [0, m) (sample_f32's arithmetic; the last uv repeated past m) on an (S, S) map of
   C channels per texel: weights w[tap][ray] and offsets o[tap][ray] (floats from the map's start) of the texels
   (y0, x0), (y0, x1), (y1, x0), (y1, x1); computed over the tile (vectorised). Clamped coordinates are >= 0, so the
   integer part is a truncation. */
static void tile_taps(const float *uv, int64_t m, int64_t S, int64_t C, float w[4][TILE], int64_t o[4][TILE]) {
    const float hi = (float)(S - 1);
    float u[2][TILE];
    for (int64_t i = 0; i < TILE; i++)
        for (int d = 0; d < 2; d++) u[d][i] = uv[2 * (i < m ? i : m - 1) + d];
    for (int64_t i = 0; i < TILE; i++) {
        float gx = 2.0f * u[0][i] - 1.0f, gy = 1.0f - 2.0f * u[1][i];
        float ix = ((gx + 1.0f) * (float)S - 1.0f) / 2.0f, iy = ((gy + 1.0f) * (float)S - 1.0f) / 2.0f;
        /* NaN -> 0, as sample_f32's NaN check; comparisons rather than fminf/fmaxf, which stay libm calls here */
        ix = ix > 0.0f ? ix : 0.0f; ix = ix < hi ? ix : hi;
        iy = iy > 0.0f ? iy : 0.0f; iy = iy < hi ? iy : hi;
        int32_t x0 = (int32_t)ix, y0 = (int32_t)iy;
        float fx = ix - (float)x0, fy = iy - (float)y0;
        int32_t x1 = x0 + (x0 + 1 < S), y1 = y0 + (y0 + 1 < S);
        w[0][i] = (1.0f - fx) * (1.0f - fy); w[1][i] = fx * (1.0f - fy); w[2][i] = (1.0f - fx) * fy; w[3][i] = fx * fy;
        o[0][i] = ((int64_t)y0 * S + x0) * C; o[1][i] = ((int64_t)y0 * S + x1) * C;
        o[2][i] = ((int64_t)y1 * S + x0) * C; o[3][i] = ((int64_t)y1 * S + x1) * C;
    }
}

/* y (N, TILE) = rows (TILE, N) transposed; N a multiple of 8 */
#if TILE == 8 && defined(__AVX__)
#include <immintrin.h>
static void rows_to_tile(const float *rows, int64_t N, vtile *y) {
    for (int64_t k = 0; k < N; k += 8) {  /* an 8 x 8 block in registers: 24 shuffles instead of 64 inserts */
        const float *s = rows + k;
        __m256 r0 = _mm256_loadu_ps(s), r1 = _mm256_loadu_ps(s + N), r2 = _mm256_loadu_ps(s + 2 * N),
               r3 = _mm256_loadu_ps(s + 3 * N), r4 = _mm256_loadu_ps(s + 4 * N), r5 = _mm256_loadu_ps(s + 5 * N),
               r6 = _mm256_loadu_ps(s + 6 * N), r7 = _mm256_loadu_ps(s + 7 * N);
        __m256 t0 = _mm256_unpacklo_ps(r0, r1), t1 = _mm256_unpackhi_ps(r0, r1), t2 = _mm256_unpacklo_ps(r2, r3),
               t3 = _mm256_unpackhi_ps(r2, r3), t4 = _mm256_unpacklo_ps(r4, r5), t5 = _mm256_unpackhi_ps(r4, r5),
               t6 = _mm256_unpacklo_ps(r6, r7), t7 = _mm256_unpackhi_ps(r6, r7);
        __m256 u0 = _mm256_shuffle_ps(t0, t2, 0x44), u1 = _mm256_shuffle_ps(t0, t2, 0xEE),
               u2 = _mm256_shuffle_ps(t1, t3, 0x44), u3 = _mm256_shuffle_ps(t1, t3, 0xEE),
               u4 = _mm256_shuffle_ps(t4, t6, 0x44), u5 = _mm256_shuffle_ps(t4, t6, 0xEE),
               u6 = _mm256_shuffle_ps(t5, t7, 0x44), u7 = _mm256_shuffle_ps(t5, t7, 0xEE);
        y[k] = (vtile)_mm256_permute2f128_ps(u0, u4, 0x20); y[k + 1] = (vtile)_mm256_permute2f128_ps(u1, u5, 0x20);
        y[k + 2] = (vtile)_mm256_permute2f128_ps(u2, u6, 0x20); y[k + 3] = (vtile)_mm256_permute2f128_ps(u3, u7, 0x20);
        y[k + 4] = (vtile)_mm256_permute2f128_ps(u0, u4, 0x31); y[k + 5] = (vtile)_mm256_permute2f128_ps(u1, u5, 0x31);
        y[k + 6] = (vtile)_mm256_permute2f128_ps(u2, u6, 0x31); y[k + 7] = (vtile)_mm256_permute2f128_ps(u3, u7, 0x31);
    }
}
#else
static void rows_to_tile(const float *rows, int64_t N, vtile *y) {
    for (int64_t k = 0; k < N; k++) {
        vtile v;
        for (int64_t i = 0; i < TILE; i++) v[i] = rows[i * N + k];
        y[k] = v;
    }
}
#endif

/* Bilinear samples (sample_f32's arithmetic) of uvs [0, m) of a tile into ft (C, TILE): ray i reads map_alt where
   alt[i] is set, else map; C channels of four taps per ray. */
static void sample_tile(const float *map, const float *map_alt, const uint8_t *alt, const float *uv, int64_t m,
                        int64_t S, int64_t C, float *ft) {
    float w[4][TILE];
    int64_t o[4][TILE];
    tile_taps(uv, m, S, C, w, o);
    const float *base[TILE];
    for (int64_t i = 0; i < TILE; i++) base[i] = (alt && alt[i < m ? i : m - 1]) ? map_alt : map;
    int64_t c = 0;
    for (; c + 8 <= C; c += 8) {  /* 8 channels of a ray in one vector, then the (TILE, 8) block transposed into ft */
        float blk[TILE * 8];
        for (int64_t i = 0; i < TILE; i++) {
            const float *mp = base[i] + c;
            v8 t00, t01, t10, t11;
            memcpy(&t00, mp + o[0][i], 32); memcpy(&t01, mp + o[1][i], 32);
            memcpy(&t10, mp + o[2][i], 32); memcpy(&t11, mp + o[3][i], 32);
            v8 v = w[0][i] * t00 + w[1][i] * t01 + w[2][i] * t10 + w[3][i] * t11;
            memcpy(blk + 8 * i, &v, 32);
        }
        rows_to_tile(blk, 8, (vtile *)ft + c);
    }
    for (; c < C; c++)
        for (int64_t i = 0; i < TILE; i++) {
            const float *mp = base[i] + c;
            ft[c * TILE + i] = w[0][i] * mp[o[0][i]] + w[1][i] * mp[o[1][i]] + w[2][i] * mp[o[2][i]] + w[3][i] * mp[o[3][i]];
        }
}

/* Projected features (FastShader.project_features): rows (TILE, N) += per ray the bilinear samples of (S, S, N) maps
   that hold the feature layer's feature columns times a feature map: pa at uv_a (when pa), then pb at uv_b, or pc
   where alt[i] is set. Sampling commutes with the product, so this is the layer's Wf f without f. N a multiple of 8. */
static void add_projected(const float *pa, const float *uv_a, const float *pb, const float *pc, const uint8_t *alt,
                          const float *uv_b, int64_t m, int64_t S, int64_t N, float *rows) {
    float wa[4][TILE], wb[4][TILE];
    int64_t oa[4][TILE], ob[4][TILE];
    if (pa) tile_taps(uv_a, m, S, N, wa, oa);
    tile_taps(uv_b, m, S, N, wb, ob);
    for (int64_t i = 0; i < TILE; i++) {
        const float *mb = (alt && alt[i < m ? i : m - 1]) ? pc : pb;
        for (int64_t n0 = 0; n0 < N; n0 += 8) {
            v8 acc, t0, t1, t2, t3;
            memcpy(&acc, rows + i * N + n0, 32);
            if (pa) {
                memcpy(&t0, pa + oa[0][i] + n0, 32); memcpy(&t1, pa + oa[1][i] + n0, 32);
                memcpy(&t2, pa + oa[2][i] + n0, 32); memcpy(&t3, pa + oa[3][i] + n0, 32);
                acc += wa[0][i] * t0 + wa[1][i] * t1 + wa[2][i] * t2 + wa[3][i] * t3;
            }
            memcpy(&t0, mb + ob[0][i] + n0, 32); memcpy(&t1, mb + ob[1][i] + n0, 32);
            memcpy(&t2, mb + ob[2][i] + n0, 32); memcpy(&t3, mb + ob[3][i] + n0, 32);
            acc += wb[0][i] * t0 + wb[1][i] * t1 + wb[2][i] * t2 + wb[3][i] * t3;
            memcpy(rows + i * N + n0, &acc, 32);
        }
    }
}

/* rows (TILE, N) = the bias b (N) for every ray */
static void bias_rows(const float *b, int64_t N, float *rows) {
    for (int64_t i = 0; i < TILE; i++) memcpy(rows + i * N, b, (size_t)N * sizeof(float));
}

/* Two tiles keep a vector register each (the compiler would otherwise reload them for every product); only where a
   tile fits one register (AVX for 8 lanes, AVX-512 for 16): wider vectors have no register to ask for. */
#if defined(__x86_64__) && defined(__GNUC__) && defined(__AVX__)
#define IN_REGISTER(v) __asm__("" : "+v"(v))
#else
#define IN_REGISTER(v) ((void)0)
#endif
#define GROUP 2  /* tiles shaded together: their dense layers share every weight (dense2) */

/* y (N, TILE) = relu(b + x (K, TILE) W (K, N) + f (F, TILE) Wf (F, N)) for two tiles at once (x0 .. y0, x1 .. y1;
   one tile passed twice for a tile alone), 4 outputs at a time: each broadcast weight serves 2 products, 6 loads per
   8 products instead of 9 for one tile (the load ports, not the FMAs, bounded the layers on AVX2). No b: y holds the
   start. N a multiple of 4. */
static void dense2(const vtile *x0, const vtile *x1, int64_t K, const float *w, const float *b, const vtile *f0,
                   const vtile *f1, int64_t F, const float *wf, int64_t N, vtile *y0, vtile *y1) {
    for (int64_t n0 = 0; n0 < N; n0 += 4) {
        vtile a0[4], a1[4];
        for (int j = 0; j < 4; j++) {
            a0[j] = b ? (vtile){0} + b[n0 + j] : y0[n0 + j];
            a1[j] = b ? (vtile){0} + b[n0 + j] : y1[n0 + j];
        }
        for (int64_t k = 0; k < K; k++) {
            vtile u = x0[k], v = x1[k];
            IN_REGISTER(u); IN_REGISTER(v);
            const float *wr = w + k * N + n0;
            for (int j = 0; j < 4; j++) { float s = wr[j]; a0[j] += u * s; a1[j] += v * s; }
        }
        for (int64_t k = 0; k < F; k++) {
            vtile u = f0[k], v = f1[k];
            IN_REGISTER(u); IN_REGISTER(v);
            const float *wr = wf + k * N + n0;
            for (int j = 0; j < 4; j++) { float s = wr[j]; a0[j] += u * s; a1[j] += v * s; }
        }
        for (int j = 0; j < 4; j++) {
            y0[n0 + j] = (vtile)((vtilei)a0[j] & (a0[j] > (vtile){0}));
            y1[n0 + j] = (vtile)((vtilei)a1[j] & (a1[j] > (vtile){0}));
        }
    }
}

/* The output layer, its sigmoid and the colours of rays [0, m) of a tile (x: (K, TILE)) to out[3 pixels[r0 + i] ..]
   (out[3 (r0 + i) ..] without pixels). */
static void write_colours(const vtile *x, int64_t K, const float *wo, const float *bo, int64_t m, const int64_t *pixels,
                          int64_t r0, float *out) {
    vtile acc[3];
    for (int j = 0; j < 3; j++) acc[j] = (vtile){0} + bo[j];
    for (int64_t k = 0; k < K; k++)
        for (int j = 0; j < 3; j++) acc[j] += x[k] * wo[j * K + k];
    float rgb[3][TILE];
    for (int j = 0; j < 3; j++)
        for (int i = 0; i < TILE; i++) rgb[j][i] = 1.0f / (1.0f + exp_approx(-acc[j][i]));
    for (int64_t i = 0; i < m; i++) {
        float *o = out + 3 * (pixels ? pixels[r0 + i] : r0 + i);
        o[0] = rgb[0][i]; o[1] = rgb[1][i]; o[2] = rgb[2][i];
    }
}

/* The first layer's encoded part from per-coordinate tables (FastShader.pe_table): rows (TILE, N) = b + the sum over the
   tile's 2 nuv coordinates of a cubic Hermite interpolation of that coordinate's table. Table c holds T + 1 nodes
   x_j = j / T of 2 N floats: g_c(x_j) (N), then g_c'(x_j) / T (N), g_c = the layer's weights times the coordinate's
   encoding, so the sin/cos and 2 L products per coordinate become 4 rows of the table. Returns 0, computing nothing,
   when a uv of the tile is outside [0, 1] (the caller encodes that tile). T a power of 2 keeps x T exact. */
static int table_layer(const float *const *uvs, int nuv, int64_t m, const float *table, int64_t T, int64_t N,
                       const float *b, float *rows) {
    int inside = 1;  /* (branch-free, so it vectorises; NaN is outside) */
    for (int u = 0; u < nuv; u++)
        for (int64_t i = 0; i < 2 * m; i++) inside &= (uvs[u][i] >= 0.0f) & (uvs[u][i] <= 1.0f);
    if (!inside) return 0;
    for (int64_t i = 0; i < TILE; i++) {
        int64_t r = i < m ? i : m - 1;
        const float *node[4];  /* per coordinate: its first node */
        float h[4][4];         /* per coordinate: Hermite weights of g_j, g'_j, g_j+1, g'_j+1 */
        int nc = 2 * nuv;
        for (int c = 0; c < nc; c++) {
            float t = uvs[c / 2][2 * r + c % 2] * (float)T;
            int64_t j = (int64_t)t;
            if (j > T - 1) j = T - 1;
            float s = t - (float)j, s2 = s * s, s3 = s2 * s;
            h[c][0] = 2.0f * s3 - 3.0f * s2 + 1.0f; h[c][1] = s3 - 2.0f * s2 + s;
            h[c][2] = 3.0f * s2 - 2.0f * s3; h[c][3] = s3 - s2;
            node[c] = table + ((int64_t)c * (T + 1) + j) * 2 * N;
        }
        for (int64_t n0 = 0; n0 < N; n0 += 8) {  /* 8 outputs in one vector, summed over the 4 nc table rows */
            v8 acc;
            memcpy(&acc, b + n0, 32);
            for (int c = 0; c < nc; c++) {
                v8 g0, d0, g1, d1;
                memcpy(&g0, node[c] + n0, 32); memcpy(&d0, node[c] + N + n0, 32);
                memcpy(&g1, node[c] + 2 * N + n0, 32); memcpy(&d1, node[c] + 3 * N + n0, 32);
                acc += h[c][0] * g0 + h[c][1] * d0 + h[c][2] * g1 + h[c][3] * d1;
            }
            memcpy(rows + i * N + n0, &acc, 32);
        }
    }
    return 1;
}

/* Native bf16 dot products (AVX512-BF16, compiled in only where -march=native has them): the hidden layers with
   bf16 inputs and weights, fp32 sums. An activation tile is held as row pairs, (K/2, TILE, 2) bf16: lanes 2i, 2i+1 of
   vector k are rows 2k, 2k+1 of ray i, so one vdpbf16ps adds two products for 16 rays to one output, the weight pair
   (w[2k][n], w[2k+1][n]) broadcast as one 32-bit word. */
#if defined(__AVX512BF16__) && defined(__AVX512BW__)
#include <immintrin.h>
#define FUSED_BF16 1

static const uint16_t interleave_idx[32] = {0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23,
                                            8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31};

/* rows a and b of 16 rays as one pair vector (round to nearest even, as torch's .to(bfloat16)) */
static inline __m512bh pair_rows(__m512 a, __m512 b) {
    __m512i v = (__m512i)_mm512_cvtne2ps_pbh(b, a);  /* a in lanes 0..15, b in 16..31 */
    return (__m512bh)_mm512_permutexvar_epi16(_mm512_loadu_si512(interleave_idx), v);
}

/* (K, TILE) fp32 rows as ceil(K/2) pair vectors (an odd last row paired with 0) */
static void pair_tile(const vtile *x, int64_t K, __m512bh *xp) {
    int64_t k = 0;
    for (; k + 1 < K; k += 2) xp[k / 2] = pair_rows((__m512)x[k], (__m512)x[k + 1]);
    if (k < K) xp[k / 2] = pair_rows((__m512)x[k], _mm512_setzero_ps());
}

/* encode_tile_f32 straight into row pairs: (u, v), then per frequency (sin u, sin v) and (cos u, cos v), which is
   how the encoding's rows pair up (each uv's rows are even in number); no fp32 rows stored and read back. */
static void encode_pairs(const float *uv, int64_t m, int L, int include_input, __m512bh *xp) {
    float s[2][TILE], c[2][TILE], u[2][TILE];
    base_sin_cos(uv, m, u, s, c);
    vtile s0, s1, c0, c1, u0, u1;
    memcpy(&s0, s[0], 64); memcpy(&s1, s[1], 64); memcpy(&c0, c[0], 64); memcpy(&c1, c[1], 64);
    memcpy(&u0, u[0], 64); memcpy(&u1, u[1], 64);
    if (include_input) *xp++ = pair_rows((__m512)u0, (__m512)u1);
    for (int k = 0; k < L; k++) {
        *xp++ = pair_rows((__m512)s0, (__m512)s1);
        *xp++ = pair_rows((__m512)c0, (__m512)c1);
        vtile t0 = 2.0f * s0 * c0, t1 = 2.0f * s1 * c1;
        c0 = c0 * c0 - s0 * s0; c1 = c1 * c1 - s1 * s1; s0 = t0; s1 = t1;
    }
}

/* relu(b + x W + f Wf) for N outputs (a multiple of 8): x (K2 pairs), W (K2, N) and Wf (F2, N) weight pairs; into
   yp as pairs, or into yf as fp32 rows when yf is given (the last hidden layer, read by the fp32 output layer). */
static void dense_bf16(const __m512bh *x, int64_t K2, const uint32_t *w, const float *b, const __m512bh *f, int64_t F2,
                       const uint32_t *wf, int64_t N, __m512bh *yp, vtile *yf) {
    for (int64_t n0 = 0; n0 < N; n0 += 8) {
        __m512 acc[8];
        for (int j = 0; j < 8; j++) acc[j] = _mm512_set1_ps(b[n0 + j]);
        for (int64_t k = 0; k < K2; k++) {
            __m512bh xv = x[k];
            const uint32_t *wr = w + k * N + n0;
            for (int j = 0; j < 8; j++) acc[j] = _mm512_dpbf16_ps(acc[j], xv, (__m512bh)_mm512_set1_epi32((int)wr[j]));
        }
        for (int64_t k = 0; k < F2; k++) {
            __m512bh fv = f[k];
            const uint32_t *wr = wf + k * N + n0;
            for (int j = 0; j < 8; j++) acc[j] = _mm512_dpbf16_ps(acc[j], fv, (__m512bh)_mm512_set1_epi32((int)wr[j]));
        }
        for (int j = 0; j < 8; j++) acc[j] = _mm512_max_ps(acc[j], _mm512_setzero_ps());  /* NaN -> 0, as dense */
        if (yf)
            for (int j = 0; j < 8; j++) yf[n0 + j] = (vtile)acc[j];
        else
            for (int j = 0; j < 8; j += 2) yp[(n0 + j) / 2] = pair_rows(acc[j], acc[j + 1]);
    }
}
#else
#define FUSED_BF16 0
#endif

/* 1 when the bf16 hidden layers are compiled in and this CPU runs them. */
int deliffas_fused_bf16(void) {
#if FUSED_BF16 && defined(__GNUC__)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512bf16") ? 1 : 0;
#else
    return FUSED_BF16;
#endif
}

/* Shade rays [0, n): inputs as deliffas_ray_inputs (fp32); layers: nh hidden layers, per layer 5 int64 in dims
   (K, N, feature rows F (0 or the feature width), offset of W (K, N), of Wf (F, N)), the bias at W + K N + F N;
   then the output layer (3, K) and its bias (3,) at dims[5 nh]. E, Fd: the encoded and feature widths (E = the
   first layer's K); wmax: the widest hidden layer. Colour of ray r to out[3 pixels[r] ..] (out[3 r ..] if no
   pixels). params are 4-byte words: fp32, or with bf16 (deliffas_fused_bf16() must be 1) the hidden layers'
   weights as bf16 pairs, W (K/2, N) and Wf (F/2, N) with dims giving K/2 and F/2, biases and the output layer
   fp32. proj_in (with fp32 only): the feature layer's (the one with F > 0) feature part from projected maps
   (add_projected; S x S texels of that layer's N): proj_out at uv_out (NULL without an outer map), proj_in at uv_in,
   proj_peel at uv_in where from_outer (NULL without from_outer); no features sampled then. Returns 0, -1 when the
   scratch tiles cannot be allocated, -2 for more than 512 channels per map, -3 for bf16 without the kernel. */
int deliffas_fused_shade(int64_t n, const float *uv_in, const uint8_t *from_outer, const float *uv_out,
                         int outer_encoded, int L, int include_input, const float *map_in, const float *map_out,
                         int64_t S, int64_t C, int64_t nh, const int64_t *dims, const float *params, int64_t E,
                         int64_t Fd, int64_t wmax, const int64_t *pixels, float *out, int bf16, const float *pe_table,
                         int64_t table_nodes, const float *proj_out, const float *proj_in, const float *proj_peel) {
    if (C > 512) return -2;
    if (bf16 && !FUSED_BF16) return -3;
    /* per tile, fp32: E + Fd input rows, two hidden layers and the rows; bf16: the inputs' and two hidden layers'
       pairs besides */
    int64_t per_tile = E + Fd + 3 * wmax + (bf16 ? (E + 1) / 2 + (Fd + 1) / 2 + wmax : 0);
    if (bf16) pe_table = proj_in = 0;  /* the table and the projected maps serve the fp32 pass */
    char *mem = aligned_alloc(64, (size_t)(GROUP * per_tile) * sizeof(vtile));
    if (!mem) return -1;
    vtile *xe[GROUP], *xf[GROUP], *h[GROUP][2], *rows[GROUP], *pairs[GROUP];
    for (int t = 0; t < GROUP; t++) {
        xe[t] = (vtile *)mem + t * per_tile; xf[t] = xe[t] + E; h[t][0] = xf[t] + Fd; h[t][1] = h[t][0] + wmax;
        rows[t] = h[t][1] + wmax; pairs[t] = rows[t] + wmax;
    }
    (void)pairs;  /* (read by the bf16 layers only) */
    const float *uvs[2] = {outer_encoded ? uv_out : uv_in, uv_in};
    int nuv = outer_encoded ? 2 : 1;
    const int64_t *od = dims + 5 * nh;
    const float *wo = params + od[0], *bo = wo + 3 * od[1];
    int64_t per_uv = (include_input ? 2 : 0) + 4 * (int64_t)L;
    for (int64_t g0 = 0; g0 < n; g0 += GROUP * TILE) {
        int nt = 0;  /* tiles in this group */
        int64_t r0s[GROUP], ms[GROUP];
        int tabled[GROUP];  /* the first layer's encoded part from the tables */
        const uint8_t *peel[GROUP];
        for (; nt < GROUP && g0 + nt * TILE < n; nt++) {
            int t = nt;
            int64_t r0 = r0s[t] = g0 + t * TILE, m = ms[t] = n - r0 < TILE ? n - r0 : TILE;
            int pairs_direct = FUSED_BF16 && bf16 && nh > 0;  /* encodings straight into bf16 pairs */
            tabled[t] = 0;
            if (pe_table && nh > 0) {
                const float *tile_uvs[2] = {uvs[0] + 2 * r0, uvs[1] + 2 * r0};
                tabled[t] = table_layer(tile_uvs, nuv, m, pe_table, table_nodes, dims[1],
                                        params + dims[3] + dims[0] * dims[1] + dims[2] * dims[1], (float *)rows[t]);
            }
            if (!pairs_direct && !tabled[t]) {
                float *xt = (float *)xe[t];
                void (*encode)(const float *, int64_t, int, int, float *) = bf16 ? encode_tile_f32 : encode_tile;
                if (outer_encoded) { encode(uv_out + 2 * r0, m, L, include_input, xt); xt += per_uv * TILE; }
                encode(uv_in + 2 * r0, m, L, include_input, xt);
            }
            peel[t] = (map_out && from_outer) ? from_outer + r0 : 0;
            if (!proj_in) {
                float *ft = (float *)xf[t];
                if (map_out) { sample_tile(map_out, map_out, 0, uv_out + 2 * r0, m, S, C, ft); ft += C * TILE; }
                sample_tile(map_in, map_out, peel[t], uv_in + 2 * r0, m, S, C, ft);
            }
            if (bf16 && nh > 0) {  /* the bf16 hidden layers and the colours, a tile at a time */
#if FUSED_BF16
                __m512bh *pe = (__m512bh *)pairs[t], *pf = pe + (E + 1) / 2;
                __m512bh *ph[2] = {pf + (Fd + 1) / 2, pf + (Fd + 1) / 2 + wmax / 2};
                __m512bh *pp = pe;
                if (outer_encoded) { encode_pairs(uv_out + 2 * r0, m, L, include_input, pp); pp += per_uv / 2; }
                encode_pairs(uv_in + 2 * r0, m, L, include_input, pp);
                pair_tile(xf[t], Fd, pf);
                const __m512bh *xp = pe;
                const uint32_t *words = (const uint32_t *)params;
                for (int64_t l = 0; l < nh; l++) {
                    const int64_t *d = dims + 5 * l;
                    const uint32_t *w = words + d[3], *wf = words + d[4];
                    const float *b = params + d[3] + d[0] * d[1] + d[2] * d[1];
                    dense_bf16(xp, d[0], w, b, d[2] ? pf : 0, d[2], wf, d[1], ph[l & 1], l == nh - 1 ? h[t][0] : 0);
                    xp = ph[l & 1];
                }
                write_colours(h[t][0], od[1], wo, bo, m, pixels, r0, out);
#endif
            }
        }
        if (bf16 && nh > 0) continue;
        const vtile *x[GROUP];
        for (int t = 0; t < nt; t++) x[t] = xe[t];
        for (int64_t l = 0; l < nh; l++) {
            const int64_t *d = dims + 5 * l;
            const float *w = params + d[3], *wf = params + d[4], *b = w + d[0] * d[1] + d[2] * d[1];
            int projected = d[2] && proj_in, alike = 1;
            for (int t = 0; t < nt; t++) {
                int from_table = l == 0 && tabled[t];
                alike &= from_table == (l == 0 && tabled[0]);
                if (projected || from_table) {  /* the layer starts from rows: b + the encoded part and/or the projected features */
                    if (!from_table) bias_rows(b, d[1], (float *)rows[t]);
                    if (projected)
                        add_projected(map_out ? proj_out : 0, uv_out + 2 * r0s[t], proj_in, proj_peel, peel[t],
                                      uv_in + 2 * r0s[t], ms[t], S, d[1], (float *)rows[t]);
                    rows_to_tile((const float *)rows[t], d[1], h[t][l & 1]);
                }
            }
            int64_t F = projected ? 0 : d[2];
            int pair = nt == 2 && alike;  /* both tiles in one call; else each alone, passed twice */
            for (int t = 0; t < nt; t += 1 + pair) {
                int u = pair ? 1 : t, from_table = l == 0 && tabled[t];
                dense2(x[t], x[u], from_table ? 0 : d[0], w, projected || from_table ? 0 : b, F ? xf[t] : 0,
                       F ? xf[u] : 0, F, wf, d[1], h[t][l & 1], h[u][l & 1]);
            }
            for (int t = 0; t < nt; t++) x[t] = h[t][l & 1];
        }
        for (int t = 0; t < nt; t++) write_colours(x[t], od[1], wo, bo, ms[t], pixels, r0s[t], out);
    }
    free(mem);
    return 0;
}
"""


def _declare_fused(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.deliffas_fused_shade.argtypes = [i64, p, p, p, i32, i32, i32, p, p, i64, i64, i64, p, p, i64, i64, i64, p, p, i32,
                                         p, i64, p, p, p]
    lib.deliffas_fused_shade.restype = i32
    lib.deliffas_fused_bf16.argtypes = []
    lib.deliffas_fused_bf16.restype = i32


_FUSED = LazyLibrary("fused_shade", _FUSED_SOURCE, ("-ffp-contract=fast", "-fno-math-errno", "-fno-trapping-math", "-std=gnu11"),
                     setup=_declare_fused, fallback="the per-stage fast path (ray inputs, then the MLP by addmm)")


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.deliffas_ray_inputs.argtypes = [i64, i64, p, p, p, i32, i32, i32, p, p, i64, i64, i32, p, i64, p, i64]
    lib.deliffas_ray_inputs.restype = None
    lib.deliffas_rgb_out.argtypes = [i64, p, i64, i32, i64, p, p, p, p]
    lib.deliffas_rgb_out.restype = None


_KERNEL = LazyLibrary("ray_inputs", _SOURCE, ("-fno-fast-math", "-ffp-contract=off", "-fno-math-errno"), setup=_declare,
                      fallback="DeliffasModel.gather_inputs")


@functools.lru_cache(maxsize=1)
def native_bf16() -> bool:
    """Whether this CPU has native bf16 arithmetic (x86 ``avx512_bf16`` / ``amx_bf16``, Arm ``bf16``)."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        return False
    return any(flag in flags.split() for flag in ("avx512_bf16", "amx_bf16", "bf16"))


def _lanes(width: int) -> int:
    """A layer width padded to a multiple of 8, as the fused pass lays out its outputs (8 a vector)."""
    return -(-width // 8) * 8


def _bf16_pairs(w: torch.Tensor) -> torch.Tensor:
    """(K, N) fp32 with K even as (K/2, N) int32 words, each the bf16 pair (w[2k, n], w[2k+1, n]) (low half first)."""
    k, n = w.shape
    if k == 0:  # (no feature columns; an empty tensor's strides cannot be viewed as int32)
        return torch.empty(0, n, dtype=torch.int32)
    return w.to(torch.bfloat16).reshape(k // 2, 2, n).transpose(1, 2).contiguous().view(torch.int32).reshape(k // 2, n)


def supports(model: DeliffasModel) -> bool:
    """Whether :class:`FastShader` can shade ``model``'s variant (no view direction, one inner U-Net)."""
    spec = model.spec
    return (not spec.viewdir and spec.inner_unets == 1 and tuple(spec.encoded_uvs) in (("outer", "inner"), ("inner",))
            and (spec.outer_unet or not spec.inner_from_outer) and model.pe_uv.in_dim == 2)


class FastShader:
    """``model.shade`` for inference on CPU, fused and chunked (module docstring).

    Args:
        model: the model (its weights are read on each call; bf16 copies are refreshed when they change).
        dtype: torch.float32 or torch.bfloat16, the dtype of the MLP's products.
        row_chunk: rays per MLP chunk.
        use_kernel: False = torch only (the C passes' plain path; also without a C compiler).
        fused: False = :meth:`shade_fused` runs the per-stage path (inputs, then the MLP).
        pe_table: :meth:`shade_fused`'s fp32 pass takes the first layer's encoded part from per-coordinate tables
            (:meth:`encoding_table`) instead of encoding and multiplying; False = exact.
        project_features: :meth:`shade_fused`'s fp32 pass samples the feature layer's projected maps
            (:meth:`projected_maps`) instead of the features; False = samples the features and multiplies.
    """

    def __init__(self, model: DeliffasModel, dtype: torch.dtype = torch.float32, row_chunk: int = ROW_CHUNK,
                 use_kernel: bool = True, fused: bool = True, pe_table: bool = False,
                 project_features: bool = False) -> None:
        if not supports(model):
            raise ValueError(f"FastShader: variant {model.config.variant!r} is not supported (see fast_shade.supports)")
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"FastShader: dtype must be float32 or bfloat16, got {dtype}")
        self.model, self.dtype, self.row_chunk, self.use_kernel = model, dtype, int(row_chunk), bool(use_kernel)
        self.fused = bool(fused)
        self.pe_table = bool(pe_table)
        self.project_features = bool(project_features)
        self._projected_lock = threading.Lock()
        self._projected_key: tuple | None = None
        self._projected: tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None] | None = None
        self._projected_features: tuple[torch.Tensor, torch.Tensor | None] | None = None  # the key's tensors, held
        self._table_key: tuple | None = None
        self._table: torch.Tensor | None = None
        self._fused_key: tuple | None = None
        self._fused: tuple[torch.Tensor, torch.Tensor, int] | None = None
        self._weights_key: tuple | None = None
        self._layers: list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]] = []

    # ------------------------------------------------------------------ weights
    def _key(self) -> tuple:
        return tuple((p.data_ptr(), p._version) for p in self.model.mlp.parameters())

    def layers(self) -> list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]]:
        """Per Linear: (W_h^T (in, out), W_f^T (F, out) or None, bias (out,)) in the MLP's dtype; the output layer
        as (W (3, in), None, bias (3,)) in fp32 (colours from fp32 logits; W untransposed, the layout both its
        kernel and torch's fp32 product with out = 3 want: the transposed copy took 4x longer).

        W_f^T is the feature columns of the layer after the concatenation (features come first)."""
        key = self._key()
        if key != self._weights_key:
            mlp = self.model.mlp
            out = []
            for i, lin in enumerate(mlp.hidden):
                w, w_f = lin.weight.detach(), None
                if i == mlp.config.feature_layer + 1 and mlp.feature_dim:
                    w_f, w = w[:, : mlp.feature_dim], w[:, mlp.feature_dim:]
                    w_f = w_f.t().contiguous().to(self.dtype)
                out.append((w.t().contiguous().to(self.dtype), w_f, lin.bias.detach().to(self.dtype).contiguous()))
            last = mlp.output
            out.append((last.weight.detach().float().contiguous(), None, last.bias.detach().float().contiguous()))
            self._layers, self._weights_key = out, key
        return self._layers

    # ------------------------------------------------------------------ inputs
    def _ray_args(self, features: FrameFeatures, query: RayQuery) -> tuple[tuple, list] | None:
        """The per-ray arguments of the C passes (uv_in .. C), and the tensors they point into (keep them alive);
        None when the C passes cannot read these inputs (several frames, non-fp32 maps)."""
        model = self.model
        single = features.batch_size == 1 and (query.batch_index.numel() == 0 or not bool(query.batch_index.any()))
        if not single or features.inner.dtype != torch.float32:
            return None
        spec = model.spec
        maps = [m.permute(0, 2, 3, 1).contiguous() if m is not None else None for m in (features.inner, features.outer)]
        map_in, map_out = maps[0], (maps[1] if spec.outer_unet else None)
        if spec.outer_unet and map_out is None:
            raise ValueError("shade: features.outer is None; encode() with normal_outer first")
        uv_in = query.uv_inner.float().contiguous()
        uv_out = query.uv_outer.float().contiguous() if query.uv_outer is not None else uv_in
        peel = query.inner_from_outer
        if peel is not None and not spec.inner_from_outer and bool(peel.any()):
            raise ValueError(f"shade: inner_from_outer has True entries but variant {model.config.variant!r} has no outer feature map")
        peel_u8 = peel.to(torch.uint8).contiguous() if peel is not None and spec.inner_from_outer else None
        S, C = map_in.shape[1], map_in.shape[3]
        args = (uv_in.data_ptr(), peel_u8.data_ptr() if peel_u8 is not None else None, uv_out.data_ptr(),
                int(spec.encoded_uvs[0] == "outer"), model.pe_uv.num_freqs, int(model.pe_uv.include_input),
                map_in.data_ptr(), map_out.data_ptr() if map_out is not None else None, S, C)
        return args, [uv_in, uv_out, peel_u8, map_in, map_out]

    def inputs(self, features: FrameFeatures, query: RayQuery) -> tuple[torch.Tensor, torch.Tensor]:
        """The MLP's operands: encoded (N, E) and feats (N, F) in the shader's dtype (C kernel, else torch)."""
        model, n = self.model, query.num_rays
        lib = _KERNEL.get() if self.use_kernel else None
        got = self._ray_args(features, query) if lib is not None else None
        if got is None:
            enc, feats = model.gather_inputs(features, query)
            return enc.to(self.dtype), feats.to(self.dtype).contiguous()
        E, F = model.mlp.in_dim, model.mlp.feature_dim
        enc = torch.empty(n, E, dtype=self.dtype)
        feats = torch.empty(n, F, dtype=self.dtype)
        lib.deliffas_ray_inputs(0, n, *got[0], int(self.dtype == torch.bfloat16), enc.data_ptr(), E, feats.data_ptr(), F)
        return enc, feats

    # ------------------------------------------------------------------ fused
    def _fused_params(self, bf16: bool) -> tuple[torch.Tensor, torch.Tensor, int]:
        """The MLP for the fused pass: (dims (5 nh + 2,) int64, params as 4-byte words, widest hidden layer); hidden
        widths padded to multiples of 8 with zero columns (their ReLU outputs are 0 and meet zero rows downstream).

        fp32: every weight and bias fp32. ``bf16``: the hidden layers' W and Wf as bf16 row pairs (K/2, N, 2) (an odd
        K padded with a zero row), dims giving K/2 and F/2; biases and the output layer fp32."""
        key = (self._key(), bf16)
        if self._fused_key != key:
            mlp = self.model.mlp
            dims, parts, offset, k_in = [], [], 0, mlp.in_dim
            for i, lin in enumerate(mlp.hidden):
                w = lin.weight.detach().float()
                f = mlp.feature_dim if (i == mlp.config.feature_layer + 1 and mlp.feature_dim) else 0
                w_f, w_h = w[:, :f], w[:, f:]
                n_out = _lanes(w.shape[0])
                pad = lambda t, rows: torch.nn.functional.pad(t, (0, n_out - t.shape[1], 0, rows - t.shape[0]))  # noqa: E731
                bias = pad(lin.bias.detach().float()[None], 1).view(torch.int32)
                if bf16:
                    k2, f2 = -(-k_in // 2), -(-f // 2)
                    block = [_bf16_pairs(pad(w_h.t(), 2 * k2)), _bf16_pairs(pad(w_f.t(), 2 * f2)), bias]
                    dims += [k2, n_out, f2, offset, offset + k2 * n_out]
                else:
                    block = [pad(w_h.t(), k_in).view(torch.int32), pad(w_f.t(), f).view(torch.int32), bias]
                    dims += [k_in, n_out, f, offset, offset + k_in * n_out]
                parts += [b.reshape(-1) for b in block]
                offset += sum(b.numel() for b in block)
                k_in = n_out
            w_o = torch.nn.functional.pad(mlp.output.weight.detach().float(), (0, k_in - mlp.output.in_features))
            dims += [offset, k_in]
            parts += [w_o.reshape(-1).view(torch.int32), mlp.output.bias.detach().float().view(torch.int32)]
            widest = max([dims[5 * i + 1] for i in range(len(mlp.hidden))] + [1])
            self._fused = (torch.tensor(dims, dtype=torch.int64), torch.cat(parts).contiguous(), widest)
            self._fused_key = key
        return self._fused

    def encoding_table(self) -> torch.Tensor | None:
        """The first hidden layer's encoded part as per-coordinate tables for :meth:`shade_fused` (``pe_table``).

        The layer adds ``W_e PE(uv)`` to its bias; the encoding treats each coordinate x on its own (x, then sin and
        cos of 2^k pi x), so that sum is ``sum_c g_c(x_c)`` over the 2 or 4 encoded coordinates, with ``g_c`` a fixed
        function of one variable into the layer's width. Tabled at ``TABLE_NODES + 1`` nodes on [0, 1] with its
        derivative, a cubic Hermite interpolation replaces 2 L + 1 products per coordinate by four table rows; its
        error is about ``(2^(L-1) pi / TABLE_NODES)^4 / 384`` of the highest frequency's weights (6e-5 for L = 10).

        Returns (2 nuv, TABLE_NODES + 1, 2, N) float32, N the layer's width padded to 8 (g, then g' / TABLE_NODES),
        rebuilt when the weights change; None when the table does not apply (no hidden layer, or an encoded
        width other than 2 or 4 coordinates' encodings)."""
        key = self._key()
        if key == self._table_key:
            return self._table
        model, mlp = self.model, self.model.mlp
        pe = model.pe_uv
        per_uv = pe.out_dim  # one uv's encoding: (u, v) if included, then sin and cos of both per frequency
        nuv = len(model.spec.encoded_uvs)
        table = None
        if mlp.hidden and nuv in (1, 2) and mlp.in_dim == nuv * per_uv:
            lin = mlp.hidden[0]
            f = mlp.feature_dim if mlp.config.feature_layer + 1 == 0 else 0
            w = lin.weight.detach().to(torch.float64)[:, f:]  # (N, E): the encoded columns
            n_out = _lanes(w.shape[0])
            x = torch.arange(TABLE_NODES + 1, dtype=torch.float64) / TABLE_NODES  # (T + 1,)
            table = torch.zeros(2 * nuv, TABLE_NODES + 1, 2, n_out, dtype=torch.float64)
            for u in range(nuv):
                for d in range(2):
                    base, g, dg = u * per_uv, table[2 * u + d, :, 0, : w.shape[0]], table[2 * u + d, :, 1, : w.shape[0]]
                    if pe.include_input:
                        g += x[:, None] * w[:, base + d]
                        dg += w[:, base + d]
                    first = base + (2 if pe.include_input else 0)
                    for k in range(pe.num_freqs):
                        freq = math.pi * 2.0**k
                        ws, wc = w[:, first + 4 * k + d], w[:, first + 4 * k + 2 + d]
                        sn, cs = torch.sin(freq * x)[:, None], torch.cos(freq * x)[:, None]
                        g += sn * ws + cs * wc
                        dg += freq * (cs * ws - sn * wc)
            table[:, :, 1] /= TABLE_NODES
            table = table.float().contiguous()
        self._table, self._table_key = table, key
        return table

    def projected_maps(self, features: FrameFeatures) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor | None] | None:
        """The feature layer's feature part as maps for :meth:`shade_fused` (``project_features``).

        The layer after the concatenation adds ``Wf_o f_o + Wf_i f_i`` (the outer sample at uv_outer, then the inner
        one at uv_inner); a bilinear sample is a weighted sum of texels, so it commutes with the product:
        ``Wf_i sample(map_in, uv) = sample(map_in Wf_i^T, uv)``. With the maps projected once per frame's features
        (per pose: every camera shares them), each ray samples N columns and skips the F N products.

        Returns (outer map x Wf_o^T or None, inner map x Wf_i^T, outer map x Wf_i^T for peeled rays or None), each
        (S, S, N) float32, N the layer's width padded to 8; cached for the last features (held, so the key stays
        unique) and weights. None when nothing is to project (no feature columns, several frames, non-fp32 maps)
        or the maps would exceed :data:`PROJECTED_MAX_BYTES`."""
        mlp, spec = self.model.mlp, self.model.spec
        inner, outer = features.inner, features.outer if spec.outer_unet else None
        if not mlp.feature_dim or features.batch_size != 1 or inner.dtype != torch.float32:
            return None
        S, C = int(inner.shape[2]), int(inner.shape[1])
        n_out = _lanes(mlp.hidden[mlp.config.feature_layer + 1].out_features)
        count = (outer is not None) + 1 + (outer is not None and spec.inner_from_outer)
        if count * S * S * n_out * 4 > PROJECTED_MAX_BYTES:
            return None
        key = (self._key(), id(inner), inner._version, id(outer), outer._version if outer is not None else None)
        with self._projected_lock:
            if self._projected_key == key:
                return self._projected
            w = mlp.hidden[mlp.config.feature_layer + 1].weight.detach().float()[:, : mlp.feature_dim]
            w = torch.nn.functional.pad(w, (0, 0, 0, n_out - w.shape[0]))  # (N, F), zero rows for padded outputs
            w_o, w_i = (w[:, :C], w[:, C:]) if outer is not None else (None, w)

            def project(m: torch.Tensor, wt: torch.Tensor) -> torch.Tensor:
                return (m[0].permute(1, 2, 0).reshape(S * S, C) @ wt.t()).reshape(S, S, n_out).contiguous()

            maps = (project(outer, w_o) if outer is not None else None, project(inner, w_i),
                    project(outer, w_i) if outer is not None and spec.inner_from_outer else None)
            # the key holds the features' ids: keep them alive so no other tensor takes their id
            self._projected, self._projected_key, self._projected_features = maps, key, (inner, outer)
            return maps

    def fused_bf16(self) -> bool:
        """Whether :meth:`shade_fused` runs its hidden layers in bf16: the shader's dtype is bf16 and the fused kernel
        was built with native bf16 dot products (AVX512-BF16) this CPU has; else the pass is fp32."""
        lib = _FUSED.get() if self.fused and self.use_kernel and self.dtype == torch.bfloat16 else None
        return lib is not None and bool(lib.deliffas_fused_bf16())

    def fused_available(self) -> bool:
        """Whether :meth:`shade_fused` runs its C pass (``fused=True`` and the kernel built)."""
        return self.fused and self.use_kernel and _FUSED.get() is not None

    def shade_fused(self, features: FrameFeatures, query: RayQuery, out: torch.Tensor | None = None,
                    rows: torch.Tensor | None = None) -> torch.Tensor:
        """``mlp(*inputs(...), out, rows)`` in one C pass, the hidden layers in bf16 where :meth:`fused_bf16`, else
        fp32 (module docstring); the per-stage path where the pass is unavailable or cannot read the inputs."""
        lib = _FUSED.get() if self.fused and self.use_kernel else None
        got = self._ray_args(features, query) if lib is not None else None
        if got is None:
            return self.mlp(*self.inputs(features, query), out=out, rows=rows)
        n = query.num_rays
        out, rows = self._check_out(n, out, rows)
        bf16 = self.fused_bf16()
        dims, params, widest = self._fused_params(bf16)
        table = self.encoding_table() if self.pe_table and not bf16 else None
        projected = self.projected_maps(features) if self.project_features and not bf16 else None
        projected = projected if projected is not None else (None, None, None)
        model = self.model
        status = lib.deliffas_fused_shade(n, *got[0], len(model.mlp.hidden), dims.data_ptr(), params.data_ptr(),
                                          model.mlp.in_dim, model.mlp.feature_dim, widest,
                                          rows.data_ptr() if rows is not None else None, out.data_ptr(), int(bf16),
                                          table.data_ptr() if table is not None else None, TABLE_NODES,
                                          *(t.data_ptr() if t is not None else None for t in projected))
        if status == -2:
            raise ValueError(f"FastShader.shade_fused: at most 512 feature channels per map, got {features.inner.shape[1]}")
        if status != 0:
            raise MemoryError("FastShader.shade_fused: the scratch tiles could not be allocated")
        return out

    @staticmethod
    def _check_out(n: int, out: torch.Tensor | None, rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        if out is None:
            return torch.empty(n, 3, dtype=torch.float32), None
        if rows is None or rows.shape != (n,) or rows.dtype != torch.int64 or out.dtype != torch.float32 \
                or out.dim() != 2 or out.shape[1] != 3 or not out.is_contiguous():
            raise ValueError("FastShader: out must be a contiguous (P, 3) float32 canvas and rows (N,) int64")
        return out, rows.contiguous()

    # ------------------------------------------------------------------ MLP
    def mlp(self, enc: torch.Tensor, feats: torch.Tensor, out: torch.Tensor | None = None,
            rows: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) float32 RGB of the operands from :meth:`inputs`; or, with ``out`` (P, 3) float32 and ``rows`` (N,)
        int64, ray i's colour written to ``out[rows[i]]`` (an image canvas) and ``out`` returned.

        Hidden layers: ``addmm`` into two buffers reused across row chunks; the output layer, its sigmoid
        and the write: one C pass in fp32 (``use_kernel=False`` or no kernel: torch's fp32 product)."""
        layers = self.layers()
        hidden, (w_out, _, b_out) = layers[:-1], layers[-1]
        n = enc.shape[0]
        out, rows = self._check_out(n, out, rows)
        lib = _KERNEL.get() if self.use_kernel else None
        chunk = min(self.row_chunk, max(n, 1))
        widths = [w_h.shape[1] for w_h, _, _ in hidden]
        bufs = [torch.empty(chunk, max(widths), dtype=self.dtype) for _ in range(2)]
        rows_c = rows
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            h = enc[start:start + m]
            f = feats[start:start + m]
            for i, (w_h, w_f, bias) in enumerate(hidden):
                y = bufs[i % 2][:m, : w_h.shape[1]]
                torch.addmm(bias, h, w_h, out=y)
                if w_f is not None:
                    y.addmm_(f, w_f)
                h = y.relu_()
            if lib is not None:
                lib.deliffas_rgb_out(m, h.data_ptr(), h.stride(0), int(h.dtype == torch.bfloat16), h.shape[1],
                                     w_out.data_ptr(), b_out.data_ptr(),
                                     rows_c[start:].data_ptr() if rows_c is not None else None,
                                     out.data_ptr() if rows_c is not None else out[start:].data_ptr())
            else:
                rgb = torch.addmm(b_out, h.float(), w_out.t()).sigmoid_()
                if rows_c is None:
                    out[start:start + m] = rgb
                else:
                    out.index_copy_(0, rows_c[start:start + m], rgb)
        return out

    @torch.no_grad()
    def shade(self, features: FrameFeatures, query: RayQuery) -> torch.Tensor:
        """(N, 3) float32 RGB in (0, 1): ``model.shade(features, query)`` within the dtype's precision."""
        return self.mlp(*self.inputs(features, query))
