/* Triangle-id rasterizer: per (sub-)pixel center, the nearest front-facing and the nearest
 * back-facing triangle of each view, both layers in one pass over the triangles.
 *
 * Why: the G-buffer needs only *which* triangle each pixel center sees per layer (gbuffer.c
 * then intersects the exact ray with it); the OpenGL passes (geometry/raster.py, Mesa's
 * llvmpipe on a CPU) took two draws and two readbacks per view, most of a small frame's
 * G-buffer. The conventions are those passes' (raster.py, which stays the reference):
 *   - clip = M (x, y, z, 1), M = P V of raster._view_matrices (float64, row-major);
 *     window x = (x/w + 1) W / 2 and y = (1 - y/w) H / 2 (y down: row 0 at the top);
 *   - window positions snapped to 1/256 pixel, as llvmpipe snaps them: a pixel is covered
 *     where its center (i + 0.5, j + 0.5) is inside the snapped triangle, by exact integer
 *     edge functions with a top-left fill rule in OpenGL's window coordinates (y up; with
 *     y down: left and bottom edges), llvmpipe's too, so triangles sharing an edge cover
 *     each center on it once (no gaps, no double cover);
 *   - front-facing = counter-clockwise with y up (GL_CCW): negative area with y down;
 *   - the nearest by 1/w (affine in screen space, decreasing with view depth; float64,
 *     compared to 2^-28 relative, finer than a 24-bit depth buffer), and on equal depths
 *     the lower face index, as with GL_LESS drawing the faces in order: depth and index
 *     are one 64-bit key per pixel (40 bits of depth above a 24-bit face index, the
 *     OpenGL passes' id limit too), kept at its minimum and turned into the id at the
 *     end;
 *   - triangles are clipped in homogeneous space against the near and far planes of P
 *     (z = -w, z = w; where the camera is close to or inside the mesh the near plane cuts
 *     them) and against a guard band 2^20 pixels around the frame (the integer edge
 *     functions' range; only triangles reaching that far are cut, which changes no
 *     covered pixel); a point cut from an edge is computed from the edge's endpoints in
 *     a canonical order, the same bits for both triangles sharing it. Triangles entirely
 *     outside one frustum plane are skipped, bounding boxes clamped to the frame,
 *     zero-area (after snapping) triangles skipped.
 * The ids agree with OpenGL's but at centers on or within ~1/256 pixel of an edge (their
 * rounding and tie rules), which gbuffer.c's repair decides by the exact ray anyway.
 *
 * Threads: one work item per (view, row band); a band projects its view's vertices into
 * its thread's scratch and rasterizes every triangle overlapping its rows into its own
 * keys, then writes its own rows of the outputs (no locks). Plain C (threads: common.h),
 * a triangle's wider boxes in AVX2 lanes where built for it (the same integer and double
 * operations as the scalar loop); built and loaded by native.py.
 */

#include <stdlib.h>
#include <string.h>

#include "common.h"
#include "subpixels.h"

typedef struct {
    int64_t b, h, w;
    const float *vertices;  /* (V, 3) world positions of all views' meshes */
    const int64_t *faces;   /* (F, 3) vertex indices, local to their view's vertex range */
    const int64_t *views;   /* (B, 5): vertex offset, vertex count, face offset, face
                             * count, id offset (added to the face index written) */
    const double *mvp;      /* (B, 16) row-major P V */
    void *front, *back;     /* out (B, rows, W) face id + id offset, -1 where none */
    int64_t row0, rows;     /* the frame's rows drawn: [row0, row0 + rows) of the H (rows 0:
                             * all H); a pixel's ids do not depend on the rows drawn with
                             * it, so a frame drawn in strips is the frame drawn whole */
    int ids32;              /* 1: the outputs are int32 (ids < 2^31), else int64 */
    int64_t sub_n;          /* n > 0 (with ids32): the frame is an n x n sub-pixel grid, and
                             * ``flags`` (B, rows / n, W / n) gets its pixels' sub-pixel
                             * flags (subpixels.h), computed as the ids are written */
    uint8_t *flags;
    Folds folds;
} RasterJob;

#define SUB_BITS 8                     /* window positions in 1/256 pixel */
#define SUB ((int64_t)1 << SUB_BITS)
#define HALF (SUB / 2)                 /* a pixel center's offset */
#define GUARD 1048576.0                /* guard band, pixels beyond the frame (2^20) */
#define MAX_SIZE 1048576               /* frame width and height at most (2^20) */
/* Within the band positions stay below 2^22 pixels = 2^30 units, so every edge function,
 * a difference of two products of such differences, stays below 2^62. */

enum { NEAR = 1, FAR = 2, G_LEFT = 4, G_RIGHT = 8, G_BOTTOM = 16, G_TOP = 32,
       LEFT = 64, RIGHT = 128, BOTTOM = 256, TOP = 512 };
#define CLIPPED (NEAR | FAR | G_LEFT | G_RIGHT | G_BOTTOM | G_TOP)

#define ID_BITS 24
#define ID_MASK (((uint64_t)1 << ID_BITS) - 1)
#define EMPTY UINT64_MAX               /* no face: -1 as an int64 */

typedef struct {
    double q;         /* 1/w */
    int32_t x, y;     /* snapped window position (units of 1/SUB pixel, y down) */
} SPt;

typedef struct {
    SPt p;
    int32_t code;     /* the planes it is outside of (CLIPPED ones: p unset) */
} SVert;

typedef struct {
    int64_t r0, r1, w;   /* this band's rows [r0, r1) of a w-wide frame */
    uint64_t *key[2];    /* front, back: per pixel the least depth << ID_BITS | face */
} Band;

typedef struct {
    double gx, gy;        /* the guard band in NDC: |x| <= gx w, |y| <= gy w */
    double half_w, half_h;
} Frame;

typedef struct {
    const RasterJob *job;
    int64_t bands;        /* row bands per view */
    int failed;           /* scratch memory could not be allocated */
} RasterRun;

/* The signed distance of a clip-space point to clipping plane ``plane`` (a CLIPPED bit's
 * index), >= 0 inside. */
static inline double plane_dist(const double *c, int plane, const Frame *fr) {
    switch (plane) {
        case 0: return c[2] + c[3];
        case 1: return c[3] - c[2];
        case 2: return c[0] + fr->gx * c[3];
        case 3: return fr->gx * c[3] - c[0];
        case 4: return c[1] + fr->gy * c[3];
        default: return fr->gy * c[3] - c[1];
    }
}

/* The planes a clip-space point is outside of (NaN: of all but the frustum's). */
static int32_t outcode(const double *c, const Frame *fr) {
    int32_t k = 0;
    if (!(c[2] + c[3] >= 0.0) || !(c[3] > 0.0)) k |= NEAR;  /* NaN too */
    if (!(c[3] - c[2] >= 0.0)) k |= FAR;
    if (c[0] < -c[3]) k |= LEFT;
    if (c[0] > c[3]) k |= RIGHT;
    if (c[1] < -c[3]) k |= BOTTOM;
    if (c[1] > c[3]) k |= TOP;
    for (int plane = 2; plane < 6; plane++)  /* the guard band, as the clipping tests it */
        if (!(plane_dist(c, plane, fr) >= 0.0)) k |= 1 << plane;
    return k;
}

/* Snapped window position and 1/w of a clip-space point inside the guard band (w > 0);
 * the one formula for vertices and cut points alike. Returns 0 where it is not finite. */
static inline int project(const double *c, const Frame *fr, SPt *out) {
    double inv = 1.0 / c[3];
    double sx = (c[0] * inv + 1.0) * fr->half_w, sy = (1.0 - c[1] * inv) * fr->half_h;
    sx = floor(sx * (double)SUB + 0.5);
    sy = floor(sy * (double)SUB + 0.5);
    if (!(fabs(sx) < 4.0 * GUARD * (double)SUB && fabs(sy) < 4.0 * GUARD * (double)SUB))
        return 0;
    out->x = (int32_t)sx;
    out->y = (int32_t)sy;
    out->q = inv;
    return 1;
}

/* A vertex in clip space: M (x, y, z, 1). */
static inline void to_clip(const double *m, const float *v, double *c) {
    double x = (double)v[0], y = (double)v[1], z = (double)v[2];
    for (int r = 0; r < 4; r++)
        c[r] = ((m[4 * r] * x + m[4 * r + 1] * y) + m[4 * r + 2] * z) + m[4 * r + 3];
}

static inline int64_t min3i(int64_t a, int64_t b, int64_t c) {
    int64_t m = a < b ? a : b;
    return m < c ? m : c;
}

static inline int64_t max3i(int64_t a, int64_t b, int64_t c) {
    int64_t m = a > b ? a : b;
    return m > c ? m : c;
}

/* One edge p -> q of a positively oriented triangle: E(P) = dx (P.y - p.y) - dy (P.x - p.x)
 * is >= 0 inside; minus 1 unless it is a left or (y down) bottom edge, OpenGL's top (with
 * y down the inward normal is (-dy, dx): left where dy < 0, bottom where dy == 0 and
 * dx < 0), so that a center on a shared edge is inside for exactly one of the two
 * triangles (the one of llvmpipe's rule: tests/test_native_raster.py). */
static inline int64_t edge_at(const SPt *p, const SPt *q, int64_t px, int64_t py) {
    int64_t dx = (int64_t)q->x - p->x, dy = (int64_t)q->y - p->y;
    int tl = dy < 0 || (dy == 0 && dx < 0);
    return dx * (py - p->y) - dy * (px - p->x) - (tl ? 0 : 1);
}

/* A center's key: the depth (the complement of 1/w's bits, q > 0: they grow with q)
 * above the face id, or EMPTY's bits where an edge function is negative (outside). */
static inline uint64_t center_key(int64_t w0, int64_t w1, int64_t w2, double q, uint64_t id) {
    uint64_t qbits;
    memcpy(&qbits, &q, 8);
    uint64_t out = (uint64_t)((w0 | w1 | w2) >> 63);  /* all ones: outside */
    return ((~qbits >> ID_BITS) << ID_BITS | id) | out;
}

static inline uint64_t keep_less(uint64_t cur, uint64_t k) { return k < cur ? k : cur; }

#if defined(__AVX2__)
#include <immintrin.h>
#define TR_RASTER4 1
#ifndef RASTER4_FROM
#define RASTER4_FROM 3   /* the narrowest box drawn in lanes (fastest here) */
#endif

/* center_key and keep_less for the row's nx centers in groups of four lanes, the same
 * integer and double operations; a last group past the box but inside the band's row
 * (``room`` keys from key) leaves the keys past it as they are, else it is done one by
 * one. */
static void raster_row4(uint64_t *key, int64_t nx, int64_t room, int64_t e0, int64_t e1,
                        int64_t e2, int64_t sx0, int64_t sx1, int64_t sx2, double qrow,
                        double qstep, uint64_t id) {
    __m256i w0 = _mm256_setr_epi64x(e0, e0 + sx0, e0 + 2 * sx0, e0 + 3 * sx0);
    __m256i w1 = _mm256_setr_epi64x(e1, e1 + sx1, e1 + 2 * sx1, e1 + 3 * sx1);
    __m256i w2 = _mm256_setr_epi64x(e2, e2 + sx2, e2 + 2 * sx2, e2 + 3 * sx2);
    __m256i s0 = _mm256_set1_epi64x(4 * sx0), s1 = _mm256_set1_epi64x(4 * sx1),
            s2 = _mm256_set1_epi64x(4 * sx2);
    __m256d xs = _mm256_setr_pd(0.0, 1.0, 2.0, 3.0), four = _mm256_set1_pd(4.0);
    __m256d qr = _mm256_set1_pd(qrow), qs = _mm256_set1_pd(qstep);
    __m256i ids = _mm256_set1_epi64x((int64_t)id), zero = _mm256_setzero_si256();
    __m256i ones = _mm256_set1_epi64x(-1), sign = _mm256_set1_epi64x(INT64_MIN);
    __m256i lane = _mm256_setr_epi64x(0, 1, 2, 3);
    for (int64_t x = 0; x < nx; x += 4) {
        __m256i qbits = _mm256_castpd_si256(_mm256_add_pd(qr, _mm256_mul_pd(xs, qs)));
        __m256i k = _mm256_slli_epi64(_mm256_srli_epi64(_mm256_xor_si256(qbits, ones), ID_BITS),
                                      ID_BITS);
        __m256i out = _mm256_cmpgt_epi64(zero, _mm256_or_si256(_mm256_or_si256(w0, w1), w2));
        k = _mm256_or_si256(_mm256_or_si256(k, ids), out);
        if (x + 4 > room) {  /* the row's end: the rest one by one */
            for (; x < nx; x++)
                key[x] = keep_less(key[x], center_key(e0 + x * sx0, e1 + x * sx1, e2 + x * sx2,
                                                       qrow + (double)x * qstep, id));
            return;
        }
        /* a group past the box (its last) keeps those keys: the lanes inside only */
        __m256i in = _mm256_cmpgt_epi64(_mm256_set1_epi64x(nx - x), lane);
        __m256i cur = _mm256_loadu_si256((const __m256i *)(key + x));
        __m256i less = _mm256_and_si256(in, _mm256_cmpgt_epi64(_mm256_xor_si256(cur, sign),
                                        _mm256_xor_si256(k, sign)));  /* k < cur, unsigned */
        _mm256_storeu_si256((__m256i *)(key + x), _mm256_blendv_epi8(cur, k, less));
        w0 = _mm256_add_epi64(w0, s0);
        w1 = _mm256_add_epi64(w1, s1);
        w2 = _mm256_add_epi64(w2, s2);
        xs = _mm256_add_pd(xs, four);
    }
}
#endif

/* Rasterize the snapped triangle (a, b, c), face ``id`` (< 2^ID_BITS), into the band. */
static void raster_tri(const Band *bd, const SPt *a, const SPt *b, const SPt *c, uint64_t id) {
    /* the centers X = x SUB + HALF in [min, max]: x in [ceil((min - HALF) / SUB),
     * floor((max - HALF) / SUB)] (arithmetic shifts floor) */
    int64_t y0 = -((HALF - min3i(a->y, b->y, c->y)) >> SUB_BITS);
    int64_t y1 = (max3i(a->y, b->y, c->y) - HALF) >> SUB_BITS;
    if (y0 < bd->r0) y0 = bd->r0;
    if (y1 > bd->r1 - 1) y1 = bd->r1 - 1;
    if (y0 > y1) return;
    int64_t x0 = -((HALF - min3i(a->x, b->x, c->x)) >> SUB_BITS);
    int64_t x1 = (max3i(a->x, b->x, c->x) - HALF) >> SUB_BITS;
    if (x0 < 0) x0 = 0;
    if (x1 > bd->w - 1) x1 = bd->w - 1;
    if (x0 > x1) return;
    int64_t area = ((int64_t)b->x - a->x) * ((int64_t)c->y - a->y)
                   - ((int64_t)c->x - a->x) * ((int64_t)b->y - a->y);
    if (area == 0) return;
    int layer = area < 0 ? 0 : 1;  /* counter-clockwise with y up: front */
    if (area < 0) {                /* orient positively: swap b and c */
        const SPt *t = b;
        b = c;
        c = t;
        area = -area;
    }
    int64_t px = x0 * SUB + HALF, py = y0 * SUB + HALF;
    int64_t e0 = edge_at(b, c, px, py), e1 = edge_at(c, a, px, py), e2 = edge_at(a, b, px, py);
    /* per pixel right: -dy SUB; per row down: dx SUB */
    int64_t sx0 = -((int64_t)c->y - b->y) * SUB, sx1 = -((int64_t)a->y - c->y) * SUB,
            sx2 = -((int64_t)b->y - a->y) * SUB;
    int64_t sy0 = ((int64_t)c->x - b->x) * SUB, sy1 = ((int64_t)a->x - c->x) * SUB,
            sy2 = ((int64_t)b->x - a->x) * SUB;
    /* 1/w over the plane, per unit: q(P) = q_a + qx (P.x - a.x) + qy (P.y - a.y) */
    double bx = (double)((int64_t)b->x - a->x), by = (double)((int64_t)b->y - a->y);
    double cx = (double)((int64_t)c->x - a->x), cy = (double)((int64_t)c->y - a->y);
    double qb = b->q - a->q, qc = c->q - a->q, inv = 1.0 / (double)area;
    double qx = (qb * cy - qc * by) * inv, qy = (qc * bx - qb * cx) * inv;
    double qstep = qx * (double)SUB;
    double q_left = a->q + qx * (double)(px - a->x);
    /* 1/w at a center: its row's value plus x steps (not summed pixel by pixel), so
     * that the lanes below compute it alike. Boxes narrower than a lane group: branch-free
     * (small triangles make the tests unpredictable), the box as one loop (one exit per
     * triangle, not per row: at a row's end the edge functions, 1/w and the row move on by
     * selects); wider ones row by row, four centers at a time where built for AVX2. The
     * key, or EMPTY where the center is outside, kept where less; the rows are this
     * band's own. */
    int64_t nx = x1 - x0 + 1, ny = y1 - y0 + 1;
    double qrow = q_left + qy * (double)(y0 * SUB + HALF - a->y), qys = qy * (double)SUB;
    uint64_t *key = bd->key[layer] + (y0 - bd->r0) * bd->w + x0;
#ifdef TR_RASTER4
    if (nx >= RASTER4_FROM) {
        for (int64_t r = 0; r < ny; r++, key += bd->w) {
            raster_row4(key, nx, bd->w - x0, e0, e1, e2, sx0, sx1, sx2, qrow, qstep, id);
            e0 += sy0;
            e1 += sy1;
            e2 += sy2;
            qrow += qys;
        }
        return;
    }
#endif
    int64_t n = nx * ny, x = 0;
    for (int64_t i = 0; i < n; i++) {
        key[x] = keep_less(key[x], center_key(e0 + x * sx0, e1 + x * sx1, e2 + x * sx2,
                                               qrow + (double)x * qstep, id));
        int wrap = x == nx - 1;
        e0 = wrap ? e0 + sy0 : e0;
        e1 = wrap ? e1 + sy1 : e1;
        e2 = wrap ? e2 + sy2 : e2;
        qrow = wrap ? qrow + qys : qrow;
        key = wrap ? key + bd->w : key;
        x = wrap ? 0 : x + 1;
    }
}

/* The point where the edge (p, q) crosses a plane (dp, dq: their signed distances, of
 * opposite signs), from the endpoints in a canonical order (the same bits for both
 * triangles sharing the edge). */
static void cut(const double *p, const double *q, double dp, double dq, double *out) {
    int swap = 0;
    for (int i = 0; i < 4; i++)
        if (p[i] != q[i]) {
            swap = q[i] < p[i];
            break;
        }
    if (swap) {
        const double *t = p;
        double dt = dp;
        p = q; q = t; dp = dq; dq = dt;
    }
    double t = dp / (dp - dq);
    for (int i = 0; i < 4; i++) out[i] = p[i] + t * (q[i] - p[i]);
}

/* A triangle crossing the near or far plane or the guard band: clipped in homogeneous
 * space against the planes its corners are outside of (Sutherland-Hodgman, at most 9
 * corners), projected, and rasterized as a fan. */
static void raster_clipped(const Band *bd, const double *c0, const double *c1,
                           const double *c2, int32_t planes, const Frame *fr, uint64_t id) {
    double buf[2][9][4];
    int n = 3;
    for (int i = 0; i < 4; i++) {
        buf[0][0][i] = c0[i];
        buf[0][1][i] = c1[i];
        buf[0][2][i] = c2[i];
    }
    int cur = 0;
    for (int plane = 0; plane < 6; plane++) {
        if (!(planes & (1 << plane))) continue;
        int m = 0;
        double (*in)[4] = buf[cur], (*out)[4] = buf[1 - cur];
        for (int i = 0; i < n; i++) {
            const double *p = in[i], *q = in[(i + 1) % n];
            double dp = plane_dist(p, plane, fr), dq = plane_dist(q, plane, fr);
            if (dp >= 0.0) {
                for (int k = 0; k < 4; k++) out[m][k] = p[k];
                m++;
            }
            if ((dp >= 0.0) != (dq >= 0.0)) {
                cut(p, q, dp, dq, out[m]);
                m++;
            }
        }
        n = m;
        cur = 1 - cur;
        if (n < 3) return;
    }
    SPt s[9];
    for (int i = 0; i < n; i++)
        if (!(buf[cur][i][3] > 0.0) || !project(buf[cur][i], fr, &s[i])) return;
    for (int i = 1; i + 1 < n; i++) raster_tri(bd, &s[0], &s[i], &s[i + 1], id);
}

/* A thread's scratch, grown as its items need and kept from one item to the next (its
 * keys stay in cache): the keys of a band's two layers, its view's projected vertices. */
typedef struct {
    uint64_t *key;
    SVert *sv;
    int64_t key_n, sv_n;
} Scratch;

static int reserve(void **buf, int64_t *have, int64_t want, size_t size) {
    if (*have >= want) return 1;
    free(*buf);
    *buf = malloc(size * (size_t)want);
    *have = *buf != NULL ? want : 0;
    return *buf != NULL;
}

/* A band's keys to ids: the face + id offset, -1 where none (loops the compiler puts
 * in lanes: the output's type decided once, outside). */
static void keys_to_ids32(const uint64_t *restrict key, int64_t n, int64_t id_off,
                          int32_t *restrict out) {
    for (int64_t p = 0; p < n; p++)
        out[p] = key[p] == EMPTY ? -1 : (int32_t)((int64_t)(key[p] & ID_MASK) + id_off);
}

static void keys_to_ids64(const uint64_t *restrict key, int64_t n, int64_t id_off,
                          int64_t *restrict out) {
    for (int64_t p = 0; p < n; p++)
        out[p] = key[p] == EMPTY ? -1 : (int64_t)(key[p] & ID_MASK) + id_off;
}

/* One (view, row band) work item. */
static void raster_item(RasterRun *run, int64_t item, Scratch *sc) {
    const RasterJob *j = run->job;
    int64_t view = item / run->bands, band = item % run->bands;
    int64_t h = j->h, w = j->w;
    int64_t row0 = j->rows > 0 ? j->row0 : 0, rows = j->rows > 0 ? j->rows : h;
    Band bd;
    int64_t unit = j->sub_n > 0 ? j->sub_n : 1;  /* bands of whole pixel rows */
    bd.r0 = row0 + unit * (band * (rows / unit) / run->bands);
    bd.r1 = row0 + unit * ((band + 1) * (rows / unit) / run->bands);
    bd.w = w;
    int64_t npix = (bd.r1 - bd.r0) * w;
    int64_t at = (view * rows + bd.r0 - row0) * w;  /* this band's first output pixel */
    const int64_t *vw = j->views + 5 * view;
    int64_t voff = vw[0], vn = vw[1], foff = vw[2], fn = vw[3], id_off = vw[4];
    if ((uint64_t)fn > ID_MASK || !reserve((void **)&sc->key, &sc->key_n, 2 * npix, 8) ||
        !reserve((void **)&sc->sv, &sc->sv_n, vn > 0 ? vn : 1, sizeof(SVert))) {
        __atomic_store_n(&run->failed, 1, __ATOMIC_RELAXED);  /* too many faces, or memory */
        return;
    }
    bd.key[0] = sc->key;
    bd.key[1] = sc->key + npix;
    for (int64_t p = 0; p < 2 * npix; p++) sc->key[p] = EMPTY;
    SVert *sv = sc->sv;
    Frame fr = {1.0 + 2.0 * GUARD / (double)w, 1.0 + 2.0 * GUARD / (double)h,
                0.5 * (double)w, 0.5 * (double)h};
    const double *m = j->mvp + 16 * view;
    const float *vs = j->vertices + 3 * voff;
    for (int64_t v = 0; v < vn; v++) {
        double c[4];
        to_clip(m, vs + 3 * v, c);
        sv[v].code = outcode(c, &fr);
        if (!(sv[v].code & CLIPPED) && !project(c, &fr, &sv[v].p)) sv[v].code |= NEAR;
    }
    const int64_t *fs = j->faces + 3 * foff;
    for (int64_t f = 0; f < fn; f++) {
        int64_t i0 = fs[3 * f], i1 = fs[3 * f + 1], i2 = fs[3 * f + 2];
        if (i0 < 0 || i0 >= vn || i1 < 0 || i1 >= vn || i2 < 0 || i2 >= vn) continue;
        int32_t k0 = sv[i0].code, k1 = sv[i1].code, k2 = sv[i2].code;
        if (k0 & k1 & k2) continue;  /* all outside one plane */
        if ((k0 | k1 | k2) & CLIPPED) {
            double c0[4], c1[4], c2[4];  /* the same values as the vertex loop's */
            to_clip(m, vs + 3 * i0, c0);
            to_clip(m, vs + 3 * i1, c1);
            to_clip(m, vs + 3 * i2, c2);
            raster_clipped(&bd, c0, c1, c2, (k0 | k1 | k2) & CLIPPED, &fr, (uint64_t)f);
        } else {
            raster_tri(&bd, &sv[i0].p, &sv[i1].p, &sv[i2].p, (uint64_t)f);
        }
    }
    if (j->sub_n > 0) {  /* a pixel row's n rows of ids, then its flags (in cache) */
        int64_t n = j->sub_n, nw = n * w, pw = w / n;
        int32_t *front = (int32_t *)j->front + at, *back = (int32_t *)j->back + at;
        uint8_t *fl = j->flags + ((view * rows + bd.r0 - row0) / n) * pw;
        for (int64_t r = 0; r < npix; r += nw, fl += pw) {
            keys_to_ids32(bd.key[0] + r, nw, id_off, front + r);
            keys_to_ids32(bd.key[1] + r, nw, id_off, back + r);
            sub_flags_row(&j->folds, front + r, back + r, pw, n, fl);
        }
        return;
    }
    for (int l = 0; l < 2; l++) {  /* keys to ids: the face + id offset, -1 where none */
        void *out = l ? j->back : j->front;
        if (j->ids32) keys_to_ids32(bd.key[l], npix, id_off, (int32_t *)out + at);
        else keys_to_ids64(bd.key[l], npix, id_off, (int64_t *)out + at);
    }
}

static void raster_range(const void *job, int64_t begin, int64_t end) {
    Scratch sc = {NULL, NULL, 0, 0};
    RasterRun *run = (RasterRun *)job;
    for (int64_t i = begin; i < end; i++) raster_item(run, i, &sc);
    free(sc.key);
    free(sc.sv);
}

/* Entry point (ctypes, native.py): both layers of all B views on ``threads`` threads, the
 * views split into row bands where there are fewer views than threads. Returns 0, or -1
 * where a thread could not be started, memory was short or the frame is too large. */
int torchrefract_raster(const RasterJob *job, int threads) {
    if (job->b <= 0 || job->h <= 0 || job->w <= 0) return 0;
    if (job->h > MAX_SIZE || job->w > MAX_SIZE) return -1;
    if (job->rows < 0 || job->row0 < 0 || (job->rows > 0 && job->row0 + job->rows > job->h))
        return -1;
    int64_t n = job->sub_n;
    if (n < 0 || (n > 0 && (!job->ids32 || job->w % n || job->h % n || job->row0 % n ||
                            job->rows % n)))
        return -1;  /* flags need whole pixels */
    int64_t rows = job->rows > 0 ? job->rows : job->h;
    int64_t bands = 1;
    if (threads > job->b) bands = (threads + job->b - 1) / job->b;
    int64_t most = rows / 16 > 1 ? rows / 16 : 1;  /* bands of >= 16 rows */
    if (bands > most) bands = most;
    RasterRun run = {job, bands, 0};
    int rc = tr_parallel_for_grain(raster_range, &run, job->b * bands, 2, threads, 1);
    return rc != 0 || run.failed ? -1 : 0;
}

int64_t torchrefract_raster_job_size(void) { return (int64_t)sizeof(RasterJob); }

/* The sub-pixel flags (subpixels.h) of ids drawn elsewhere: (B, h, w) pixels from both
 * layers' int32 ids on their (B, n h, n w) grid. */
typedef struct {
    int64_t b, h, w, n;
    const int32_t *front, *back;
    Folds folds;
    uint8_t *out;               /* (B, h, w) */
} SubFlagsJob;

static void sub_flags_range(const void *job, int64_t begin, int64_t end) {
    const SubFlagsJob *j = (const SubFlagsJob *)job;
    int64_t nw = j->n * j->w;
    for (int64_t r = begin; r < end; r++) {  /* pixel rows of all views */
        int64_t at = r * j->n * nw;
        sub_flags_row(&j->folds, j->front + at, j->back + at, j->w, j->n, j->out + r * j->w);
    }
}

int torchrefract_sub_flags(const SubFlagsJob *job, int threads) {
    if (job->n < 1) return -1;
    return tr_parallel_for_grain(sub_flags_range, job, job->b * job->h, 8, threads, 1);
}

int64_t torchrefract_sub_flags_job_size(void) { return (int64_t)sizeof(SubFlagsJob); }
