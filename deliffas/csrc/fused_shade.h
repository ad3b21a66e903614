/* The exported functions of fused_shade.c (the fused shading pass): the ctypes bindings of deliffas/fast/shade.py
   are read from these prototypes (deliffas/native.py, declare). dir_args is ray_inputs.h's. */
#ifndef DELIFFAS_FUSED_SHADE_H
#define DELIFFAS_FUSED_SHADE_H
#include <stdint.h>
#include "ray_inputs.h"

int deliffas_fused_bf16(void);
int deliffas_fused_shade(int64_t n, const float *uv_in, const uint8_t *from_outer, const float *uv_out,
                         int outer_encoded, int L, int include_input, const float *map_in, const float *map_out,
                         int64_t S, int64_t C, const dir_args *dir, int64_t nh, const int64_t *dims, const float *params, int64_t E,
                         int64_t Fd, int64_t wmax, const int64_t *pixels, float *out, int bf16, const float *pe_table,
                         int64_t table_nodes, const float *proj_out, const float *proj_in, const float *proj_peel);

#endif
