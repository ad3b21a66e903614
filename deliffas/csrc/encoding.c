/* Positional encodings of several coordinate sets written into one row-major (n, E) float32 array
   (deliffas/models/encoding.py, encode_parts): part p's D_p (include_p + 2 L_p) columns follow part p-1's,
   each row in positional_encoding's NeRF order [x, sin(a_0 x), cos(a_0 x), sin(a_1 x), ...], each block all
   D_p coordinates. The angle is the float32 product torch forms, a_k x = float(x * float(2^k pi)), which is
   2^k float(x * float(pi)) exactly (a power of two scales without rounding): sin and cos of float(x * float(pi))
   in double (reduction by the nearest multiple of pi, Taylor to degree 16, error < 1e-11), then the double-angle
   recurrence in double, which doubles the error at each step (< 1e-8 at the 10th frequency, < 1e-6 at the 16th,
   MAX_FREQS, for |x| <= MAX_ABS), rounded to float once. Rows go in blocks; every loop over a block's
   coordinates vectorises (no libm call, no integer conversion), and the rows are then assembled by small copies.
   Built without FMA contraction and without fast-math (-fno-trapping-math lets nearbyint and floor vectorise). */
#include "encoding.h"
#include <math.h>
#include <stdint.h>
#include <string.h>

#define BLOCK 64
#define MAX_FREQS 16
#define MAX_ABS 1e4f
#define MAX_DIMS 4

/* sin and cos of a (|a| <= pi MAX_ABS) in double, branch-free: a = k pi + r, |r| <= pi / 2, Taylor to degree 16
   ((pi/2)^17 / 17! < 1e-11); the sign (-1)^k from k - 2 floor(k / 2) in double. */
static inline void sin_cos(double a, double *s, double *c) {
    const double pi = 3.14159265358979323846;
    double k = nearbyint(a * (1.0 / pi)), r = a - k * pi, r2 = r * r;
    double sn = r * (1.0 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880
                  + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0))))))));
    double cs = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800
                  + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0 + r2 * (1.0 / 20922789888000.0))))))));
    double sign = 1.0 - 2.0 * (k - 2.0 * floor(k * 0.5));
    *s = sign * sn;
    *c = sign * cs;
}

/* Rows [0, m) (m <= BLOCK) of one part: x (m, D) row-major, into out's columns [0, width) at row stride E. Every
   loop over the block's m D coordinates vectorises: sin and cos, then per frequency the values as floats into
   f (the columns of frequency k, in x's order) and the doubling; then each row copies its 2 D values per frequency. */
#define COPY_ROWS(D)                                                                                          \
    for (int64_t r = 0; r < m; r++) {                                                                         \
        float *restrict o = out + r * E;                                                                      \
        if (include_input) { memcpy(o, x + r * (D), (D) * sizeof(float)); o += (D); }                         \
        for (int k = 0; k < L; k++, o += 2 * (D)) {                                                           \
            memcpy(o, f[k][0] + r * (D), (D) * sizeof(float));                                                \
            memcpy(o + (D), f[k][1] + r * (D), (D) * sizeof(float));                                          \
        }                                                                                                     \
    }

static void encode_block(const float *restrict x, int64_t m, int D, int L, int include_input,
                         float *restrict out, int64_t E) {
    const float pi = (float)3.14159265358979323846;
    const int64_t md = m * D;
    double s[BLOCK * MAX_DIMS], c[BLOCK * MAX_DIMS];
    float f[MAX_FREQS][2][BLOCK * MAX_DIMS];
    for (int64_t i = 0; i < md; i++) s[i] = (double)(x[i] * pi);
    for (int64_t i = 0; i < md; i++) sin_cos(s[i], &s[i], &c[i]);
    for (int k = 0; k < L; k++) {
        float *restrict fs = f[k][0], *restrict fc = f[k][1];
        for (int64_t i = 0; i < md; i++) {
            fs[i] = (float)s[i];
            fc[i] = (float)c[i];
            double t = 2.0 * s[i] * c[i];
            c[i] = (c[i] - s[i]) * (c[i] + s[i]);
            s[i] = t;
        }
    }
    switch (D) {  /* fixed sizes: the copies are single moves */
        case 2: COPY_ROWS(2) break;
        case 3: COPY_ROWS(3) break;
        default: COPY_ROWS(D)
    }
}

/* Encode `parts` coordinate sets of n rows each: xs[p] (n, dims[p]) float32 row-major, freqs[p] = L_p in
   [0, MAX_FREQS], include[p] 0 or 1, into out (n, E). Returns 0; 1 when a dimension or frequency count is out of
   range or the parts' widths do not sum to E; 2 when a coordinate exceeds MAX_ABS in magnitude, beyond the
   reduction's accuracy (nothing is written in either case; NaN and its encodings are NaN, as in torch). */
int64_t deliffas_encode_parts_f32(int32_t parts, const float *const *xs, const int32_t *dims, const int32_t *freqs,
                                  const int32_t *include, int64_t n, float *out, int64_t E) {
    int64_t total = 0;
    for (int32_t p = 0; p < parts; p++) {
        if (dims[p] < 1 || dims[p] > MAX_DIMS || freqs[p] < 0 || freqs[p] > MAX_FREQS) return 1;
        total += (int64_t)dims[p] * ((include[p] ? 1 : 0) + 2 * (int64_t)freqs[p]);
    }
    if (total != E) return 1;
    for (int32_t p = 0; p < parts; p++) {
        int bad = 0;
        for (int64_t i = 0; i < n * dims[p]; i++) bad |= fabsf(xs[p][i]) > MAX_ABS;
        if (bad) return 2;
    }
    for (int64_t r0 = 0; r0 < n; r0 += BLOCK) {
        int64_t m = n - r0 < BLOCK ? n - r0 : BLOCK, col = 0;
        for (int32_t p = 0; p < parts; p++) {
            encode_block(xs[p] + r0 * dims[p], m, dims[p], freqs[p], include[p], out + r0 * E + col, E);
            col += (int64_t)dims[p] * ((include[p] ? 1 : 0) + 2 * (int64_t)freqs[p]);
        }
    }
    return 0;
}
