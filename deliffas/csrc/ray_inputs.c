/* Per-ray inputs of the MLP (deliffas/fast/shade.py, FastShader.inputs): positional encodings of the ray's
   uvs (and view direction) and bilinearly sampled features written straight into the MLP's row-major GEMM
   operands; and the output layer's colours written to their pixels. Built without FMA contraction and without
   fast-math. */
#include "ray_inputs.h"
#include "ray_inputs_impl.h"

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

/* Rows [start, stop) of enc (n, E): PE(uv_outer) if outer_encoded, PE(uv_inner), then with dir PE(its direction);
   and of feats (n, F) (rows_f32). */
void deliffas_ray_inputs(int64_t start, int64_t stop, const float *uv_in, const uint8_t *from_outer,
                         const float *uv_out, int outer_encoded, int L, int include_input, const float *map_in,
                         const float *map_out, int64_t S, int64_t C, const dir_args *dir, int bf16, void *enc,
                         int64_t E, void *feats, int64_t F) {
    if (bf16)
        rows_bf16(start, stop, uv_in, from_outer, uv_out, outer_encoded, L, include_input, map_in, map_out, S, C,
                  dir, (uint16_t *)enc, E, (uint16_t *)feats, F);
    else
        rows_f32(start, stop, uv_in, from_outer, uv_out, outer_encoded, L, include_input, map_in, map_out, S, C,
                 dir, (float *)enc, E, (float *)feats, F);
}
