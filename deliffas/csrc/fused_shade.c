/* The whole shading of a ray in one pass (deliffas/fast/shade.py, FastShader.shade_fused), a tile of rays at a
   time with the rays in the vector lanes (GCC/clang vector extensions: 16 rays in AVX-512 registers, 8 in AVX2's
   under -march=native): encodings and samples (ray_inputs.c, into a transposed tile), every hidden layer (bias,
   products, ReLU) in fp32 from tile to tile in L1, the output layer, its sigmoid and the write into the canvas.
   Nothing per ray reaches memory but its colour. FMA contraction is on here (a separate build), so values differ
   from torch's fp32 in the last bits. */
#include "ray_inputs.c"

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
