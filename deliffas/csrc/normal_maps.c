/* One pass per frame over the S^2 texels (deliffas/geometry/normal_maps.py, NormalMapGather): texel t with vertex
   ids vid[k][t] (vid[0][t] = -1 when the texel is not valid) and weights w[k][t] (planar (3, S^2) tables) gets
     n = (v[vid0] w0 + v[vid1] w1) + v[vid2] w2,  n / |n| if |n|^2 > eps2 else 0,
   written to out[c][t]. Built without FMA contraction and without fast-math, so the AVX2 and the
   scalar loop give bit-identical results and the values equal the torch gather path's to an ulp. */
#include "normal_maps.h"
#include <stdint.h>
#include <math.h>
#if defined(__AVX2__)
#include <immintrin.h>
#endif

#define SCALAR_LOOP(T, SQRT)                                                                 \
    for (; t < S2; ++t) {                                                                    \
        int32_t a = vid[t];                                                                  \
        if (a < 0) { out[t] = 0; out[S2 + t] = 0; out[2 * S2 + t] = 0; continue; }           \
        const T* r0 = vn + 3 * (int64_t)a;                                                   \
        const T* r1 = vn + 3 * (int64_t)vid[S2 + t];                                         \
        const T* r2 = vn + 3 * (int64_t)vid[2 * S2 + t];                                     \
        T b0 = w[t], b1 = w[S2 + t], b2 = w[2 * S2 + t];                                     \
        T x = r0[0] * b0 + r1[0] * b1 + r2[0] * b2;                                          \
        T y = r0[1] * b0 + r1[1] * b1 + r2[1] * b2;                                          \
        T z = r0[2] * b0 + r1[2] * b1 + r2[2] * b2;                                          \
        T sq = x * x + y * y + z * z;                                                        \
        T inv = sq > eps2 ? (T)1 / SQRT(sq) : (T)0;                                          \
        out[t] = x * inv; out[S2 + t] = y * inv; out[2 * S2 + t] = z * inv;                  \
    }

static void frame_f32(const float* vn, const int32_t* vid, const float* w, float* out, int64_t S2, float eps2) {
    int64_t t = 0;
#if defined(__AVX2__)
    const __m256 veps = _mm256_set1_ps(eps2), one = _mm256_set1_ps(1.0f), zero = _mm256_setzero_ps();
    const __m256i three = _mm256_set1_epi32(3), neg1 = _mm256_set1_epi32(-1);
    for (; t + 8 <= S2; t += 8) {
        __m256i a = _mm256_loadu_si256((const __m256i*)(vid + t));
        __m256i valid = _mm256_cmpgt_epi32(a, neg1);
        if (_mm256_testz_si256(valid, valid)) {
            _mm256_storeu_ps(out + t, zero);
            _mm256_storeu_ps(out + S2 + t, zero);
            _mm256_storeu_ps(out + 2 * S2 + t, zero);
            continue;
        }
        __m256 m = _mm256_castsi256_ps(valid);
        __m256i i0 = _mm256_mullo_epi32(a, three);
        __m256i i1 = _mm256_mullo_epi32(_mm256_loadu_si256((const __m256i*)(vid + S2 + t)), three);
        __m256i i2 = _mm256_mullo_epi32(_mm256_loadu_si256((const __m256i*)(vid + 2 * S2 + t)), three);
        __m256 b0 = _mm256_loadu_ps(w + t), b1 = _mm256_loadu_ps(w + S2 + t), b2 = _mm256_loadu_ps(w + 2 * S2 + t);
#define G(c, i) _mm256_mask_i32gather_ps(zero, vn + (c), (i), m, 4)
#define DOT(c) _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(G(c, i0), b0), _mm256_mul_ps(G(c, i1), b1)), \
                             _mm256_mul_ps(G(c, i2), b2))
        __m256 x = DOT(0), y = DOT(1), z = DOT(2);
#undef DOT
#undef G
        __m256 sq = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(x, x), _mm256_mul_ps(y, y)), _mm256_mul_ps(z, z));
        __m256 ok = _mm256_cmp_ps(sq, veps, _CMP_GT_OQ);
        __m256 inv = _mm256_and_ps(_mm256_div_ps(one, _mm256_sqrt_ps(_mm256_blendv_ps(one, sq, ok))), ok);
        _mm256_storeu_ps(out + t, _mm256_mul_ps(x, inv));
        _mm256_storeu_ps(out + S2 + t, _mm256_mul_ps(y, inv));
        _mm256_storeu_ps(out + 2 * S2 + t, _mm256_mul_ps(z, inv));
    }
#endif
    SCALAR_LOOP(float, sqrtf)
}

static void frame_f64(const double* vn, const int32_t* vid, const float* w, double* out, int64_t S2, double eps2) {
    int64_t t = 0;
    SCALAR_LOOP(double, sqrt)
}

void deliffas_normal_maps_f32(const float* vn, int64_t vn_stride, const int32_t* vid, const float* w,
                              float* out, int64_t S2, int64_t B, float eps2) {
    for (int64_t b = 0; b < B; ++b) frame_f32(vn + b * vn_stride, vid, w, out + b * 3 * S2, S2, eps2);
}

void deliffas_normal_maps_f64(const double* vn, int64_t vn_stride, const int32_t* vid, const float* w,
                              double* out, int64_t S2, int64_t B, double eps2) {
    for (int64_t b = 0; b < B; ++b) frame_f64(vn + b * vn_stride, vid, w, out + b * 3 * S2, S2, eps2);
}

int deliffas_normal_maps_avx2(void) {
#if defined(__AVX2__)
    return 1;
#else
    return 0;
#endif
}
