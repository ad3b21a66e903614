/* The exported functions of rasterize.c (the rasteriser with depth peeling): the ctypes bindings of
   deliffas/fast/rasterize.py are read from these prototypes (deliffas/native.py, declare). */
#ifndef DELIFFAS_RASTERIZE_H
#define DELIFFAS_RASTERIZE_H
#include <stdint.h>

int deliffas_raster_depth(const double *P, const int32_t *faces, int64_t F, int64_t c0, int64_t r0, int64_t w,
                          int64_t h, float *z, int32_t *face);
int64_t deliffas_raster_uv(const double *pin, const double *pout, const int32_t *faces, int64_t F,
                           const float *corner_uvs, int64_t c0, int64_t r0, int64_t w, int64_t h, int64_t W,
                           const double *m, double eps, float *zi, int32_t *fi, float *zo, int32_t *fo,
                           int64_t *pix, float *uv_in, uint8_t *from_outer, float *uv_out, float *viewdir);

#endif
