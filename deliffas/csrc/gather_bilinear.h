/* The exported functions of gather_bilinear.c (the bilinear gather and its scatter-add): the ctypes bindings of
   deliffas/geometry/sampling.py are read from these prototypes (deliffas/native.py, declare). */
#ifndef DELIFFAS_GATHER_BILINEAR_H
#define DELIFFAS_GATHER_BILINEAR_H
#include <stdint.h>

int64_t deliffas_gather_bilinear_f32(const float *table, int64_t texels, int64_t channels,
                                     const int64_t *index, const float *weight, int64_t count,
                                     float *out);
int64_t deliffas_scatter_bilinear_f32(const float *grad_out, int64_t texels, int64_t channels,
                                      const int64_t *index, const float *weight, int64_t count,
                                      float *grad);

#endif
