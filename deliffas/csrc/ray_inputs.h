/* The exported functions of ray_inputs.c (the per-stage shading's ray inputs and output layer) and the dir_args
   structure they (and fused_shade.c) take: the ctypes bindings of deliffas/fast/shade.py are read from these
   prototypes and this struct (deliffas/native.py: declare, header_structs). */
#ifndef DELIFFAS_RAY_INPUTS_H
#define DELIFFAS_RAY_INPUTS_H
#include <stdint.h>

/* The view direction of variants that encode one (FastShader._ray_args): viewdir (n, 3) unit directions; normals
   NULL, or the inner normal map (S, S, 3) channels_last when the encoded direction is the reflection about it
   (DeliffasModel._reflected); L, include_input: the direction's encoding. */
typedef struct {
    const float *viewdir;
    const float *normals;
    int64_t S;
    int32_t L, include_input;
} dir_args;

void deliffas_rgb_out(int64_t n, const void *h, int64_t ld, int bf16, int64_t K, const float *w, const float *b,
                      const int64_t *pixels, float *out);
void deliffas_ray_inputs(int64_t start, int64_t stop, const float *uv_in, const uint8_t *from_outer,
                         const float *uv_out, int outer_encoded, int L, int include_input, const float *map_in,
                         const float *map_out, int64_t S, int64_t C, const dir_args *dir, int bf16, void *enc,
                         int64_t E, void *feats, int64_t F);

#endif
