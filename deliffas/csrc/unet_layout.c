/* dst[n][p][c] = src[n][c][p] for float32 (deliffas/models/unet_cpu.py, channels_last): N maps of C planes of
   P pixels to channels_last order. Loops specialised for the U-Net's usual 3 (T + 1) input channels (gcc
   vectorises them), a pixel-blocked loop otherwise. Exact copies: no arithmetic. */
#include "unet_layout.h"
#include <stdint.h>
#define INTERLEAVE(C) \
    static void interleave_##C(const float *restrict src, float *restrict dst, int64_t pixels) { \
        for (int64_t p = 0; p < pixels; p++) \
            for (int c = 0; c < C; c++) dst[p * C + c] = src[c * pixels + p]; \
    }
INTERLEAVE(3)
INTERLEAVE(6)
INTERLEAVE(9)
INTERLEAVE(12)

static void interleave_any(const float *restrict src, float *restrict dst, int64_t channels, int64_t pixels) {
    const int64_t block = 64;
    for (int64_t p0 = 0; p0 < pixels; p0 += block) {
        int64_t n = pixels - p0 < block ? pixels - p0 : block;
        for (int64_t c = 0; c < channels; c++) {
            const float *s = src + c * pixels + p0;
            float *d = dst + p0 * channels + c;
            for (int64_t p = 0; p < n; p++) d[p * channels] = s[p];
        }
    }
}

void deliffas_planar_to_interleaved_f32(const float *src, float *dst, int64_t batch, int64_t channels,
                                        int64_t pixels) {
    for (int64_t n = 0; n < batch; n++) {
        const float *s = src + n * channels * pixels;
        float *d = dst + n * channels * pixels;
        switch (channels) {
            case 3: interleave_3(s, d, pixels); break;
            case 6: interleave_6(s, d, pixels); break;
            case 9: interleave_9(s, d, pixels); break;
            case 12: interleave_12(s, d, pixels); break;
            default: interleave_any(s, d, channels, pixels);
        }
    }
}
