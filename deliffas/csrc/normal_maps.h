/* The exported functions of normal_maps.c (the fused normal-map gather): the ctypes bindings of
   deliffas/geometry/normal_maps.py are read from these prototypes (deliffas/native.py, declare). */
#ifndef DELIFFAS_NORMAL_MAPS_H
#define DELIFFAS_NORMAL_MAPS_H
#include <stdint.h>

void deliffas_normal_maps_f32(const float* vn, int64_t vn_stride, const int32_t* vid, const float* w,
                              float* out, int64_t S2, int64_t B, float eps2);
void deliffas_normal_maps_f64(const double* vn, int64_t vn_stride, const int32_t* vid, const float* w,
                              double* out, int64_t S2, int64_t B, double eps2);
int deliffas_normal_maps_avx2(void);

#endif
