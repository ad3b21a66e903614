"""Rasterised uvs of the inner and outer surfaces per camera pixel, with depth peeling (the ray caster's hits).

The paper gets its uv maps from a GPU rasteriser; this module does the same on the CPU and gives
the shaded rays ``geometry.raycast`` gives (``UVRaycaster.cast_foreground`` + ``uv_inner_or_exit``):

* pixel (col, row) is sampled at its centre (col + 0.5, row + 0.5); a triangle covers it when the
  centre lies inside or on the triangle's projection (both orientations: rays meet back faces too);
* per pixel, the inner surface's nearest fragment (its first hit) and the outer surface's three
  nearest fragments are kept (z-buffers on camera depth, which orders hits along one pixel's ray as
  the ray parameter t does, t = z |K^-1 (x, y, 1)|);
* a pixel is shaded when the outer surface covers it and either the inner surface covers it or an
  outer fragment lies more than ``peel_eps`` (along the ray, mm) beyond the first outer one: the
  outer exit, the ray caster's re-cast from ``t1 + eps``;
* barycentrics are perspective-correct (those of the 3-D hit point, as open3d's), the uvs the
  per-corner atlas uvs interpolated with them.

Differences from the ray caster are limited to pixel centres within round-off of a triangle edge
(open3d intersects in float32, this module in float64) and are bounded by a test. A vertex behind
the camera (camera z <= 0) makes the projection meaningless: :meth:`UVRasterizer.shaded_pixels`
then returns None and the caller ray-casts.

Two implementations give the same pixels: a C kernel (``deliffas/native.py``, built once per
process) and a vectorised numpy one over (triangle, pixel) pairs, used with ``DELIFFAS_NATIVE=0``,
without a C compiler, or with ``method="numpy"``.
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import threading
from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import Bool, Float, Integer, Real

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, to_numpy
from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.raycast import PEEL_EPS_REL, projected_pixel_window
from deliffas.io.cameras import Camera
from deliffas.native import LazyLibrary

__all__ = ["ShadedPixels", "UVRasterizer", "OUTER_LAYERS", "raster_kernel_available"]

logger = logging.getLogger(__name__)

OUTER_LAYERS = 3
"""Outer fragments kept per pixel: the first hit and two more, of which the first farther than
``peel_eps`` is the exit (two fragments at one depth occur where a pixel centre lies on an edge)."""

_SLACK = 7  # z-buffer elements after the last layer: the kernel reads and writes 8 pixels at a time
_PAIR_CHUNK = 1 << 22  # (triangle, pixel) pairs per chunk of the numpy implementation

Method = Literal["auto", "native", "numpy"]

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define L 3

/* min / max of three without libm's fmin / fmax (calls through the PLT, 2 % of the pass): a NaN coordinate
   gives some value, and such faces are skipped (their area is not finite) */
static inline double min3(double a, double b, double c) { double m = a < b ? a : b; return m < c ? m : c; }
static inline double max3(double a, double b, double c) { double m = a > b ? a : b; return m > c ? m : c; }

/* Screen-space weights (l0, l1, l2) of pixel centre (x, y) in triangle (a, b, c); 0 when outside. */
static inline int weights(const double *a, const double *b, const double *c, double x, double y,
                          double inv_area, double *l) {
    l[0] = ((c[0] - b[0]) * (y - b[1]) - (c[1] - b[1]) * (x - b[0])) * inv_area;
    l[1] = ((a[0] - c[0]) * (y - c[1]) - (a[1] - c[1]) * (x - c[0])) * inv_area;
    l[2] = ((b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])) * inv_area;
    return l[0] >= 0.0 && l[1] >= 0.0 && l[2] >= 0.0;
}

typedef double v4d __attribute__((vector_size(32)));
typedef int64_t v4l __attribute__((vector_size(32)));
typedef float v4f __attribute__((vector_size(16)));
typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));

/* (lo, hi) as one vector: in registers where the compiler has __builtin_shufflevector (GCC 12, clang), else through
   memory (correct, slower) */
static inline v8f join_halves(v4f lo, v4f hi) {
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
    return __builtin_shufflevector(lo, hi, 0, 1, 2, 3, 4, 5, 6, 7);
#else
    v8f out;
    memcpy(&out, &lo, 16);
    memcpy((char *)&out + 16, &hi, 16);
    return out;
#endif
}

/* Rows [rs, re] of face t's pixel centres in the window (its bounding box); 0 when it covers none. */
static inline int face_rows(const double *P, const int32_t *faces, int64_t t, int64_t r0, int64_t h, int64_t *rs,
                            int64_t *re) {
    const double *a = P + 3 * (int64_t)faces[3 * t], *b = P + 3 * (int64_t)faces[3 * t + 1],
                 *c = P + 3 * (int64_t)faces[3 * t + 2];
    double ymin = min3(a[1], b[1], c[1]), ymax = max3(a[1], b[1], c[1]);
    double lo = ceil(ymin - 0.5), hi = floor(ymax - 0.5);  /* clipped to the window before the casts */
    if (lo < (double)r0) lo = (double)r0;
    if (hi > (double)(r0 + h - 1)) hi = (double)(r0 + h - 1);
    if (!(lo <= hi)) return 0;  /* outside the window's rows, or NaN: raster() skips it as well */
    *rs = (int64_t)lo;
    *re = (int64_t)hi;
    return 1;
}

/* Unaligned 8-lane loads and stores in registers: memcpy into arrays of vectors went through the stack in 16-byte
   halves, and each 32-byte reload of a half-written slot waited for the stores (a third of the pass). */
typedef float v8f_u __attribute__((vector_size(32), aligned(4)));
typedef int32_t v8i_u __attribute__((vector_size(32), aligned(4)));

/* Insert fragments (wf, fv) into the first `layers` layers of 8 pixels from q where `in`: whether a fragment goes
   before layer k is monotone in k, so each layer takes its own value, the fragment's or the previous layer's.
   Depth is stored as w = 1 / camera z (nearer = larger): it interpolates linearly in screen space, so no division. */
static inline __attribute__((always_inline)) void insert8(float *z, int32_t *face, int64_t plane, int64_t q, int layers,
                                                          v8i in, v8f wf, v8i fv) {
    v8i wi = (v8i)wf, zk[L], fk[L], before[L];
#pragma GCC unroll 4
    for (int k = 0; k < layers; k++) {
        v8f zk_f = *(const v8f_u *)(z + k * plane + q);
        fk[k] = *(const v8i_u *)(face + k * plane + q);
        zk[k] = (v8i)zk_f;
        before[k] = in & ((fk[k] < 0) | (wf > zk_f));
    }
#pragma GCC unroll 4
    for (int k = layers - 1; k >= 0; k--) {
        v8i nz = (wi & before[k]) | (zk[k] & ~before[k]);
        v8i nf = (fv & before[k]) | (fk[k] & ~before[k]);
        if (k > 0) {
            nz = (zk[k - 1] & before[k - 1]) | (nz & ~before[k - 1]);
            nf = (fk[k - 1] & before[k - 1]) | (nf & ~before[k - 1]);
        }
        *(v8f_u *)(z + k * plane + q) = (v8f)nz;
        *(v8i_u *)(face + k * plane + q) = nf;
    }
}

/* z-buffer pass of faces list[0 .. count) of one surface over window rows [rlo, rhi]: P (V, 3) = (x px, y px,
   camera z > 0); keeps the `layers` (<= L) nearest fragments per window pixel, sorted by depth (a fragment after
   those at its depth), in z (float: 1 / camera z, larger is nearer) and face (int32, -1 = none), layer k of window
   pixel p at k w h + p. Both need 7 elements of slack after the last layer. With `cover` (the inner surface's
   faces, this band rasterised), 8 pixels that all have one keep only the nearest fragment: the farther layers are
   read only where the inner surface is missed (the exit search), and these blends and stores took a third of the
   outer pass.
   8 pixels of a row at a time in vectors (GCC/clang vector extensions), without branches: the coverage test
   (the same operations as weights() per pixel, so the same pixels), the depth, and the insertion into each layer
   (whether the fragment goes before layer k is monotone in k, so each layer takes its own value, the fragment's
   or the previous layer's). Per pixel with branches this took 2-3x longer: the order of the faces says nothing
   about depth, so the insertion's branches were mispredicted at about every other fragment. Tried and not kept:
   8-pixel groups aligned in the window (no faster) and per-row spans from the edges' crossings instead of the
   bounding box (three divisions a row cost more than the lanes they save on faces a few pixels wide). */
static void raster(const double *P, const int32_t *faces, const int32_t *list, int64_t count, int64_t c0, int64_t r0,
                   int64_t w, int64_t h, int64_t rlo, int64_t rhi, float *z, int32_t *face, int layers,
                   const int32_t *cover) {
    const v4d lane = {0.5, 1.5, 2.5, 3.5};
    const int64_t plane = w * h;
    for (int64_t i = 0; i < count; i++) {
        int64_t t = list ? list[i] : i;
        const double *a = P + 3 * (int64_t)faces[3 * t], *b = P + 3 * (int64_t)faces[3 * t + 1],
                     *c = P + 3 * (int64_t)faces[3 * t + 2];
        double area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if (!(area != 0.0) || !isfinite(area)) continue;
        int64_t rs, re;  /* the bounding box's rows in the band */
        if (!face_rows(P, faces, t, rlo, rhi - rlo + 1, &rs, &re)) continue;
        /* and its columns in the window, clipped in double before the integer casts as face_rows' rows (a
           coordinate beyond the int64 range would make them undefined) */
        double csd = ceil(min3(a[0], b[0], c[0]) - 0.5), ced = floor(max3(a[0], b[0], c[0]) - 0.5);
        if (csd < (double)c0) csd = (double)c0;
        if (ced > (double)(c0 + w - 1)) ced = (double)(c0 + w - 1);
        if (!(csd <= ced)) continue;
        int64_t cs = (int64_t)csd, ce = (int64_t)ced;
        double inv_area = 1.0 / area, ia = 1.0 / a[2], ib = 1.0 / b[2], ic = 1.0 / c[2];
        double d0 = c[1] - b[1], d1 = a[1] - c[1], d2 = b[1] - a[1];
        double xend = (double)ce + 1.0;  /* centre x = col + 0.5 < xend: col <= ce */
        v8i fv = (v8i){0} + (int32_t)t;
        for (int64_t row = rs; row <= re; row++) {
            double y = row + 0.5;
            double e0 = (c[0] - b[0]) * (y - b[1]), e1 = (a[0] - c[0]) * (y - c[1]), e2 = (b[0] - a[0]) * (y - a[1]);
            for (int64_t col0 = cs; col0 <= ce; col0 += 8) {
                /* w = 1 / z, interpolated (> 0: every vertex is in front of the camera), 0 where the centre is not
                   covered: the mask rides on w, so no 64- to 32-bit mask narrowing. In two halves of 4 doubles: GCC
                   lowers 8-double compares to scalar code without AVX-512, and the halves join in registers. */
                v4f wh[2];
                for (int half = 0; half < 2; half++) {
                    v4d x = (double)(col0 + 4 * half) + lane;
                    v4d m0 = (e0 - d0 * (x - b[0])) * inv_area;
                    v4d m1 = (e1 - d1 * (x - c[0])) * inv_area;
                    v4d m2 = (e2 - d2 * (x - a[0])) * inv_area;
                    v4l covered = (m0 >= 0.0) & (m1 >= 0.0) & (m2 >= 0.0) & (x < xend);
                    v4d wd = m0 * ia + m1 * ib + m2 * ic;
                    wh[half] = __builtin_convertvector((v4d)((v4l)wd & covered), v4f);
                }
                v8f zf = join_halves(wh[0], wh[1]);
                v8i in = zf > 0.0f;
                int64_t q = (row - r0) * w + (col0 - c0);
                int all_covered = cover != 0;
                if (cover) {
                    v8i cv = *(const v8i_u *)(cover + q);
                    for (int j = 0; j < 8; j++) all_covered &= cv[j] >= 0;
                }
                if (all_covered)
                    insert8(z, face, plane, q, 1, in, zf, fv);
                else
                    insert8(z, face, plane, q, layers, in, zf, fv);
            }
        }
    }
}

/* Window rows are rasterised in bands of BAND rows, each band's faces in turn, so the band's z-buffer rows (the
   outer surface's: 3 layers of z and face, 24 bytes a pixel) stay in cache: face by face over the whole window, a
   z-buffer of 10-20 MB missed the cache at most fragments. */
#define BAND 16

/* Faces of P binned by band: band k's faces at list[start[k] .. start[k + 1]), in face order; start (nb + 1).
   Returns the list (malloc; free it), or NULL when out of memory. */
static int32_t *bin_faces(const double *P, const int32_t *faces, int64_t F, int64_t r0, int64_t h, int64_t *start) {
    int64_t nb = (h + BAND - 1) / BAND, rs, re;
    for (int64_t k = 0; k <= nb; k++) start[k] = 0;
    for (int64_t t = 0; t < F; t++)
        if (face_rows(P, faces, t, r0, h, &rs, &re))
            for (int64_t k = (rs - r0) / BAND; k <= (re - r0) / BAND; k++) start[k + 1]++;
    for (int64_t k = 0; k < nb; k++) start[k + 1] += start[k];
    int32_t *list = malloc((size_t)(start[nb] > 0 ? start[nb] : 1) * sizeof(int32_t));
    int64_t *fill = malloc((size_t)(nb > 0 ? nb : 1) * sizeof(int64_t));
    if (!list || !fill) { free(list); free(fill); return NULL; }
    for (int64_t k = 0; k < nb; k++) fill[k] = start[k];
    for (int64_t t = 0; t < F; t++)
        if (face_rows(P, faces, t, r0, h, &rs, &re))
            for (int64_t k = (rs - r0) / BAND; k <= (re - r0) / BAND; k++) list[fill[k]++] = (int32_t)t;
    free(fill);
    return list;
}

/* One plain z-buffer pass (nearest fragment per window pixel), banded as below: the benchmarks' irreducible raster
   work. Returns 0, -1 when out of memory. */
int deliffas_raster_depth(const double *P, const int32_t *faces, int64_t F, int64_t c0, int64_t r0, int64_t w,
                          int64_t h, float *z, int32_t *face) {
    int64_t nb = (h + BAND - 1) / BAND;
    int64_t *start = malloc((size_t)(nb + 1) * sizeof(int64_t));
    int32_t *list = start ? bin_faces(P, faces, F, r0, h, start) : NULL;
    if (!list) { free(start); return -1; }
    for (int64_t k = 0; k < nb; k++) {
        int64_t rlo = r0 + k * BAND, rhi = rlo + BAND - 1 < r0 + h - 1 ? rlo + BAND - 1 : r0 + h - 1;
        for (int64_t i = (rlo - r0) * w; i < (rhi - r0 + 1) * w; i++) face[i] = -1;
        raster(P, faces, list + start[k], start[k + 1] - start[k], c0, r0, w, h, rlo, rhi, z, face, 1, 0);
    }
    free(list);
    free(start);
    return 0;
}

/* Per face of P: the uv at pixel centre (x, y) as two ratios of affine functions of (x, y), nine doubles a face:
   u = (k0 x + k1 y + k2) / (k6 x + k7 y + k8), v = (k3 x + k4 y + k5) / (same). The perspective-correct barycentrics
   are q_i / sum q, q_i = l_i / z_i with l_i the screen-space weights, affine in (x, y); expanding them once per face
   leaves an uv two dot products and a division (within 1e-6 of the numpy version, which evaluates the weights per
   pixel). Zeros where the area is 0 or not finite: such faces are never hit. */
static void face_consts(const double *P, const int32_t *faces, const float *corner_uvs, int64_t F, double *k) {
    for (int64_t t = 0; t < F; t++) {
        const double *v[3] = {P + 3 * (int64_t)faces[3 * t], P + 3 * (int64_t)faces[3 * t + 1],
                              P + 3 * (int64_t)faces[3 * t + 2]};
        const double *a = v[0], *b = v[1], *c = v[2];
        double area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        double *kt = k + 9 * t;
        for (int j = 0; j < 9; j++) kt[j] = 0.0;
        if (!(area != 0.0) || !isfinite(area)) continue;
        double A = 1.0 / area;
        for (int i = 0; i < 3; i++) {  /* l_i = (e_y (y - p1) - e_x (x - p0)) A over the edge opposite corner i */
            const double *p = v[(i + 1) % 3], *q = v[(i + 2) % 3];
            double ex = q[1] - p[1], ey = q[0] - p[0], iz = 1.0 / v[i][2];
            double lx = -ex * A * iz, ly = ey * A * iz, l0 = (ex * p[0] - ey * p[1]) * A * iz;
            const float *cu = corner_uvs + 6 * t + 2 * i;
            kt[0] += lx * cu[0]; kt[1] += ly * cu[0]; kt[2] += l0 * cu[0];
            kt[3] += lx * cu[1]; kt[4] += ly * cu[1]; kt[5] += l0 * cu[1];
            kt[6] += lx; kt[7] += ly; kt[8] += l0;
        }
    }
}

/* Shaded pixels of the window in row-major order; returns their number N (-1 when out of memory).
   pin/pout (V, 3) projected surfaces, faces (F, 3), corner_uvs (F, 6), window (c0, r0, w, h),
   image width W, m = R^T K^-1 (3, 3) row-major, eps = peel distance along the ray (mm).
   Scratch: zi, fi (w h + 7), zo, fo (L w h + 7), layer-major. Outputs (capacity w h): pix (N,) int64 row W + col,
   uv_in (N, 2), from_outer (N,) uint8, uv_out (N, 2), viewdir (N, 3) (NULL: not computed).
   Band by band: both surfaces' z-buffer rows, then that band's shaded pixels, while its rows are in cache. */
int64_t deliffas_raster_uv(const double *pin, const double *pout, const int32_t *faces, int64_t F,
                           const float *corner_uvs, int64_t c0, int64_t r0, int64_t w, int64_t h, int64_t W,
                           const double *m, double eps, float *zi, int32_t *fi, float *zo, int32_t *fo,
                           int64_t *pix, float *uv_in, uint8_t *from_outer, float *uv_out, float *viewdir) {
    int64_t nb = (h + BAND - 1) / BAND, n = w * h;
    int64_t *start_in = malloc((size_t)(nb + 1) * sizeof(int64_t)), *start_out = malloc((size_t)(nb + 1) * sizeof(int64_t));
    double *k_in = malloc((size_t)(F > 0 ? F : 1) * 9 * sizeof(double)), *k_out = malloc((size_t)(F > 0 ? F : 1) * 9 * sizeof(double));
    int32_t *list_in = start_in ? bin_faces(pin, faces, F, r0, h, start_in) : NULL;
    int32_t *list_out = start_out ? bin_faces(pout, faces, F, r0, h, start_out) : NULL;
    double *rowbuf = malloc((size_t)(w > 0 ? w : 1) * 7 * sizeof(double)), *num[6], *xs = rowbuf;
    int64_t out = 0;
    if (!start_in || !start_out || !k_in || !k_out || !list_in || !list_out || !rowbuf) { out = -1; goto done; }
    for (int j = 0; j < 6; j++) num[j] = rowbuf + (j + 1) * w;  /* per shaded pixel of a row: uv numerators, denominator (inner, outer) */
    face_consts(pin, faces, corner_uvs, F, k_in);
    face_consts(pout, faces, corner_uvs, F, k_out);
    for (int64_t band = 0; band < nb; band++) {
        int64_t rlo = r0 + band * BAND, rhi = rlo + BAND - 1 < r0 + h - 1 ? rlo + BAND - 1 : r0 + h - 1;
        for (int64_t i = (rlo - r0) * w; i < (rhi - r0 + 1) * w; i++) fi[i] = -1;
        for (int k = 0; k < L; k++)
            for (int64_t i = (rlo - r0) * w; i < (rhi - r0 + 1) * w; i++) fo[k * n + i] = -1;
        raster(pin, faces, list_in + start_in[band], start_in[band + 1] - start_in[band], c0, r0, w, h, rlo, rhi, zi, fi, 1, 0);
        raster(pout, faces, list_out + start_out[band], start_out[band + 1] - start_out[band], c0, r0, w, h, rlo, rhi, zo,
               fo, L, fi);
        for (int64_t r = rlo - r0; r <= rhi - r0; r++) {
            /* the row's shaded pixels: which faces (branches, per pixel), then their divisions and square roots in
               loops over the row that the compiler vectorises (one pixel at a time, these took most of the time) */
            int64_t first = out, cnt = 0;
            double y = r0 + r + 0.5;
            for (int64_t cc = 0; cc < w; cc++) {
                int64_t p = r * w + cc;
                if (fo[p] < 0) continue;
                double x = c0 + cc + 0.5;
                int64_t inner_face = fi[p];
                int outer_exit = 0;
                if (inner_face < 0) {
                    double d0 = m[0] * x + m[1] * y + m[2], d1 = m[3] * x + m[4] * y + m[5], d2 = m[6] * x + m[7] * y + m[8];
                    double zmin = 1.0 / (double)zo[p] + eps / sqrt(d0 * d0 + d1 * d1 + d2 * d2);
                    for (int k = 1; k < L; k++) {
                        if (fo[k * n + p] >= 0 && 1.0 / (double)zo[k * n + p] > zmin) {
                            inner_face = fo[k * n + p];
                            outer_exit = 1;
                            break;
                        }
                    }
                    if (!outer_exit) continue;
                }
                const double *ki = (outer_exit ? k_out : k_in) + 9 * inner_face, *ko = k_out + 9 * (int64_t)fo[p];
                pix[out] = (r0 + r) * W + c0 + cc;
                from_outer[out] = (uint8_t)outer_exit;
                xs[cnt] = x;
                for (int j = 0; j < 3; j++) {
                    num[j][cnt] = ki[3 * j] * x + ki[3 * j + 1] * y + ki[3 * j + 2];
                    num[3 + j][cnt] = ko[3 * j] * x + ko[3 * j + 1] * y + ko[3 * j + 2];
                }
                cnt++;
                out++;
            }
            float *ui = uv_in + 2 * first, *uo = uv_out + 2 * first, *vd = viewdir ? viewdir + 3 * first : 0;
            for (int64_t j = 0; j < cnt; j++) {  /* uv = numerator / denominator (face_uv) */
                double si = 1.0 / num[2][j], so = 1.0 / num[5][j];
                ui[2 * j] = (float)(num[0][j] * si);
                ui[2 * j + 1] = (float)(num[1][j] * si);
                uo[2 * j] = (float)(num[3][j] * so);
                uo[2 * j + 1] = (float)(num[4][j] * so);
            }
            for (int64_t j = 0; j < (viewdir ? cnt : 0); j++) {
                double x = xs[j];
                double d0 = m[0] * x + m[1] * y + m[2], d1 = m[3] * x + m[4] * y + m[5], d2 = m[6] * x + m[7] * y + m[8];
                double len = sqrt(d0 * d0 + d1 * d1 + d2 * d2);
                vd[3 * j] = (float)(d0 / len);
                vd[3 * j + 1] = (float)(d1 / len);
                vd[3 * j + 2] = (float)(d2 / len);
            }
        }
    }
done:
    free(start_in); free(start_out); free(k_in); free(k_out); free(list_in); free(list_out); free(rowbuf);
    return out;
}
"""


def _declare(lib: ctypes.CDLL) -> None:
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.deliffas_raster_uv.argtypes = [p, p, p, i64, p, i64, i64, i64, i64, i64, p, ctypes.c_double,
                                       p, p, p, p, p, p, p, p, p]
    lib.deliffas_raster_uv.restype = i64
    lib.deliffas_raster_depth.argtypes = [p, p, i64, i64, i64, i64, i64, p, p]
    lib.deliffas_raster_depth.restype = ctypes.c_int


_KERNEL = LazyLibrary("rasterize", _SOURCE, ("-fno-fast-math", "-ffp-contract=off", "-fno-math-errno"), setup=_declare,
                      fallback="the numpy rasteriser, about 20-50x slower")


def raster_kernel_available() -> bool:
    """Whether the C rasteriser is built and loaded in this process (builds it on the first call)."""
    return _KERNEL.get() is not None


@dataclass(frozen=True)
class ShadedPixels:
    """The pixels of one camera image the light field shades, in row-major order.

    Attributes:
        pixels: (N,) int64 flat pixel index row * W + col.
        uv_inner: (N, 2) float32, the inner surface's first-hit uv, or the outer exit uv.
        inner_from_outer: (N,) bool, True where ``uv_inner`` is the outer exit.
        uv_outer: (N, 2) float32, the outer surface's first-hit uv.
        viewdir: (N, 3) float32 unit ray directions, world frame; None when not asked for.
    """

    pixels: Integer[np.ndarray, "N"]
    uv_inner: Float[np.ndarray, "N 2"]
    inner_from_outer: Bool[np.ndarray, "N"]
    uv_outer: Float[np.ndarray, "N 2"]
    viewdir: Float[np.ndarray, "N 3"] | None

    @property
    def num_rays(self) -> int:
        """N."""
        return int(self.pixels.shape[0])


def _project(camera: Camera, verts: np.ndarray) -> np.ndarray:
    """(V, 3) float64 (x px, y px, camera z mm) of world points (V, 3) mm."""
    cam = verts @ camera.R.T + camera.t  # (V, 3) camera frame
    img = cam @ np.asarray(camera.K, np.float64).T
    out = np.empty_like(cam)
    out[:, 0] = img[:, 0] / img[:, 2]
    out[:, 1] = img[:, 1] / img[:, 2]
    out[:, 2] = cam[:, 2]
    return out


class UVRasterizer:
    """One frame's inner and outer surfaces, rasterised per camera (scratch buffers reused across calls, one set per
    thread).

    numpy inside: vertices and faces may be numpy arrays or torch tensors (copied to numpy here, the
    one conversion); the results (:class:`ShadedPixels`) are numpy.

    Args:
        inner_verts: (V, 3) float, mm, the posed mesh.
        faces: (F, 3) int, shared by both surfaces.
        outer_verts: (V, 3) float, mm, the offset shell.
        atlas: UVAtlas with ``face_uvs`` (F, 3).
        method: "auto" (the C kernel when available, else numpy), "native" or "numpy".
    """

    def __init__(self, inner_verts: Real[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"],
                 outer_verts: Real[ArrayLike, "V 3"], atlas: UVAtlas, method: Method = "auto") -> None:
        sizes = check_shape("inner_verts", inner_verts, "V 3")
        sizes = check_shape("faces", faces, "F 3", sizes)
        check_shape("outer_verts", outer_verts, "V 3", sizes)
        if atlas.num_faces != sizes["F"]:
            raise ValueError(f"atlas: face_uvs has {atlas.num_faces} rows, faces has {sizes['F']}")
        if method not in ("auto", "native", "numpy"):
            raise ValueError(f"method: expected 'auto', 'native' or 'numpy', got {method!r}")
        self.method = method
        self.inner = to_numpy(inner_verts, np.float64)  # the numpy boundary: tensors (any device) come to the CPU
        self.outer = to_numpy(outer_verts, np.float64)
        self.faces = np.ascontiguousarray(to_numpy(faces), np.int32)
        self.corner_uvs = np.ascontiguousarray(atlas.uvs.astype(np.float32)[atlas.face_uvs].reshape(-1, 6))  # (F, 6)
        diag = float(np.linalg.norm(self.outer.max(0) - self.outer.min(0))) if len(self.outer) else 1.0
        self.peel_eps = PEEL_EPS_REL * max(diag, 1e-6)
        self.hull_points = np.concatenate([self.inner, self.outer])  # (2V, 3)
        self._local = threading.local()  # scratch buffers per thread: frames may render in several at once

    def _buffer(self, name: str, size: int, dtype) -> np.ndarray:
        scratch = self._local.__dict__.setdefault("scratch", {})
        buf = scratch.get(name)
        if buf is None or buf.size < size:
            buf = scratch[name] = np.empty(max(size, 1), dtype)
        return buf[:size]

    def depth_pass(self, camera: Camera) -> Integer[np.ndarray, "h w"] | None:
        """Face index (h, w) int32 (-1 = none) of the outer surface's nearest fragment per pixel of the
        projected window: one plain z-buffer pass, no peeling and no uvs (C kernel only; the benchmarks'
        baseline). None when a vertex is behind the camera."""
        window = projected_pixel_window(camera, self.hull_points)
        lib = _KERNEL.get()
        if window is None or lib is None:
            return None
        c0, r0, c1, r1 = window
        pout = _project(camera, self.outer)
        n = (c1 - c0) * (r1 - r0)
        z, face = self._buffer("zi", n + _SLACK, np.float32), self._buffer("fi", n + _SLACK, np.int32)
        if lib.deliffas_raster_depth(pout.ctypes.data, self.faces.ctypes.data, len(self.faces), c0, r0,
                                     c1 - c0, r1 - r0, z.ctypes.data, face.ctypes.data) != 0:
            raise MemoryError("UVRasterizer.depth_pass: the face bins could not be allocated")
        return face[:n].reshape(r1 - r0, c1 - c0)

    def shaded_pixels(self, camera: Camera, viewdir: bool = True) -> ShadedPixels | None:
        """The shaded pixels of ``camera``, or None when a vertex is not in front of it (ray-cast then).
        ``viewdir=False`` leaves out the view directions (0.8 ms of a 940 x 1285 frame; most variants read none)."""
        window = projected_pixel_window(camera, self.hull_points)
        if window is None:
            return None
        c0, r0, c1, r1 = window
        pin, pout = _project(camera, self.inner), _project(camera, self.outer)
        m = np.ascontiguousarray(camera.R.T @ np.linalg.inv(camera.K), np.float64)  # (3, 3): pixel -> world dir
        lib = None if self.method == "numpy" else _KERNEL.get()
        if lib is None and self.method == "native":
            raise RuntimeError(f"UVRasterizer: the C rasteriser is unavailable ({_KERNEL.load().reason})")
        if lib is None:
            got = _raster_numpy(pin, pout, self.faces, self.corner_uvs, (c0, r0, c1, r1), camera.width, m,
                                self.peel_eps)
            return got if viewdir else dataclasses.replace(got, viewdir=None)
        w, h = c1 - c0, r1 - r0
        n = w * h
        ptr = lambda a: a.ctypes.data  # noqa: E731
        zi, fi = self._buffer("zi", n + _SLACK, np.float32), self._buffer("fi", n + _SLACK, np.int32)
        zo, fo = (self._buffer("zo", n * OUTER_LAYERS + _SLACK, np.float32),
                  self._buffer("fo", n * OUTER_LAYERS + _SLACK, np.int32))
        pix, uv_in = self._buffer("pix", n, np.int64), self._buffer("uv_in", 2 * n, np.float32)
        from_outer, uv_out = self._buffer("from_outer", n, np.uint8), self._buffer("uv_out", 2 * n, np.float32)
        dirs = self._buffer("viewdir", 3 * n, np.float32) if viewdir else None
        count = lib.deliffas_raster_uv(ptr(pin), ptr(pout), ptr(self.faces), len(self.faces), ptr(self.corner_uvs),
                                       c0, r0, w, h, camera.width, ptr(m), self.peel_eps, ptr(zi), ptr(fi), ptr(zo),
                                       ptr(fo), ptr(pix), ptr(uv_in), ptr(from_outer), ptr(uv_out),
                                       ptr(dirs) if dirs is not None else None)
        if count < 0:
            raise MemoryError("UVRasterizer.shaded_pixels: the face bins could not be allocated")
        return ShadedPixels(pixels=pix[:count].copy(), uv_inner=uv_in[: 2 * count].reshape(count, 2).copy(),
                            inner_from_outer=from_outer[:count].astype(bool),
                            uv_outer=uv_out[: 2 * count].reshape(count, 2).copy(),
                            viewdir=dirs[: 3 * count].reshape(count, 3).copy() if dirs is not None else None)


# ------------------------------------------------------------------------------------------- numpy version
def _fragments(P: np.ndarray, faces: np.ndarray, window: tuple[int, int, int, int]):
    """Every (pixel, depth, face) fragment of a surface in the window: flat window pixel (M,) int64,
    1 / z (M,) float32 (rounded as the kernel stores it), face (M,) int64."""
    c0, r0, c1, r1 = window
    w = c1 - c0
    a, b, c = P[faces[:, 0]], P[faces[:, 1]], P[faces[:, 2]]  # (F, 3) each
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    xs, ys = np.stack([a[:, 0], b[:, 0], c[:, 0]]), np.stack([a[:, 1], b[:, 1], c[:, 1]])
    with np.errstate(invalid="ignore"):
        cs = np.maximum(np.ceil(xs.min(0) - 0.5), c0)
        ce = np.minimum(np.floor(xs.max(0) - 0.5), c1 - 1)
        rs = np.maximum(np.ceil(ys.min(0) - 0.5), r0)
        re = np.minimum(np.floor(ys.max(0) - 0.5), r1 - 1)
        ok = (area != 0) & np.isfinite(area) & (ce >= cs) & (re >= rs)
    tri = np.flatnonzero(ok)
    nc, nr = (ce[tri] - cs[tri] + 1).astype(np.int64), (re[tri] - rs[tri] + 1).astype(np.int64)
    counts = nc * nr
    parts = []
    cum = np.cumsum(counts)
    edges = np.searchsorted(cum, np.arange(_PAIR_CHUNK, int(cum[-1]) if len(cum) else 0, _PAIR_CHUNK), side="right")
    for start, stop in zip([0, *edges], [*edges, len(tri)]):
        if stop <= start:
            continue
        sel = slice(start, stop)
        t = np.repeat(tri[sel], counts[sel])  # (M,) triangle of each pair
        offset = np.arange(len(t)) - np.repeat(np.cumsum(counts[sel]) - counts[sel], counts[sel])
        ncol = np.repeat(nc[sel], counts[sel])
        col = np.repeat(cs[tri[sel]].astype(np.int64), counts[sel]) + offset % ncol
        row = np.repeat(rs[tri[sel]].astype(np.int64), counts[sel]) + offset // ncol
        x, y = col + 0.5, row + 0.5
        A, B, C = a[t], b[t], c[t]
        inv = 1.0 / area[t]
        with np.errstate(over="ignore", invalid="ignore"):  # faces projected absurdly far: no pixel, as the kernel
            l0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv
            l1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv
            l2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv
            # 1 / z interpolated and rounded as the kernel stores it; the kernel drops a covered centre whose
            # rounded value is not > 0 (none with every vertex in front of the camera)
            inv_z = (l0 * (1.0 / A[:, 2]) + l1 * (1.0 / B[:, 2]) + l2 * (1.0 / C[:, 2])).astype(np.float32)
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (inv_z > 0)
        parts.append((((row - r0) * w + (col - c0))[inside], inv_z[inside], t[inside]))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.int64)
    return tuple(np.concatenate(p) for p in zip(*parts))


def _face_uv(P, faces, corner_uvs, face, x, y) -> np.ndarray:
    """(M, 2) float32 perspective-correct uvs of faces (M,) at pixel centres (x, y) (M,)."""
    A, B, C = P[faces[face, 0]], P[faces[face, 1]], P[faces[face, 2]]
    inv = 1.0 / ((B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (B[:, 1] - A[:, 1]) * (C[:, 0] - A[:, 0]))
    q0 = ((C[:, 0] - B[:, 0]) * (y - B[:, 1]) - (C[:, 1] - B[:, 1]) * (x - B[:, 0])) * inv * (1.0 / A[:, 2])
    q1 = ((A[:, 0] - C[:, 0]) * (y - C[:, 1]) - (A[:, 1] - C[:, 1]) * (x - C[:, 0])) * inv * (1.0 / B[:, 2])
    q2 = ((B[:, 0] - A[:, 0]) * (y - A[:, 1]) - (B[:, 1] - A[:, 1]) * (x - A[:, 0])) * inv * (1.0 / C[:, 2])
    s = 1.0 / (q0 + q1 + q2)
    cu = corner_uvs[face].astype(np.float64)  # (M, 6)
    return np.stack([(q0 * cu[:, 0] + q1 * cu[:, 2] + q2 * cu[:, 4]) * s,
                     (q0 * cu[:, 1] + q1 * cu[:, 3] + q2 * cu[:, 5]) * s], axis=1).astype(np.float32)


def _raster_numpy(pin, pout, faces, corner_uvs, window, width: int, m: np.ndarray, eps: float) -> ShadedPixels:
    """The kernel's result from sorted fragments (the reference the C kernel is tested against)."""
    c0, r0, c1, r1 = window
    w = c1 - c0
    n = w * (r1 - r0)
    faces64 = faces.astype(np.int64)
    inner_face = np.full(n, -1, np.int64)
    pix, inv_z, face = _fragments(pin, faces64, window)
    order = np.lexsort((-inv_z, pix))  # nearest first per pixel
    pix, face = pix[order], face[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    inner_face[pix[first]] = face[first]
    pix, inv_z, face = _fragments(pout, faces64, window)
    order = np.lexsort((-inv_z, pix))
    pix, face = pix[order], face[order]
    z = 1.0 / inv_z[order].astype(np.float64)
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    rank = np.arange(len(pix)) - np.maximum.accumulate(np.where(first, np.arange(len(pix)), 0))
    outer_face = np.full(n, -1, np.int64)
    outer_face[pix[first]] = face[first]
    # window pixel centres and ray lengths |R^T K^-1 (x, y, 1)|
    col, row = pix % w + c0 + 0.5, pix // w + r0 + 0.5
    length = np.sqrt(sum((m[j, 0] * col + m[j, 1] * row + m[j, 2]) ** 2 for j in range(3)))
    z0 = np.repeat(z[first], np.diff(np.append(np.flatnonzero(first), len(pix))))
    later = (rank > 0) & (rank < OUTER_LAYERS) & (z > z0 + eps / length)
    later_idx = np.flatnonzero(later)
    keep = np.ones(len(later_idx), bool)
    keep[1:] = pix[later_idx[1:]] != pix[later_idx[:-1]]
    exit_face = np.full(n, -1, np.int64)
    exit_face[pix[later_idx[keep]]] = face[later_idx[keep]]
    from_outer = (inner_face < 0) & (exit_face >= 0)
    shaded = np.flatnonzero((outer_face >= 0) & ((inner_face >= 0) | from_outer))  # row-major window order
    x, y = shaded % w + c0 + 0.5, shaded // w + r0 + 0.5
    fo = from_outer[shaded]
    uv_in = np.empty((len(shaded), 2), np.float32)
    uv_in[~fo] = _face_uv(pin, faces64, corner_uvs, inner_face[shaded[~fo]], x[~fo], y[~fo])
    uv_in[fo] = _face_uv(pout, faces64, corner_uvs, exit_face[shaded[fo]], x[fo], y[fo])
    dirs = np.stack([m[j, 0] * x + m[j, 1] * y + m[j, 2] for j in range(3)], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return ShadedPixels(pixels=(shaded // w + r0) * width + shaded % w + c0, uv_inner=uv_in, inner_from_outer=fo,
                        uv_outer=_face_uv(pout, faces64, corner_uvs, outer_face[shaded], x, y),
                        viewdir=dirs.astype(np.float32))
