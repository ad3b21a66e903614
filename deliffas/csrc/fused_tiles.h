/* The inputs of a tile of rays for the fused pass (fused_shade.c, which includes this header: its static functions
   inline into the pass): the rays in the vector lanes (GCC/clang vector extensions: 16 rays in AVX-512 registers, 8
   in AVX2's under -march=native), their positional encodings, view directions and bilinear samples written as
   transposed tiles (a row per input, TILE rays a row), as ray_inputs.c computes them per ray (its helpers in
   ray_inputs_impl.h); and the first layer's encoded part from per-coordinate tables. */
#ifndef DELIFFAS_FUSED_TILES_H
#define DELIFFAS_FUSED_TILES_H
#include "ray_inputs_impl.h"

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

/* The positional encoding of a tile's points x (D <= 3 coordinates of TILE rays: a uv, a direction) into xt (rows,
   TILE), as encode_f32 per ray: sin and cos by the same reduction and series, written so the compiler vectorises over
   the tile (rounding to the nearest multiple of pi by the 1.5 2^52 shift instead of nearbyint). */
static inline void encode_points(float x[][TILE], int D, int L, int include_input, float *xt) {
    const float pi = (float)3.14159265358979323846;
    const double dpi = 3.14159265358979323846, shift = 6755399441055744.0;
    double s[3][TILE], c[3][TILE];
    for (int d = 0; d < D; d++) {
        if (include_input)
            for (int64_t i = 0; i < TILE; i++) xt[d * TILE + i] = x[d][i];
        for (int64_t i = 0; i < TILE; i++) {
            double a = (double)(x[d][i] * pi);
            double k = (a * (1.0 / dpi) + shift) - shift, r = a - k * dpi, r2 = r * r;
            double sn = r * (1.0 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880
                          + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0))))))));
            double cs = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800
                          + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0 + r2 * (1.0 / 20922789888000.0))))))));
            /* k's parity: for a direction in doubles, which vectorises the loop on AVX2 (it has no double <-> int64
               conversion): 1.9 against 4.7-5.0 ms for 197 k rays; a uv's scalar loop was the faster (7.2 against 8.4 ms) */
            double sign = D == 3 ? 1.0 - 2.0 * (k - 2.0 * floor(0.5 * k)) : 1.0 - 2.0 * (double)((int64_t)k & 1);
            s[d][i] = sign * sn;
            c[d][i] = sign * cs;
        }
    }
    float *o = xt + (include_input ? D : 0) * TILE;
    for (int k = 0; k < L; k++, o += 2 * D * TILE) {
        for (int d = 0; d < D; d++)
            for (int64_t i = 0; i < TILE; i++) {
                o[d * TILE + i] = (float)s[d][i];
                o[(D + d) * TILE + i] = (float)c[d][i];
            }
        for (int d = 0; d < D; d++)
            for (int64_t i = 0; i < TILE; i++) {
                double t = 2.0 * s[d][i] * c[d][i];
                c[d][i] = c[d][i] * c[d][i] - s[d][i] * s[d][i];
                s[d][i] = t;
            }
    }
}

/* encode_points of the uvs [0, m) of a tile (a partial tile repeats its last uv). */
static void encode_tile(const float *uv, int64_t m, int L, int include_input, float *xt) {
    float u[2][TILE];
    for (int64_t i = 0; i < TILE; i++)
        for (int d = 0; d < 2; d++) u[d][i] = uv[2 * (i < m ? i : m - 1) + d];
    encode_points(u, 2, L, include_input, xt);
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

/* The encoded direction of rays [0, m) of a tile (ray_direction, then encode_f32, per ray; the last ray repeated past
   m) into xt (dir_width(dir) rows, TILE): dir's rays from r0 on, uv their inner uvs (r0's first); the normal's taps
   (tile_taps), the reflection and the encoding computed over the tile. */
static void encode_dir_tile(const dir_args *dir, int64_t r0, const float *uv, int64_t m, float *xt) {
    float x[3][TILE];
    for (int64_t i = 0; i < TILE; i++)
        for (int d = 0; d < 3; d++) x[d][i] = dir->viewdir[3 * (r0 + (i < m ? i : m - 1)) + d];
    if (dir->normals) {
        float w[4][TILE];
        int64_t o[4][TILE];
        tile_taps(uv, m, dir->S, 3, w, o);
        for (int64_t i = 0; i < TILE; i++) {
            float nv[3];
            for (int d = 0; d < 3; d++) {
                const float *p = dir->normals + d;
                nv[d] = w[0][i] * p[o[0][i]] + w[1][i] * p[o[1][i]] + w[2][i] * p[o[2][i]] + w[3][i] * p[o[3][i]];
            }
            float len = sqrtf(nv[0] * nv[0] + nv[1] * nv[1] + nv[2] * nv[2]);
            len = len > 1e-6f ? len : 1e-6f;
            for (int d = 0; d < 3; d++) nv[d] /= len;
            float t = 2.0f * (x[0][i] * nv[0] + x[1][i] * nv[1] + x[2][i] * nv[2]);
            for (int d = 0; d < 3; d++) x[d][i] -= t * nv[d];
        }
    }
    encode_points(x, 3, dir->L, dir->include_input, xt);
}

#endif
