/* Relighting's texel reads at a rotation (matte/relight.py, ``_Group.reads``): per
 * lookup its u (its lobe's rotation-0 azimuth shifted, ``relight._shifted``, or its lobe's
 * given u), the column that follows by the lookups' grid and ``grid_sample``'s
 * unnormalization, and its four texel indices and bilinear weights; written out (``idx``,
 * ``wts``), or gathered at once (``tex`` given: ``_Taps.values``), each lookup's value the
 * weighted sum of its four texels as ``F.embedding_bag`` (mode sum, per-sample weights)
 * sums them on the CPU: w0 t0, then a fused multiply-add per further texel (measured:
 * the same bits).
 *
 * The same operations, in the same order and types, as the tensor code, which stays the
 * reference (tests/test_relight.py holds this kernel to it: indices and weights equal,
 * values equal): the shift in float64 rounded once to float32, then the column's float32
 * steps one by one (no contraction, no fast-math: native.FLAGS); the scalars as torch
 * casts a Python number for a float32 tensor (to float32). */

#include "common.h"

typedef struct {
    int64_t n;                  /* lookups */
    const double *u0;           /* (n,) each lookup's lobe's u at rotation 0 (shifted u) */
    const int64_t *view;        /* (n,) each lookup's view, or NULL: rot[0] for all */
    const float *rot;           /* (B,) the rotations, degrees */
    int64_t nrot;               /* B */
    const float *u;             /* (S,) per-lobe u (the renderer's), or NULL: shifted u0 */
    const int64_t *lobe;        /* (n,) each lookup's lobe (read with u only) */
    int plain;                  /* envmap.lookup's grid (else sg_lookup_env's sample()) */
    int64_t w_map;              /* plain: the map's width */
    int64_t cols, last;         /* the image's (padded) columns; its last texel's index */
    const float *x0p1, *w;      /* (n,) SG: the level's x0 + 1 and width */
    const int32_t *row;         /* (n,) the upper row's first texel index */
    const float *sn;            /* (n, 2) the rows' weights */
    int32_t *idx;               /* (n, 4) out: texel indices (with tex NULL) */
    float *wts;                 /* (n, 4) out: weights (with tex NULL) */
    const float *tex;           /* (T, 3) texels (relight._texels_last), or NULL */
    float *vals;                /* (n, 3) out: each lookup's value (with tex) */
    int32_t *status;            /* (1,) out, with tex: 1 where an index was out of the
                                 * image (a NaN u: the caller runs its tensor code) */
} RelightJob;

/* One range of lookups, for the mode given by constants (``shifted``: u0 shifted, else
 * the lobes' u; ``viewed``: one rotation per view; ``plain``: envmap.lookup's grid;
 * ``fast``: floor() as a truncation, where every u0 + rot / 360 is within 2^31 of 0 (every
 * |rot| < 1e11) and no column is NaN; else the C library's floor, and NaN carried as
 * torch carries it), so that each mode's loop is compiled on its own; the fast ones are
 * vectorized (no operation under a condition, only selects). Returns whether a column was
 * NaN (the fast mode's results are then wrong: the range is computed again in the exact
 * one). Lookup i's indices and weights go to idx, wts at 4 (i - begin). */
static inline __attribute__((always_inline)) int reads_body(
        const RelightJob *j, int64_t begin, int64_t end, const int shifted, const int viewed,
        const int plain, const int fast, int32_t *restrict idx, float *restrict wts) {
    const float cols_m1 = (float)(j->cols - 1);
    const float half = (float)((double)(j->cols - 1) / 2.0);  /* (cols - 1) / 2 */
    const float wm = (float)j->w_map, wm1 = (float)(j->w_map + 1);
    const int32_t cols = (int32_t)j->cols, last = (int32_t)j->last;
    const double *restrict u0 = j->u0;
    const int64_t *restrict view = j->view, *restrict lobe = j->lobe;
    const float *restrict rot = j->rot, *restrict uu = j->u, *restrict x0p1 = j->x0p1,
                *restrict wl = j->w, *restrict sn = j->sn;
    const int32_t *restrict row = j->row;
    const double r0 = (double)rot[0] * (1.0 / 360.0);
    int bad = 0;
    for (int64_t i = begin; i < end; i++) {
        float x;
        if (shifted) {
            /* relight._shifted: u = u0 + rot.double() * (1 / 360); (u - floor(u)).float() */
            double r = viewed ? (double)rot[view[i]] * (1.0 / 360.0) : r0;
            double ud = u0[i] + r;
            double fl;
            if (fast) {  /* floor(ud): the truncation, one less where that is above */
                double t = (double)(int32_t)ud;
                fl = t - (t > ud ? 1.0 : 0.0);
            } else {
                fl = floor(ud);
            }
            x = (float)(ud - fl);
        } else {
            x = uu[lobe[i]];  /* u.index_select(0, lobe) */
        }
        if (plain) {  /* x = u W - 0.5 + 1; gx = 2 x / (W + 1) - 1 */
            x = x * wm; x = x - 0.5f; x = x + 1.0f; x = x * 2.0f; x = x / wm1; x = x - 1.0f;
        } else {  /* x = x0 + 1 + u w - 0.5; gx = 2 x / (cols - 1) - 1 */
            x = x * wl[i]; x = x + x0p1[i]; x = x - 0.5f; x = x * 2.0f;
            x = x / cols_m1; x = x - 1.0f;
        }
        /* ix = (gx + 1) (cols - 1) / 2 clamped to [0, cols - 1] (torch's clamp keeps NaN);
         * x_w = floor(ix), we = ix - x_w (the right column's weight), e = 1 - we;
         * c = x_w.to(int32) */
        float ix0 = (x + 1.0f) * half, x_w, we, e;
        int32_t c;
        if (fast) {  /* ix in [0, cols - 1] (< 2^31): floor is the truncation */
            bad |= ix0 != ix0;
            float ix = ix0 >= 0.0f ? ix0 : 0.0f;
            ix = ix > cols_m1 ? cols_m1 : ix;
            c = (int32_t)ix;
            x_w = (float)c;
            we = ix - x_w;
            e = 1.0f - we;
        } else {
            float ix = ix0 < 0.0f ? 0.0f : ix0;
            ix = ix > cols_m1 ? cols_m1 : ix;
            x_w = floorf(ix);
            we = ix - x_w;
            e = 1.0f - we;
            c = x_w == x_w ? (int32_t)x_w : INT32_MIN;  /* NaN: x86's INT32_MIN, no UB */
        }
        /* taps (row, col), (row, col + 1), (row + 1, col), (row + 1, col + 1), each
         * clamp_(max=last); weights the rows' times the columns' */
        const int64_t k = i - begin;
        int32_t i0 = row[i] + c;
        int32_t i1 = i0 + 1, i2 = i0 + cols, i3 = i0 + cols + 1;
        idx[4 * k] = i0 > last ? last : i0;
        idx[4 * k + 1] = i1 > last ? last : i1;
        idx[4 * k + 2] = i2 > last ? last : i2;
        idx[4 * k + 3] = i3 > last ? last : i3;
        const float s0 = sn[2 * i], s1 = sn[2 * i + 1];
        wts[4 * k] = s0 * e;
        wts[4 * k + 1] = s0 * we;
        wts[4 * k + 2] = s1 * e;
        wts[4 * k + 3] = s1 * we;
    }
    return bad;
}

/* Lookups [begin, end): indices and weights into idx, wts (at 4 (i - begin)). Returns
 * whether the exact mode ran (a NaN column, where an index may be outside the image). */
static int reads_into(const RelightJob *j, int64_t begin, int64_t end, int32_t *idx,
                      float *wts) {
    const int plain = j->plain != 0, viewed = j->view != NULL;
    /* |u0| <= 0.5 (an azimuth / 2 pi): u0 + rot / 360 is within 2^31 of 0 */
    int small = 1;
    for (int64_t b = 0; b < j->nrot; b++) small &= fabsf(j->rot[b]) < 1e11f;
    int bad = 1;
    if (j->u != NULL)
        bad = plain ? reads_body(j, begin, end, 0, 0, 1, 1, idx, wts)
                    : reads_body(j, begin, end, 0, 0, 0, 1, idx, wts);
    else if (small && !viewed)
        bad = plain ? reads_body(j, begin, end, 1, 0, 1, 1, idx, wts)
                    : reads_body(j, begin, end, 1, 0, 0, 1, idx, wts);
    else if (small)
        bad = plain ? reads_body(j, begin, end, 1, 1, 1, 1, idx, wts)
                    : reads_body(j, begin, end, 1, 1, 0, 1, idx, wts);
    if (bad) {  /* a NaN column, or a rotation of 1e11 degrees or more */
        if (j->u != NULL) reads_body(j, begin, end, 0, 0, plain, 0, idx, wts);
        else reads_body(j, begin, end, 1, viewed, plain, 0, idx, wts);
    }
    return bad;
}

static void reads_range(const void *job, int64_t begin, int64_t end) {
    const RelightJob *j = (const RelightJob *)job;
    reads_into(j, begin, end, j->idx + 4 * begin, j->wts + 4 * begin);
}

#define TR_RELIGHT_BLOCK 256

/* Lookups [begin, end) in blocks: their reads (reads_into), then each lookup's value, as
 * F.embedding_bag sums its bag: w0 t0, then fmaf(w_k, t_k, sum) for k = 1, 2, 3. */
static void values_range(const void *job, int64_t begin, int64_t end) {
    const RelightJob *j = (const RelightJob *)job;
    int32_t idx[4 * TR_RELIGHT_BLOCK];
    float wts[4 * TR_RELIGHT_BLOCK];
    const uint32_t last = (uint32_t)j->last;
    for (int64_t b0 = begin; b0 < end; b0 += TR_RELIGHT_BLOCK) {
        int64_t b1 = b0 + TR_RELIGHT_BLOCK < end ? b0 + TR_RELIGHT_BLOCK : end;
        const int check = reads_into(j, b0, b1, idx, wts);
        for (int64_t i = b0; i < b1; i++) {
            const int32_t *ix = idx + 4 * (i - b0);
            const float *w = wts + 4 * (i - b0);
            float *out = j->vals + 3 * i;
            if (check && ((uint32_t)ix[0] > last || (uint32_t)ix[1] > last
                          || (uint32_t)ix[2] > last || (uint32_t)ix[3] > last)) {
                /* (embedding_bag raises) */
                __atomic_store_n(j->status, 1, __ATOMIC_RELAXED);
                out[0] = out[1] = out[2] = 0.0f;
                continue;
            }
            const float *t0 = j->tex + 3 * (int64_t)ix[0], *t1 = j->tex + 3 * (int64_t)ix[1],
                        *t2 = j->tex + 3 * (int64_t)ix[2], *t3 = j->tex + 3 * (int64_t)ix[3];
            for (int c = 0; c < 3; c++) {
                float acc = w[0] * t0[c];
                acc = fmaf(w[1], t1[c], acc);
                acc = fmaf(w[2], t2[c], acc);
                acc = fmaf(w[3], t3[c], acc);
                out[c] = acc;
            }
        }
    }
}

int torchrefract_relight_reads(RelightJob *job, int threads) {
    if (job->tex != NULL)
        return tr_parallel_for(values_range, job, job->n, 16384, threads);
    return tr_parallel_for(reads_range, job, job->n, 16384, threads);
}

int64_t torchrefract_relight_reads_job_size(void) { return (int64_t)sizeof(RelightJob); }
