/* What torchrefract's two kernels (march.c: float32, gbuffer.c: float64) share: the
 * 3-vector operations and the triangle hit, written once for both types and computed as
 * torch computes them, and the split of a job over threads.
 *
 * Each operation rounds as the tensor code's does (built with -ffp-contract=off and no
 * fast-math): optics.dot sums (a0 b0 + a1 b1) + a2 b2; torch.cross and Tensor.norm use one
 * fused multiply-add per component on CPU (measured), written out as fma here;
 * gbuffer.intersect_triangles and gbuffer.interpolate line by line; torch's min is NaN
 * where any element is.
 */

#ifndef TORCHREFRACT_COMMON_H
#define TORCHREFRACT_COMMON_H

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif

/* Attributes of the functions TR_DEFINE_LANES writes (empty; an instance for a lane type
 * of an instruction set the build does not assume defines it around its instantiation,
 * e.g. __attribute__((target("avx2,fma")))). */
#define TR_LANES_ATTR

/* The operations written once for any lane type T: a scalar (M, its comparisons' type, is
 * int; SEL a ternary) or a GCC vector of 4 doubles (gbuffer.c's AVX2 path: M the integer
 * vector of a comparison, SEL a blend), so that both compute the same bits. K(T, x) is
 * the constant x as a T. The triangle's corners come as T values (9: v0, v1, v2). */
#define TR_DEFINE_LANES(T, M, S, FMA, FABS, SQRT, DET_EPS, SEL, K)                        \
    static inline TR_LANES_ATTR T dot3##S(const T *a, const T *b) {                                      \
        T x = a[0] * b[0];                                                                  \
        T y = a[1] * b[1];                                                                  \
        T z = a[2] * b[2];                                                                  \
        return (x + y) + z;                                                                 \
    }                                                                                       \
    /* torch.cross: a1 b2 - (a2 b1), the second product rounded first */                  \
    static inline TR_LANES_ATTR void cross3##S(const T *a, const T *b, T *out) {                         \
        out[0] = FMA(a[1], b[2], -(a[2] * b[1]));                                           \
        out[1] = FMA(a[2], b[0], -(a[0] * b[2]));                                           \
        out[2] = FMA(a[0], b[1], -(a[1] * b[0]));                                           \
    }                                                                                       \
    /* Tensor.norm: the squares accumulated by fused multiply-adds, then the root */       \
    static inline TR_LANES_ATTR T norm3##S(const T *a) {                                                  \
        T acc = a[0] * a[0];                                                                \
        acc = FMA(a[1], a[1], acc);                                                         \
        acc = FMA(a[2], a[2], acc);                                                         \
        return SQRT(acc);                                                                   \
    }                                                                                       \
    static inline TR_LANES_ATTR T min3##S(const T *b) {                                                   \
        T m = b[0];                                                                         \
        m = SEL(b[1] < m, b[1], m);                                                         \
        m = SEL(b[2] < m, b[2], m);                                                         \
        M nan = (b[0] != b[0]) | (b[1] != b[1]) | (b[2] != b[2]);                           \
        return SEL(nan, K(T, NAN), m);                                                      \
    }                                                                                       \
    /* gbuffer.intersect_triangles for one ray and the triangle v (9 values): returns t   \
     * (inf where the ray is parallel to the plane), writes the barycentrics               \
     * (1 - u - v, u, v). */                                                                \
    static inline TR_LANES_ATTR T hit##S(const T *o, const T *d, const T *v, T *bary) {                  \
        T e1[3], e2[3], p[3], s[3], q[3];                                                   \
        for (int i = 0; i < 3; i++) {                                                       \
            e1[i] = v[3 + i] - v[i];                                                        \
            e2[i] = v[6 + i] - v[i];                                                        \
        }                                                                                   \
        cross3##S(d, e2, p);                                                                \
        T det = dot3##S(e1, p);                                                             \
        M ok = FABS(det) > K(T, DET_EPS);                                                   \
        T inv = SEL(ok, K(T, 1) / SEL(ok, det, K(T, 1)), K(T, 0));                          \
        for (int i = 0; i < 3; i++) s[i] = o[i] - v[i];                                     \
        T u = dot3##S(s, p) * inv;                                                          \
        cross3##S(s, e1, q);                                                                \
        T vv = dot3##S(d, q) * inv;                                                         \
        T t = dot3##S(e2, q) * inv;                                                         \
        t = SEL(ok, t, K(T, INFINITY));                                                     \
        T one_u = K(T, 1) - u;                                                              \
        bary[0] = one_u - vv;                                                               \
        bary[1] = u;                                                                        \
        bary[2] = vv;                                                                       \
        return t;                                                                           \
    }                                                                                       \
    /* gbuffer.interpolate's weights: barycentrics clamped to the triangle (NaN kept),     \
     * renormalized */                                                                      \
    static inline TR_LANES_ATTR void weights##S(const T *bary, T *w) {                                    \
        for (int i = 0; i < 3; i++)                                                         \
            w[i] = SEL(bary[i] != bary[i], bary[i],                                         \
                       SEL(bary[i] < K(T, 0), K(T, 0), bary[i]));                           \
        T sum = (w[0] + w[1]) + w[2];                                                       \
        sum = SEL(sum < K(T, 1e-12), K(T, 1e-12), sum);                                     \
        for (int i = 0; i < 3; i++) w[i] = w[i] / sum;                                      \
    }                                                                                       \
    /* ... and the c-channel corner values (3 x c, as T) blended with them */               \
    static inline TR_LANES_ATTR void blend##S(const T *w, const T *corners, int c, T *out) {              \
        for (int m = 0; m < c; m++) {                                                       \
            T a = w[0] * corners[m];                                                        \
            T b = w[1] * corners[c + m];                                                    \
            T z = w[2] * corners[2 * c + m];                                                \
            out[m] = (a + b) + z;                                                           \
        }                                                                                   \
    }

#define TR_SEL_SCALAR(m, a, b) ((m) ? (a) : (b))
#define TR_K_SCALAR(T, x) ((T)(x))

/* The scalar instance, with the corners read from float32 arrays (the kernels' tables):
 * intersect##S(o, d, tv, bary) and interpolate##S(bary, corners, c, out). */
#define TR_DEFINE_VEC3(T, S, FMA, FABS, SQRT, DET_EPS)                                     \
    TR_DEFINE_LANES(T, int, S, FMA, FABS, SQRT, DET_EPS, TR_SEL_SCALAR, TR_K_SCALAR)       \
    static inline T intersect##S(const T *o, const T *d, const float *tv, T *bary) {        \
        T v[9];                                                                             \
        for (int i = 0; i < 9; i++) v[i] = (T)tv[i];                                        \
        return hit##S(o, d, v, bary);                                                       \
    }                                                                                       \
    static inline void interpolate##S(const T *bary, const float *corners, int c,           \
                                      T *out) {                                         \
        T w[3], cv[9];                                                                      \
        weights##S(bary, w);                                                                \
        for (int i = 0; i < 3 * c; i++) cv[i] = (T)corners[i];                              \
        blend##S(w, cv, c, out);                                                            \
    }

/* Run fn(job, begin, end) over [0, n) split into one contiguous range per thread (the
 * calling thread takes the last); below min_n items, or with one thread, in this thread.
 * With OpenMP the ranges are chunks, multiples of ``grain`` items (tr_parallel_for: 64,
 * for many light items; a few heavy items, as raster.c's row bands, take grain 1).
 * Returns 0, or -1 where a thread could not be started (the started ones are joined). */
typedef void (*tr_range_fn)(const void *job, int64_t begin, int64_t end);

typedef struct { tr_range_fn fn; const void *job; int64_t begin, end; } TrRange;

static void *tr_run_range(void *arg) {
    const TrRange *rg = (const TrRange *)arg;
    rg->fn(rg->job, rg->begin, rg->end);
    return NULL;
}

static int tr_parallel_for_grain(tr_range_fn fn, const void *job, int64_t n, int64_t min_n,
                                 int threads, int64_t grain) {
    if (threads < 1) threads = 1;
    if (threads > 64) threads = 64;
    if (n < min_n || threads == 1) {
        fn(job, 0, n);
        return 0;
    }
#ifdef _OPENMP
    /* Built with -fopenmp (native.py, where the compiler has it): the same ranges on the
     * OpenMP runtime's threads. Loaded into a process whose torch brought libgomp.so.1,
     * that is torch's own pool: its workers, still spinning after the last tensor op,
     * take the ranges at once instead of competing with threads of ours for the cores
     * (measured: the cone kernels ran 2x slower right after tensor ops with pthreads).
     * The range is cut into 16 chunks per thread (multiples of the grain: 64 so a march
     * block of 16 rays is never split), handed out dynamically: a thread whose core is
     * busy with another process takes fewer, instead of holding up the others at the end. */
    if (grain < 1) grain = 1;
    int64_t chunk = (n + 16 * (int64_t)threads - 1) / (16 * (int64_t)threads);
    chunk = (chunk + grain - 1) / grain * grain;
    int64_t chunks = (n + chunk - 1) / chunk;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
    for (int64_t c = 0; c < chunks; c++)
        fn(job, c * chunk, c * chunk + chunk < n ? c * chunk + chunk : n);
    return 0;
#endif
    pthread_t ids[64];
    TrRange rgs[64];
    int64_t per = (n + threads - 1) / threads;
    int started = 0, rc = 0;
    for (int i = 0; i < threads; i++) {
        int64_t b = (int64_t)i * per, e = b + per < n ? b + per : n;
        rgs[i].fn = fn; rgs[i].job = job; rgs[i].begin = b; rgs[i].end = e;
        if (i == threads - 1) break;  /* the calling thread runs the last range */
        if (pthread_create(&ids[i], NULL, tr_run_range, &rgs[i]) != 0) {
            rc = -1;
            break;
        }
        started++;
    }
    if (rc == 0) tr_run_range(&rgs[threads - 1]);
    for (int i = 0; i < started; i++) pthread_join(ids[i], NULL);
    return rc;
}

static int tr_parallel_for(tr_range_fn fn, const void *job, int64_t n, int64_t min_n,
                           int threads) {
    return tr_parallel_for_grain(fn, job, n, min_n, threads, 64);
}

#endif
