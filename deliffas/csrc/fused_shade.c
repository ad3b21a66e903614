/* The whole shading of a ray in one pass (deliffas/fast/shade.py, FastShader.shade_fused), a tile of rays at a
   time with the rays in the vector lanes (GCC/clang vector extensions: 16 rays in AVX-512 registers, 8 in AVX2's
   under -march=native): encodings and samples (fused_tiles.c, into a transposed tile), every hidden layer (bias,
   products, ReLU) in fp32 from tile to tile in L1, the output layer, its sigmoid and the write into the canvas.
   Nothing per ray reaches memory but its colour. FMA contraction is on here (a separate build), so values differ
   from torch's fp32 in the last bits. */
#include "fused_tiles.c"

#include <stdlib.h>

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

/* Shade rays [0, n): inputs as deliffas_ray_inputs (fp32; the direction's rows last of the E encoded); layers: nh hidden layers, per layer 5 int64 in dims
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
                         int64_t S, int64_t C, const dir_args *dir, int64_t nh, const int64_t *dims, const float *params, int64_t E,
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
    int64_t per_uv = (include_input ? 2 : 0) + 4 * (int64_t)L, De = E - dir_width(dir);  /* De: the uvs' rows */
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
            if (dir) encode_dir_tile(dir, r0, uv_in + 2 * r0, m, (float *)(xe[t] + De));  /* also where tabled */
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
                pair_tile(xe[t] + De, E - De, pe + De / 2);  /* the direction's rows (De is even) */
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
                int64_t k0 = from_table ? De : 0;  /* tabled: the direction's rows remain */
                dense2(x[t] + k0, x[u] + k0, d[0] - k0, w + k0 * d[1], projected || from_table ? 0 : b, F ? xf[t] : 0,
                       F ? xf[u] : 0, F, wf, d[1], h[t][l & 1], h[u][l & 1]);
            }
            for (int t = 0; t < nt; t++) x[t] = h[t][l & 1];
        }
        for (int t = 0; t < nt; t++) write_colours(x[t], od[1], wo, bo, ms[t], pixels, r0s[t], out);
    }
    free(mem);
    return 0;
}
