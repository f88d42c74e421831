/* The march kernel's entry points (march_core.h holds the march itself). */

#include "march_core.h"

static void march_range(const void *job, int64_t begin, int64_t end) {
    const Job *j = (const Job *)job;
    float lo[BLOCK], hi[BLOCK];
    for (int64_t r = begin; r < end; r += BLOCK) {
        int m = end - r < BLOCK ? (int)(end - r) : BLOCK;
#ifdef HAVE_AVX2_PATH
        if (j->simd && m == BLOCK) search_block_avx2(j, r, lo, hi);
        else search_block(j, r, m, lo, hi);
#else
        search_block(j, r, m, lo, hi);
#endif
        for (int i = 0; i < m; i++) exit_ray(j, r + i, lo[i], hi[i]);
    }
}

/* Entry point (ctypes, native.py): march all rays of ``job`` on ``threads`` threads.
 * Returns 0, or -1 where a thread could not be started (then nothing is guaranteed).
 * The AVX2 search runs where ``job->simd`` asks for it (native.py: only where the plane
 * indices fit its 32-bit gathers) and the CPU has AVX2. */
int torchrefract_march(Job *job, int threads) {
#ifdef HAVE_AVX2_PATH
    job->simd = job->simd && __builtin_cpu_supports("avx2");
#endif
    return tr_parallel_for(march_range, job, job->n, 4096, threads);
}

/* The layout of Job, for native.py's check that its ctypes mirror matches. */
int64_t torchrefract_march_job_size(void) { return (int64_t)sizeof(Job); }

/* march.camera_planes: per pixel the back layer's plane (and with ``pw`` 8 the front
 * layer's) in its view's camera coordinates, in the tensor code's operations and order
 * (march._planes, march._to_camera): n the geometric normal turned away from the eye (the
 * front's towards it), c = n . x, then (basis n, c - n . eye); (0, 0, 0, -1) (and zeros)
 * where the layer(s) are empty. */
typedef struct {
    int64_t n, hw;              /* B*H*W, H*W */
    int pw;                     /* 4 or 8 */
    const float *pos_b, *gn_b;  /* (B*H*W, 3) the back layer */
    const float *pos_f, *gn_f;  /* (B*H*W, 3) the front layer (pw 8) */
    const uint8_t *mask_b, *mask_f;  /* (B*H*W,) */
    const float *eye, *basis;   /* (B, 3), (B, 9) rows: right, up, forward */
    float *out;                 /* (B*H*W, pw) */
} PlanesJob;

static void plane_of(const float *x, const float *gn, const float *eye, const float *bs,
                     int away_from_eye, float *out) {
    float rel[3] = {x[0] - eye[0], x[1] - eye[1], x[2] - eye[2]}, n[3];
    float away = dot3(rel, gn);
    int flip = away_from_eye ? away < 0.0f : away > 0.0f;
    for (int k = 0; k < 3; k++) n[k] = flip ? -gn[k] : gn[k];
    float c = dot3(n, x);
    for (int k = 0; k < 3; k++) out[k] = dot3(n, bs + 3 * k);
    out[3] = c - dot3(n, eye);
}

static void planes_range(const void *job, int64_t begin, int64_t end) {
    const PlanesJob *j = (const PlanesJob *)job;
    for (int64_t p = begin; p < end; p++) {
        int64_t b = p / j->hw;
        float *o = j->out + p * j->pw;
        int valid = j->mask_b[p] && (j->pw == 4 || j->mask_f[p]);
        if (!valid) {
            for (int k = 0; k < j->pw; k++) o[k] = 0.0f;
            o[3] = -1.0f;
            continue;
        }
        plane_of(j->pos_b + 3 * p, j->gn_b + 3 * p, j->eye + 3 * b, j->basis + 9 * b, 1, o);
        if (j->pw == 8)
            plane_of(j->pos_f + 3 * p, j->gn_f + 3 * p, j->eye + 3 * b, j->basis + 9 * b, 0,
                     o + 4);
    }
}

int torchrefract_planes(PlanesJob *job, int threads) {
    return tr_parallel_for(planes_range, job, job->n, 16384, threads);
}

int64_t torchrefract_planes_job_size(void) { return (int64_t)sizeof(PlanesJob); }
