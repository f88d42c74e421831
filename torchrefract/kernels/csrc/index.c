/* The set elements of a frame-sized mask as flat indices, in order, with each one's view
 * (geometry/gbuffer.py's GBuffer.object_index and object_views): what
 * ``mask.nonzero()`` and ``idx // (H * W)`` give, in two sweeps on all threads instead of
 * torch's one-threaded nonzero and an int64 division per element.
 *
 * ``mask_count`` counts each block's set elements and turns the counts into each block's
 * first slot (exclusive prefix sums) and the total; the caller allocates that many, then
 * ``mask_index`` writes every block's indices from its first slot. */

#include <string.h>

#include "common.h"

typedef struct {
    int64_t n, hw, block;       /* elements, elements a view, elements a block */
    const uint8_t *mask;        /* (N,) 0 / 1 (torch.bool) */
    int64_t *first;             /* (ceil(N / block),) count: out; index: in */
    int64_t total;              /* count: out */
    int64_t *idx, *view;        /* (total,) index: out */
} MaskJob;

static inline int64_t block_end(const MaskJob *j, int64_t k) {
    int64_t e = (k + 1) * j->block;
    return e < j->n ? e : j->n;
}

static void count_range(const void *job, int64_t begin, int64_t end) {
    const MaskJob *j = (const MaskJob *)job;
    for (int64_t k = begin; k < end; k++) {
        uint32_t c = 0;  /* a block holds fewer than 2^32 elements (the caller's) */
        for (int64_t p = k * j->block, e = block_end(j, k); p < e; p++) c += j->mask[p];
        j->first[k] = (int64_t)c;
    }
}

/* Entry point (ctypes, native.py): the blocks' counts on ``threads`` threads, then their
 * first slots and the total. */
int torchrefract_mask_count(MaskJob *job, int threads) {
    int64_t blocks = (job->n + job->block - 1) / job->block;
    int rc = tr_parallel_for_grain(count_range, job, blocks, 2, threads, 1);
    int64_t at = 0;
    for (int64_t k = 0; k < blocks; k++) {
        int64_t c = job->first[k];
        job->first[k] = at;
        at += c;
    }
    job->total = at;
    return rc;
}

int64_t torchrefract_mask_count_job_size(void) { return (int64_t)sizeof(MaskJob); }

static void index_range(const void *job, int64_t begin, int64_t end) {
    const MaskJob *j = (const MaskJob *)job;
    for (int64_t k = begin; k < end; k++) {
        int64_t p = k * j->block, e = block_end(j, k), at = j->first[k];
        int64_t b = p / j->hw, next = (b + 1) * j->hw;  /* the view, without a division
                                                          * per element */
        while (p < e) {
            if (p == next) {
                b++;
                next += j->hw;
            }
            int64_t stop = next < e ? next : e;
            /* eight elements at a time where they are all clear or all set (the runs of
             * an image's rows), one at a time elsewhere */
            for (; p + 8 <= stop; p += 8) {
                uint64_t w;
                memcpy(&w, j->mask + p, 8);
                if (w == 0) continue;
                if (w == 0x0101010101010101ULL) {
                    for (int q = 0; q < 8; q++) {
                        j->idx[at + q] = p + q;
                        j->view[at + q] = b;
                    }
                    at += 8;
                    continue;
                }
                int64_t set[8];  /* without a branch per element (a sparse lattice's) */
                int c = 0;
                for (int q = 0; q < 8; q++) {
                    set[c] = p + q;
                    c += j->mask[p + q];
                }
                for (int q = 0; q < c; q++) {
                    j->idx[at + q] = set[q];
                    j->view[at + q] = b;
                }
                at += c;
            }
            for (; p < stop; p++)
                if (j->mask[p]) {
                    j->idx[at] = p;
                    j->view[at++] = b;
                }
        }
    }
}

/* Entry point (ctypes, native.py): every block's indices and views from its first slot. */
int torchrefract_mask_index(const MaskJob *job, int threads) {
    int64_t blocks = (job->n + job->block - 1) / job->block;
    return tr_parallel_for_grain(index_range, job, blocks, 2, threads, 1);
}

int64_t torchrefract_mask_index_job_size(void) { return (int64_t)sizeof(MaskJob); }

/* adaptive.lattice's first pass: a level's waiting pixels (status 2) taken out of the
 * frame's shade mask, ``mask[b, y s, x s] &= status[b, y, x] != 2`` for the level's
 * (B, h, w) status over the (B, H, W) mask at stride s (a strided torch op is ~10x
 * slower). */
typedef struct {
    int64_t b, h, w, stride, fh, fw;
    const uint8_t *status;      /* (B, h, w) */
    uint8_t *mask;              /* (B, H, W) torch.bool, in place */
} WaitJob;

static void wait_range(const void *job, int64_t begin, int64_t end) {
    const WaitJob *j = (const WaitJob *)job;
    for (int64_t r = begin; r < end; r++) {  /* the level's rows */
        int64_t bi = r / j->h, y = r % j->h;
        const uint8_t *st = j->status + r * j->w;
        uint8_t *m = j->mask + (bi * j->fh + y * j->stride) * j->fw;
        for (int64_t x = 0; x < j->w; x++) m[x * j->stride] &= (uint8_t)(st[x] != 2);
    }
}

/* Entry point (ctypes, native.py). */
int torchrefract_clear_waiting(const WaitJob *job, int threads) {
    return tr_parallel_for_grain(wait_range, job, job->b * job->h, 64, threads, 16);
}

int64_t torchrefract_clear_waiting_job_size(void) { return (int64_t)sizeof(WaitJob); }

/* subsamples.gather's bookkeeping: the picked pixels (their flat indices, in order, and
 * each view's count) laid out in K slots a view, and their n x n samples on the
 * (B, n h, n w) grid of the rasterized ids, in the tensor code's order (slot, sample row,
 * sample column): each slot's pixel (-1 past a view's), each sample's row and column
 * (those of pixel 0 past a view's pixels), both layers' ids there (-1 past), and of the
 * samples taken (every sample of a picked pixel) their flat index in the ids (view-major)
 * and in the slots. */
typedef struct {
    int64_t b, h, w, n, k;
    const int64_t *idx;         /* (N,) picked pixels, flat over (B, h, w), increasing */
    const int64_t *first;       /* (B,) each view's first entry of idx */
    const int64_t *count;       /* (B,) each view's entries */
    const int32_t *ids0, *ids1; /* (B, n h, n w) rasterized ids, front and back */
    int64_t *pixels;            /* out (B, k) */
    int64_t *rows, *cols;       /* out (B, k n n) */
    int64_t *sid0, *sid1;       /* out (B, k n n) the layers' ids, -1 past */
    int64_t *flat, *taken;      /* out (N n n) */
} SlotsJob;

static void slots_range(const void *job, int64_t begin, int64_t end) {
    const SlotsJob *j = (const SlotsJob *)job;
    int64_t n = j->n, nn = n * n, hw = j->h * j->w, grid = hw * nn, nw = n * j->w;
    for (int64_t bi = begin; bi < end; bi++) {
        int64_t f0 = j->first[bi], c = j->count[bi];
        for (int64_t s = 0; s < j->k; s++) {
            int64_t pix = s < c ? j->idx[f0 + s] - bi * hw : -1, p = pix < 0 ? 0 : pix;
            int64_t py = p / j->w, px = p % j->w;
            j->pixels[bi * j->k + s] = pix;
            for (int64_t i = 0; i < n; i++)
                for (int64_t q = 0; q < n; q++) {
                    int64_t o = (bi * j->k + s) * nn + i * n + q;
                    int64_t r = n * py + i, col = n * px + q, at = r * nw + col;
                    j->rows[o] = r;
                    j->cols[o] = col;
                    j->sid0[o] = pix < 0 ? -1 : (int64_t)j->ids0[bi * grid + at];
                    j->sid1[o] = pix < 0 ? -1 : (int64_t)j->ids1[bi * grid + at];
                    if (pix >= 0) {  /* slot s of view bi: taken entry (f0 + s) n n + ... */
                        int64_t t = (f0 + s) * nn + i * n + q;
                        j->flat[t] = bi * grid + at;
                        j->taken[t] = o;
                    }
                }
        }
    }
}

/* Entry point (ctypes, native.py): the views on ``threads`` threads. */
int torchrefract_sample_slots(const SlotsJob *job, int threads) {
    return tr_parallel_for_grain(slots_range, job, job->b, 2, threads, 1);
}

int64_t torchrefract_sample_slots_job_size(void) { return (int64_t)sizeof(SlotsJob); }

/* The write-back after the samples' layers: ids[flat[t]] = tri[taken[t]] for both layers
 * (subsamples.gather: the samples' exact ids in the rasterized grid). */
typedef struct {
    int64_t m;
    const int64_t *flat, *taken;
    const int32_t *tri0, *tri1;  /* (B k n n) the samples' layers' ids */
    int32_t *ids0, *ids1;        /* (B n h n w), in place */
} PutIdsJob;

static void put_ids_range(const void *job, int64_t begin, int64_t end) {
    const PutIdsJob *j = (const PutIdsJob *)job;
    for (int64_t t = begin; t < end; t++) {
        j->ids0[j->flat[t]] = j->tri0[j->taken[t]];
        j->ids1[j->flat[t]] = j->tri1[j->taken[t]];
    }
}

int torchrefract_put_ids(const PutIdsJob *job, int threads) {
    return tr_parallel_for(put_ids_range, job, job->m, 16384, threads);
}

int64_t torchrefract_put_ids_job_size(void) { return (int64_t)sizeof(PutIdsJob); }
