/* Bilinear gather and its scatter-add transpose (deliffas/geometry/sampling.py, _GatherBilinear):
     forward   out[m][c] = sum_k weight[k][m] table[index[k][m]][c]      (k = 0..3, in that order)
     backward  grad[index[k][m]][c] += weight[k][m] grad_out[m][c]      (m, then k, in order: deterministic)
   table and grad are (texels, C) float32 (channels-last), index int64 (4, M), weight float32 (4, M). Both return
   the number of indices outside [0, texels) and touch nothing when there is one (the caller then raises). Built
   without FMA contraction (ISO C99): each product is rounded as in torch's mul / addcmul. */
#include "gather_bilinear.h"
#include <stdint.h>
#include <string.h>

static int64_t out_of_range(const int64_t *index, int64_t count, int64_t texels) {
    int64_t bad = 0;
    for (int64_t i = 0; i < 4 * count; i++) bad += (uint64_t)index[i] >= (uint64_t)texels;
    return bad;
}

#define GATHER_ROWS(C)                                                                                \
    for (int64_t m = 0; m < count; m++) {                                                             \
        const float *t0 = table + index[m] * C, *t1 = table + index[count + m] * C;                   \
        const float *t2 = table + index[2 * count + m] * C, *t3 = table + index[3 * count + m] * C;   \
        const float w0 = weight[m], w1 = weight[count + m];                                           \
        const float w2 = weight[2 * count + m], w3 = weight[3 * count + m];                           \
        float *restrict o = out + m * C;                                                              \
        for (int64_t c = 0; c < C; c++) o[c] = ((t0[c] * w0 + t1[c] * w1) + t2[c] * w2) + t3[c] * w3; \
    }

#define SCATTER_ROWS(C)                                                                               \
    for (int64_t m = 0; m < count; m++) {                                                             \
        const float *restrict g = grad_out + m * C;                                                   \
        for (int k = 0; k < 4; k++) {                                                                 \
            float *restrict d = grad + index[k * count + m] * C;                                      \
            const float w = weight[k * count + m];                                                    \
            for (int64_t c = 0; c < C; c++) d[c] += w * g[c];                                         \
        }                                                                                             \
    }

int64_t deliffas_gather_bilinear_f32(const float *restrict table, int64_t texels, int64_t channels,
                                     const int64_t *restrict index, const float *restrict weight, int64_t count,
                                     float *restrict out) {
    const int64_t bad = out_of_range(index, count, texels);
    if (bad) return bad;
    switch (channels) {  /* fixed widths unroll fully; the rest loop over channels */
        case 3: GATHER_ROWS(3) break;
        case 24: GATHER_ROWS(24) break;
        case 32: GATHER_ROWS(32) break;
        default: GATHER_ROWS(channels)
    }
    return 0;
}

int64_t deliffas_scatter_bilinear_f32(const float *restrict grad_out, int64_t texels, int64_t channels,
                                      const int64_t *restrict index, const float *restrict weight, int64_t count,
                                      float *restrict grad) {
    const int64_t bad = out_of_range(index, count, texels);
    if (bad) return bad;
    memset(grad, 0, (size_t)(texels * channels) * sizeof(float));
    switch (channels) {
        case 3: SCATTER_ROWS(3) break;
        case 24: SCATTER_ROWS(24) break;
        case 32: SCATTER_ROWS(32) break;
        default: SCATTER_ROWS(channels)
    }
    return 0;
}

