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

/* One triangle's row for lane type T (a double, or 4 in AVX2 lanes: the same operations,
 * each rounded once, so the same bits): corners t (9 values), the view's eye and basis;
 * the row's 4 values as T. SQRT, SEL and K as common.h's lanes take them. */
#define TR_PLANE_ROW(T, SQRT, SEL, K)                                                       \
    do {                                                                                    \
        T e1[3], e2[3], n[3], rel[3];                                                       \
        for (int k = 0; k < 3; k++) {                                                       \
            e1[k] = t[3 + k] - t[k];                                                        \
            e2[k] = t[6 + k] - t[k];                                                        \
            rel[k] = t[k] - eye[k];                                                         \
        }                                                                                   \
        n[0] = e1[1] * e2[2] - e1[2] * e2[1];                                               \
        n[1] = e1[2] * e2[0] - e1[0] * e2[2];                                               \
        n[2] = e1[0] * e2[1] - e1[1] * e2[0];                                               \
        T len = SQRT(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);                              \
        len = SEL(len < K(T, 1e-300), K(T, 1e-300), len);                                   \
        for (int k = 0; k < 3; k++) n[k] = n[k] / len;                                      \
        T away = (rel[0] * n[0] + rel[1] * n[1]) + rel[2] * n[2];                           \
        for (int k = 0; k < 3; k++) n[k] = SEL(away < K(T, 0.0), -n[k], n[k]);             \
        for (int k = 0; k < 3; k++)                                                         \
            row[k] = (n[0] * bs[3 * k] + n[1] * bs[3 * k + 1]) + n[2] * bs[3 * k + 2];      \
        row[3] = (n[0] * rel[0] + n[1] * rel[1]) + n[2] * rel[2];                           \
    } while (0)

/* Row r of view v (its triangle face0[v] + r - first[v]), one at a time. */
static inline void table_row(const TriPlanesJob *j, int64_t v, int64_t r, const double *eye,
                             const double *bs) {
    const float *tf = j->tv + 9 * (j->face0[v] + r - j->first[v]);
    double t[9], row[4];
    for (int k = 0; k < 9; k++) t[k] = (double)tf[k];
    TR_PLANE_ROW(double, sqrt, TR_SEL_SCALAR, TR_K_SCALAR);
    for (int k = 0; k < 4; k++) j->out[4 * r + k] = (float)row[k];
}

#if defined(__AVX2__)
typedef double v4d_p __attribute__((vector_size(32)));
#define SEL4P(m, a, b) ((v4d_p)_mm256_blendv_pd((__m256d)(b), (__m256d)(a), (__m256d)(m)))
#define K4P(T, x) ((T){(x), (x), (x), (x)})
static inline v4d_p sqrt4p(v4d_p a) { return (v4d_p)_mm256_sqrt_pd((__m256d)a); }

/* Rows r .. r + 3 of view v in lanes, stored as 4 rows of 4 floats. */
static inline void table_rows4(const TriPlanesJob *j, int64_t v, int64_t r, const double *e,
                               const double *b) {
    const float *tf = j->tv + 9 * (j->face0[v] + r - j->first[v]);  /* 4 consecutive */
    v4d_p t[9], eye[3], bs[9], row[4];
    for (int k = 0; k < 9; k++) {
        t[k] = (v4d_p){tf[k], tf[9 + k], tf[18 + k], tf[27 + k]};
        bs[k] = K4P(v4d_p, b[k]);
    }
    for (int k = 0; k < 3; k++) eye[k] = K4P(v4d_p, e[k]);
    TR_PLANE_ROW(v4d_p, sqrt4p, SEL4P, K4P);
    __m128 o[4];
    for (int k = 0; k < 4; k++) o[k] = _mm256_cvtpd_ps((__m256d)row[k]);
    _MM_TRANSPOSE4_PS(o[0], o[1], o[2], o[3]);
    for (int l = 0; l < 4; l++) _mm_storeu_ps(j->out + 4 * (r + l), o[l]);
}
#endif

static void tri_planes_range(const void *job, int64_t begin, int64_t end) {
    const TriPlanesJob *j = (const TriPlanesJob *)job;
    int64_t v = 0;
    while (v + 1 < j->nv && j->first[v + 1] <= begin) v++;
    for (int64_t r = begin; r < end; v++) {  /* the rows of view v in [begin, end) */
        int64_t stop = j->first[v + 1] < end ? j->first[v + 1] : end;
        double eye[3], bs[9];
        for (int k = 0; k < 3; k++) eye[k] = (double)j->eye[3 * v + k];
        for (int k = 0; k < 9; k++) bs[k] = (double)j->basis[9 * v + k];
#if defined(__AVX2__)
        for (; r + 4 <= stop; r += 4) table_rows4(j, v, r, eye, bs);
#endif
        for (; r < stop; r++) table_row(j, v, r, eye, bs);
    }
}

int torchrefract_tri_planes(TriPlanesJob *job, int threads) {
    return tr_parallel_for(tri_planes_range, job, job->n, 16384, threads);
}

int64_t torchrefract_tri_planes_job_size(void) { return (int64_t)sizeof(TriPlanesJob); }
