/* Rasterised uvs of the inner and outer surfaces per camera pixel, with depth peeling
   (deliffas/fast/rasterize.py, UVRasterizer). Built without FMA contraction and without fast-math. */
#include "rasterize.h"
#include <math.h>
#include <stddef.h>
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
int64_t deliffas_raster_uv(const deliffas_raster_uv_args *a) {
    const double *pin = a->pin, *pout = a->pout, *m = a->m; const int32_t *faces = a->faces; double eps = a->eps;
    const float *corner_uvs = a->corner_uvs; int64_t F = a->F, c0 = a->c0, r0 = a->r0, w = a->w, h = a->h, W = a->W;
    float *zi = a->zi, *zo = a->zo, *uv_in = a->uv_in, *uv_out = a->uv_out, *viewdir = a->viewdir;
    int32_t *fi = a->fi, *fo = a->fo; int64_t *pix = a->pix; uint8_t *from_outer = a->from_outer;
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

/* The layout of deliffas_raster_uv_args as this compiler lays it out: its sizeof, then the offsetof of each field in
   declaration order, into out (unless NULL); returns their number. deliffas/native.py checks the Structure it
   parses from rasterize.h against it. */
#define RASTER_UV_AT(f) (int64_t)offsetof(deliffas_raster_uv_args, f)
int64_t deliffas_raster_uv_args_layout(int64_t *out) {
    const int64_t layout[] = {
        (int64_t)sizeof(deliffas_raster_uv_args), RASTER_UV_AT(pin), RASTER_UV_AT(pout), RASTER_UV_AT(faces),
        RASTER_UV_AT(corner_uvs), RASTER_UV_AT(m), RASTER_UV_AT(zi), RASTER_UV_AT(fi), RASTER_UV_AT(zo),
        RASTER_UV_AT(fo), RASTER_UV_AT(pix), RASTER_UV_AT(uv_in), RASTER_UV_AT(from_outer), RASTER_UV_AT(uv_out),
        RASTER_UV_AT(viewdir), RASTER_UV_AT(F), RASTER_UV_AT(c0), RASTER_UV_AT(r0), RASTER_UV_AT(w), RASTER_UV_AT(h),
        RASTER_UV_AT(W), RASTER_UV_AT(eps)};
    int64_t count = (int64_t)(sizeof layout / sizeof layout[0]);
    for (int64_t i = 0; out && i < count; i++) out[i] = layout[i];
    return count;
}
