/* The U-Net's output sigmoid with the saturation penalty on its logits (deliffas/models/feature_sigmoid.py):
     penalty   sum_i beyond(s_i)^2,  beyond(s) = s - clamp(s, -m, m) (torch's softshrink)
     backward  out_i = (g_i (1 - y_i)) y_i + beyond(s_i) c
   with y = sigmoid(s) and c the penalty's gradient scale. The backward is torch's sigmoid_backward, torch's
   mul of the penalty's gradient and the sum autograd forms of the two, in one pass: the same float32
   roundings in the same order. Built without FMA contraction (ISO C99). The penalty's sum is in 16 float lanes
   added in double: the logged value only, which no gradient reads. Arrays are in the maps' memory order. */
#include "feature_sigmoid.h"
#include <stdint.h>

static inline float beyond(float s, float m) { return s > m ? s - m : (s < -m ? s + m : 0.0f); }

double deliffas_beyond_margin_sq_f32(const float *restrict s, int64_t n, float m) {
    float lanes[16] = {0};
    const int64_t whole = n - n % 16;
    for (int64_t i = 0; i < whole; i += 16) {
        float b[16];
        for (int j = 0; j < 16; j++) {
            const float v = s[i + j], hi = v - m, lo = v + m;
            b[j] = hi > 0.0f ? hi : (lo < 0.0f ? lo : 0.0f);
        }
        for (int j = 0; j < 16; j++) lanes[j] += b[j] * b[j];
    }
    double total = 0.0;
    for (int j = 0; j < 16; j++) total += lanes[j];
    for (int64_t i = whole; i < n; i++) total += (double)beyond(s[i], m) * beyond(s[i], m);
    return total;
}

void deliffas_sigmoid_saturation_backward_f32(const float *restrict g, const float *restrict y,
                                              const float *restrict s, int64_t n, float m, float c,
                                              float *restrict out) {
    for (int64_t i = 0; i < n; i++) {
        const float sig = (g[i] * (1.0f - y[i])) * y[i];
        out[i] = sig + beyond(s[i], m) * c;
    }
}
