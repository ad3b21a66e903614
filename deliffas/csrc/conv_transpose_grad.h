/* The exported functions of conv_transpose_grad.c (the transposed convolution's gradients): the ctypes bindings
   of deliffas/models/unet_grad.py are read from these prototypes (deliffas/native.py, declare). */
#ifndef DELIFFAS_CONV_TRANSPOSE_GRAD_H
#define DELIFFAS_CONV_TRANSPOSE_GRAD_H
#include <stdint.h>

int deliffas_conv_transpose_grad_wide_vectors(void);
int deliffas_conv_transpose_k4s2_input_grad_f32(const float *g, const float *wt, int64_t h,
                                                int64_t w, int64_t ci, int64_t co, float *dx);
int deliffas_conv_transpose_k4s2_weight_grad_f32(const float *x, const float *g, int64_t h,
                                                 int64_t w, int64_t ci, int64_t co, float *dwt,
                                                 float *db);
int deliffas_conv_k4s2_weight_grad_f32(const float *x, const float *g, int64_t h, int64_t w,
                                       int64_t ci, int64_t co, float *dwt);

#endif
