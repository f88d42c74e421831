/* The box filter of supersampled buffers (result.box, result.masked_box, result.plan_box):
 * each pixel the mean of its n x n sub-pixels, in one pass over the buffer. The tensor
 * code's float32 operations and order (the sub-pixels summed row-major, then divided by
 * n * n; masked: each value times its mask as 0 or 1, over the covered fraction, 0 where
 * none is covered), so the bits are the same; torch's strided adds over a buffer of few
 * channels cost many reads of it (docs/decisions.md, "Adaptive 2x2"). */

#include "common.h"

typedef struct {
    int64_t b, h, w, n, c;      /* pixels (B, h, w), n x n sub-pixels each, c channels */
    const float *x;             /* (B, h n, w n, c) */
    const uint8_t *mask;        /* (B, h n, w n) or NULL: the plain box */
    const uint8_t *uniform;     /* (B, h, w) or NULL: pixels whose value is their first
                                 * sub-pixel's alone (adaptive.plan; covered throughout) */
    float *out;                 /* (B, h, w, c) */
} BoxJob;

/* The pixel's n x n sub-pixel values of channel k summed row-major (times their masks). */
static inline float block_sum(const float *restrict x, const uint8_t *restrict mask,
                              int64_t first, int64_t n, int64_t nw, int64_t c, int64_t k) {
    float s = mask ? x[first * c + k] * (mask[first] ? 1.0f : 0.0f) : x[first * c + k];
    for (int64_t i = 0; i < n; i++)
        for (int64_t jj = 0; jj < n; jj++)
            if (i || jj) {
                int64_t q = first + i * nw + jj;
                s = mask ? s + x[q * c + k] * (mask[q] ? 1.0f : 0.0f) : s + x[q * c + k];
            }
    return s;
}

/* n = 2 (the default supersampling) written out: the same operations in the same order,
 * dividing by 4 as multiplying by 0.25 (both exact: the same correctly rounded value). */
static void box2_range(const BoxJob *j, int64_t begin, int64_t end) {
    const float *restrict xs = j->x;
    const uint8_t *restrict mask = j->mask, *restrict uniform = j->uniform;
    float *restrict out = j->out;
    const int64_t c = j->c, h = j->h, w = j->w, nw = 2 * w;
    for (int64_t row = begin; row < end; row++) {
        int64_t bi = row / h, y = row - bi * h, s0 = (bi * h * 2 + y * 2) * nw;
        const float *r0 = xs + s0 * c, *r1 = xs + (s0 + nw) * c;
        const uint8_t *m0 = mask ? mask + s0 : NULL, *m1 = mask ? mask + s0 + nw : NULL;
        const uint8_t *u = uniform ? uniform + row * w : NULL;
        float *o = out + row * w * c;
        for (int64_t x = 0; x < w; x++, r0 += 2 * c, r1 += 2 * c, o += c) {
            if (u && u[x]) {
                for (int64_t k = 0; k < c; k++) o[k] = (((r0[k] + r0[k]) + r0[k]) + r0[k]) * 0.25f;
                continue;
            }
            if (!m0) {
                for (int64_t k = 0; k < c; k++)
                    o[k] = (((r0[k] + r0[c + k]) + r1[k]) + r1[c + k]) * 0.25f;
                continue;
            }
            float a = m0[2 * x] ? 1.0f : 0.0f, b = m0[2 * x + 1] ? 1.0f : 0.0f;
            float d = m1[2 * x] ? 1.0f : 0.0f, e = m1[2 * x + 1] ? 1.0f : 0.0f;
            float cnt = ((a + b) + d) + e;
            if (cnt == 0.0f) {
                for (int64_t k = 0; k < c; k++) o[k] = 0.0f;
                continue;
            }
            float den = cnt * 0.25f;
            for (int64_t k = 0; k < c; k++)
                o[k] = ((((r0[k] * a + r0[c + k] * b) + r1[k] * d) + r1[c + k] * e) * 0.25f) / den;
        }
    }
}

/* n = 1 with a mask: each value where covered, else 0 (the tensor code's where). */
static void select_range(const BoxJob *j, int64_t begin, int64_t end) {
    const int64_t c = j->c, w = j->w;
    for (int64_t row = begin; row < end; row++) {
        const float *x = j->x + row * w * c;
        const uint8_t *m = j->mask + row * w;
        float *o = j->out + row * w * c;
        for (int64_t p = 0; p < w; p++)
            for (int64_t k = 0; k < c; k++) o[p * c + k] = m[p] ? x[p * c + k] : 0.0f;
    }
}

static void box_range(const void *job, int64_t begin, int64_t end) {
    const BoxJob *j = (const BoxJob *)job;
    if (j->n == 1) {
        select_range(j, begin, end);
        return;
    }
    if (j->n == 2) {
        box2_range(j, begin, end);
        return;
    }
    const float *restrict xs = j->x;
    const uint8_t *restrict mask = j->mask, *restrict uniform = j->uniform;
    float *restrict out = j->out;
    const int64_t n = j->n, c = j->c, h = j->h, w = j->w, nw = w * n, nn = n * n;
    const float inv = (float)nn;
    for (int64_t row = begin; row < end; row++) {  /* a row of pixels: (bi, y) */
        int64_t bi = row / h, y = row - bi * h;
        int64_t s0 = (bi * h * n + y * n) * nw;  /* the row's first sub-pixel, flat */
        for (int64_t x = 0; x < w; x++) {
            int64_t p = row * w + x, first = s0 + x * n;
            float *o = out + p * c;
            if (uniform && uniform[p]) {  /* n*n copies of the first, summed */
                const float *v = xs + first * c;
                for (int64_t k = 0; k < c; k++) {
                    float s = v[k];
                    for (int64_t i = 1; i < nn; i++) s = s + v[k];
                    o[k] = s / inv;
                }
                continue;
            }
            if (!mask) {
                for (int64_t k = 0; k < c; k++) o[k] = block_sum(xs, NULL, first, n, nw, c, k) / inv;
                continue;
            }
            float d = mask[first] ? 1.0f : 0.0f;
            for (int64_t i = 0; i < n; i++)
                for (int64_t jj = 0; jj < n; jj++)
                    if (i || jj) d = d + (mask[first + i * nw + jj] ? 1.0f : 0.0f);
            if (d == 0.0f) {  /* none covered: 0 (the tensor code's where) */
                for (int64_t k = 0; k < c; k++) o[k] = 0.0f;
                continue;
            }
            float den = d / inv;
            for (int64_t k = 0; k < c; k++)
                o[k] = (block_sum(xs, mask, first, n, nw, c, k) / inv) / den;
        }
    }
}

int torchrefract_box(const BoxJob *job, int threads) {
    return tr_parallel_for_grain(box_range, job, job->b * job->h, 16, threads, 1);
}

int64_t torchrefract_box_job_size(void) { return (int64_t)sizeof(BoxJob); }
