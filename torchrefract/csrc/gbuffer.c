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
 * (tests/test_native.py). Plain C with pthreads; built and loaded by native.py.
 */

#include <math.h>
#include <pthread.h>
#include <stdint.h>

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

typedef struct { const LayerJob *job; int64_t begin, end; } LayerRange;

static inline double dot3d(const double *a, const double *b) {
    double x = a[0] * b[0];
    double y = a[1] * b[1];
    double z = a[2] * b[2];
    return (x + y) + z;
}

/* torch.cross as torch's CPU kernel computes it (one fused multiply-add per component). */
static inline void cross3d(const double *a, const double *b, double *out) {
    out[0] = fma(a[1], b[2], -(a[2] * b[1]));
    out[1] = fma(a[2], b[0], -(a[0] * b[2]));
    out[2] = fma(a[0], b[1], -(a[1] * b[0]));
}

/* gbuffer.intersect_triangles in float64 for one ray and face f. */
static double intersect_d(const double *o, const double *d, const float *tv, int64_t f,
                          double *bary) {
    double v[9];
    for (int i = 0; i < 9; i++) v[i] = (double)tv[9 * f + i];
    double e1[3], e2[3], p[3], s[3], q[3];
    for (int i = 0; i < 3; i++) {
        e1[i] = v[3 + i] - v[i];
        e2[i] = v[6 + i] - v[i];
    }
    cross3d(d, e2, p);
    double det = dot3d(e1, p);
    int ok = fabs(det) > 1e-30;
    double inv = ok ? 1.0 / det : 0.0;
    for (int i = 0; i < 3; i++) s[i] = o[i] - v[i];
    double u = dot3d(s, p) * inv;
    cross3d(s, e1, q);
    double vv = dot3d(d, q) * inv;
    double t = dot3d(e2, q) * inv;
    if (!ok) t = INFINITY;
    double one_u = 1.0 - u;
    bary[0] = one_u - vv;
    bary[1] = u;
    bary[2] = vv;
    return t;
}

static inline double min3d(const double *b) {  /* torch's min: NaN if any is NaN */
    if (b[0] != b[0] || b[1] != b[1] || b[2] != b[2]) return NAN;
    double m = b[0];
    if (b[1] < m) m = b[1];
    if (b[2] < m) m = b[2];
    return m;
}

/* Tensor.norm over 3 components as torch's CPU kernel computes it (measured): the squares
 * accumulated by fused multiply-adds, then the square root. */
static inline double norm3d(const double *a) {
    double acc = a[0] * a[0];
    acc = fma(a[1], a[1], acc);
    acc = fma(a[2], a[2], acc);
    return sqrt(acc);
}

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
        double t = intersect_d(o, d, j->tv, c, cb);
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

static void interpolate_d(const double *bary, const float *corners, int c, double *out) {
    double w[3];
    for (int i = 0; i < 3; i++) w[i] = bary[i] < 0.0 ? 0.0 : bary[i];
    if (bary[0] != bary[0]) w[0] = bary[0];  /* clamp propagates NaN */
    if (bary[1] != bary[1]) w[1] = bary[1];
    if (bary[2] != bary[2]) w[2] = bary[2];
    double sum = (w[0] + w[1]) + w[2];
    if (sum < 1e-12) sum = 1e-12;
    for (int i = 0; i < 3; i++) w[i] = w[i] / sum;
    for (int m = 0; m < c; m++) {
        double a = w[0] * (double)corners[m];
        double b = w[1] * (double)corners[c + m];
        double z = w[2] * (double)corners[2 * c + m];
        out[m] = (a + b) + z;
    }
}

static void layer_pixel(const LayerJob *j, int64_t p) {
    int64_t id = j->ids[p];
    j->mask[p] = 0;
    j->tri[p] = -1;
    j->dist[p] = 0.0f;
    j->depth[p] = 0.0f;
    for (int i = 0; i < 3; i++) {
        j->position[3 * p + i] = 0.0f;
        j->bary[3 * p + i] = 0.0f;
        j->geo_normal[3 * p + i] = 0.0f;
        j->normal[3 * p + i] = 0.0f;
    }
    j->uv[2 * p] = 0.0f;
    j->uv[2 * p + 1] = 0.0f;
    if (id < 0) return;
    int64_t hw = j->h * j->w, bi = p / hw;
    double o[3], d[3], bary[3];
    for (int i = 0; i < 3; i++) {
        o[i] = (double)j->eye[3 * bi + i];
        d[i] = (double)j->dirs[3 * p + i];
    }
    double t = intersect_d(o, d, j->tv, id, bary);
    double own_min = min3d(bary);
    if (own_min < -j->tol) {
        int64_t fixed = repair(j, bi, (p / j->w) % j->h, p % j->w, id, own_min, o, d);
        if (fixed < 0) return;
        if (fixed != id) {
            id = fixed;
            t = intersect_d(o, d, j->tv, id, bary);
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
    interpolate_d(bary, j->tn + 9 * id, 3, n);
    double nl = norm3d(n);
    if (nl < 1e-300) nl = 1e-300;
    interpolate_d(bary, j->tuv + 6 * id, 2, uv);
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

static void *layer_range(void *arg) {
    const LayerRange *rg = (const LayerRange *)arg;
    for (int64_t p = rg->begin; p < rg->end; p++) layer_pixel(rg->job, p);
    return NULL;
}

/* Entry point (ctypes, native.py): one layer of all B*H*W pixels on ``threads`` threads.
 * Returns 0, or -1 where a thread could not be started. */
int torchrefract_layer(const LayerJob *job, int threads) {
    if (threads < 1) threads = 1;
    if (threads > 64) threads = 64;
    int64_t n = job->b * job->h * job->w;
    if (n < 16384 || threads == 1) {
        LayerRange rg = {job, 0, n};
        layer_range(&rg);
        return 0;
    }
    pthread_t ids[64];
    LayerRange rgs[64];
    int64_t per = (n + threads - 1) / threads;
    int started = 0, rc = 0;
    for (int i = 0; i < threads; i++) {
        int64_t b = (int64_t)i * per, e = b + per < n ? b + per : n;
        rgs[i].job = job; rgs[i].begin = b; rgs[i].end = e;
        if (i == threads - 1) break;
        if (pthread_create(&ids[i], NULL, layer_range, &rgs[i]) != 0) {
            rc = -1;
            break;
        }
        started++;
    }
    if (rc == 0) layer_range(&rgs[threads - 1]);
    for (int i = 0; i < started; i++) pthread_join(ids[i], NULL);
    return rc;
}

int64_t torchrefract_layer_job_size(void) { return (int64_t)sizeof(LayerJob); }
