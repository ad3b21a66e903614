/* The static helpers of the per-ray inputs (ray_inputs.c, whose exported functions are declared in ray_inputs.h):
   positional encodings, bilinear samples and the view direction per ray in one variant per output type (fp32,
   bf16), and the output layer's sigmoid. Included by ray_inputs.c and, through fused_tiles.h, by fused_shade.c
   (one translation unit each, so these inline into their callers). Built without FMA contraction and without
   fast-math in ray_inputs.c; fused_shade.c builds them with its own flags. */
#ifndef DELIFFAS_RAY_INPUTS_IMPL_H
#define DELIFFAS_RAY_INPUTS_IMPL_H
#include "ray_inputs.h"

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Rows of one encoded direction: 3 (include_input + 2 L). */
static inline int64_t dir_width(const dir_args *dir) {
    return dir ? 3 * ((dir->include_input ? 1 : 0) + 2 * (int64_t)dir->L) : 0;
}

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
   encode: positional encoding of one point x of D <= 3 coordinates (a uv, a direction) into out[i0 ..]: x, then
   per k: sin(a_k x_d) for each d, cos(a_k x_d) for each d, a_k x = 2^k float(x * float(pi)) (what torch rounds
   x * float(2^k pi) to), by the double-angle recurrence in float64.
   sample: bilinear lookup of a channels_last (S, S, C) map at uv (grid_sample, align_corners False, border).
   rows: rows [start, stop) of enc (n, E): PE(uv_outer) if outer_encoded, then PE(uv_inner), then with dir the
   encoded direction (ray_direction); and of
   feats (n, F): the outer map at uv_outer if map_out is given, then the inner feature (the outer map at
   uv_inner where from_outer). */
#define VARIANT(NAME, T, PUT)                                                                                  \
static void encode_##NAME(const float *x, int D, int L, int include_input, T *out) {                           \
    int64_t i = 0;                                                                                             \
    if (include_input) for (int d = 0; d < D; d++, i++) PUT(out, i, x[d]);                                     \
    if (L == 0) return;                                                                                        \
    const float pi = (float)3.14159265358979323846;                                                            \
    double s[3], c[3];                                                                                         \
    for (int d = 0; d < D; d++) sin_cos((double)(x[d] * pi), &s[d], &c[d]);                                    \
    for (int k = 0; k < L; k++) {                                                                              \
        for (int d = 0; d < D; d++) { PUT(out, i + d, (float)s[d]); PUT(out, i + D + d, (float)c[d]); }        \
        i += 2 * D;                                                                                            \
        for (int d = 0; d < D; d++) {                                                                          \
            double t = 2.0 * s[d] * c[d];                                                                      \
            c[d] = c[d] * c[d] - s[d] * s[d]; s[d] = t;                                                        \
        }                                                                                                      \
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
                        const float *map_out, int64_t S, int64_t C, const dir_args *dir, T *enc, int64_t E,   \
                        T *feats, int64_t F) {                                                                 \
    int64_t per_uv = (include_input ? 2 : 0) + 4 * (int64_t)L;                                                 \
    for (int64_t r = start; r < stop; r++) {                                                                   \
        T *e = enc + r * E, *f = feats + r * F;                                                                \
        if (outer_encoded) { encode_##NAME(uv_out + 2 * r, 2, L, include_input, e); e += per_uv; }             \
        encode_##NAME(uv_in + 2 * r, 2, L, include_input, e);                                                 \
        if (dir) {                                                                                             \
            float d[3];                                                                                        \
            ray_direction(dir, r, uv_in + 2 * r, d);                                                           \
            encode_##NAME(d, 3, dir->L, dir->include_input, e + per_uv);                                       \
        }                                                                                                      \
        if (map_out) { sample_##NAME(map_out, S, C, uv_out + 2 * r, f); f += C; }                              \
        const float *m = (from_outer && from_outer[r] && map_out) ? map_out : map_in;                          \
        sample_##NAME(m, S, C, uv_in + 2 * r, f);                                                              \
    }                                                                                                          \
}

static void sample_f32(const float *map, int64_t S, int64_t C, const float *uv, float *out);

/* The direction ray r encodes, into out (3): its view direction d, or with dir->normals its reflection about the
   unit normal at uv, in DeliffasModel._reflected's order: n = sample / max(|sample|, 1e-6), d - (2 (d . n)) n. */
static void ray_direction(const dir_args *dir, int64_t r, const float *uv, float out[3]) {
    const float *d = dir->viewdir + 3 * r;
    if (!dir->normals) { out[0] = d[0]; out[1] = d[1]; out[2] = d[2]; return; }
    float n[3];
    sample_f32(dir->normals, dir->S, 3, uv, n);
    float len = sqrtf(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    len = len > 1e-6f ? len : 1e-6f;
    n[0] /= len; n[1] /= len; n[2] /= len;
    float t = 2.0f * (d[0] * n[0] + d[1] * n[1] + d[2] * n[2]);
    out[0] = d[0] - t * n[0]; out[1] = d[1] - t * n[1]; out[2] = d[2] - t * n[2];
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

#endif
