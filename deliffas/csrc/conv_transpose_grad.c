/* The gradients of a transposed convolution with kernel 4, stride 2, padding 1 (the U-Net's final layer in
   training; deliffas/models/unet_grad.py), one image, every map channels-last:
     forward   y[oy][ox][co] = sum of x[iy][ix][ci] w[ci][co][ky][kx] over iy, ky (oy = 2 iy + ky - 1), ix, kx, ci
     input     dx[iy][ix][ci] = sum over ky, kx, co of g[2 iy + ky - 1][2 ix + kx - 1][co] w[ci][co][ky][kx]
     weight    dw[ci][co][ky][kx] = sum over iy, ix of x[iy][ix][ci] g[2 iy + ky - 1][2 ix + kx - 1][co]
   (terms whose output pixel falls outside the map are left out). The weights come as wt[ky][kx][co][ci] and the
   weight gradient leaves as dwt[ky][kx][ci][co] (and, where db is not NULL, the bias gradient db[co], the sum of
   g over its pixels), so that the vectorised channels are contiguous: the input gradient runs 16 input channels
   per vector, the weight gradient 16 output channels in one vector (GNU vector extensions, split into two
   registers where the CPU's are narrower). Built for 16 input and 16 output channels (oneDNN was as fast for the
   32 -> 8 and 64 -> 16 layers below). Each sum runs in a fixed order (deterministic), with FMA contraction. The
   functions return 1 for channel counts they are not built for. */
#include "conv_transpose_grad.h"
#include <stdint.h>
#include <string.h>

#define ROWS_PER_BLOCK 8 /* input rows whose x and g stay in cache across the 16 taps of the weight gradient */

typedef float v16 __attribute__((vector_size(64)));
typedef float u16 __attribute__((vector_size(64), aligned(4), may_alias));

static inline v16 load16(const float *p) { return *(const u16 *)p; }
static inline void store16(float *p, v16 v) { *(u16 *)p = v; }

/* dx of 16 input channels (from cb) of one input pixel, any position: the taps whose output pixel is inside */
static void input_grad_pixel(const float *restrict g, const float *restrict wt, int64_t h, int64_t w, int64_t ci,
                             int64_t co, int64_t cb, int64_t iy, int64_t ix, float *restrict dx) {
    v16 acc = {0};
    for (int ky = 0; ky < 4; ky++) {
        const int64_t oy = 2 * iy + ky - 1;
        if (oy < 0 || oy >= 2 * h) continue;
        for (int kx = 0; kx < 4; kx++) {
            const int64_t ox = 2 * ix + kx - 1;
            if (ox < 0 || ox >= 2 * w) continue;
            const float *gr = g + (oy * 2 * w + ox) * co, *wk = wt + (ky * 4 + kx) * co * ci + cb;
            for (int64_t c = 0; c < co; c++) acc += gr[c] * load16(wk + c * ci);
        }
    }
    store16(dx + (iy * w + ix) * ci + cb, acc);
}

/* PIXELS input pixels of a row at once (PIXELS accumulators), every tap inside the map */
#define INPUT_GRAD(CI, CO, PIXELS)                                                                              \
    for (int64_t cb = 0; cb < CI; cb += 16)                                                                     \
        for (int64_t iy = 0; iy < h; iy++) {                                                                    \
            int64_t ix = 0;                                                                                     \
            if (iy > 0 && iy < h - 1) {                                                                         \
                input_grad_pixel(g, wt, h, w, CI, CO, cb, iy, 0, dx);                                           \
                for (ix = 1; ix + PIXELS <= w - 1; ix += PIXELS) {                                              \
                    v16 acc[PIXELS] = {{0}};                                                                    \
                    for (int ky = 0; ky < 4; ky++)                                                              \
                        for (int kx = 0; kx < 4; kx++) {                                                        \
                            const float *gr = g + ((2 * iy + ky - 1) * 2 * w + 2 * ix + kx - 1) * CO;           \
                            const float *wk = wt + (ky * 4 + kx) * CO * CI + cb;                                \
                            for (int c = 0; c < CO; c++) {                                                      \
                                const v16 wv = load16(wk + c * CI);                                             \
                                for (int p = 0; p < PIXELS; p++) acc[p] += gr[2 * p * CO + c] * wv;             \
                            }                                                                                   \
                        }                                                                                       \
                    for (int p = 0; p < PIXELS; p++) store16(dx + (iy * w + ix + p) * CI + cb, acc[p]);         \
                }                                                                                               \
            }                                                                                                   \
            for (; ix < w; ix++) input_grad_pixel(g, wt, h, w, CI, CO, cb, iy, ix, dx);                         \
        }

/* tap by tap over blocks of input rows, 16 input channels (from cb) in 16 accumulators of every output channel;
   the bias gradient in the loops of the four taps that visit every output pixel once (ky, kx in {1, 2}) */
#define WEIGHT_GRAD(CI, CO)                                                                                         \
    memset(dwt, 0, sizeof(float) * 16 * CI * CO);                                                                   \
    v16 bias_acc = {0};                                                                                             \
    for (int64_t y0 = 0; y0 < h; y0 += ROWS_PER_BLOCK) {                                                            \
        const int64_t y1 = y0 + ROWS_PER_BLOCK < h ? y0 + ROWS_PER_BLOCK : h;                                       \
        for (int tap = 0; tap < 16; tap++)                                                                          \
            for (int64_t cb = 0; cb < CI; cb += 16) {                                                               \
                const int ky = tap / 4, kx = tap % 4;                                                               \
                const int bias_tap = db && cb == 0 && (ky == 1 || ky == 2) && (kx == 1 || kx == 2);                 \
                float *out = dwt + (tap * CI + cb) * CO;                                                            \
                v16 acc[16];                                                                                        \
                for (int c = 0; c < 16; c++) acc[c] = load16(out + c * CO);                                         \
                const int64_t ix0 = kx == 0 ? 1 : 0, ix1 = kx == 3 ? w - 1 : w;                                     \
                for (int64_t iy = y0; iy < y1; iy++) {                                                              \
                    const int64_t oy = 2 * iy + ky - 1;                                                             \
                    if (oy < 0 || oy >= 2 * h) continue;                                                            \
                    for (int64_t ix = ix0; ix < ix1; ix++) {                                                        \
                        const float *xr = x + (iy * w + ix) * CI + cb;                                              \
                        const v16 gv = load16(g + (oy * 2 * w + 2 * ix + kx - 1) * CO);                             \
                        for (int c = 0; c < 16; c++) acc[c] += xr[c] * gv;                                          \
                        if (bias_tap) bias_acc += gv;                                                               \
                    }                                                                                               \
                }                                                                                                   \
                for (int c = 0; c < 16; c++) store16(out + c * CO, acc[c]);                                         \
            }                                                                                                       \
    }                                                                                                               \
    if (db) store16(db, bias_acc);

/* 1 where the 16-float vectors above are single registers (AVX-512): elsewhere the compiler splits them and the
   loops run several times slower than oneDNN, so the caller keeps torch's backward (the 8-float loops below run
   at full speed with AVX2 as well). */
int deliffas_conv_transpose_grad_wide_vectors(void) {
#ifdef __AVX512F__
    return 1;
#else
    return 0;
#endif
}

int deliffas_conv_transpose_k4s2_input_grad_f32(const float *restrict g, const float *restrict wt, int64_t h,
                                                 int64_t w, int64_t ci, int64_t co, float *restrict dx) {
    if (ci == 16 && co == 16) { INPUT_GRAD(16, 16, 8) return 0; }
    return 1;
}

int deliffas_conv_transpose_k4s2_weight_grad_f32(const float *restrict x, const float *restrict g, int64_t h,
                                                  int64_t w, int64_t ci, int64_t co, float *restrict dwt,
                                                  float *restrict db) {
    if (ci == 16 && co == 16) { WEIGHT_GRAD(16, 16) return 0; }
    return 1;
}

/* The weight gradient of a convolution with kernel 4, stride 2, padding 1 whose input needs none (the U-Net's
   first layer: 9 input channels, the temporal normal maps, 8 output channels), x of h x w pixels, g of h/2 x w/2:
     dw[co][ci][ky][kx] = sum over oy, ox of g[oy][ox][co] x[2 oy + ky - 1][2 ox + kx - 1][ci]
   left as dwt[ky][kx][ci][co]: the 8 output channels in one vector, tap by tap over blocks of output rows. */
typedef float v8 __attribute__((vector_size(32)));
typedef float u8 __attribute__((vector_size(32), aligned(4), may_alias));

#define CONV_WEIGHT_GRAD(CI)                                                                                        \
    memset(dwt, 0, sizeof(float) * 16 * CI * 8);                                                                    \
    for (int64_t y0 = 0; y0 < ho; y0 += ROWS_PER_BLOCK) {                                                           \
        const int64_t y1 = y0 + ROWS_PER_BLOCK < ho ? y0 + ROWS_PER_BLOCK : ho;                                     \
        for (int tap = 0; tap < 16; tap++) {                                                                        \
            const int ky = tap / 4, kx = tap % 4;                                                                   \
            float *out = dwt + tap * CI * 8;                                                                        \
            v8 acc[CI];                                                                                             \
            for (int c = 0; c < CI; c++) acc[c] = *(const u8 *)(out + c * 8);                                       \
            const int64_t ox0 = kx == 0 ? 1 : 0, ox1 = kx == 3 ? wo - 1 : wo;                                       \
            for (int64_t oy = y0; oy < y1; oy++) {                                                                  \
                const int64_t iy = 2 * oy + ky - 1;                                                                 \
                if (iy < 0 || iy >= h) continue;                                                                    \
                for (int64_t ox = ox0; ox < ox1; ox++) {                                                            \
                    const float *xr = x + (iy * w + 2 * ox + kx - 1) * CI;                                          \
                    const v8 gv = *(const u8 *)(g + (oy * wo + ox) * 8);                                            \
                    for (int c = 0; c < CI; c++) acc[c] += xr[c] * gv;                                              \
                }                                                                                                   \
            }                                                                                                       \
            for (int c = 0; c < CI; c++) *(u8 *)(out + c * 8) = acc[c];                                             \
        }                                                                                                           \
    }

int deliffas_conv_k4s2_weight_grad_f32(const float *restrict x, const float *restrict g, int64_t h, int64_t w,
                                        int64_t ci, int64_t co, float *restrict dwt) {
    const int64_t ho = h / 2, wo = w / 2;
    if (ci == 9 && co == 8 && h % 2 == 0 && w % 2 == 0) { CONV_WEIGHT_GRAD(9) return 0; }
    return 1;
}
