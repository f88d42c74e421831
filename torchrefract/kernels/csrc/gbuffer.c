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
    double v[9], e1[3], e2[3], gn[3], n[3], uv[2];
    for (int m = 0; m < 9; m++) v[m] = (double)j->tv[9 * id + m];
    for (int m = 0; m < 3; m++) {
        e1[m] = v[3 + m] - v[m];
        e2[m] = v[6 + m] - v[m];
    }
    cross3d(e1, e2, gn);
    double gl = norm3d(gn);
    if (gl < 1e-300) gl = 1e-300;
    interpolated(bary, j->tn + 9 * id, 3, n);
    double nl = norm3d(n);
    if (nl < 1e-300) nl = 1e-300;
    interpolated(bary, j->tuv + 6 * id, 2, uv);
    double f[3] = {(double)j->forward[3 * bi], (double)j->forward[3 * bi + 1],
                   (double)j->forward[3 * bi + 2]};
    j->mask[p] = 1;
    j->tri[p] = id;
    for (int i = 0; i < 3; i++) {
        double td = t * d[i];
        j->position[3 * p + i] = (float)(o[i] + td);
        j->bary[3 * p + i] = (float)bary[i];
        j->geo_normal[3 * p + i] = (float)(gn[i] / gl);
        j->normal[3 * p + i] = (float)(n[i] / nl);
    }
    j->dist[p] = (float)t;
    j->depth[p] = (float)(t * dot3d(d, f));
    j->uv[2 * p] = (float)uv[0];
    j->uv[2 * p + 1] = (float)uv[1];
}

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
    for (int64_t p = begin; p < end; p++)
        if (j->ids[p] >= 0) layer_pixel(j, p);
}

/* Entry point (ctypes, native.py): one layer of all B*H*W pixels on ``threads`` threads.
 * Returns 0, or -1 where a thread could not be started. */
int torchrefract_layer(const LayerJob *job, int threads) {
    return tr_parallel_for(layer_range, job, job->b * job->h * job->w, 16384, threads);
}

int64_t torchrefract_layer_job_size(void) { return (int64_t)sizeof(LayerJob); }
