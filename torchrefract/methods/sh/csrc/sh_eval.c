/* Method sh: eq. 2's evaluation of the precomputed mapping at surface points, the
 * native twin of shade._evaluate_tensor (methods/sh/native.py builds and calls it).
 *
 * Per point: its three surface samples (with barycentric weights S_oi) and E view
 * directions in object space; per (sample, direction): the direction in the sample's
 * tangent frame, the mirrored-hemisphere real SH basis up to band L (eqs. 4-7; the
 * recurrences of basis.real_sh, only the l + m even functions, in the order of
 * basis.even_indices), windowed (sec. 4.3), times the sample's coefficients, blended with
 * S_oi. Vectorized with GCC/Clang vector types: the SH of a point's 3 E directions
 * together (8 directions per vector), then the product with the coefficients 8 channels
 * at a time (the table is stored (S, K, 8): the C <= 8 channels of a coefficient side by
 * side), one broadcast and multiply-add per (direction, coefficient), the partial sums in
 * registers; the samples of the points ahead are prefetched while one computes. Float32
 * throughout and no contraction (as the tensor code: -ffp-contract=off); the sums run in
 * another order (the images agree to float32 rounding, tests/test_sh.py). */

#include "../../../kernels/csrc/common.h"
#include "sh_jobs.h"

#if defined(__F16C__) && defined(__AVX__)
#include <immintrin.h>
#define SH_HALF 1 /* the table stays float16 (as stored): half the bytes gathered per pixel */
#else
#define SH_HALF 0
#endif

TR_DEFINE_VEC3(float, f, fmaf, fabsf, sqrtf, 1e-30f)

#define SH_MAXL 8
#define SH_MAXK 45 /* (L + 1)(L + 2) / 2 at L = 8 */
#define SH_CPAD 8  /* channels per coefficient in the table */
#define SH_MAXE 5
#define SH_NV 2    /* vectors of 8 directions: 3 samples x at most 5 directions */

typedef float v8f __attribute__((vector_size(32)));


/* The constants of basis.real_sh for the even functions, in basis.even_indices' order:
 * band l, signed m, and the factor (K_l^0, or sqrt(2) K_l^m) rounded to float32 as torch
 * multiplies it; Q_m^m = (-1)^m (2m - 1)!!. */
typedef struct {
    int k;
    int l[SH_MAXK], m[SH_MAXK];
    float f[SH_MAXK];
    float qmm[SH_MAXL + 1];
    int kidx[SH_MAXL + 1][2 * SH_MAXL + 1]; /* k of (l, m) at [l][SH_MAXL + m], l + m even */
} ShConst;

static void sh_constants(int order, ShConst *cst) {
    int k = 0;
    for (int l = 0; l <= order; l++)
        for (int m = -l; m <= l; m++) {
            if ((l + m) & 1) continue;
            int am = m < 0 ? -m : m;
            double kk = sqrt((2.0 * l + 1) / (4.0 * M_PI)
                             * exp(lgamma(l - am + 1.0) - lgamma(l + am + 1.0)));
            cst->l[k] = l;
            cst->m[k] = m;
            cst->kidx[l][SH_MAXL + m] = k;
            cst->f[k] = (float)(m == 0 ? kk : sqrt(2.0) * kk);
            k++;
        }
    cst->k = k;
    for (int m = 0; m <= order; m++) {
        double q = 1.0;
        for (int i = 1; i < 2 * m; i += 2) q *= i;
        cst->qmm[m] = (float)((m & 1 ? -1.0 : 1.0) * q);
    }
}

static inline v8f splat(float a) { return (v8f){a, a, a, a, a, a, a, a}; }

/* ysh[k][v]: the even functions of the directions (x, y, z)[v] (nv vectors of 8), band by
 * band per m: Q_l^m(z) by its recurrence (two terms live), each even (l, m) written as it
 * comes; the same operations in the same order as a table of all Q_l^m would take. */
static inline __attribute__((always_inline)) void sh_even(
        const ShConst *cst, int order, int nv, const v8f *x, const v8f *y, const v8f *z,
        v8f ysh[SH_MAXK][SH_NV]) {
    v8f c[SH_NV], s[SH_NV], qa[SH_NV], qb[SH_NV]; /* cos, sin m phi (x sin^m); Q_{l-1,2}^m */
    for (int v = 0; v < nv; v++) {
        c[v] = splat(1.0f);
        s[v] = splat(0.0f);
    }
#pragma GCC unroll 9
    for (int m = 0; m <= order; m++) {
        for (int v = 0; v < nv && m > 0; v++) {
            v8f c1 = c[v] * x[v] - s[v] * y[v];
            s[v] = c[v] * y[v] + s[v] * x[v];
            c[v] = c1;
        }
#pragma GCC unroll 9
        for (int l = m; l <= order; l++) {
            for (int v = 0; v < nv; v++) { /* the vectors side by side: chains overlap */
                v8f q;
                if (l == m) {
                    q = splat(cst->qmm[m]);
                } else if (l == m + 1) {
                    q = splat((float)(2 * m + 1)) * z[v] * qa[v];
                } else {
                    /* (l - m) Q_l^m = (2l - 1) z Q_{l-1}^m - (l + m - 1) Q_{l-2}^m, divided
                     * as the tensor code does (folding 1 / (l - m) into the constants
                     * moved a few pixels by 1.6e-4 relative) */
                    q = (splat((float)(2 * l - 1)) * z[v] * qa[v]
                         - splat((float)(l + m - 1)) * qb[v]) / splat((float)(l - m));
                }
                qb[v] = qa[v];
                qa[v] = q;
                if ((l + m) & 1) continue;
                if (m == 0) {
                    int k = cst->kidx[l][SH_MAXL];
                    ysh[k][v] = splat(cst->f[k]) * q;
                } else {
                    int kp = cst->kidx[l][SH_MAXL + m], kn = cst->kidx[l][SH_MAXL - m];
                    ysh[kp][v] = splat(cst->f[kp]) * q * c[v];
                    ysh[kn][v] = splat(cst->f[kn]) * q * s[v];
                }
            }
        }
    }
}

/* layout.interpolation for one point: the three lattice samples of the small triangle the
 * barycentrics fall in, and their weights (float32, formula by formula). */
static void interpolate_point(const ShEvalJob *job, int64_t face, const float *bi,
                              int64_t *smp, float *sw) {
    const int64_t n = job->rate;
    float b[3];
    for (int t = 0; t < 3; t++) b[t] = bi[t] < 0.0f ? 0.0f : bi[t];
    float sum = (b[0] + b[1]) + b[2];
    if (sum < 1e-12f) sum = 1e-12f;
    for (int t = 0; t < 3; t++) b[t] = b[t] / sum;
    float u = b[1] * (float)n, v = b[2] * (float)n;
    int64_t ii = (int64_t)floorf(u), jj = (int64_t)floorf(v);
    ii = ii < 0 ? 0 : (ii > n - 1 ? n - 1 : ii);
    jj = jj < 0 ? 0 : (jj > n - 1 ? n - 1 : jj);
    if (ii + jj > n - 1) ii = n - 1 - jj < 0 ? 0 : n - 1 - jj;
    float fu = u - (float)ii, fv = v - (float)jj;
    int upper = (fu + fv > 1.0f) && (ii + jj < n - 1);
    int64_t pi[3], pj[3];
    float w[3];
    if (upper) {
        pi[0] = ii + 1; pj[0] = jj + 1;
        pi[1] = ii;     pj[1] = jj + 1;
        pi[2] = ii + 1; pj[2] = jj;
        w[0] = (fu + fv) - 1.0f;
        w[1] = 1.0f - fu;
        w[2] = 1.0f - fv;
    } else {
        pi[0] = ii;     pj[0] = jj;
        pi[1] = ii + 1; pj[1] = jj;
        pi[2] = ii;     pj[2] = jj + 1;
        w[0] = (1.0f - fu) - fv;
        w[1] = fu;
        w[2] = fv;
    }
    for (int t = 0; t < 3; t++) w[t] = w[t] < 0.0f ? 0.0f : w[t];
    float ws = (w[0] + w[1]) + w[2];
    if (ws < 1e-12f) ws = 1e-12f;
    const int64_t npts = (n + 1) * (n + 2) / 2;
    const int64_t *lat = job->lattice + face * npts;
    for (int t = 0; t < 3; t++) {
        sw[t] = w[t] / ws;
        smp[t] = lat[pj[t] * (n + 1) - (pj[t] * (pj[t] - 1)) / 2 + pi[t]];
    }
}

/* optics.smooth.normalize */
static inline void normalize3(float *v) {
    float l = norm3f(v);
    if (l < 1e-20f) l = 1e-20f;
    for (int t = 0; t < 3; t++) v[t] = v[t] / l;
}

/* shade._map_pixels' view directions: omega, then omega +- r u, omega +- r v (normalized),
 * u, v from optics.smooth.tangent_frame. */
static void spread_directions(const float *om, float r, float dirs[SH_MAXE][3]) {
    float h[3] = {0.0f, 0.0f, 0.0f}, u[3], v[3];
    h[fabsf(om[0]) < 0.9f ? 0 : 1] = 1.0f;
    cross3f(om, h, u);
    normalize3(u);
    cross3f(om, u, v);
    for (int t = 0; t < 3; t++) {
        dirs[0][t] = om[t];
        float ru = r * u[t], rv = r * v[t];
        dirs[1][t] = om[t] + ru;
        dirs[2][t] = om[t] + -ru;
        dirs[3][t] = om[t] + rv;
        dirs[4][t] = om[t] + -rv;
    }
    for (int j = 1; j < SH_MAXE; j++) normalize3(dirs[j]);
}

static inline v8f coeff_row(const void *coeffs, int64_t sample, int k) {
#if SH_HALF
    const uint16_t *h = (const uint16_t *)coeffs + (sample * SH_MAXK + k) * SH_CPAD;
    return (v8f)_mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)h));
#else
    return ((const v8f *)coeffs)[sample * SH_MAXK + k];
#endif
}

/* The samples and weights of point i: given, or from its face and barycentrics. */
static inline void point_samples(const void *vjob, int64_t i, int64_t *smp, float *sw) {
    const ShEvalJob *job = (const ShEvalJob *)vjob;
    if (job->samples) {
        for (int t = 0; t < 3; t++) {
            smp[t] = job->samples[i * 3 + t];
            sw[t] = job->s_w[i * 3 + t];
        }
    } else {
        interpolate_point(job, job->faces[i], job->bary + i * 3, smp, sw);
    }
}

/* A sample's frame and coefficient rows (45 x 8 float16: 720 bytes) into the cache. */
static inline void prefetch_sample(const ShEvalJob *job, int64_t sample) {
    __builtin_prefetch(job->frame + sample * 9);
    const char *c = (const char *)job->coeffs + sample * SH_MAXK * SH_CPAD * (SH_HALF ? 2 : 4);
    for (int b = 0; b < SH_MAXK * SH_CPAD * (SH_HALF ? 2 : 4); b += 64)
        __builtin_prefetch(c + b);
}

#define SH_AHEAD 2 /* points whose samples are found and prefetched ahead */
#define SH_RING (SH_AHEAD + 1)

/* The samples and weights of point i of a job (point_samples, map_samples). */
typedef void (*samples_fn)(const void *job, int64_t i, int64_t *smp, float *sw);

/* The samples of the points i .. i + SH_AHEAD of a range (slot q % SH_RING): those ahead
 * are asked into the cache while point i computes (neighbouring points, such as a
 * lattice's, need not share their samples). */
typedef struct {
    int64_t smp[SH_RING][3];
    float sw[SH_RING][3];
} SampleRing;

static inline void ring_fill(SampleRing *rg, const ShEvalJob *ev, samples_fn at,
                             const void *job, int64_t q) {
    at(job, q, rg->smp[q % SH_RING], rg->sw[q % SH_RING]);
    for (int t = 0; t < 3; t++) prefetch_sample(ev, rg->smp[q % SH_RING][t]);
}

/* Point i's slot, the points SH_AHEAD after it found (from ``begin``, the first ones). */
static inline __attribute__((always_inline)) int ring_step(
        SampleRing *rg, const ShEvalJob *ev, samples_fn at, const void *job, int64_t i,
        int64_t begin, int64_t end) {
    if (i == begin)
        for (int64_t q = begin; q < end && q < begin + SH_AHEAD; q++)
            ring_fill(rg, ev, at, job, q);
    if (i + SH_AHEAD < end) ring_fill(rg, ev, at, job, i + SH_AHEAD);
    return (int)(i % SH_RING);
}

/* A sample's coefficient row k (its channels side by side) times the window's k-th weight. */
static inline v8f windowed(const ShEvalJob *job, const v8f *wv, int64_t sample, int k) {
    return coeff_row(job->coeffs, sample, k) * wv[k];
}

/* What every point of a call shares: the constants of the basis and the window. */
typedef struct {
    ShConst cst;
    int nk;
    v8f wv[SH_MAXK];
} ShShared;

static void shared_init(const ShEvalJob *job, ShShared *sh) {
    sh_constants((int)job->order, &sh->cst);
    sh->nk = sh->cst.k;
    for (int k = 0; k < sh->nk; k++) sh->wv[k] = splat(job->weights[k]);
}

static void eval_products(const ShEvalJob *job, const ShShared *sh, const int64_t *smp,
                          const float *swt, int e, const float *yflat, v8f acc[SH_MAXE]);

/* Eq. 2 at one point: its samples smp (weights swt) for the e view directions dirs;
 * acc[j] lanes c: channel c at direction j. */
static void eval_point(const ShEvalJob *job, const ShShared *sh, const int64_t *smp,
                       const float *swt, int e, float dirs[SH_MAXE][3], v8f acc[SH_MAXE]) {
    const int order = (int)job->order, nv = (3 * e + 7) / 8;
    v8f xv[SH_NV], yv[SH_NV], zv[SH_NV];
    v8f ysh[SH_MAXK][SH_NV];
    float *xs = (float *)xv, *ys = (float *)yv, *zs = (float *)zv;
    for (int v = 0; v < SH_NV; v++) {
        xv[v] = splat(0.0f);
        yv[v] = splat(0.0f);
        zv[v] = splat(1.0f);
    }
    for (int s = 0; s < 3; s++) {
        const float *fr = job->frame + smp[s] * 9;
        for (int j = 0; j < e; j++) {
            const float *o = dirs[j];
            int d = s * e + j;
            /* einsum("ner,nsar->nsea"): sum over r in order */
            xs[d] = (o[0] * fr[0] + o[1] * fr[1]) + o[2] * fr[2];
            ys[d] = (o[0] * fr[3] + o[1] * fr[4]) + o[2] * fr[5];
            zs[d] = (o[0] * fr[6] + o[1] * fr[7]) + o[2] * fr[8];
        }
    }
    if (order == SH_MAXL && nv == SH_NV) /* the default: loops of known length, unrolled */
        sh_even(&sh->cst, SH_MAXL, SH_NV, xv, yv, zv, ysh);
    else
        sh_even(&sh->cst, order, nv, xv, yv, zv, ysh);
    eval_products(job, sh, smp, swt, e, (const float *)ysh, acc);
}

/* eval_point's products: the windowed coefficients of the three samples times their SH at
 * the e directions (yflat: ysh[k][v] lane t at (k * SH_NV + v) * 8 + t), blended. */
static void eval_products(const ShEvalJob *job, const ShShared *sh, const int64_t *smp,
                          const float *swt, int e, const float *yflat, v8f acc[SH_MAXE]) {
    const int nk = sh->nk;
    const v8f *wv = sh->wv;
    for (int j = 0; j < e; j++) acc[j] = splat(0.0f);
    for (int s = 0; s < 3; s++) {
        const float *ys0 = yflat + s * e;
        v8f sw = splat(swt[s]);
        if (e == 1) {
            /* one direction: four partial sums, so the adds do not wait on each other */
            v8f p0 = splat(0.0f), p1 = p0, p2 = p0, p3 = p0;
            int k = 0;
            for (; k + 4 <= nk; k += 4) {
                const float *yk = ys0 + k * SH_NV * 8;
                p0 += splat(yk[0]) * windowed(job, wv, smp[s], k);
                p1 += splat(yk[SH_NV * 8]) * windowed(job, wv, smp[s], k + 1);
                p2 += splat(yk[2 * SH_NV * 8]) * windowed(job, wv, smp[s], k + 2);
                p3 += splat(yk[3 * SH_NV * 8]) * windowed(job, wv, smp[s], k + 3);
            }
            for (; k < nk; k++)
                p0 += splat(ys0[k * SH_NV * 8]) * windowed(job, wv, smp[s], k);
            acc[0] += sw * ((p0 + p1) + (p2 + p3));
            continue;
        }
        if (e == SH_MAXE) {
            /* the view and its four offsets: ten partial sums held in registers (an
             * array indexed by a run-time e lives in memory, each add waiting on a
             * store), even and odd k apart */
            v8f a0 = splat(0.0f), a1 = a0, a2 = a0, a3 = a0, a4 = a0;
            v8f b0 = a0, b1 = a0, b2 = a0, b3 = a0, b4 = a0;
            int k = 0;
            for (; k + 2 <= nk; k += 2) {
                v8f w = windowed(job, wv, smp[s], k);
                v8f u = windowed(job, wv, smp[s], k + 1);
                const float *yk = ys0 + k * SH_NV * 8, *yu = yk + SH_NV * 8;
                a0 += splat(yk[0]) * w;
                a1 += splat(yk[1]) * w;
                a2 += splat(yk[2]) * w;
                a3 += splat(yk[3]) * w;
                a4 += splat(yk[4]) * w;
                b0 += splat(yu[0]) * u;
                b1 += splat(yu[1]) * u;
                b2 += splat(yu[2]) * u;
                b3 += splat(yu[3]) * u;
                b4 += splat(yu[4]) * u;
            }
            if (k < nk) {
                v8f w = windowed(job, wv, smp[s], k);
                const float *yk = ys0 + k * SH_NV * 8;
                a0 += splat(yk[0]) * w;
                a1 += splat(yk[1]) * w;
                a2 += splat(yk[2]) * w;
                a3 += splat(yk[3]) * w;
                a4 += splat(yk[4]) * w;
            }
            acc[0] += sw * (a0 + b0);
            acc[1] += sw * (a1 + b1);
            acc[2] += sw * (a2 + b2);
            acc[3] += sw * (a3 + b3);
            acc[4] += sw * (a4 + b4);
            continue;
        }
        v8f part[SH_MAXE];
        for (int j = 0; j < e; j++) part[j] = splat(0.0f);
        for (int k = 0; k < nk; k++) {
            v8f w = windowed(job, wv, smp[s], k);
            const float *yk = ys0 + k * SH_NV * 8;
            for (int j = 0; j < e; j++) part[j] += splat(yk[j]) * w;
        }
        for (int j = 0; j < e; j++) acc[j] += sw * part[j];
    }
}

static void sh_eval_range(const void *vjob, int64_t begin, int64_t end) {
    const ShEvalJob *job = (const ShEvalJob *)vjob;
    const int e = (int)job->e, nc = (int)job->c, nr = (int)job->c_rest;
    ShShared sh;
    shared_init(job, &sh);
    float dirs[SH_MAXE][3];
    v8f acc[SH_MAXE];
    SampleRing rg;
    for (int64_t i = begin; i < end; i++) {
        const int slot = ring_step(&rg, job, point_samples, job, i, begin, end);
        const int64_t *smp = rg.smp[slot];
        const float *swt = rg.sw[slot];
        if (job->spread) {
            spread_directions(job->omega + i * 3, job->spread[i], dirs);
        } else {
            for (int j = 0; j < e; j++)
                for (int t = 0; t < 3; t++) dirs[j][t] = job->omega[(i * e + j) * 3 + t];
        }
        eval_point(job, &sh, smp, swt, e, dirs, acc);
        float *out = job->out + i * e * nc;
        for (int j = 0; j < e; j++) {
            const float *a = (const float *)&acc[j];
            int cj = j == 0 ? nc : nr;
            for (int c = 0; c < cj; c++) out[j * nc + c] = a[c];
            for (int c = cj; c < nc; c++) out[j * nc + c] = 0.0f;
        }
    }
}

int64_t torchrefract_sh_eval_job_size(void) { return (int64_t)sizeof(ShEvalJob); }

int torchrefract_sh_eval_half(void) { return SH_HALF; }

int torchrefract_sh_eval(const ShEvalJob *job, int threads) {
    if (job->e < 1 || job->e > SH_MAXE || job->order < 0 || job->order > SH_MAXL
        || job->c < 1 || job->c > SH_CPAD || job->c_rest < 0 || job->c_rest > job->c
        || (job->spread && job->e != SH_MAXE) || (!job->samples && job->rate < 1))
        return -2;
    return tr_parallel_for(sh_eval_range, job, job->n, 256, threads);
}


/* The samples and weights of the q-th position mapped: its pixel's front face and
 * barycentrics. */
static inline void map_samples(const void *vjob, int64_t q, int64_t *smp, float *sw) {
    const ShMapJob *job = (const ShMapJob *)vjob;
    const int64_t p = job->sel[q], pix = job->pix[p];
    interpolate_point(&job->eval, (int64_t)job->tri[pix] - job->face_offset[job->item[p]],
                      job->gbary + pix * 3, smp, sw);
}

/* The positions [begin, end) of ``job`` with the call's shared constants ``shp``. */
static void sh_map_points(const ShMapJob *job, const ShShared *shp, int64_t begin,
                          int64_t end) {
    const ShEvalJob *ev = &job->eval;
    float dirs[SH_MAXE][3];
    v8f acc[SH_MAXE];
    SampleRing rg;
    for (int64_t q = begin; q < end; q++) {
        const int64_t p = job->sel[q], b = job->item[p];
        const float *rot = job->rotation + b * 9, *vw = job->view + p * 3;
        const int slot = ring_step(&rg, ev, map_samples, job, q, begin, end);
        const int64_t *smp = rg.smp[slot];
        const float *swt = rg.sw[slot];
        float om[3];
        for (int t = 0; t < 3; t++) /* view @ R: world -> object */
            om[t] = (vw[0] * rot[t] + vw[1] * rot[3 + t]) + vw[2] * rot[6 + t];
        const int rough = job->rough[b] != 0;
        float var_v = 0.0f, r = 0.0f;
        if (rough) {
            var_v = job->var_view[p];
            r = sqrtf(var_v);
            r = r > job->max_spread ? job->max_spread : r;
            spread_directions(om, r, dirs);
        } else {
            for (int t = 0; t < 3; t++) dirs[0][t] = om[t];
        }
        eval_point(ev, shp, smp, swt, rough ? SH_MAXE : 1, dirs, acc);
        const float *v0 = (const float *)&acc[0];
        float center[3] = {v0[0], v0[1], v0[2]};
        normalize3(center);
        float var_geo = 0.0f;
        if (rough) {
            float r2 = r * r;
            r2 = r2 < 1e-12f ? 1e-12f : r2;
            float sum = 0.0f;
            for (int j = 1; j < SH_MAXE; j++) { /* chords between the exits ~ angles */
                const float *vj = (const float *)&acc[j];
                float d[3] = {vj[0], vj[1], vj[2]};
                normalize3(d);
                for (int t = 0; t < 3; t++) d[t] = d[t] - center[t];
                sum += (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2];
            }
            var_geo = sum / 4.0f * (var_v / r2);
            /* the rough interfaces met inside: Beckmann slopes' variance per axis
             * alpha^2 / 2 times the path's gain */
            const float a = job->alpha[p], gain = v0[6] > 0.0f ? v0[6] : 0.0f;
            var_geo = var_geo + (0.5f * a * a) * gain;
        }
        if (norm3f(v0) < 1e-3f) /* ringing cancelled the vector: go straight */
            for (int t = 0; t < 3; t++) center[t] = -om[t];
        float *dir = job->direction + p * 3;
        for (int t = 0; t < 3; t++) /* object -> world: R center */
            dir[t] = (center[0] * rot[t * 3] + center[1] * rot[t * 3 + 1])
                     + center[2] * rot[t * 3 + 2];
        const float len = v0[3] * job->radius * job->scale[b];
        job->length[p] = len > 0.0f ? len : 0.0f;
        job->cos_exit[p] = v0[4] < 0.0f ? 0.0f : (v0[4] > 1.0f ? 1.0f : v0[4]);
        job->throughput[p] = v0[5] < 0.0f ? 0.0f : (v0[5] > 1.0f ? 1.0f : v0[5]);
        job->var_geo[p] = var_geo;
    }
}

static void sh_map_range(const void *vjob, int64_t begin, int64_t end) {
    const ShMapJob *job = (const ShMapJob *)vjob;
    ShShared sh;
    shared_init(&job->eval, &sh);
    sh_map_points(job, &sh, begin, end);
}

int64_t torchrefract_sh_shared_size(void) { return (int64_t)sizeof(ShShared); }

void torchrefract_sh_shared_init(const ShMapJob *job, void *shared) {
    shared_init(&job->eval, (ShShared *)shared);
}

void torchrefract_sh_map_range(const ShMapJob *job, const void *shared, int64_t begin,
                               int64_t end) {
    sh_map_points(job, (const ShShared *)shared, begin, end);
}

int64_t torchrefract_sh_map_job_size(void) { return (int64_t)sizeof(ShMapJob); }

int torchrefract_sh_map(const ShMapJob *job, int threads) {
    const ShEvalJob *ev = &job->eval;
    if (ev->order < 0 || ev->order > SH_MAXL || ev->c < 7 || ev->c > SH_CPAD || ev->rate < 1)
        return -2;
    return tr_parallel_for(sh_map_range, job, job->n, 256, threads);
}
