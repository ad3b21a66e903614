/* The whole shading of a ray in one pass (deliffas/fast/shade.py, FastShader.shade_fused), a tile of rays at a
   time with the rays in the vector lanes (GCC/clang vector extensions: 16 rays in AVX-512 registers, 8 in AVX2's
   under -march=native): encodings and samples (fused_tiles.h, into a transposed tile), every hidden layer (bias,
   products, ReLU) in fp32 from tile to tile in L1, the output layer, its sigmoid and the write into the canvas.
   Nothing per ray reaches memory but its colour. FMA contraction is on here (a separate build), so values differ
   from torch's fp32 in the last bits. */
#include "fused_shade.h"
#include "fused_tiles.h"

#include <stddef.h>
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

/* deliffas_fused_shade's arguments (see there) and what follows from them, shared by its steps. */
typedef struct {
    int64_t n;
    const float *uv_in;
    const uint8_t *from_outer;
    const float *uv_out;
    int outer_encoded, L, include_input;
    const float *map_in, *map_out;
    int64_t S, C;
    const dir_args *dir;
    int64_t nh;
    const int64_t *dims;
    const float *params;
    int64_t E, Fd, wmax;
    const int64_t *pixels;
    float *out;
    int bf16;
    const float *pe_table;
    int64_t table_nodes;
    const float *proj_out, *proj_in, *proj_peel;
    const float *uvs[2];  /* the uvs the tables read: the encoded outer ones (or the inner), the inner */
    int nuv;
    const float *wo, *bo;  /* the output layer and its bias */
    int64_t per_uv, De;    /* encoded rows per uv; the uvs' rows (the direction's follow) */
    const float *tex_in, *tex_out;  /* texture atlases apart from the maps (NULL: none, or joined to the maps) */
    int64_t St, Ct;                 /* their side and channels */
} fused_args;

/* A tile's scratch, TILE rays a row: E encoded and Fd feature rows, two hidden layers of wmax rows, rows (TILE, N)
   for a layer that starts from rows, and the bf16 pairs. */
typedef struct {
    vtile *xe, *xf, *h[2], *rows, *pairs;
} tile_scratch;

/* The tiles of a group: their first rays and ray counts, whether the first layer's encoded part came from the tables,
   and their from_outer flags (NULL without an outer map). */
typedef struct {
    int nt;
    int64_t r0[GROUP], m[GROUP];
    int tabled[GROUP];
    const uint8_t *peel[GROUP];
} tile_group;

/* The inputs of rays [r0, r0 + m) into tile t of the group: the first layer's encoded part from the tables (into
   rows) or the encoding (unless the bf16 layers encode straight into pairs), the direction, the sampled features
   (unless projected). */
static inline void tile_inputs(const fused_args *a, const tile_scratch *s, tile_group *g, int t, int64_t r0,
                               int64_t m) {
    int pairs_direct = FUSED_BF16 && a->bf16 && a->nh > 0;  /* encodings straight into bf16 pairs */
    const int64_t *dims = a->dims;
    g->r0[t] = r0; g->m[t] = m; g->tabled[t] = 0;
    if (a->pe_table && a->nh > 0) {
        const float *tile_uvs[2] = {a->uvs[0] + 2 * r0, a->uvs[1] + 2 * r0};
        g->tabled[t] = table_layer(tile_uvs, a->nuv, m, a->pe_table, a->table_nodes, dims[1],
                                   a->params + dims[3] + dims[0] * dims[1] + dims[2] * dims[1], (float *)s->rows);
    }
    if (!pairs_direct && !g->tabled[t]) {
        float *xt = (float *)s->xe;
        void (*encode)(const float *, int64_t, int, int, float *) = a->bf16 ? encode_tile_f32 : encode_tile;
        if (a->outer_encoded) { encode(a->uv_out + 2 * r0, m, a->L, a->include_input, xt); xt += a->per_uv * TILE; }
        encode(a->uv_in + 2 * r0, m, a->L, a->include_input, xt);
    }
    if (a->dir) encode_dir_tile(a->dir, r0, a->uv_in + 2 * r0, m, (float *)(s->xe + a->De));  /* also where tabled */
    g->peel[t] = (a->map_out && a->from_outer) ? a->from_outer + r0 : 0;
    if (!a->proj_in) {  /* per surface: its map's C channels, then its atlas's Ct where apart (each at its side) */
        float *ft = (float *)s->xf;
        if (a->map_out) {
            sample_tile(a->map_out, a->map_out, 0, a->uv_out + 2 * r0, m, a->S, a->C, ft); ft += a->C * TILE;
            if (a->tex_out) { sample_tile(a->tex_out, a->tex_out, 0, a->uv_out + 2 * r0, m, a->St, a->Ct, ft); ft += a->Ct * TILE; }
        }
        sample_tile(a->map_in, a->map_out, g->peel[t], a->uv_in + 2 * r0, m, a->S, a->C, ft); ft += a->C * TILE;
        if (a->tex_in) sample_tile(a->tex_in, a->tex_out, g->peel[t], a->uv_in + 2 * r0, m, a->St, a->Ct, ft);
    }
}

#if FUSED_BF16
/* The bf16 hidden layers and the colours of rays [r0, r0 + m), a tile: the encodings straight into pairs, the
   direction's and the features' rows paired, each layer's output as pairs (the last one's as fp32 rows). */
static inline void shade_tile_bf16(const fused_args *a, const tile_scratch *s, int64_t r0, int64_t m) {
    int64_t E = a->E, Fd = a->Fd, De = a->De;
    __m512bh *pe = (__m512bh *)s->pairs, *pf = pe + (E + 1) / 2;
    __m512bh *ph[2] = {pf + (Fd + 1) / 2, pf + (Fd + 1) / 2 + a->wmax / 2};
    __m512bh *pp = pe;
    if (a->outer_encoded) { encode_pairs(a->uv_out + 2 * r0, m, a->L, a->include_input, pp); pp += a->per_uv / 2; }
    encode_pairs(a->uv_in + 2 * r0, m, a->L, a->include_input, pp);
    pair_tile(s->xe + De, E - De, pe + De / 2);  /* the direction's rows (De is even) */
    pair_tile(s->xf, Fd, pf);
    const __m512bh *xp = pe;
    const uint32_t *words = (const uint32_t *)a->params;
    for (int64_t l = 0; l < a->nh; l++) {
        const int64_t *d = a->dims + 5 * l;
        const uint32_t *w = words + d[3], *wf = words + d[4];
        const float *b = a->params + d[3] + d[0] * d[1] + d[2] * d[1];
        dense_bf16(xp, d[0], w, b, d[2] ? pf : 0, d[2], wf, d[1], ph[l & 1], l == a->nh - 1 ? s->h[0] : 0);
        xp = ph[l & 1];
    }
    write_colours(s->h[0], a->dims[5 * a->nh + 1], a->wo, a->bo, m, a->pixels, r0, a->out);
}
#endif

/* Layer l of the group's tiles that start from rows (the tables' encoded part, projected features: b + those into
   rows, transposed into the layer's output tile, which dense2 then adds to); returns 1 when every tile starts
   alike (both from the tables, or neither), so dense2 can take two at once. */
static inline int start_from_rows(const fused_args *a, const tile_scratch *s, const tile_group *g, int64_t l,
                                  const float *b, int projected) {
    const int64_t *d = a->dims + 5 * l;
    int alike = 1;
    for (int t = 0; t < g->nt; t++) {
        int from_table = l == 0 && g->tabled[t];
        alike &= from_table == (l == 0 && g->tabled[0]);
        if (projected || from_table) {  /* the layer starts from rows: b + the encoded part and/or the projected features */
            if (!from_table) bias_rows(b, d[1], (float *)s[t].rows);
            if (projected)
                add_projected(a->map_out ? a->proj_out : 0, a->uv_out + 2 * g->r0[t], a->proj_in, a->proj_peel,
                              g->peel[t], a->uv_in + 2 * g->r0[t], g->m[t], a->S, d[1], (float *)s[t].rows);
            rows_to_tile((const float *)s[t].rows, d[1], s[t].h[l & 1]);
        }
    }
    return alike;
}

/* The fp32 hidden layers of a group's tiles (two tiles in one dense2 call where they start alike) and their
   colours. */
static inline void shade_group_fp32(const fused_args *a, const tile_scratch *s, const tile_group *g) {
    int nt = g->nt;
    const vtile *x[GROUP];
    for (int t = 0; t < nt; t++) x[t] = s[t].xe;
    for (int64_t l = 0; l < a->nh; l++) {
        const int64_t *d = a->dims + 5 * l;
        const float *w = a->params + d[3], *wf = a->params + d[4], *b = w + d[0] * d[1] + d[2] * d[1];
        int projected = d[2] && a->proj_in;
        int alike = start_from_rows(a, s, g, l, b, projected);
        int64_t F = projected ? 0 : d[2];
        int pair = nt == 2 && alike;  /* both tiles in one call; else each alone, passed twice */
        for (int t = 0; t < nt; t += 1 + pair) {
            int u = pair ? 1 : t, from_table = l == 0 && g->tabled[t];
            int64_t k0 = from_table ? a->De : 0;  /* tabled: the direction's rows remain */
            dense2(x[t] + k0, x[u] + k0, d[0] - k0, w + k0 * d[1], projected || from_table ? 0 : b, F ? s[t].xf : 0,
                   F ? s[u].xf : 0, F, wf, d[1], s[t].h[l & 1], s[u].h[l & 1]);
        }
        for (int t = 0; t < nt; t++) x[t] = s[t].h[l & 1];
    }
    for (int t = 0; t < nt; t++)
        write_colours(x[t], a->dims[5 * a->nh + 1], a->wo, a->bo, g->m[t], a->pixels, g->r0[t], a->out);
}

/* Shade rays [0, n): inputs as deliffas_ray_inputs (fp32; the direction's rows last of the E encoded); layers: nh hidden layers, per layer 5 int64 in dims
   (K, N, feature rows F (0 or the feature width), offset of W (K, N), of Wf (F, N)), the bias at W + K N + F N;
   then the output layer (3, K) and its bias (3,) at dims[5 nh]. E, Fd: the encoded and feature widths (E = the
   first layer's K); wmax: the widest hidden layer. Colour of ray r to out[3 pixels[r] ..] (out[3 r ..] if no
   pixels). params are 4-byte words: fp32, or with bf16 (deliffas_fused_bf16() must be 1) the hidden layers'
   weights as bf16 pairs, W (K/2, N) and Wf (F/2, N) with dims giving K/2 and F/2, biases and the output layer
   fp32. proj_in (with fp32 only): the feature layer's (the one with F > 0) feature part from projected maps
   (add_projected; S x S texels of that layer's N): proj_out at uv_out (NULL without an outer map), proj_in at uv_in,
   proj_peel at uv_in where from_outer (NULL without from_outer); no features sampled then. tex_in, tex_out: texture
   atlases (St x St texels of Ct channels) sampled apart, after each surface's map (tex_out where from_outer for the
   inner one); NULL where the maps carry them or there are none. Returns 0, -1 when the
   scratch tiles cannot be allocated, -2 for more than 512 channels per map, -3 for bf16 without the kernel. */
int deliffas_fused_shade(const deliffas_fused_shade_args *args) {
    /* the arguments as locals of their names (args, not a: the pass's fused_args is a) */
    int64_t n = args->n, S = args->S, C = args->C, nh = args->nh, E = args->E, Fd = args->Fd, wmax = args->wmax;
    int64_t table_nodes = args->table_nodes;
    int outer_encoded = args->outer_encoded, L = args->L, include_input = args->include_input, bf16 = args->bf16;
    const float *uv_in = args->uv_in, *uv_out = args->uv_out, *map_in = args->map_in, *map_out = args->map_out;
    const float *params = args->params, *pe_table = args->pe_table, *proj_out = args->proj_out;
    const float *proj_in = args->proj_in, *proj_peel = args->proj_peel;
    const uint8_t *from_outer = args->from_outer;
    const dir_args *dir = args->dir;
    const int64_t *dims = args->dims, *pixels = args->pixels;
    float *out = args->out;
    if (C > 512 || args->Ct > 512) return -2;
    if (bf16 && !FUSED_BF16) return -3;
    /* per tile, fp32: E + Fd input rows, two hidden layers and the rows; bf16: the inputs' and two hidden layers'
       pairs besides */
    int64_t per_tile = E + Fd + 3 * wmax + (bf16 ? (E + 1) / 2 + (Fd + 1) / 2 + wmax : 0);
    if (bf16) pe_table = proj_in = 0;  /* the table and the projected maps serve the fp32 pass */
    char *mem = aligned_alloc(64, (size_t)(GROUP * per_tile) * sizeof(vtile));
    if (!mem) return -1;
    tile_scratch s[GROUP];
    for (int t = 0; t < GROUP; t++) {
        s[t].xe = (vtile *)mem + t * per_tile; s[t].xf = s[t].xe + E; s[t].h[0] = s[t].xf + Fd;
        s[t].h[1] = s[t].h[0] + wmax; s[t].rows = s[t].h[1] + wmax; s[t].pairs = s[t].rows + wmax;
    }
    const float *wo = params + dims[5 * nh];
    fused_args a = {n, uv_in, from_outer, uv_out, outer_encoded, L, include_input, map_in, map_out, S, C, dir, nh, dims,
                    params, E, Fd, wmax, pixels, out, bf16, pe_table, table_nodes, proj_out, proj_in, proj_peel,
                    {outer_encoded ? uv_out : uv_in, uv_in}, outer_encoded ? 2 : 1, wo, wo + 3 * dims[5 * nh + 1],
                    (include_input ? 2 : 0) + 4 * (int64_t)L, E - dir_width(dir), args->tex_in, args->tex_out,
                    args->St, args->Ct};
    for (int64_t g0 = 0; g0 < n; g0 += GROUP * TILE) {
        tile_group g;
        for (g.nt = 0; g.nt < GROUP && g0 + g.nt * TILE < n; g.nt++) {
            int64_t r0 = g0 + g.nt * TILE, m = n - r0 < TILE ? n - r0 : TILE;
            tile_inputs(&a, &s[g.nt], &g, g.nt, r0, m);
#if FUSED_BF16
            if (bf16 && nh > 0) shade_tile_bf16(&a, &s[g.nt], r0, m);  /* the bf16 layers and colours, a tile at a time */
#endif
        }
        if (!(bf16 && nh > 0)) shade_group_fp32(&a, s, &g);
    }
    free(mem);
    return 0;
}

/* The layout of deliffas_fused_shade_args as this compiler lays it out: its sizeof, then the offsetof of each field
   in declaration order, into out (unless NULL); returns their number. deliffas/native.py checks the Structure it
   parses from fused_shade.h against it. */
#define FUSED_AT(f) (int64_t)offsetof(deliffas_fused_shade_args, f)
int64_t deliffas_fused_shade_args_layout(int64_t *out) {
    const int64_t layout[] = {
        (int64_t)sizeof(deliffas_fused_shade_args), FUSED_AT(uv_in), FUSED_AT(from_outer), FUSED_AT(uv_out),
        FUSED_AT(map_in), FUSED_AT(map_out), FUSED_AT(dir), FUSED_AT(dims), FUSED_AT(params), FUSED_AT(pixels),
        FUSED_AT(out), FUSED_AT(pe_table), FUSED_AT(proj_out), FUSED_AT(proj_in), FUSED_AT(proj_peel), FUSED_AT(tex_in),
        FUSED_AT(tex_out), FUSED_AT(n), FUSED_AT(S), FUSED_AT(C), FUSED_AT(nh), FUSED_AT(E), FUSED_AT(Fd), FUSED_AT(wmax),
        FUSED_AT(table_nodes), FUSED_AT(St), FUSED_AT(Ct), FUSED_AT(outer_encoded), FUSED_AT(L), FUSED_AT(include_input), FUSED_AT(bf16)};
    int64_t count = (int64_t)(sizeof layout / sizeof layout[0]);
    for (int64_t i = 0; out && i < count; i++) out[i] = layout[i];
    return count;
}
