/* The exported functions of rasterize.c (the rasteriser with depth peeling) and the argument structure of
   deliffas_raster_uv: the ctypes bindings of deliffas/fast/rasterize.py are read from these prototypes and this
   structure (deliffas/native.py, declare and header_structs). */
#ifndef DELIFFAS_RASTERIZE_H
#define DELIFFAS_RASTERIZE_H
#include <stdint.h>

/* deliffas_raster_uv's arguments (described there), by name: pointers, then 64-bit integers and the double (no
   padding on the usual ABIs; deliffas_raster_uv_args_layout gives the compiler's layout, which deliffas/native.py
   checks its Structure against). */
typedef struct {
    const double *pin;
    const double *pout;
    const int32_t *faces;
    const float *corner_uvs;
    const double *m;
    float *zi;
    int32_t *fi;
    float *zo;
    int32_t *fo;
    int64_t *pix;
    float *uv_in;
    uint8_t *from_outer;
    float *uv_out;
    float *viewdir;
    int64_t F;
    int64_t c0;
    int64_t r0;
    int64_t w;
    int64_t h;
    int64_t W;
    double eps;
} deliffas_raster_uv_args;

int deliffas_raster_depth(const double *P, const int32_t *faces, int64_t F, int64_t c0, int64_t r0, int64_t w,
                          int64_t h, float *z, int32_t *face);
int64_t deliffas_raster_uv(const deliffas_raster_uv_args *a);
int64_t deliffas_raster_uv_args_layout(int64_t *out);

#endif
