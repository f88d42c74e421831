/* The discrete part of torchrefract's ray march (march.py), one ray at a time: the
 * functions shared by the march kernel (march.c) and the fused shading (specular.c).
 *
 * The same decisions as march.py's tensor code, in the same float32 arithmetic (built with
 * -ffp-contract=off and no fast-math, so every product, sum and quotient rounds as torch's
 * elementwise ops do): the uniform search over the bounding chord, the bisections, the
 * exit candidates (the triangle seen at the crossing pixel, then at the last pixel still
 * inside, per marched layer) and the walk to the triangle that contains the hit. It
 * returns which triangle each ray leaves through; where a gradient is wanted, march.py
 * then intersects the ray with that triangle in torch (the differentiable part), and
 * elsewhere this kernel also returns the exit's values as march._exit computes them
 * (exit_values). The search and bisections run 16 rays in lockstep, as AVX2 vectors
 * where the CPU has them (search_block_avx2: the same operations per lane).
 *
 * Why by hand: the tensor form is a chain of ~20 elementwise ops and a gather per sample
 * over all rays (memory traffic, compactions); here each ray's state stays in registers
 * and only its plane and triangle reads touch memory. Plain C (threads: common.h), no Python or
 * torch headers: torchrefract/native.py builds it with the system C compiler on first use
 * and falls back to the tensor code when that fails.
 *
 * The formulas mirror, line by line:
 *   march._pixel_of_camera, march._crossed_at (the plane test), march._march's search
 *   and bisections, its ``candidates`` and ``tries``, march._walk_to_containing, and
 *   gbuffer.intersect_triangles, optics.dot ((a0 b0 + a1 b1) + a2 b2), gbuffer.interpolate
 *   and march._exit.
 */

#ifndef TORCHREFRACT_MARCH_CORE_H
#define TORCHREFRACT_MARCH_CORE_H

#include "optics.h"

typedef struct {
    int64_t n;
    const float *c0, *ct;   /* (N, 3) camera coordinates of the start and per unit s */
    const float *s_max;     /* (N,) bounding chord */
    const float *s_min;     /* (N,) smallest accepted exit distance */
    const float *sx_v, *sy_v; /* (B,) per-view pixel scales */
    const int64_t *batch;   /* (N,) view of each ray */
    const float *planes;    /* (R, 4) each view's triangles' camera-space planes, normal
                             * away from the eye (march.Marched.table) */
    const int64_t *plane_base; /* (B,) view b's triangle t has row plane_base[b] + t */
    int pw;                 /* 4: back layer only, 8: back and front (march_inside) */
    int64_t h, w;
    int steps, refine;
    const float *p1, *t;    /* (N, 3) world start and direction */
    const int32_t *tri_front, *tri_back;    /* (B*H*W,) triangle seen per pixel, -1 where
                                             * the layer is empty (march.Marched) */
    const float *tv;        /* (T, 3, 3) triangle vertices */
    const int64_t *across;  /* (T, 3) face across the edge opposite each vertex, -1 */
    int walk_steps;
    int simd;               /* 1: the AVX2 search where the CPU has it (0: scalar only; the
                             * caller sets 0 where the pixel or plane indices exceed 32
                             * bits) */
    const float *tn;        /* (T, 3, 3) corner shading normals (for the exits below) */
    /* out, optional (NULL: not wanted; march.py then computes them in torch, with
     * gradients): the exit distance (N,), barycentrics (N, 3), unit shading normal (N, 3)
     * and position (N, 3), as march._exit computes them */
    float *s_out, *bary_out, *normal_out, *pos_out;
    uint8_t *found;         /* out (N,) */
    int64_t *tri;           /* out (N,) exit triangle or -1 */
    int64_t *layer;         /* out (N,) 0 front, 1 back, -1 */
} Job;


static inline int argmin3(const float *b) {  /* torch.argmin: the first of equal minima */
    int k = 0;
    if (b[1] < b[k]) k = 1;
    if (b[2] < b[k]) k = 2;
    return k;
}

/* march._pixel_of_camera: the flat pixel (clamped into the frame, as torch's clamp does)
 * and whether the point lies in the frame, of camera coordinates c. */
static inline int64_t pixel_of(const Job *j, int64_t r, const float *c, int *inside) {
    int64_t b = j->batch[r];
    float z = c[2];
    float zs = z < 1e-12f ? 1e-12f : z;
    if (z != z) zs = z;  /* clamp propagates NaN */
    float hw = 0.5f * (float)j->w, hh = 0.5f * (float)j->h;
    float px = floorf(c[0] / zs * j->sx_v[b] + hw);
    float py = floorf(hh - c[1] / zs * j->sy_v[b]);
    float wm = (float)(j->w - 1), hm = (float)(j->h - 1);
    *inside = (z > 1e-12f) && px >= 0.0f && px <= wm && py >= 0.0f && py <= hm;
    float pxc = px < 0.0f ? 0.0f : (px > wm ? wm : px);
    float pyc = py < 0.0f ? 0.0f : (py > hm ? hm : py);
    if (pxc != pxc) pxc = 0.0f;  /* NaN: any pixel (the caller ignores it) */
    if (pyc != pyc) pyc = 0.0f;
    return b * j->h * j->w + (int64_t)pyc * j->w + (int64_t)pxc;
}

static inline void point_at(const Job *j, int64_t r, float s, float *c) {
    const float *c0 = j->c0 + 3 * r, *ct = j->ct + 3 * r;
    for (int i = 0; i < 3; i++) {
        float m = s * ct[i];
        c[i] = c0[i] + m;
    }
}

/* The plane row of triangle t (>= 0) in the view of ray r (march.Marched). */
static inline const float *plane_row(const Job *j, int64_t r, int32_t t) {
    return j->planes + 4 * (j->plane_base[j->batch[r]] + (int64_t)t);
}

/* march._crossed_at for one ray at parameter s: outside the frame, a marched layer empty
 * at the pixel, beyond the back triangle's plane, or (pw 8) in front of the front
 * triangle's (its row negated: c - n . x > 0). */
static int crossed_at(const Job *j, int64_t r, float s) {
    float c[3];
    point_at(j, r, s, c);
    int inside;
    int64_t flat = pixel_of(j, r, c, &inside);
    if (!inside) return 1;
    int32_t tb = j->tri_back[flat];
    if (tb < 0) return 1;
    const float *pl = plane_row(j, r, tb);
    if (dot3(pl, c) - pl[3] > 0.0f) return 1;
    if (j->pw == 8) {
        int32_t tf = j->tri_front[flat];
        if (tf < 0) return 1;
        const float *pf = plane_row(j, r, tf);
        if (pf[3] - dot3(pf, c) > 0.0f) return 1;
    }
    return 0;
}

/* One exit candidate (march._march's ``candidates``): the triangle seen at parameter s in
 * the chosen layer, and whether the ray's hit with it is accepted. */
static int candidate(const Job *j, int64_t r, float s, int use_front, int64_t *cand_out,
                     float *st_out, float *bt_out) {
    float c[3];
    point_at(j, r, s, c);
    int inside;
    int64_t flat = pixel_of(j, r, c, &inside);
    int64_t cand = -1;
    if (inside) cand = use_front ? j->tri_front[flat] : j->tri_back[flat];
    if (cand < 0) return 0;
    float st = intersect(j->p1 + 3 * r, j->t + 3 * r, j->tv + 9 * cand, bt_out);
    float hi = j->s_max[r] * 1.5f;
    *cand_out = cand;
    *st_out = st;
    return isfinite(st) && st > j->s_min[r] && st <= hi;
}

#define BLOCK 16

/* The uniform search and the bisections of rays [r0, r0 + m), m <= BLOCK, in lockstep:
 * each pass tests one sample of every ray of the block, so their (independent) plane reads
 * overlap instead of waiting on each other. */
static void search_block(const Job *j, int64_t r0, int m, float *lo_out, float *hi_out) {
    float lo[BLOCK], hi[BLOCK], last[BLOCK];
    int done[BLOCK];
    for (int i = 0; i < m; i++) {
        lo[i] = 0.0f;
        hi[i] = j->s_max[r0 + i];
        last[i] = 0.0f;
        done[i] = 0;
    }
    /* The first sample that has crossed brackets the crossing; a ray that never crosses
     * gets lo = hi = s_max. */
    int active = m;
    for (int k = 1; k <= j->steps && active > 0; k++) {
        float frac = (float)((double)k / (double)j->steps);
        for (int i = 0; i < m; i++) {
            if (done[i]) continue;
            float s = j->s_max[r0 + i] * frac;
            if (crossed_at(j, r0 + i, s)) {
                hi[i] = s;
                lo[i] = last[i];
                done[i] = 1;
                active--;
            } else {
                last[i] = s;
            }
        }
    }
    for (int i = 0; i < m; i++)
        if (!done[i]) lo[i] = last[i];
    for (int b = 0; b < j->refine; b++) {
        for (int i = 0; i < m; i++) {
            float mid = 0.5f * (lo[i] + hi[i]);
            int c = crossed_at(j, r0 + i, mid);
            hi[i] = c ? mid : hi[i];
            lo[i] = c ? lo[i] : mid;
        }
    }
    for (int i = 0; i < m; i++) {
        lo_out[i] = lo[i];
        hi_out[i] = hi[i];
    }
}

/* march._exit's values for ray r leaving through ``tri`` (-1: not found), given the ray's
 * hit with it (``hit_s``, ``hit_bt``: ``intersect``'s, computed while the exit was found):
 * the clamped barycentric interpolation of its corner normals, normalized, and the
 * position p1 + s t. */
static void exit_values(const Job *j, int64_t r, int64_t tri, float hit_s,
                        const float *hit_bt) {
    float s = 0.0f, bt[3] = {0.0f, 0.0f, 0.0f}, n[3] = {0.0f, 0.0f, 0.0f};
    const float *p1 = j->p1 + 3 * r, *t = j->t + 3 * r;
    if (tri >= 0) {
        s = hit_s;
        for (int m = 0; m < 3; m++) bt[m] = hit_bt[m];
        interpolate(bt, j->tn + 9 * tri, 3, n);
        float len = norm3(n);
        if (len < 1e-20f) len = 1e-20f;
        for (int m = 0; m < 3; m++) n[m] = n[m] / len;
    }
    j->s_out[r] = s;
    for (int m = 0; m < 3; m++) {
        j->bary_out[3 * r + m] = bt[m];
        j->normal_out[3 * r + m] = n[m];
        float st = s * t[m];
        j->pos_out[3 * r + m] = p1[m] + st;
    }
}


#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define HAVE_AVX2_PATH 1

/* search_block with AVX2, 8 rays per vector and two vectors per pass (BLOCK = 16 rays; a
 * part block's empty lanes copies of its first ray, dropped): the same operations lane by
 * lane (IEEE add, multiply, divide, floor, compare: the same values as the scalar code,
 * which stays the path for one ray and CPUs without AVX2). Plane indices are 32-bit (the
 * caller checks the size). */
typedef struct { __m256 c0x, c0y, c0z, ctx, cty, ctz, sx, sy; __m256i base, pbase; } Lanes;

/* The planes of the triangles ``t`` (8 lanes; rows pbase + t, row pbase where t < 0) at
 * the camera points (cx, cy, cz): n . c - d per lane. */
__attribute__((target("avx2"))) static inline __m256 plane_value8(const Job *j, __m256i pbase,
                                                                  __m256i t, __m256 cx,
                                                                  __m256 cy, __m256 cz) {
    __m256i row = _mm256_add_epi32(pbase, _mm256_max_epi32(t, _mm256_setzero_si256()));
    /* each lane's row (n, d) by one 16-byte load, then a 4x8 transpose: the values of
     * four gathers, with a quarter of the loads */
    int rw[8];
    _mm256_storeu_si256((__m256i *)rw, row);
    const float *pl = j->planes;
    __m256 a0 = _mm256_set_m128(_mm_loadu_ps(pl + 4 * (int64_t)rw[4]),
                                _mm_loadu_ps(pl + 4 * (int64_t)rw[0]));
    __m256 a1 = _mm256_set_m128(_mm_loadu_ps(pl + 4 * (int64_t)rw[5]),
                                _mm_loadu_ps(pl + 4 * (int64_t)rw[1]));
    __m256 a2 = _mm256_set_m128(_mm_loadu_ps(pl + 4 * (int64_t)rw[6]),
                                _mm_loadu_ps(pl + 4 * (int64_t)rw[2]));
    __m256 a3 = _mm256_set_m128(_mm_loadu_ps(pl + 4 * (int64_t)rw[7]),
                                _mm_loadu_ps(pl + 4 * (int64_t)rw[3]));
    __m256 t0 = _mm256_unpacklo_ps(a0, a1), t1 = _mm256_unpackhi_ps(a0, a1);
    __m256 t2 = _mm256_unpacklo_ps(a2, a3), t3 = _mm256_unpackhi_ps(a2, a3);
    __m256 n0 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(1, 0, 1, 0));
    __m256 n1 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(3, 2, 3, 2));
    __m256 n2 = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(1, 0, 1, 0));
    __m256 d = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(3, 2, 3, 2));
    __m256 dt = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(n0, cx), _mm256_mul_ps(n1, cy)),
                              _mm256_mul_ps(n2, cz));
    return _mm256_sub_ps(dt, d);
}

/* The triangles at 8 pixels (scalar loads: cheaper than a gather here). */
__attribute__((target("avx2"))) static inline __m256i tri8(const int32_t *tri, const int *fl) {
    return _mm256_setr_epi32(tri[fl[0]], tri[fl[1]], tri[fl[2]], tri[fl[3]], tri[fl[4]],
                             tri[fl[5]], tri[fl[6]], tri[fl[7]]);
}

/* pixel_of at point_at(s) of 8 lanes: the camera point (cx, cy, cz), whether it lies in the
 * frame (all-ones lanes), and the flat pixel (clamped into the frame). */
__attribute__((target("avx2"), always_inline)) static inline __m256i
pixel8(const Job *j, const Lanes *L, __m256 s, __m256 *cx_out, __m256 *cy_out, __m256 *cz_out,
       __m256 *inside_out) {
    __m256 cx = _mm256_add_ps(L->c0x, _mm256_mul_ps(s, L->ctx));
    __m256 cy = _mm256_add_ps(L->c0y, _mm256_mul_ps(s, L->cty));
    __m256 cz = _mm256_add_ps(L->c0z, _mm256_mul_ps(s, L->ctz));
    const __m256 eps = _mm256_set1_ps(1e-12f);
    __m256 zs = _mm256_max_ps(cz, eps);  /* NaN z: eps (the lane is outside anyway) */
    __m256 hw = _mm256_set1_ps(0.5f * (float)j->w), hh = _mm256_set1_ps(0.5f * (float)j->h);
    __m256 px = _mm256_floor_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_div_ps(cx, zs), L->sx),
                                              hw));
    __m256 py = _mm256_floor_ps(_mm256_sub_ps(hh, _mm256_mul_ps(_mm256_div_ps(cy, zs),
                                                                L->sy)));
    const __m256 zero = _mm256_setzero_ps();
    __m256 wm = _mm256_set1_ps((float)(j->w - 1)), hm = _mm256_set1_ps((float)(j->h - 1));
    __m256 inside = _mm256_and_ps(
        _mm256_and_ps(_mm256_cmp_ps(cz, eps, _CMP_GT_OQ),
                      _mm256_and_ps(_mm256_cmp_ps(px, zero, _CMP_GE_OQ),
                                    _mm256_cmp_ps(px, wm, _CMP_LE_OQ))),
        _mm256_and_ps(_mm256_cmp_ps(py, zero, _CMP_GE_OQ), _mm256_cmp_ps(py, hm, _CMP_LE_OQ)));
    /* clamped into the frame (max(x, 0) gives 0 for NaN x): always a valid index */
    __m256 pxc = _mm256_min_ps(_mm256_max_ps(px, zero), wm);
    __m256 pyc = _mm256_min_ps(_mm256_max_ps(py, zero), hm);
    __m256i flat = _mm256_add_epi32(L->base, _mm256_add_epi32(
        _mm256_mullo_epi32(_mm256_cvttps_epi32(pyc), _mm256_set1_epi32((int)j->w)),
        _mm256_cvttps_epi32(pxc)));
    *cx_out = cx;
    *cy_out = cy;
    *cz_out = cz;
    *inside_out = inside;
    return flat;
}

__attribute__((target("avx2"), always_inline)) static inline __m256
crossed8(const Job *j, const Lanes *L, __m256 s) {
    __m256 cx, cy, cz, inside;
    __m256i flat = pixel8(j, L, s, &cx, &cy, &cz, &inside);
    const __m256 zero = _mm256_setzero_ps();
    /* the back triangle at the pixel (-1: empty, crossed) and its plane */
    int fl[8];
    _mm256_storeu_si256((__m256i *)fl, flat);
    __m256i tb = tri8(j->tri_back, fl);
    __m256 beyond = _mm256_or_ps(
        _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), tb)),
        _mm256_cmp_ps(plane_value8(j, L->pbase, tb, cx, cy, cz), zero, _CMP_GT_OQ));
    if (j->pw == 8) {  /* the front's plane faces the eye: d - n . c > 0 */
        __m256i tf = tri8(j->tri_front, fl);
        __m256 fv = plane_value8(j, L->pbase, tf, cx, cy, cz);
        beyond = _mm256_or_ps(beyond, _mm256_or_ps(
            _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), tf)),
            _mm256_cmp_ps(fv, zero, _CMP_LT_OQ)));
    }
    /* crossed = ~inside | beyond (all-ones lanes) */
    return _mm256_or_ps(_mm256_andnot_ps(inside, _mm256_castsi256_ps(_mm256_set1_epi32(-1))),
                        beyond);
}

/* The lanes of rays [r0, r0 + 8), those from r0 + valid on copies of ray ``first`` (a part
 * block's empty lanes: computed alongside, dropped); their s_max in ``smax``. */
__attribute__((target("avx2"))) static void lanes8(const Job *j, int64_t r0, int valid,
                                                   int64_t first, Lanes *L, __m256 *smax) {
    float tmp[9][8];
    int bi[8], pb[8];
    for (int i = 0; i < 8; i++) {
        int64_t r = i < valid ? r0 + i : first, b = j->batch[r];
        for (int k = 0; k < 3; k++) {
            tmp[k][i] = j->c0[3 * r + k];
            tmp[3 + k][i] = j->ct[3 * r + k];
        }
        tmp[6][i] = j->sx_v[b];
        tmp[7][i] = j->sy_v[b];
        tmp[8][i] = j->s_max[r];
        bi[i] = (int)(b * j->h * j->w);
        pb[i] = (int)j->plane_base[b];
    }
    L->c0x = _mm256_loadu_ps(tmp[0]);
    L->c0y = _mm256_loadu_ps(tmp[1]);
    L->c0z = _mm256_loadu_ps(tmp[2]);
    L->ctx = _mm256_loadu_ps(tmp[3]);
    L->cty = _mm256_loadu_ps(tmp[4]);
    L->ctz = _mm256_loadu_ps(tmp[5]);
    L->sx = _mm256_loadu_ps(tmp[6]);
    L->sy = _mm256_loadu_ps(tmp[7]);
    L->base = _mm256_loadu_si256((const __m256i *)bi);
    L->pbase = _mm256_loadu_si256((const __m256i *)pb);
    *smax = _mm256_loadu_ps(tmp[8]);
}

__attribute__((target("avx2"))) static void search_block_avx2(const Job *j, int64_t r0,
                                                              int m, float *lo_out,
                                                              float *hi_out) {
    Lanes L[2];
    __m256 smax[2], lo[2], hi[2], last[2], done[2];
    for (int v = 0; v < 2; v++) {
        lanes8(j, r0 + 8 * v, m - 8 * v, r0, &L[v], &smax[v]);
        lo[v] = _mm256_setzero_ps();
        hi[v] = smax[v];
        last[v] = _mm256_setzero_ps();
        done[v] = _mm256_setzero_ps();
    }
    for (int k = 1; k <= j->steps; k++) {
        __m256 frac = _mm256_set1_ps((float)((double)k / (double)j->steps));
        int all = 1;
        for (int v = 0; v < 2; v++) {
            /* a vector whose rays have all crossed keeps its values: skip its sample */
            if (_mm256_movemask_ps(done[v]) == 0xff) continue;
            __m256 s = _mm256_mul_ps(smax[v], frac);
            __m256 c = _mm256_andnot_ps(done[v], crossed8(j, &L[v], s));  /* newly crossed */
            hi[v] = _mm256_blendv_ps(hi[v], s, c);
            lo[v] = _mm256_blendv_ps(lo[v], last[v], c);
            done[v] = _mm256_or_ps(done[v], c);
            last[v] = _mm256_blendv_ps(s, last[v], done[v]);
            all &= _mm256_movemask_ps(done[v]) == 0xff;
        }
        if (all) break;
    }
    for (int v = 0; v < 2; v++) lo[v] = _mm256_blendv_ps(last[v], lo[v], done[v]);
    const __m256 half = _mm256_set1_ps(0.5f);
    for (int b = 0; b < j->refine; b++) {
        for (int v = 0; v < 2; v++) {
            __m256 mid = _mm256_mul_ps(half, _mm256_add_ps(lo[v], hi[v]));
            __m256 c = crossed8(j, &L[v], mid);
            hi[v] = _mm256_blendv_ps(hi[v], mid, c);
            lo[v] = _mm256_blendv_ps(mid, lo[v], c);
        }
    }
    for (int v = 0; v < 2; v++) {
        _mm256_storeu_ps(lo_out + 8 * v, lo[v]);
        _mm256_storeu_ps(hi_out + 8 * v, hi[v]);
    }
}
#endif

/* The search of rays [r0, r0 + m), m <= BLOCK: in AVX2 lanes where the job asks for it
 * (``simd``, set where the CPU has AVX2) and there is more than one ray, else scalar. */
static void search_rays(const Job *j, int64_t r0, int m, float *lo, float *hi) {
#ifdef HAVE_AVX2_PATH
    if (j->simd && m > 1) {
        search_block_avx2(j, r0, m, lo, hi);
        return;
    }
#endif
    search_block(j, r0, m, lo, hi);
}

/* The exit candidates of ray r bracketed by [lo, hi], in march._march's order of
 * ``tries``: their parameters ss and layers (1: front); returns how many. */
static int exit_tries(const Job *j, int64_t r, float lo, float hi, float *ss, int *fronts) {
    if (j->pw == 8) {
        float c[3];
        point_at(j, r, hi, c);
        int inside;
        int64_t flat = pixel_of(j, r, c, &inside);
        /* the layer whose plane is crossed farther (none where a layer is empty) */
        int32_t tb = j->tri_back[flat], tf = j->tri_front[flat];
        int primary_front = 0;
        if (tb >= 0 && tf >= 0) {
            const float *pb = plane_row(j, r, tb), *pf = plane_row(j, r, tf);
            primary_front = (pf[3] - dot3(pf, c)) > (dot3(pb, c) - pb[3]);
        }
        ss[0] = hi; fronts[0] = primary_front;
        ss[1] = lo; fronts[1] = primary_front;
        ss[2] = hi; fronts[2] = !primary_front;
        ss[3] = lo; fronts[3] = !primary_front;
        return 4;
    }
    ss[0] = hi; fronts[0] = 0;
    ss[1] = lo; fronts[1] = 0;
    return 2;
}

/* One ray's first exit candidate (its first try), taken ahead for a whole block. */
typedef struct {
    float ss[4], st, bt[3];
    int fronts[4], ntries, ok;
    int64_t cand;
} FirstTry;

static inline void first_try(const Job *j, int64_t r, float lo, float hi, FirstTry *f) {
    f->ntries = exit_tries(j, r, lo, hi, f->ss, f->fronts);
    f->ok = candidate(j, r, f->ss[0], f->fronts[0], &f->cand, &f->st, f->bt);
}

/* The exit of ray r (its first try ``f`` taken): the exit triangle, layer and hit (s and
 * barycentrics) written to found, tri, layer and hit_s, hit_bt. */
static void exit_pick(const Job *j, int64_t r, const FirstTry *f, float *hit_s_out,
                      float *hit_bt_out) {
    float smax = j->s_max[r];
    int64_t tri = -1;
    int layer = -1;
    float bary[3] = {0.0f, 0.0f, 0.0f}, hit_s = 0.0f, hit_bt[3] = {0.0f, 0.0f, 0.0f};
    for (int i = 0; i < f->ntries; i++) {
        int64_t cand;
        float st, bt[3];
        int ok;
        if (i == 0) {
            ok = f->ok;
            cand = f->cand;
            st = f->st;
            bt[0] = f->bt[0]; bt[1] = f->bt[1]; bt[2] = f->bt[2];
        } else {
            ok = candidate(j, r, f->ss[i], f->fronts[i], &cand, &st, bt);
        }
        if (ok) {
            tri = cand;
            layer = f->fronts[i] ? 0 : 1;
            bary[0] = bt[0]; bary[1] = bt[1]; bary[2] = bt[2];
            hit_s = st;
            hit_bt[0] = bt[0]; hit_bt[1] = bt[1]; hit_bt[2] = bt[2];
            break;
        }
    }

    /* march._walk_to_containing: across the edge opposite the most negative barycentric
     * until the hit is inside, keeping the most-inside hit seen. */
    const float eps = -1e-6f;
    if (tri >= 0 && min3(bary) < eps) {
        int64_t cur = tri;
        float cur_bary[3] = {bary[0], bary[1], bary[2]};
        float best = min3(cur_bary);
        float lo_s = j->s_min[r], hi_s = 1.5f * smax;
        for (int step = 0; step < j->walk_steps; step++) {
            int worst = argmin3(cur_bary);
            int64_t nxt = j->across[cur * 3 + worst];
            float bt[3];
            float st = intersect(j->p1 + 3 * r, j->t + 3 * r,
                                 j->tv + 9 * (nxt < 0 ? 0 : nxt), bt);
            int ok = nxt >= 0 && isfinite(st) && st > lo_s && st <= hi_s;
            float score = min3(bt);
            if (!ok) break;
            cur = nxt;
            cur_bary[0] = bt[0]; cur_bary[1] = bt[1]; cur_bary[2] = bt[2];
            if (score > best) {
                tri = nxt;
                best = score;
                hit_s = st;
                hit_bt[0] = bt[0]; hit_bt[1] = bt[1]; hit_bt[2] = bt[2];
            }
            if (!(score < eps)) break;
        }
    }
    j->found[r] = tri >= 0;
    j->tri[r] = tri;
    j->layer[r] = layer;
    *hit_s_out = hit_s;
    for (int m = 0; m < 3; m++) hit_bt_out[m] = hit_bt[m];
}

#ifdef HAVE_AVX2_PATH
/* The lanes of 8 rows of ``n`` floats at ``src`` (rows ``stride`` apart) as n vectors. */
__attribute__((target("avx2"))) static inline void columns8(const float *src, int64_t stride,
                                                            int n, __m256 *out) {
    float tmp[9][8];
    for (int i = 0; i < 8; i++)
        for (int k = 0; k < n; k++) tmp[k][i] = src[stride * i + k];
    for (int k = 0; k < n; k++) out[k] = _mm256_loadu_ps(tmp[k]);
}

/* common.h's 3-vector bodies (hit, weights, blend, norm3) on 8 float lanes: the scalar
 * code's operations lane by lane. */
typedef float v8f __attribute__((vector_size(32)));
typedef int v8i __attribute__((vector_size(32)));
__attribute__((target("avx2,fma"))) static inline v8f fma8(v8f a, v8f b, v8f c) {
    return (v8f)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
}
__attribute__((target("avx2,fma"))) static inline v8f abs8(v8f a) {
    return (v8f)((v8i)a & (v8i){0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff,
                                0x7fffffff, 0x7fffffff, 0x7fffffff});
}
__attribute__((target("avx2,fma"))) static inline v8f sqrt8(v8f a) {
    return (v8f)_mm256_sqrt_ps((__m256)a);
}
#define SEL8(m, a, b) ((v8f)_mm256_blendv_ps((__m256)(b), (__m256)(a), (__m256)(m)))
#define K8(T, x) ((T){(x), (x), (x), (x), (x), (x), (x), (x)})
#undef TR_LANES_ATTR
#define TR_LANES_ATTR __attribute__((target("avx2,fma")))
TR_DEFINE_LANES(v8f, v8i, 8, fma8, abs8, sqrt8, 1e-30f, SEL8, K8)
#undef TR_LANES_ATTR
#define TR_LANES_ATTR

/* first_try for rays [r0, r0 + 8) of the back layer's march (pw 4): the candidate at hi
 * (pixel8, the back triangle there) and the ray's hit with it (common.h's hit) in lanes,
 * the same operations as candidate's, lane by lane. */
__attribute__((target("avx2,fma"))) static void first_try8(const Job *j, int64_t r0,
                                                           const float *lo, const float *hi,
                                                           FirstTry *f) {
    Lanes L;
    __m256 smax, cx, cy, cz, inside;
    lanes8(j, r0, 8, r0, &L, &smax);
    __m256i flat = pixel8(j, &L, _mm256_loadu_ps(hi), &cx, &cy, &cz, &inside);
    int fl[8], in = _mm256_movemask_ps(inside);
    int64_t cand[8];
    _mm256_storeu_si256((__m256i *)fl, flat);
    float vt[9][8];
    for (int i = 0; i < 8; i++) {
        cand[i] = (in >> i) & 1 ? j->tri_back[fl[i]] : -1;
        const float *tv = j->tv + 9 * (cand[i] < 0 ? 0 : cand[i]);
        for (int k = 0; k < 9; k++) vt[k][i] = tv[k];
    }
    __m256 o[3], d[3];
    v8f v[9], bary[3];
    for (int k = 0; k < 9; k++) v[k] = (v8f)_mm256_loadu_ps(vt[k]);
    columns8(j->p1 + 3 * r0, 3, 3, o);
    columns8(j->t + 3 * r0, 3, 3, d);
    v8f o8[3] = {(v8f)o[0], (v8f)o[1], (v8f)o[2]}, d8[3] = {(v8f)d[0], (v8f)d[1], (v8f)d[2]};
    __m256 t = (__m256)hit8(o8, d8, v, bary);
    __m256 b0 = (__m256)bary[0], u = (__m256)bary[1], vv = (__m256)bary[2];
    /* accepted: finite, beyond s_min, within 1.5 s_max */
    float smin[8];
    for (int i = 0; i < 8; i++) smin[i] = j->s_min[r0 + i];
    __m256 acc = _mm256_and_ps(
        _mm256_cmp_ps(_mm256_andnot_ps(_mm256_set1_ps(-0.0f), t), _mm256_set1_ps(INFINITY),
                      _CMP_LT_OQ),
        _mm256_and_ps(_mm256_cmp_ps(t, _mm256_loadu_ps(smin), _CMP_GT_OQ),
                      _mm256_cmp_ps(t, _mm256_mul_ps(smax, _mm256_set1_ps(1.5f)),
                                    _CMP_LE_OQ)));
    float st[8], bt[3][8];
    _mm256_storeu_ps(st, t);
    _mm256_storeu_ps(bt[0], b0);
    _mm256_storeu_ps(bt[1], u);
    _mm256_storeu_ps(bt[2], vv);
    int a = _mm256_movemask_ps(acc);
    for (int i = 0; i < 8; i++) {
        FirstTry *fi = f + i;
        fi->ntries = exit_tries(j, r0 + i, lo[i], hi[i], fi->ss, fi->fronts);
        fi->ok = cand[i] >= 0 && ((a >> i) & 1);
        if (cand[i] < 0) continue;  /* candidate leaves the rest unset */
        fi->cand = cand[i];
        fi->st = st[i];
        for (int k = 0; k < 3; k++) fi->bt[k] = bt[k][i];
    }
}

/* exit_values for rays [r0, r0 + 8) in lanes, op for op. */
__attribute__((target("avx2,fma"))) static void exit_values8(const Job *j, int64_t r0,
                                                             const float *hit_s,
                                                             const float (*hit_bt)[3]) {
    float c[9][8], okf[8];
    for (int i = 0; i < 8; i++) {
        int64_t tri = j->tri[r0 + i];
        const float *tn = j->tn + 9 * (tri < 0 ? 0 : tri);
        for (int k = 0; k < 9; k++) c[k][i] = tn[k];
        okf[i] = tri >= 0 ? 1.0f : 0.0f;
    }
    const __m256 zero = _mm256_setzero_ps();
    __m256 ok = _mm256_cmp_ps(_mm256_loadu_ps(okf), zero, _CMP_GT_OQ);
    __m256 s = _mm256_and_ps(ok, _mm256_loadu_ps(hit_s));
    __m256 bt[3], p1[3], t[3];
    columns8(hit_bt[0], 3, 3, bt);
    columns8(j->p1 + 3 * r0, 3, 3, p1);
    columns8(j->t + 3 * r0, 3, 3, t);
    v8f bt8[3], w[3], c8[9], n8[3];
    for (int k = 0; k < 3; k++) bt8[k] = (v8f)(bt[k] = _mm256_and_ps(ok, bt[k]));
    for (int k = 0; k < 9; k++) c8[k] = (v8f)_mm256_loadu_ps(c[k]);
    weights8(bt8, w);  /* interpolate's clamped, renormalized weights */
    blend8(w, c8, 3, n8);
    __m256 n[3] = {(__m256)n8[0], (__m256)n8[1], (__m256)n8[2]};
    __m256 len = (__m256)norm38(n8);
    const __m256 tiny2 = _mm256_set1_ps(1e-20f);
    len = _mm256_blendv_ps(len, tiny2, _mm256_cmp_ps(len, tiny2, _CMP_LT_OQ));
    float out[9][8], so[8];
    _mm256_storeu_ps(so, s);
    for (int m = 0; m < 3; m++) {
        _mm256_storeu_ps(out[m], bt[m]);
        _mm256_storeu_ps(out[3 + m], _mm256_and_ps(ok, _mm256_div_ps(n[m], len)));
        _mm256_storeu_ps(out[6 + m], _mm256_add_ps(p1[m], _mm256_mul_ps(s, t[m])));
    }
    for (int i = 0; i < 8; i++) {
        int64_t r = r0 + i;
        j->s_out[r] = so[i];
        for (int m = 0; m < 3; m++) {
            j->bary_out[3 * r + m] = out[m][i];
            j->normal_out[3 * r + m] = out[3 + m][i];
            j->pos_out[3 * r + m] = out[6 + m][i];
        }
    }
}
#endif

/* The exits of rays [r0, r0 + m), m <= BLOCK, bracketed by [lo, hi], in three passes over
 * the block (each ray's values as one ray at a time would find them): the first candidates,
 * the rest of the tries and the walks, then the exit values. Each pass's rays are
 * independent, so their divisions and memory reads overlap instead of waiting on one ray's
 * chain at a time. */
static void exit_block(const Job *j, int64_t r0, int m, const float *lo, const float *hi) {
    FirstTry f[BLOCK];
    float hit_s[BLOCK], hit_bt[BLOCK][3];
#ifdef HAVE_AVX2_PATH
    /* a full block in AVX2 lanes (the first tries of the back layer's march, the exit
     * values), where the CPU has AVX2 and FMA (cross3's fused multiply-adds) */
    int lanes = j->simd && m == BLOCK && __builtin_cpu_supports("fma");
#else
    int lanes = 0;
#endif
    if (lanes && j->pw == 4) {
#ifdef HAVE_AVX2_PATH
        first_try8(j, r0, lo, hi, f);
        first_try8(j, r0 + 8, lo + 8, hi + 8, f + 8);
#endif
    } else {
        for (int i = 0; i < m; i++) first_try(j, r0 + i, lo[i], hi[i], &f[i]);
    }
    for (int i = 0; i < m; i++) exit_pick(j, r0 + i, &f[i], &hit_s[i], hit_bt[i]);
    if (!j->s_out) return;
    if (lanes) {
#ifdef HAVE_AVX2_PATH
        exit_values8(j, r0, hit_s, (const float (*)[3])hit_bt);
        exit_values8(j, r0 + 8, hit_s + 8, (const float (*)[3])(hit_bt + 8));
#endif
    } else {
        for (int i = 0; i < m; i++) exit_values(j, r0 + i, j->tri[r0 + i], hit_s[i], hit_bt[i]);
    }
}

#endif
