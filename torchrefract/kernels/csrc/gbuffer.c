/* The exact G-buffer layer (gbuffer._layer and gbuffer._repair_edge_ids), one pixel at a
 * time, in the tensor code's float64 arithmetic.
 *
 * For every pixel the rasterizer covered: intersect the pixel's ray with the rasterized
 * triangle; where the hit falls outside it (the rasterizer snaps vertices to a sub-pixel
 * grid), re-pick the nearest triangle really hit among the 3x3 neighbourhood's ids and the
 * triangle's edge neighbours and theirs (or keep the id for a tiny miss, or empty the
 * pixel); then the position, distance, camera depth, barycentrics, geometric and
 * interpolated shading normals and UVs, stored as float32. The same operations in the
 * same order as the tensor code (built with -ffp-contract=off and no fast-math; the fused
 * multiply-adds of torch.cross written out as fma), so the layers are identical
 * (tests/test_native.py). Plain C (threads: common.h); built and loaded by native.py.
 */

#include <string.h>

#include "common.h"

/* A hit's attributes for lane type T (the scalar and the AVX2 code alike): from the
 * triangle's corners v, corner normals tn and UVs tuv (as T) and the barycentrics, the unit
 * geometric normal gn, the unit interpolated shading normal n and the UV, as
 * gbuffer._layer_tensor computes them (lengths below 1e-300 taken as 1e-300). */
#define TR_DEFINE_LAYER_ATTRS(T, S, SEL, K)                                                 \
    static inline void attrs##S(const T *v, const T *tn, const T *tuv, const T *bary,      \
                                T *gn, T *n, T *uv) {                                       \
        T e1[3], e2[3], w[3];                                                               \
        for (int m = 0; m < 3; m++) {                                                       \
            e1[m] = v[3 + m] - v[m];                                                        \
            e2[m] = v[6 + m] - v[m];                                                        \
        }                                                                                   \
        cross3##S(e1, e2, gn);                                                              \
        T gl = norm3##S(gn);                                                                \
        gl = SEL(gl < K(T, 1e-300), K(T, 1e-300), gl);                                      \
        weights##S(bary, w);                                                                \
        blend##S(w, tn, 3, n);                                                              \
        T nl = norm3##S(n);                                                                 \
        nl = SEL(nl < K(T, 1e-300), K(T, 1e-300), nl);                                      \
        for (int i = 0; i < 3; i++) {                                                       \
            gn[i] = gn[i] / gl;                                                             \
            n[i] = n[i] / nl;                                                               \
        }                                                                                   \
        blend##S(w, tuv, 2, uv);                                                            \
    }

#if defined(__AVX2__) && defined(__FMA__)
/* Four pixels at a time in AVX2 lanes, by the same TR_DEFINE_LANES bodies as the scalar
 * code (IEEE operations, each correctly rounded: the same bits lane by lane). */
#include <immintrin.h>
#define LAYER_LANES 4
typedef double v4d __attribute__((vector_size(32)));
typedef long long v4m __attribute__((vector_size(32)));
static inline v4d fma4(v4d a, v4d b, v4d c) {
    return (v4d)_mm256_fmadd_pd((__m256d)a, (__m256d)b, (__m256d)c);
}
static inline v4d sqrt4(v4d a) { return (v4d)_mm256_sqrt_pd((__m256d)a); }
static inline v4d abs4(v4d a) { return (v4d)((v4m)a & (v4m){~(1LL << 63), ~(1LL << 63),
                                                            ~(1LL << 63), ~(1LL << 63)}); }
#define SEL4(m, a, b) ((v4d)_mm256_blendv_pd((__m256d)(b), (__m256d)(a), (__m256d)(m)))
#define K4(T, x) ((T){(x), (x), (x), (x)})
TR_DEFINE_LANES(v4d, v4m, 4, fma4, abs4, sqrt4, 1e-30, SEL4, K4)
TR_DEFINE_LAYER_ATTRS(v4d, 4, SEL4, K4)
#endif

typedef struct {
    int64_t b, h, w;
    const int64_t *ids;       /* (B*H*W,) rasterized global face id or -1 */
    const float *eye;         /* (B, 3) */
    const float *dirs;        /* (B*H*W, 3) pixel ray directions */
    const float *forward;     /* (B, 3) unit camera forward */
    const float *tv;          /* (F, 3, 3) corner positions */
    const float *tn;          /* (F, 3, 3) corner shading normals */
    const float *tuv;         /* (F, 3, 2) corner UVs */
    const int64_t *neighbors; /* (F, 3) edge-adjacent faces or -1 */
    int back;                 /* 1: the back-face layer (faces pointing away) */
    double tol, keep_tol;
    /* out, (B*H*W, ...) */
    uint8_t *mask;
    int64_t *tri;
    float *position, *dist, *depth, *bary, *geo_normal, *normal, *uv;
} LayerJob;

TR_DEFINE_VEC3(double, d, fma, fabs, sqrt, 1e-30)
TR_DEFINE_LAYER_ATTRS(double, d, TR_SEL_SCALAR, TR_K_SCALAR)

/* gbuffer._repair_edge_ids for the pixel (bi, py, px) with rasterized id ``id``. */
static int64_t repair(const LayerJob *j, int64_t bi, int64_t py, int64_t px, int64_t id,
                      double own_min, const double *o, const double *d) {
    int64_t cand[21];
    int k = 0;
    for (int dy = -1; dy <= 1; dy++)
        for (int dx = -1; dx <= 1; dx++) {
            int64_t y = py + dy, x = px + dx;
            cand[k++] = (y < 0 || y >= j->h || x < 0 || x >= j->w)
                            ? -1 : j->ids[(bi * j->h + y) * j->w + x];
        }
    const int64_t *ring1 = j->neighbors + 3 * id;
    for (int i = 0; i < 3; i++) cand[k++] = ring1[i];
    for (int i = 0; i < 3; i++) {
        const int64_t *ring2 = j->neighbors + 3 * (ring1[i] < 0 ? 0 : ring1[i]);
        for (int m = 0; m < 3; m++) cand[k++] = ring1[i] >= 0 ? ring2[m] : -1;
    }
    double best_t = INFINITY;
    int best = 0;
    for (int i = 0; i < 21; i++) {
        int64_t c = cand[i] < 0 ? 0 : cand[i];
        double cb[3];
        double t = intersectd(o, d, j->tv + 9 * c, cb);
        double v[9], e1[3], e2[3], gn[3];
        for (int m = 0; m < 9; m++) v[m] = (double)j->tv[9 * c + m];
        for (int m = 0; m < 3; m++) {
            e1[m] = v[3 + m] - v[m];
            e2[m] = v[6 + m] - v[m];
        }
        cross3d(e1, e2, gn);
        double facing = dot3d(gn, d);
        int facing_ok = j->back ? facing > 0.0 : facing < 0.0;
        int ok = cand[i] >= 0 && min3d(cb) >= -j->tol && t > 0.0 && isfinite(t) && facing_ok;
        if (!ok) t = INFINITY;
        if (t < best_t) {  /* torch's min: the first of equal minima */
            best_t = t;
            best = i;
        }
    }
    if (isfinite(best_t)) return cand[best];
    return own_min > -j->keep_tol ? id : -1;
}

/* One covered pixel (its outputs hold the empty values already: layer_range). */
static void layer_pixel(const LayerJob *j, int64_t p) {
    int64_t id = j->ids[p];
    int64_t hw = j->h * j->w, bi = p / hw;
    double o[3], d[3], bary[3];
    for (int i = 0; i < 3; i++) {
        o[i] = (double)j->eye[3 * bi + i];
        d[i] = (double)j->dirs[3 * p + i];
    }
    double t = intersectd(o, d, j->tv + 9 * id, bary);
    double own_min = min3d(bary);
    if (own_min < -j->tol) {
        int64_t fixed = repair(j, bi, (p / j->w) % j->h, p % j->w, id, own_min, o, d);
        if (fixed < 0) return;
        if (fixed != id) {
            id = fixed;
            t = intersectd(o, d, j->tv + 9 * id, bary);
        }
    }
    double v[9], tn[9], tuv[6], gn[3], n[3], uv[2];
    for (int m = 0; m < 9; m++) {
        v[m] = (double)j->tv[9 * id + m];
        tn[m] = (double)j->tn[9 * id + m];
    }
    for (int m = 0; m < 6; m++) tuv[m] = (double)j->tuv[6 * id + m];
    attrsd(v, tn, tuv, bary, gn, n, uv);
    double f[3] = {(double)j->forward[3 * bi], (double)j->forward[3 * bi + 1],
                   (double)j->forward[3 * bi + 2]};
    j->mask[p] = 1;
    j->tri[p] = id;
    for (int i = 0; i < 3; i++) {
        double td = t * d[i];
        j->position[3 * p + i] = (float)(o[i] + td);
        j->bary[3 * p + i] = (float)bary[i];
        j->geo_normal[3 * p + i] = (float)gn[i];
        j->normal[3 * p + i] = (float)n[i];
    }
    j->dist[p] = (float)t;
    j->depth[p] = (float)(t * dot3d(d, f));
    j->uv[2 * p] = (float)uv[0];
    j->uv[2 * p + 1] = (float)uv[1];
}

#ifdef LAYER_LANES
/* layer_pixel for four covered pixels in AVX2 lanes; a pixel whose hit falls outside its
 * rasterized triangle (rare: edges) is redone by layer_pixel, repair included. */
static void layer_lanes(const LayerJob *j, const int64_t *px) {
    int64_t hw = j->h * j->w, id[4], bi[4];
    double oa[3][4], da[3][4], va[9][4], na[9][4], uva[6][4], fa[3][4];
    for (int l = 0; l < 4; l++) {
        int64_t p = px[l];
        id[l] = j->ids[p];
        bi[l] = p / hw;
        for (int i = 0; i < 3; i++) {
            oa[i][l] = (double)j->eye[3 * bi[l] + i];
            da[i][l] = (double)j->dirs[3 * p + i];
            fa[i][l] = (double)j->forward[3 * bi[l] + i];
        }
        for (int m = 0; m < 9; m++) {
            va[m][l] = (double)j->tv[9 * id[l] + m];
            na[m][l] = (double)j->tn[9 * id[l] + m];
        }
        for (int m = 0; m < 6; m++) uva[m][l] = (double)j->tuv[6 * id[l] + m];
    }
    v4d o[3], d[3], f[3], v[9], cn[9], cuv[6], bary[3];
    for (int i = 0; i < 3; i++) {
        memcpy(&o[i], oa[i], 32);
        memcpy(&d[i], da[i], 32);
        memcpy(&f[i], fa[i], 32);
    }
    for (int m = 0; m < 9; m++) {
        memcpy(&v[m], va[m], 32);
        memcpy(&cn[m], na[m], 32);
    }
    for (int m = 0; m < 6; m++) memcpy(&cuv[m], uva[m], 32);
    v4d t = hit4(o, d, v, bary);
    v4m redo = min34(bary) < K4(v4d, -j->tol);
    v4d gn[3], n[3], uv[2];
    attrs4(v, cn, cuv, bary, gn, n, uv);
    v4d depth = t * dot34(d, f);
    float pos_f[3][4], bary_f[3][4], gn_f[3][4], n_f[3][4], uv_f[2][4], dist_f[4], depth_f[4];
    for (int i = 0; i < 3; i++) {
        _mm_storeu_ps(pos_f[i], _mm256_cvtpd_ps((__m256d)(o[i] + t * d[i])));
        _mm_storeu_ps(bary_f[i], _mm256_cvtpd_ps((__m256d)bary[i]));
        _mm_storeu_ps(gn_f[i], _mm256_cvtpd_ps((__m256d)gn[i]));
        _mm_storeu_ps(n_f[i], _mm256_cvtpd_ps((__m256d)n[i]));
    }
    for (int i = 0; i < 2; i++) _mm_storeu_ps(uv_f[i], _mm256_cvtpd_ps((__m256d)uv[i]));
    _mm_storeu_ps(dist_f, _mm256_cvtpd_ps((__m256d)t));
    _mm_storeu_ps(depth_f, _mm256_cvtpd_ps((__m256d)depth));
    for (int l = 0; l < 4; l++) {
        int64_t p = px[l];
        if (redo[l]) {
            layer_pixel(j, p);
            continue;
        }
        j->mask[p] = 1;
        j->tri[p] = id[l];
        for (int i = 0; i < 3; i++) {
            j->position[3 * p + i] = pos_f[i][l];
            j->bary[3 * p + i] = bary_f[i][l];
            j->geo_normal[3 * p + i] = gn_f[i][l];
            j->normal[3 * p + i] = n_f[i][l];
        }
        j->dist[p] = dist_f[l];
        j->depth[p] = depth_f[l];
        j->uv[2 * p] = uv_f[0][l];
        j->uv[2 * p + 1] = uv_f[1][l];
    }
}
#endif

/* The range's empty values written in bulk (mask 0, tri -1: all bits set, the rest 0.0f:
 * all bits clear), then the covered pixels: three in four pixels of a frame are empty
 * and per-pixel stores to nine arrays cost a third of the layer. */
static void layer_range(const void *job, int64_t begin, int64_t end) {
    const LayerJob *j = (const LayerJob *)job;
    size_t n = (size_t)(end - begin);
    memset(j->mask + begin, 0, n);
    memset(j->tri + begin, 0xff, n * sizeof(int64_t));
    memset(j->dist + begin, 0, n * sizeof(float));
    memset(j->depth + begin, 0, n * sizeof(float));
    memset(j->position + 3 * begin, 0, 3 * n * sizeof(float));
    memset(j->bary + 3 * begin, 0, 3 * n * sizeof(float));
    memset(j->geo_normal + 3 * begin, 0, 3 * n * sizeof(float));
    memset(j->normal + 3 * begin, 0, 3 * n * sizeof(float));
    memset(j->uv + 2 * begin, 0, 2 * n * sizeof(float));
#ifdef LAYER_LANES
    int64_t lane[LAYER_LANES];
    int k = 0;
    for (int64_t p = begin; p < end; p++)
        if (j->ids[p] >= 0) {
            lane[k++] = p;
            if (k == LAYER_LANES) {
                layer_lanes(j, lane);
                k = 0;
            }
        }
    for (int i = 0; i < k; i++) layer_pixel(j, lane[i]);
#else
    for (int64_t p = begin; p < end; p++)
        if (j->ids[p] >= 0) layer_pixel(j, p);
#endif
}

/* Entry point (ctypes, native.py): one layer of all B*H*W pixels on ``threads`` threads.
 * Returns 0, or -1 where a thread could not be started. */
int torchrefract_layer(const LayerJob *job, int threads) {
    return tr_parallel_for(layer_range, job, job->b * job->h * job->w, 16384, threads);
}

int64_t torchrefract_layer_job_size(void) { return (int64_t)sizeof(LayerJob); }
