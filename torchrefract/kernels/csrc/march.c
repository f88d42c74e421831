/* The march kernel's entry points (march_core.h holds the march itself). */

#include "march_core.h"

static void march_range(const void *job, int64_t begin, int64_t end) {
    const Job *j = (const Job *)job;
    float lo[BLOCK], hi[BLOCK];
    for (int64_t r = begin; r < end; r += BLOCK) {
        int m = end - r < BLOCK ? (int)(end - r) : BLOCK;
        search_rays(j, r, m, lo, hi);
        exit_block(j, r, m, lo, hi);
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

/* march.plane_table for the views of a batch: per triangle of each view its unit
 * geometric normal turned away from the view's eye, in the view's camera coordinates, and
 * n . (v0 - eye), computed in double as the tensor code does (cross, norm, the dot in
 * optics.dot's order), then rounded to float (march.Marched.table). View v's rows are
 * [first[v], first[v + 1]) of the table, its triangles those from face0[v] of ``tv``. */
typedef struct {
    int64_t n, nv;              /* rows (the views' triangles), views */
    const int64_t *first;       /* (nv + 1,) each view's first row, then n */
    const int64_t *face0;       /* (nv,) each view's first triangle in tv */
    const float *tv;            /* (T, 3, 3) */
    const float *eye, *basis;   /* (nv, 3), (nv, 9) rows: right, up, forward */
    float *out;                 /* (n, 4) */
} TriPlanesJob;

static void tri_planes_range(const void *job, int64_t begin, int64_t end) {
    const TriPlanesJob *j = (const TriPlanesJob *)job;
    int64_t v = 0;
    while (v + 1 < j->nv && j->first[v + 1] <= begin) v++;
    for (int64_t r = begin; r < end; v++) {  /* the rows of view v in [begin, end) */
        int64_t stop = j->first[v + 1] < end ? j->first[v + 1] : end;
        double eye[3], bs[9];
        for (int k = 0; k < 3; k++) eye[k] = (double)j->eye[3 * v + k];
        for (int k = 0; k < 9; k++) bs[k] = (double)j->basis[9 * v + k];
        for (; r < stop; r++) {
            const float *t = j->tv + 9 * (j->face0[v] + r - j->first[v]);
            double e1[3], e2[3], n[3], rel[3];
            for (int k = 0; k < 3; k++) {
                e1[k] = (double)t[3 + k] - (double)t[k];
                e2[k] = (double)t[6 + k] - (double)t[k];
                rel[k] = (double)t[k] - eye[k];
            }
            n[0] = e1[1] * e2[2] - e1[2] * e2[1];
            n[1] = e1[2] * e2[0] - e1[0] * e2[2];
            n[2] = e1[0] * e2[1] - e1[1] * e2[0];
            double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
            if (len < 1e-300) len = 1e-300;
            for (int k = 0; k < 3; k++) n[k] = n[k] / len;
            double away = (rel[0] * n[0] + rel[1] * n[1]) + rel[2] * n[2];
            if (away < 0.0)
                for (int k = 0; k < 3; k++) n[k] = -n[k];
            float *o = j->out + 4 * r;
            for (int k = 0; k < 3; k++)
                o[k] = (float)((n[0] * bs[3 * k] + n[1] * bs[3 * k + 1]) + n[2] * bs[3 * k + 2]);
            o[3] = (float)((n[0] * rel[0] + n[1] * rel[1]) + n[2] * rel[2]);
        }
    }
}

int torchrefract_tri_planes(TriPlanesJob *job, int threads) {
    return tr_parallel_for(tri_planes_range, job, job->n, 16384, threads);
}

int64_t torchrefract_tri_planes_job_size(void) { return (int64_t)sizeof(TriPlanesJob); }
