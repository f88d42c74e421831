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

/* Buffers of one frame filtered 2 x 2 (native.boxes; native.box at n = 2 is one item):
 * each pixel's coverage of the two masks (and of both) counted once, then every item with
 * box_range's operations in its order, the sub-pixels summed row-major and divided by 4
 * as multiplied by 0.25 (both exact: the same correctly rounded value). */
typedef struct {
    int64_t b, h, w, nitems;
    const uint8_t *masks[2];     /* (B, 2h, 2w) each, or NULL where no item uses it */
    const uint8_t *uniform;      /* (B, h, w) or NULL */
    const float *const *x;       /* (nitems,) each (B, 2h, 2w, c); NULL: the coverage */
    float *const *out;           /* (nitems,) each (B, h, w, c) */
    const int64_t *c;            /* (nitems,) channels */
    const int64_t *mask_of;      /* (nitems,) 0 none, 1 masks[0], 2 masks[1], 3 both */
    const uint8_t *use_uniform;  /* (nitems,) 1: the uniform pixels hold their first */
} BoxesJob;

/* CHUNK pixels of a row at a time: their masks' weights, then each item over them. */
#define CHUNK 64

/* One item over pixels [0, m) of a chunk, its channels C, masked (MASKED) and with the
 * uniform pixels' first sub-pixel (UNI) constants, so that each loop has no branch and
 * the compiler vectorizes it over the pixels: every case computed, then selected (the
 * values of box_range's branches). r0, r1: the chunk's first sub-pixel rows; wt: the
 * item's mask's four sub-pixel weights per pixel; uni: the uniform flags. */
#if defined(__GNUC__) && !defined(__clang__)
/* GCC if-converts the selects only without trapping math (no value changes: it may then
 * compute both sides of a select, as written here anyway). */
#define TR_NO_TRAPS __attribute__((optimize("no-trapping-math")))
#else
#define TR_NO_TRAPS
#endif

#define BOXES_ITEM(NAME, C, MASKED, UNI)                                                      \
    TR_NO_TRAPS static void NAME(const float *restrict r0, const float *restrict r1, float *restrict o,   \
                     const float (*restrict wt)[CHUNK], const uint8_t *restrict uni, int m,   \
                     int64_t cc) {                                                            \
        const int64_t c = (C) > 0 ? (C) : cc;                                                 \
        for (int64_t k = 0; k < c; k++)                                                       \
            for (int x = 0; x < m; x++) {                                                     \
                float v00 = r0[2 * x * c + k], v01 = r0[(2 * x + 1) * c + k];                 \
                float v10 = r1[2 * x * c + k], v11 = r1[(2 * x + 1) * c + k];                 \
                float v;                                                                      \
                if (MASKED) {                                                                 \
                    float a = wt[0][x], b = wt[1][x], d = wt[2][x], e = wt[3][x];             \
                    float cnt = ((a + b) + d) + e;                                            \
                    /* (divided by 1 where none is covered: no trap, so no branch) */         \
                    float den = cnt == 0.0f ? 1.0f : cnt * 0.25f;                             \
                    float q = ((((v00 * a + v01 * b) + v10 * d) + v11 * e) * 0.25f) / den;    \
                    v = cnt == 0.0f ? 0.0f : q;                                               \
                } else {                                                                      \
                    v = (((v00 + v01) + v10) + v11) * 0.25f;                                  \
                }                                                                             \
                if (UNI) {                                                                    \
                    float f = (((v00 + v00) + v00) + v00) * 0.25f;                            \
                    v = uni[x] ? f : v;                                                       \
                }                                                                             \
                o[x * c + k] = v;                                                             \
            }                                                                                 \
    }
#define BOXES_ITEMS(C, S)                                                                     \
    BOXES_ITEM(boxes_##S##_p, C, 0, 0)                                                        \
    BOXES_ITEM(boxes_##S##_pu, C, 0, 1)                                                       \
    BOXES_ITEM(boxes_##S##_m, C, 1, 0)                                                        \
    BOXES_ITEM(boxes_##S##_mu, C, 1, 1)                                                       \
    static void boxes_##S(const float *r0, const float *r1, float *o,                        \
                          const float (*wt)[CHUNK], const uint8_t *uni, int m, int64_t c) {   \
        if (wt) (uni ? boxes_##S##_mu : boxes_##S##_m)(r0, r1, o, wt, uni, m, c);             \
        else (uni ? boxes_##S##_pu : boxes_##S##_p)(r0, r1, o, wt, uni, m, c);                \
    }
BOXES_ITEMS(1, c1)
BOXES_ITEMS(3, c3)
BOXES_ITEMS(0, cn)

static void boxes_range(const void *job, int64_t begin, int64_t end) {
    const BoxesJob *j = (const BoxesJob *)job;
    const int64_t h = j->h, w = j->w, nw = 2 * w;
    float wt[4][4][CHUNK];  /* per mask kind (1-3): the four sub-pixels' 0 / 1 */
    int used = 0;  /* the mask kinds the items read (bits 1-3) */
    for (int64_t it = 0; it < j->nitems; it++) used |= 1 << (int)j->mask_of[it];
    for (int64_t row = begin; row < end; row++) {
        int64_t bi = row / h, y = row - bi * h, s0 = (bi * h * 2 + y * 2) * nw;
        for (int64_t x0 = 0; x0 < w; x0 += CHUNK) {
            int m = (int)(w - x0 < CHUNK ? w - x0 : CHUNK);
            int64_t q0 = s0 + 2 * x0, p0 = row * w + x0;
            for (int kind = 1; kind <= 3; kind++) {  /* bool bytes are 0 or 1 */
                if (!(used & (1 << kind))) continue;
                const uint8_t *ma = kind == 3 ? j->masks[0] : j->masks[kind - 1];
                const uint8_t *mb = kind == 3 ? j->masks[1] : ma;
                for (int k = 0; k < 4; k++) {
                    const uint8_t *pa = ma + q0 + (k >> 1) * nw + (k & 1);
                    const uint8_t *pb = mb + q0 + (k >> 1) * nw + (k & 1);
                    float *o = wt[kind][k];
                    for (int x = 0; x < m; x++) o[x] = (float)(pa[2 * x] & pb[2 * x]);
                }
            }
            const uint8_t *uni = j->uniform ? j->uniform + p0 : NULL;
            for (int64_t it = 0; it < j->nitems; it++) {
                int64_t c = j->c[it], mk = j->mask_of[it];
                float *o = j->out[it] + p0 * c;
                if (!j->x[it]) {  /* the coverage: box of the mask as 0 / 1 */
                    for (int x = 0; x < m; x++)
                        o[x] = (((wt[mk][0][x] + wt[mk][1][x]) + wt[mk][2][x]) + wt[mk][3][x])
                               * 0.25f;
                    continue;
                }
                const float *r0 = j->x[it] + q0 * c, *r1 = r0 + nw * c;
                const float (*wi)[CHUNK] = mk ? (const float (*)[CHUNK])wt[mk] : NULL;
                const uint8_t *u = j->use_uniform[it] ? uni : NULL;
                if (c == 1) boxes_c1(r0, r1, o, wi, u, m, c);
                else if (c == 3) boxes_c3(r0, r1, o, wi, u, m, c);
                else boxes_cn(r0, r1, o, wi, u, m, c);
            }
        }
    }
}

int torchrefract_boxes(const BoxesJob *job, int threads) {
    return tr_parallel_for_grain(boxes_range, job, job->b * job->h, 16, threads, 1);
}

int64_t torchrefract_boxes_job_size(void) { return (int64_t)sizeof(BoxesJob); }

int torchrefract_box(const BoxJob *job, int threads) {
    return tr_parallel_for_grain(box_range, job, job->b * job->h, 16, threads, 1);
}

int64_t torchrefract_box_job_size(void) { return (int64_t)sizeof(BoxJob); }

/* result.pixel_passes at one sample per pixel, in one sweep instead of six tensor ops:
 * the front coverage as 0 / 1, the thickness (back minus front distance clamped at 0, as
 * torch's clamp: NaN stays; 0 where a layer is empty: masked_box at n = 1), and the
 * roughness and IOR times the coverage. The tensor code's float32 operations: the same
 * bits. */
typedef struct {
    int64_t n, hw;                      /* pixels (B*H*W), per view */
    const uint8_t *front_mask, *back_mask;
    const float *front_dist, *back_dist;
    const float *rough;                 /* (B*H*W,), or (B,): per_pixel 0 */
    int per_pixel;
    const float *ior;                   /* (B,) */
    float *coverage, *thickness, *roughness, *ior_out;  /* out, (B*H*W,) each */
} OneSampleJob;

static void one_sample_range(const void *job, int64_t begin, int64_t end) {
    const OneSampleJob *j = (const OneSampleJob *)job;
    for (int64_t b = begin / j->hw, p = begin; p < end; b++) {
        int64_t stop = (b + 1) * j->hw < end ? (b + 1) * j->hw : end;
        const float ior = j->ior[b], rough_b = j->per_pixel ? 0.0f : j->rough[b];
        for (; p < stop; p++) {
            float fm = j->front_mask[p] ? 1.0f : 0.0f;
            float d = j->back_dist[p] - j->front_dist[p];
            float t = d < 0.0f ? 0.0f : d;
            j->coverage[p] = fm;
            j->thickness[p] = j->front_mask[p] && j->back_mask[p] ? t : 0.0f;
            j->roughness[p] = fm * (j->per_pixel ? j->rough[p] : rough_b);
            j->ior_out[p] = fm * ior;
        }
    }
}

int torchrefract_one_sample(const OneSampleJob *job, int threads) {
    return tr_parallel_for(one_sample_range, job, job->n, 16384, threads);
}

int64_t torchrefract_one_sample_job_size(void) { return (int64_t)sizeof(OneSampleJob); }

/* optics.ndf.build_box_mips in one call: level l + 1 is the 2 x 2 sums of level l's
 * (ceil mode: an odd size's last row or column sums what it has), as avg_pool2d with
 * divisor_override 1 adds them (from 0, row by row: ((0 + x00) + x01) + x10) + x11), and
 * level l is handed out divided by 4^l (exact: a power of two), once every level's sums
 * are made. */
typedef struct {
    int64_t b, c, nlevels;
    const int64_t *hw;          /* (nlevels, 2) each level's rows and columns */
    float *const *out;          /* (nlevels,) each (B, h_l, w_l, c); out[0] is level 0, read */
    int64_t level;              /* the level being made (set per pass) */
} MipsJob;

static void mips_range(const void *job, int64_t begin, int64_t end) {
    const MipsJob *j = (const MipsJob *)job;
    const int64_t l = j->level, c = j->c;
    const int64_t ph = j->hw[2 * (l - 1)], pw = j->hw[2 * (l - 1) + 1];
    const int64_t h = j->hw[2 * l], w = j->hw[2 * l + 1];
    const float *src = j->out[l - 1];
    float *dst = j->out[l];
    for (int64_t row = begin; row < end; row++) {  /* (view, y) of level l */
        int64_t bi = row / h, y = row - bi * h;
        const float *r0 = src + (bi * ph + 2 * y) * pw * c;
        const float *r1 = 2 * y + 1 < ph ? r0 + pw * c : NULL;
        float *o = dst + row * w * c;
        for (int64_t x = 0; x < w; x++) {
            int right = 2 * x + 1 < pw;
            const float *a = r0 + 2 * x * c;
            for (int64_t k = 0; k < c; k++) {
                float s = 0.0f + a[k];
                if (right) s += a[c + k];
                if (r1) {
                    s += r1[2 * x * c + k];
                    if (right) s += r1[(2 * x + 1) * c + k];
                }
                o[x * c + k] = s;
            }
        }
    }
}

static void scale_range(const void *job, int64_t begin, int64_t end) {
    const MipsJob *j = (const MipsJob *)job;
    float *x = j->out[j->level], d = 1.0f;
    for (int64_t i = 0; i < j->level; i++) d *= 4.0f;
    for (int64_t i = begin; i < end; i++) x[i] = x[i] / d;
}

int torchrefract_mips(MipsJob *job, int threads) {
    for (int64_t l = 1; l < job->nlevels; l++) {  /* the sums, each from the last */
        job->level = l;
        if (tr_parallel_for_grain(mips_range, job, job->b * job->hw[2 * l], 4, threads, 1))
            return -1;
    }
    for (int64_t l = 1; l < job->nlevels; l++) {  /* then each level divided by 4^l */
        job->level = l;
        if (tr_parallel_for(scale_range, job, job->b * job->hw[2 * l] * job->hw[2 * l + 1] *
                            job->c, 65536, threads))
            return -1;
    }
    return 0;
}

int64_t torchrefract_mips_job_size(void) { return (int64_t)sizeof(MipsJob); }

/* sparse._put: rows of several buffers written over others at chosen rows, in one pass
 * (torch's index_select and index_copy_ per buffer, single-threaded, took most of the
 * samples' write-back): slot s of each source goes to row dst[s] of its destination
 * (dst[s] < 0: none), ``ch[k]`` floats a row; the same values as the copies. */
typedef struct {
    int64_t n, nbuf;            /* slots; buffers */
    const int64_t *dst;         /* (n,) destination row per slot, -1: none */
    float *const *out;          /* (nbuf,) each (rows, ch[k]) */
    const float *const *src;    /* (nbuf,) each (n, ch[k]) */
    const int64_t *ch;          /* (nbuf,) */
} PutRowsJob;

static void put_rows_range(const void *job, int64_t begin, int64_t end) {
    const PutRowsJob *j = (const PutRowsJob *)job;
    for (int64_t k = 0; k < j->nbuf; k++) {
        int64_t c = j->ch[k];
        float *o = j->out[k];
        const float *x = j->src[k];
        for (int64_t s = begin; s < end; s++) {
            int64_t d = j->dst[s];
            if (d < 0) continue;
            for (int64_t q = 0; q < c; q++) o[d * c + q] = x[s * c + q];
        }
    }
}

int torchrefract_put_rows(const PutRowsJob *job, int threads) {
    return tr_parallel_for(put_rows_range, job, job->n, 8192, threads);
}

int64_t torchrefract_put_rows_job_size(void) { return (int64_t)sizeof(PutRowsJob); }
