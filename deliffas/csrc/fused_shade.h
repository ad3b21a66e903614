/* The exported functions of fused_shade.c (the fused shading pass) and the argument structure of
   deliffas_fused_shade: the ctypes bindings of deliffas/fast/shade.py are read from these prototypes and this
   structure (deliffas/native.py, declare and header_structs). dir_args is ray_inputs.h's. */
#ifndef DELIFFAS_FUSED_SHADE_H
#define DELIFFAS_FUSED_SHADE_H
#include <stdint.h>
#include "ray_inputs.h"

/* deliffas_fused_shade's arguments (described there), by name: pointers, then 64-bit integers, then 32-bit ones
   (no padding on the usual ABIs; deliffas_fused_shade_args_layout gives the compiler's layout, which
   deliffas/native.py checks its Structure against). */
typedef struct {
    const float *uv_in;
    const uint8_t *from_outer;
    const float *uv_out;
    const float *map_in;
    const float *map_out;
    const dir_args *dir;
    const int64_t *dims;
    const float *params;
    const int64_t *pixels;
    float *out;
    const float *pe_table;
    const float *proj_out;
    const float *proj_in;
    const float *proj_peel;
    const float *tex_in;
    const float *tex_out;
    int64_t n;
    int64_t S;
    int64_t C;
    int64_t nh;
    int64_t E;
    int64_t Fd;
    int64_t wmax;
    int64_t table_nodes;
    int64_t St;
    int64_t Ct;
    int32_t outer_encoded;
    int32_t L;
    int32_t include_input;
    int32_t bf16;
} deliffas_fused_shade_args;

int deliffas_fused_bf16(void);
int deliffas_fused_shade(const deliffas_fused_shade_args *args);
int64_t deliffas_fused_shade_args_layout(int64_t *out);

#endif
