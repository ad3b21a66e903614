/* The exported functions of feature_sigmoid.c (the U-Nets' sigmoid with its saturation penalty): the ctypes
   bindings of deliffas/models/feature_sigmoid.py are read from these prototypes (deliffas/native.py, declare). */
#ifndef DELIFFAS_FEATURE_SIGMOID_H
#define DELIFFAS_FEATURE_SIGMOID_H
#include <stdint.h>

double deliffas_beyond_margin_sq_f32(const float *s, int64_t n, float m);
void deliffas_sigmoid_saturation_backward_f32(const float *g, const float *y,
                                              const float *s, int64_t n, float m, float c,
                                              float *out);

#endif
