/* The exact G-buffer layer (gbuffer._layer and gbuffer._repair_edge_ids), one pixel at a
 * time, in the tensor code's float64 arithmetic.
 *
 * For every pixel the rasterizer covered: intersect the pixel's ray with the rasterized
 * triangle; where the hit falls outside it (the rasterizer snaps vertices to a sub-pixel
 * grid), re-pick the nearest triangle really hit among the 3x3 neighbourhood's ids and the
 * triangle's edge neighbours and theirs (or keep the id for a tiny miss, or empty the
 * pixel); then the position, distance, camera depth, barycentrics, the
 * interpolated shading normal and UVs, stored as float32 (the position and barycentrics
 * only where the job asks for them: the back layer's are read by nothing), and the
 * triangle id as int32. The same operations in the
 * same order as the tensor code (built with -ffp-contract=off and no fast-math; the fused
 * multiply-adds of torch.cross written out as fma), so the layers are identical
 * (tests/test_native.py). Plain C (threads: common.h); built and loaded by native.py.
 */

#include <string.h>
#ifdef __SSE2__
#include <emmintrin.h>
#endif

#include "common.h"
#include "optics.h"

/* A hit's attributes for lane type T (the scalar and the AVX2 code alike): from the
 * triangle's corner normals tn and UVs tuv (as T) and the barycentrics, the unit
 * interpolated shading normal n and the UV, as gbuffer._layer_tensor computes them
 * (lengths below 1e-300 taken as 1e-300). W: the interpolation weights' function
 * (weights##S or the same values by a shortcut). */
#define TR_DEFINE_LAYER_ATTRS(T, S, SEL, K, W)                                              \
    static inline void attrs##S(const T *tn, const T *tuv, const T *bary, T *n, T *uv) {   \
        T w[3];                                                                             \
        W(bary, w);                                                                         \
        blend##S(w, tn, 3, n);                                                              \
        T nl = norm3##S(n);                                                                 \
        nl = SEL(nl < K(T, 1e-300), K(T, 1e-300), nl);                                      \
        for (int i = 0; i < 3; i++) n[i] = n[i] / nl;                                       \
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
/* weights4, without its divisions where every lane's sum is exactly 1 (most hits inside
 * the triangle): w / 1 is w, the same bits; a NaN sum is not 1. */
static inline void weights_fast4(const v4d *bary, v4d *w) {
    for (int i = 0; i < 3; i++)
        w[i] = SEL4(bary[i] != bary[i], bary[i],
                    SEL4(bary[i] < K4(v4d, 0), K4(v4d, 0), bary[i]));
    v4d sum = (w[0] + w[1]) + w[2];
    sum = SEL4(sum < K4(v4d, 1e-12), K4(v4d, 1e-12), sum);
    if (_mm256_movemask_pd((__m256d)(sum == K4(v4d, 1))) == 0xf) return;
    for (int i = 0; i < 3; i++) w[i] = w[i] / sum;
}
TR_DEFINE_LAYER_ATTRS(v4d, 4, SEL4, K4, weights_fast4)
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
    /* out, (B*H*W, ...); position and bary may be NULL (not written) */
    uint8_t *mask;
    int32_t *tri;
    float *position, *dist, *depth, *bary, *normal, *uv;
} LayerJob;

TR_DEFINE_VEC3(double, d, fma, fabs, sqrt, 1e-30)
TR_DEFINE_LAYER_ATTRS(double, d, TR_SEL_SCALAR, TR_K_SCALAR, weightsd)

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
    double tn[9], tuv[6], n[3], uv[2];
    for (int m = 0; m < 9; m++) tn[m] = (double)j->tn[9 * id + m];
    for (int m = 0; m < 6; m++) tuv[m] = (double)j->tuv[6 * id + m];
    attrsd(tn, tuv, bary, n, uv);
    double f[3] = {(double)j->forward[3 * bi], (double)j->forward[3 * bi + 1],
                   (double)j->forward[3 * bi + 2]};
    j->mask[p] = 1;
    j->tri[p] = (int32_t)id;
    for (int i = 0; i < 3; i++) {
        double td = t * d[i];
        if (j->position) j->position[3 * p + i] = (float)(o[i] + td);
        if (j->bary) j->bary[3 * p + i] = (float)bary[i];
        j->normal[3 * p + i] = (float)n[i];
    }
    j->dist[p] = (float)t;
    j->depth[p] = (float)(t * dot3d(d, f));
    j->uv[2 * p] = (float)uv[0];
    j->uv[2 * p + 1] = (float)uv[1];
}

/* The empty values of pixels [a, b) (mask 0, tri -1: all bits set, the rest 0.0f: all
 * bits clear), in bulk. */
static void layer_empty(const LayerJob *j, int64_t a, int64_t b) {
    size_t n = (size_t)(b - a);
    memset(j->mask + a, 0, n);
    memset(j->tri + a, 0xff, n * sizeof(int32_t));
    memset(j->dist + a, 0, n * sizeof(float));
    memset(j->depth + a, 0, n * sizeof(float));
    if (j->position) memset(j->position + 3 * a, 0, 3 * n * sizeof(float));
    if (j->bary) memset(j->bary + 3 * a, 0, 3 * n * sizeof(float));
    memset(j->normal + 3 * a, 0, 3 * n * sizeof(float));
    memset(j->uv + 2 * a, 0, 2 * n * sizeof(float));
}

/* One pixel on its own (outside whole blocks of four): its empty values, then its hit
 * where covered. */
static void layer_one(const LayerJob *j, int64_t p) {
    layer_empty(j, p, p + 1);
    if (j->ids[p] >= 0) layer_pixel(j, p);
}

#ifdef LAYER_LANES
/* Four rows of 3 floats, contiguous (12 floats: x0 y0 z0 x1 ...), as x, y, z of 4 lanes. */
static inline void soa3(const float *src, __m128 *x, __m128 *y, __m128 *z) {
    __m128 r0 = _mm_loadu_ps(src), r1 = _mm_loadu_ps(src + 4), r2 = _mm_loadu_ps(src + 8);
    __m128 u = _mm_shuffle_ps(r1, r2, _MM_SHUFFLE(1, 1, 2, 2));  /* x2 x2 x3 x3 */
    *x = _mm_shuffle_ps(r0, u, _MM_SHUFFLE(2, 0, 3, 0));
    __m128 v1 = _mm_shuffle_ps(r0, r1, _MM_SHUFFLE(0, 0, 1, 1)); /* y0 y0 y1 y1 */
    __m128 v2 = _mm_shuffle_ps(r1, r2, _MM_SHUFFLE(2, 2, 3, 3)); /* y2 y2 y3 y3 */
    *y = _mm_shuffle_ps(v1, v2, _MM_SHUFFLE(2, 0, 2, 0));
    __m128 w1 = _mm_shuffle_ps(r0, r1, _MM_SHUFFLE(1, 1, 2, 2)); /* z0 z0 z1 z1 */
    __m128 w2 = _mm_shuffle_ps(r2, r2, _MM_SHUFFLE(3, 3, 0, 0)); /* z2 z2 z3 z3 */
    *z = _mm_shuffle_ps(w1, w2, _MM_SHUFFLE(2, 0, 2, 0));
}

/* The inverse: x, y, z of 4 lanes stored as 4 contiguous rows of 3 floats. */
static inline void aos3(float *dst, __m128 x, __m128 y, __m128 z) {
    __m128 a = _mm_unpacklo_ps(x, y);                            /* x0 y0 x1 y1 */
    __m128 b = _mm_unpackhi_ps(x, y);                            /* x2 y2 x3 y3 */
    __m128 m = _mm_shuffle_ps(z, x, _MM_SHUFFLE(1, 1, 0, 0));   /* z0 z0 x1 x1 */
    __m128 n = _mm_shuffle_ps(y, z, _MM_SHUFFLE(1, 1, 1, 1));   /* y1 y1 z1 z1 */
    __m128 k = _mm_shuffle_ps(z, x, _MM_SHUFFLE(3, 3, 2, 2));   /* z2 z2 x3 x3 */
    __m128 l = _mm_shuffle_ps(y, z, _MM_SHUFFLE(3, 3, 3, 3));   /* y3 y3 z3 z3 */
    _mm_storeu_ps(dst, _mm_shuffle_ps(a, m, _MM_SHUFFLE(2, 0, 1, 0)));
    _mm_storeu_ps(dst + 4, _mm_shuffle_ps(n, b, _MM_SHUFFLE(1, 0, 2, 0)));
    _mm_storeu_ps(dst + 8, _mm_shuffle_ps(k, l, _MM_SHUFFLE(2, 0, 2, 0)));
}

static inline v4d widen(__m128 x) { return (v4d)_mm256_cvtps_pd(x); }

/* The first 8 floats of the rows table + stride * id[l] (4 lanes) as doubles: out[m],
 * m < 8, lane l (a 4 x 8 transpose in float32; the widening to double is exact). */
static inline void corners8(const float *table, int stride, const int64_t *id, v4d *out) {
    __m256 r0 = _mm256_loadu_ps(table + stride * id[0]);
    __m256 r1 = _mm256_loadu_ps(table + stride * id[1]);
    __m256 r2 = _mm256_loadu_ps(table + stride * id[2]);
    __m256 r3 = _mm256_loadu_ps(table + stride * id[3]);
    __m256 t0 = _mm256_unpacklo_ps(r0, r1), t1 = _mm256_unpackhi_ps(r0, r1);
    __m256 t2 = _mm256_unpacklo_ps(r2, r3), t3 = _mm256_unpackhi_ps(r2, r3);
    __m256 c[4] = {_mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(1, 0, 1, 0)),
                   _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(3, 2, 3, 2)),
                   _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(1, 0, 1, 0)),
                   _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(3, 2, 3, 2))};
    for (int m = 0; m < 4; m++) {  /* c[m]: element m of the 4 rows | element m + 4 */
        out[m] = widen(_mm256_castps256_ps128(c[m]));
        out[m + 4] = widen(_mm256_extractf128_ps(c[m], 1));
    }
}

/* The 9 corner values (3 x 3) of 4 lanes' triangles. */
static inline void corners9(const float *table, const int64_t *id, v4d *out) {
    corners8(table, 9, id, out);
    out[8] = widen(_mm_setr_ps(table[9 * id[0] + 8], table[9 * id[1] + 8],
                               table[9 * id[2] + 8], table[9 * id[3] + 8]));
}

/* The 6 UV values (3 x 2): a 4 x 4 transpose and the last pair of each row (no load past
 * a row: the last row ends the table). */
static inline void corners6(const float *table, const int64_t *id, v4d *out) {
    __m128 r[4], q[4];
    for (int l = 0; l < 4; l++) {
        r[l] = _mm_loadu_ps(table + 6 * id[l]);
        q[l] = _mm_castsi128_ps(_mm_loadl_epi64((const __m128i *)(table + 6 * id[l] + 4)));
    }
    _MM_TRANSPOSE4_PS(r[0], r[1], r[2], r[3]);
    for (int m = 0; m < 4; m++) out[m] = widen(r[m]);
    __m128 a = _mm_unpacklo_ps(q[0], q[1]), b = _mm_unpacklo_ps(q[2], q[3]);
    out[4] = widen(_mm_movelh_ps(a, b));
    out[5] = widen(_mm_movehl_ps(b, a));
}

/* The float32 of 4 lanes, 0.0f where keep is clear. */
static inline __m128 narrow(v4d x, __m128 keep) {
    return _mm_and_ps(_mm256_cvtpd_ps((__m256d)x), keep);
}

/* The pixels p0 .. p0 + 3 (one block, at least one covered; ids: theirs), all their
 * outputs: the covered ones by layer_pixel's arithmetic in AVX2 lanes (the empty ones
 * computed on triangle 0 and discarded), the empty ones and those whose hit falls
 * outside the rasterized triangle (rare: edges) written empty; the latter then redone by
 * layer_pixel, repair included. Every output of the block is stored once, whole. */
static void layer_lanes(const LayerJob *j, int64_t p0, __m256i ids) {
    int64_t hw = j->h * j->w, id[4];
    __m256i covered = _mm256_cmpgt_epi64(ids, _mm256_set1_epi64x(-1));
    _mm256_storeu_si256((__m256i *)id, _mm256_and_si256(ids, covered));
    v4d o[3], d[3], f[3], v[9], cn[9], cuv[6], bary[3];
    int64_t b0 = p0 / hw, b3 = (p0 + 3) / hw;
    if (b0 == b3) {
        for (int i = 0; i < 3; i++) {
            o[i] = K4(v4d, (double)j->eye[3 * b0 + i]);
            f[i] = K4(v4d, (double)j->forward[3 * b0 + i]);
        }
    } else {  /* the block spans two views (H * W not a multiple of 4) */
        for (int i = 0; i < 3; i++)
            for (int l = 0; l < 4; l++) {
                int64_t bi = (p0 + l) / hw;
                o[i][l] = (double)j->eye[3 * bi + i];
                f[i][l] = (double)j->forward[3 * bi + i];
            }
    }
    __m128 dx, dy, dz;
    soa3(j->dirs + 3 * p0, &dx, &dy, &dz);
    d[0] = widen(dx);
    d[1] = widen(dy);
    d[2] = widen(dz);
    corners9(j->tv, id, v);
    corners9(j->tn, id, cn);
    corners6(j->tuv, id, cuv);
    v4d t = hit4(o, d, v, bary);
    v4m redo = (v4m)covered & (min34(bary) < K4(v4d, -j->tol));
    v4m good = (v4m)covered & ~redo;
    v4d n[3], uv[2];
    attrs4(cn, cuv, bary, n, uv);
    v4d depth = t * dot34(d, f);
    /* the kept lanes' 64-bit masks as 32-bit ones */
    __m256 g8 = _mm256_castsi256_ps((__m256i)good);
    __m128 keep = _mm_shuffle_ps(_mm256_castps256_ps128(g8), _mm256_extractf128_ps(g8, 1),
                                 _MM_SHUFFLE(2, 0, 2, 0));
    if (j->position)
        aos3(j->position + 3 * p0, narrow(o[0] + t * d[0], keep),
             narrow(o[1] + t * d[1], keep), narrow(o[2] + t * d[2], keep));
    if (j->bary)
        aos3(j->bary + 3 * p0, narrow(bary[0], keep), narrow(bary[1], keep),
             narrow(bary[2], keep));
    aos3(j->normal + 3 * p0, narrow(n[0], keep), narrow(n[1], keep), narrow(n[2], keep));
    __m128 u = narrow(uv[0], keep), w = narrow(uv[1], keep);
    _mm_storeu_ps(j->uv + 2 * p0, _mm_unpacklo_ps(u, w));
    _mm_storeu_ps(j->uv + 2 * p0 + 4, _mm_unpackhi_ps(u, w));
    _mm_storeu_ps(j->dist + p0, narrow(t, keep));
    _mm_storeu_ps(j->depth + p0, narrow(depth, keep));
    /* tri: the id where kept, else all bits set (-1), its low 32 bits (ids < 2^31);
     * mask: one byte per pixel */
    __m256i kept = _mm256_or_si256(ids, ~(__m256i)good);
    _mm_storeu_si128((__m128i *)(j->tri + p0), _mm256_castsi256_si128(
        _mm256_permutevar8x32_epi32(kept, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6))));
    int bits = _mm256_movemask_pd((__m256d)good);
    uint32_t m4 = (uint32_t)((bits & 1) | (bits & 2) << 7 | (bits & 4) << 14 |
                             (bits & 8) << 21);
    memcpy(j->mask + p0, &m4, 4);
    int again = _mm256_movemask_pd((__m256d)redo);
    for (int l = 0; l < 4; l++)
        if (again >> l & 1) layer_pixel(j, p0 + l);
}
#endif

/* Every output of pixels [begin, end): with AVX2, in blocks of four pixels (a run of
 * empty blocks written in bulk: most pixels of a frame may be empty); else the empty
 * values in bulk, then the covered pixels one by one. */
static void layer_range(const void *job, int64_t begin, int64_t end) {
    const LayerJob *j = (const LayerJob *)job;
#ifdef LAYER_LANES
    int64_t p = begin;
    for (; p < end && (p & 3); p++) layer_one(j, p);
    int64_t run = p;  /* the start of the current run of empty blocks */
    for (; p + 4 <= end; p += 4) {
        __m256i ids = _mm256_loadu_si256((const __m256i *)(j->ids + p));
        if (_mm256_movemask_pd(_mm256_castsi256_pd(ids)) == 0xf) continue;  /* all < 0 */
        if (run < p) layer_empty(j, run, p);
        layer_lanes(j, p, ids);
        run = p + 4;
    }
    if (run < p) layer_empty(j, run, p);
    for (; p < end; p++) layer_one(j, p);
#else
    layer_empty(j, begin, end);
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


/* adaptive._center_samples: each uniform pixel's first sub-pixel of the front layer, and
 * its ray, replaced in place by the sample along the pixel's center ray, on the one of the
 * pixel's sub-pixel triangles that the ray hits most inside (the largest smallest
 * barycentric; the first of equal ones, a NaN first as torch.argmax takes it). The tensor
 * code's float32 operations (gbuffer.intersect_triangles, interpolate, smooth.normalize:
 * optics.h's hit, weights, blend, norm3), so the same values. */
typedef struct {
    int64_t b, h, w, n;                 /* pixels (B, h, w); the layer (B, nh, nw) */
    const uint8_t *uniform;             /* (B, h, w) */
    const float *center_dirs;           /* (B, h, w, 3) unit center rays */
    const float *eye, *proj;            /* (B, 3), (B, 16): forward at 9..11 */
    const float *tv, *tn, *tuv;         /* (F, 3, 3), (F, 3, 3), (F, 3, 2) */
    int32_t *tri;                       /* the front layer (B*nh*nw, ...) and rays */
    float *position, *dist, *depth, *bary, *normal, *uv, *ray_dir;
} CenterJob;

static void center_range(const void *job, int64_t begin, int64_t end) {
    const CenterJob *j = (const CenterJob *)job;
    int64_t n = j->n, nw = j->w * n, hw = j->h * j->w;
    for (int64_t p = begin; p < end; p++) {
        if (!j->uniform[p]) continue;
        int64_t bi = p / hw, y = (p / j->w) % j->h, x = p % j->w;
        int64_t s0 = (bi * j->h * n + y * n) * nw + x * n;
        const float *d = j->center_dirs + 3 * p, *o = j->eye + 3 * bi;
        int64_t cand[256], best = -1;  /* n <= 16 (torchrefract_center_samples) */
        int m = 0;
        float best_score = 0.0f, best_t = 0.0f, best_bary[3] = {0.0f, 0.0f, 0.0f};
        for (int64_t i = 0; i < n; i++)
            for (int64_t k = 0; k < n; k++) {
                int64_t c = j->tri[s0 + i * nw + k];
                int seen = 0;
                for (int q = 0; q < m; q++) seen |= cand[q] == c;
                if (seen) continue;  /* a repeat gives the same values */
                cand[m++] = c;
                float bb[3];
                float t = hit(o, d, j->tv + 9 * c, bb);
                float score = min3(bb);
                int take = best < 0 || (best_score == best_score &&
                                        (score != score || score > best_score));
                if (take) {
                    best = c;
                    best_score = score;
                    best_t = t;
                    for (int e = 0; e < 3; e++) best_bary[e] = bb[e];
                }
            }
        float nrm[3], uv[2];
        interpolate(best_bary, j->tn + 9 * best, 3, nrm);
        normalize3(nrm);
        interpolate(best_bary, j->tuv + 6 * best, 2, uv);
        j->tri[s0] = (int32_t)best;
        for (int e = 0; e < 3; e++) {
            float td = best_t * d[e];
            j->position[3 * s0 + e] = o[e] + td;
            j->bary[3 * s0 + e] = best_bary[e];
            j->normal[3 * s0 + e] = nrm[e];
            j->ray_dir[3 * s0 + e] = d[e];
        }
        j->dist[s0] = best_t;
        j->depth[s0] = best_t * dot3(d, j->proj + 16 * bi + 9);
        j->uv[2 * s0] = uv[0];
        j->uv[2 * s0 + 1] = uv[1];
    }
}

/* Entry point (ctypes, native.py). Returns 0, or -1 where a thread could not be started. */
int torchrefract_center_samples(const CenterJob *job, int threads) {
    if (job->n > 16) return -1;  /* the scenes' limit; cand's size */
    return tr_parallel_for(center_range, job, job->b * job->h * job->w, 4096, threads);
}

int64_t torchrefract_center_samples_job_size(void) { return (int64_t)sizeof(CenterJob); }

/* camera.pixel_rays_rows for a batch of views of one size: the unit ray through every
 * (sub-)pixel center of rows [r0, r0 + rows), written straight into the batch's buffer.
 * The tensor code's float64 operations in its order: x = ((2 (col + 0.5)) / w - 1) t a per
 * column, y = (1 - (2 (row + 0.5)) / h) t per row, d = (f + x r) + y u, divided by its norm
 * as torch takes it (sqrt of fma(z, z, fma(y, y, x x))), rounded to float32. */
typedef struct {
    int64_t b, h, w;            /* views; rows and columns of the (sub-)pixel grid */
    int64_t r0, rows;           /* the rows [r0, r0 + rows) of it written (a strip) */
    const double *frame;        /* (B, 11): forward (3), right (3), up (3), t, a */
    float *out;                 /* (B, rows, w, 3) */
} RaysJob;

/* The unit ray of the frame ``fr`` at column offset x (the row's y u given: yu), rounded
 * to float32 into o: the scalar form of the operations above. */
static inline void unit_ray(const double *fr, double x, const double *yu, float *o) {
    double d[3];
    for (int c = 0; c < 3; c++) d[c] = (fr[c] + x * fr[3 + c]) + yu[c];
    double nrm = sqrt(fma(d[2], d[2], fma(d[1], d[1], d[0] * d[0])));
    for (int c = 0; c < 3; c++) o[c] = (float)(d[c] / nrm);
}

/* x of column ``col`` of a w-wide grid, y of row ``row`` of an h-high one (frame ``fr``). */
static inline double col_x(const double *fr, double col, int64_t w) {
    return ((2.0 * (col + 0.5)) / (double)w - 1.0) * fr[9] * fr[10];
}

static inline double row_y(const double *fr, double row, int64_t h) {
    return (1.0 - (2.0 * (row + 0.5)) / (double)h) * fr[9];
}

static void rays_range(const void *job, int64_t begin, int64_t end) {
    const RaysJob *j = (const RaysJob *)job;
    for (int64_t row = begin; row < end; row++) {
        int64_t b = row / j->rows, y = j->r0 + row - b * j->rows;
        const double *fr = j->frame + 11 * b;
        double yy = row_y(fr, (double)y, j->h);
        double yu[3] = {yy * fr[6], yy * fr[7], yy * fr[8]};
        float *o = j->out + row * j->w * 3;
        int64_t col = 0;
#ifdef LAYER_LANES
        const double *f = fr, *r = fr + 3;
        double t = fr[9], a = fr[10];
        /* 4 columns at a time: the same IEEE operations (fma, sqrt, division and the
         * conversion are each correctly rounded in the lanes as in the scalar code) */
        for (; col + 4 <= j->w; col += 4, o += 12) {
            __m256d cx = _mm256_add_pd(_mm256_set_pd((double)(col + 3), (double)(col + 2),
                                                     (double)(col + 1), (double)col),
                                       _mm256_set1_pd(0.5));
            __m256d x = _mm256_sub_pd(_mm256_div_pd(_mm256_mul_pd(_mm256_set1_pd(2.0), cx),
                                                    _mm256_set1_pd((double)j->w)),
                                      _mm256_set1_pd(1.0));
            x = _mm256_mul_pd(_mm256_mul_pd(x, _mm256_set1_pd(t)), _mm256_set1_pd(a));
            __m256d d[3];
            for (int c = 0; c < 3; c++)
                d[c] = _mm256_add_pd(_mm256_add_pd(_mm256_set1_pd(f[c]),
                                                   _mm256_mul_pd(x, _mm256_set1_pd(r[c]))),
                                     _mm256_set1_pd(yu[c]));
            __m256d nrm = _mm256_sqrt_pd(_mm256_fmadd_pd(
                d[2], d[2], _mm256_fmadd_pd(d[1], d[1], _mm256_mul_pd(d[0], d[0]))));
            float lanes[3][4];
            for (int c = 0; c < 3; c++)
                _mm_storeu_ps(lanes[c], _mm256_cvtpd_ps(_mm256_div_pd(d[c], nrm)));
            for (int k = 0; k < 4; k++)
                for (int c = 0; c < 3; c++) o[3 * k + c] = lanes[c][k];
        }
#endif
        for (; col < j->w; col++, o += 3) unit_ray(fr, col_x(fr, (double)col, j->w), yu, o);
    }
}

int torchrefract_pixel_rays(const RaysJob *job, int threads) {
    return tr_parallel_for_grain(rays_range, job, job->b * job->rows, 16, threads, 8);
}

int64_t torchrefract_pixel_rays_job_size(void) { return (int64_t)sizeof(RaysJob); }

/* camera.subpixel_rays: rays_range's ray (unit_ray) through chosen
 * (sub-)pixels of a (h, w) grid, ``rows`` and ``cols`` (B, m) per view (sparse
 * supersampling's samples). */
typedef struct {
    int64_t b, m, h, w;
    const double *frame;        /* (B, 11), as RaysJob's */
    const int64_t *rows, *cols; /* (B, m) */
    float *out;                 /* (B, m, 3) */
} RaysAtJob;

static void rays_at_range(const void *job, int64_t begin, int64_t end) {
    const RaysAtJob *j = (const RaysAtJob *)job;
    for (int64_t i = begin; i < end; i++) {
        const double *fr = j->frame + 11 * (i / j->m);
        double yy = row_y(fr, (double)j->rows[i], j->h);
        double yu[3] = {yy * fr[6], yy * fr[7], yy * fr[8]};
        unit_ray(fr, col_x(fr, (double)j->cols[i], j->w), yu, j->out + 3 * i);
    }
}

int torchrefract_rays_at(const RaysAtJob *job, int threads) {
    return tr_parallel_for(rays_at_range, job, job->b * job->m, 4096, threads);
}

int64_t torchrefract_rays_at_job_size(void) { return (int64_t)sizeof(RaysAtJob); }
