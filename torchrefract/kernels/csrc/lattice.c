/* Adaptive shading at one sample per pixel (geometry/adaptive.py, ``lattice`` and
 * ``fill``): the object pixels of the 2x2 lattice (even row, even column) are shaded, and
 * a pixel between lattice pixels waits for them where its G-buffer agrees with theirs; it
 * is then their mean where their radiances agree too, else it is shaded after all.
 *
 * A pixel's lattice neighbours: (y, x -+ 1) for an even row and odd column, (y -+ 1, x)
 * for an odd row and even column, the four diagonal ones for an odd row and column. The
 * same float32 operations as the tensor code (adaptive._lattice_torch, _fill_torch):
 * optics.dot's order, explicit sums, no contraction.
 *
 * Status per pixel (uint8): 0 not the object, 1 shaded in the first pass, 2 waiting;
 * after ``fill`` a waiting pixel is 3 (interpolated), 4 (shaded in the second pass) or 5
 * (shaded in the second pass, then blended with the interpolation: adaptive.merge).
 *
 * Continuity: a waiting pixel's ``gap`` (the plan's) is how far its G-buffer is from its
 * neighbours' as a fraction of the tolerances (1: at one of them); the fill's t is the
 * larger of it and the radiance spread over ``rtol``. Up to ``blend_from`` the pixel is
 * the mean, from 1 on it is shaded, and between, the shaded value weighs smoothstep of
 * where t lies: the image changes continuously as t crosses the thresholds. */

#include <string.h>

#include "frame.h"
#include "subpixels.h"

typedef struct {
    int64_t b, h, w;
    const uint8_t *front_mask, *back_mask;      /* (B*H*W,) */
    const float *front_normal, *back_normal;    /* (B*H*W, 3) */
    const float *back_depth;                    /* (B*H*W,) */
    const float *alpha;                         /* (B*H*W,) or (B,): per_pixel 0 */
    int per_pixel;
    float alpha_min, normal_tol, depth_tol, rtol;
    float *radiance;                            /* (B*H*W, 3): fill's in and out */
    uint8_t *status;                            /* (B*H*W,) out (plan), in and out (fill) */
    float *gap;                                 /* (B*H*W,) out (plan), in (fill) */
    float *weight;                              /* (B*H*W,) fill: out at status 5 */
    float blend_from;
    int npass;                                  /* fill: the method's passes, interpolated */
    float *const *pass;                         /* (npass,) each (B*H*W, pass_ch[k]) */
    const int64_t *pass_ch;
    /* the level's pixels (B, h, w) are the frame's (B, fh, fw) of stride ``stride``
     * (the layers, alpha, radiance and passes are the frame's; status, gap, weight the
     * level's); 0: the level is the frame */
    int64_t stride, fh, fw;
    /* plan: (B*h*w,) the level's pixels that may wait or be waited on (a supersampled
     * plan's uniform pixels: their first sub-pixels hold center samples), or NULL: all */
    const uint8_t *uniform;
    /* plan: (B, 2) out, each view's object pixels and waiting pixels (the level's), added
     * to (zeroed by the caller), or NULL */
    int64_t *counts;
} LatticeJob;

/* The frame's flat index of the level's pixel p, at (view bi, row y, column x). */
static inline int64_t frame_at(const LatticeJob *j, int64_t p, int64_t bi, int64_t y,
                               int64_t x) {
    if (j->stride <= 1) return p;
    return (bi * j->fh + y * j->stride) * j->fw + x * j->stride;
}

/* A pixel p of a (B, h, w) grid (a level's, the plan's) and its view, row and column,
 * walked in order from ``begin`` without a division per pixel (the ranges' loops: pos_at,
 * then pos_step per pixel). */
typedef struct {
    int64_t bi, y, x;
} Pos;

static inline Pos pos_at(int64_t p, int64_t h, int64_t w) {
    Pos q = {p / (h * w), (p / w) % h, p % w};
    return q;
}

static inline void pos_step(Pos *q, int64_t h, int64_t w) {
    if (++q->x == w) {
        q->x = 0;
        if (++q->y == h) {
            q->y = 0;
            q->bi++;
        }
    }
}

/* The mean of the neighbours' values (k = 2 or 4) of channel c of a (B*H*W, ch) array. */
static inline float lattice_mean(const float *x, int64_t ch, const int64_t *nb, int k,
                                 int64_t c) {
    float s = x[nb[0] * ch + c] + x[nb[1] * ch + c];
    return k == 4 ? ((s + x[nb[2] * ch + c]) + x[nb[3] * ch + c]) * 0.25f : s * 0.5f;
}

/* The roughness at the frame's pixel fp (per view: view bi's). */
static inline float alpha_of(const LatticeJob *j, int64_t bi, int64_t fp) {
    return j->per_pixel ? j->alpha[fp] : j->alpha[bi];
}

/* The reciprocal of a tolerance (tolerances below 1e-30 taken as 1e-30): measures are
 * multiplied by it (one division per pixel, not one per test). */
static inline float inv_tol(float tol) { return 1.0f / (tol > 1e-30f ? tol : 1e-30f); }

/* A range's counts of view bi added to the job's (ranges of one view may run at once). */
static void add_counts(const LatticeJob *j, int64_t bi, int64_t objects, int64_t waiting) {
    if (!j->counts || (!objects && !waiting)) return;
    __atomic_fetch_add(j->counts + 2 * bi, objects, __ATOMIC_RELAXED);
    __atomic_fetch_add(j->counts + 2 * bi + 1, waiting, __ATOMIC_RELAXED);
}

/* The level's and the frame's offsets of a pixel's lattice neighbours by its class: 0 odd
 * column of an even row (left, right), 1 odd row, even column (up, down), 2 odd row and
 * column (the four diagonal ones: up-left, up-right, down-left, down-right). */
static void neighbour_offsets(const LatticeJob *j, int64_t level[3][4], int64_t frame[3][4]) {
    int64_t s = j->stride <= 1 ? 1 : j->stride, row = s * (j->stride <= 1 ? j->w : j->fw);
    int64_t w = j->w;
    int64_t lo[3][4] = {{-1, 1, 0, 0}, {-w, w, 0, 0}, {-w - 1, -w + 1, w - 1, w + 1}};
    int64_t fo[3][4] = {{-s, s, 0, 0}, {-row, row, 0, 0},
                        {-row - s, -row + s, row - s, row + s}};
    for (int c = 0; c < 3; c++)
        for (int i = 0; i < 4; i++) {
            level[c][i] = lo[c][i];
            frame[c][i] = fo[c][i];
        }
}

/* A pixel's class (neighbour_offsets), or -1: a lattice pixel, or one whose neighbours
 * leave the frame (it waits on none). */
static inline int neighbour_class(const LatticeJob *j, const Pos *at) {
    int oy = (int)(at->y & 1), ox = (int)(at->x & 1);
    if (!oy && !ox) return -1;
    if ((ox && at->x + 1 >= j->w) || (oy && at->y + 1 >= j->h)) return -1;
    return oy && ox ? 2 : oy;
}

/* What a plan's pixels share: the normals' reciprocal tolerance, and a view's roughness
 * gap where the roughness is per view (kept while the view lasts). */
typedef struct {
    float inv_n, view_gap;
    int64_t view;
} PlanConst;

/* The roughness gap alpha_min / alpha of pixel fp of view bi (plan_pixel's first). */
static inline float alpha_gap(const LatticeJob *j, PlanConst *pc, int64_t bi, int64_t fp) {
    if (j->per_pixel) return j->alpha_min * inv_tol(j->alpha[fp]);
    if (pc->view != bi) {
        pc->view = bi;
        pc->view_gap = j->alpha_min * inv_tol(j->alpha[bi]);
    }
    return pc->view_gap;
}

/* The plan of object pixel p (frame index fp) with k neighbours at the offsets ``lo``
 * (level) and ``fo`` (frame); k a constant where inlined, so the neighbours' indices stay
 * in registers. Returns whether it waits. */
static inline __attribute__((always_inline)) int plan_pixel(const LatticeJob *j, int64_t p,
                                                            int64_t fp, int64_t bi,
                                                            const int64_t *lo,
                                                            const int64_t *fo, int k,
                                                            PlanConst *pc) {
    const float *fn = j->front_normal + 3 * fp, *bn = j->back_normal + 3 * fp;
    int back = j->back_mask[fp];
    float bd = j->back_depth[fp], tol = j->depth_tol * fabsf(bd);
    float inv_n = pc->inv_n, inv_d = inv_tol(tol);
    /* the gap: each test's measure over its tolerance, the largest (a per-view
     * roughness is the neighbours' too) */
    float gap = alpha_gap(j, pc, bi, fp);
    int wait = k > 0 && (!j->uniform || j->uniform[p]);
    for (int i = 0; i < k && wait; i++) {
        int64_t q = fp + fo[i];
        wait = j->front_mask[q] && j->back_mask[q] == back &&
               (!j->uniform || j->uniform[p + lo[i]]);
        if (j->per_pixel) gap = tmax(gap, j->alpha_min * inv_tol(alpha_of(j, bi, q)));
        gap = tmax(gap, (1.0f - dot3(j->front_normal + 3 * q, fn)) * inv_n);
        if (back) {
            gap = tmax(gap, (1.0f - dot3(j->back_normal + 3 * q, bn)) * inv_n);
            gap = tmax(gap, fabsf(j->back_depth[q] - bd) * inv_d);
        }
    }
    wait = wait && gap <= 1.0f;
    j->status[p] = wait ? 2 : 1;
    j->gap[p] = wait ? gap : 0.0f;
    return wait;
}

#ifdef TR_HAVE_ENV8  /* AVX2 lanes (lighting.h) */
#define TR_PLAN8 1

/* tmax in lanes: NaN where either is, else b where b > a, else a. */
static inline __m256 tmax8(__m256 a, __m256 b) {
    __m256 m = _mm256_blendv_ps(a, b, _mm256_cmp_ps(b, a, _CMP_GT_OQ));
    return _mm256_blendv_ps(m, _mm256_set1_ps(NAN), _mm256_cmp_ps(a, b, _CMP_UNORD_Q));
}

/* 8 bytes of a mask (0 or 1) as lanes of all ones or zeros; bytes8: as float lanes. */
static inline __m256i mask8(const uint8_t *m) {
    __m256i v = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)m));
    return _mm256_cmpgt_epi32(v, _mm256_setzero_si256());
}

static inline __m256 bytes8(const uint8_t *m) { return _mm256_castsi256_ps(mask8(m)); }

/* inv_tol in lanes. */
static inline __m256 inv_tol8(__m256 tol) {
    const __m256 tiny = _mm256_set1_ps(1e-30f);
    return _mm256_div_ps(_mm256_set1_ps(1.0f),
                         _mm256_blendv_ps(tiny, tol, _mm256_cmp_ps(tol, tiny, _CMP_GT_OQ)));
}

/* 1 - dot3 (optics.dot's order: (x x' + y y') + z z') of 8 lanes' vectors (x, y, z). */
static inline __m256 one_minus_dot_lanes(const __m256 *u, const __m256 *v) {
    __m256 d = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(u[0], v[0]), _mm256_mul_ps(u[1], v[1])),
                             _mm256_mul_ps(u[2], v[2]));
    return _mm256_sub_ps(_mm256_set1_ps(1.0f), d);
}

/* The neighbour slots of 8 pixels of row y from column x (plan8, fill8): per slot the
 * offset of an even column's neighbour and an odd one's (``off``), the lanes it is a
 * neighbour of (``use``; slots past the returned count unused); ``odd``: the lanes whose
 * column is odd. An even row's odd columns wait on (left, right), its even ones (the
 * lattice) on none; an odd row's even columns on (up, down), its odd ones on the four
 * diagonal pixels: neighbour_offsets' order, class by class. */
typedef struct {
    int64_t off[4][2];
    __m256 use[4], odd;
    int n;
} Slots8;

static inline Slots8 slots8(int64_t y, int64_t x, int64_t w) {
    Slots8 sl;
    sl.odd = _mm256_castsi256_ps((x & 1) ? _mm256_setr_epi32(-1, 0, -1, 0, -1, 0, -1, 0)
                                         : _mm256_setr_epi32(0, -1, 0, -1, 0, -1, 0, -1));
    __m256 all = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    if (!(y & 1)) {
        int64_t o[4][2] = {{-1, -1}, {1, 1}, {0, 0}, {0, 0}};
        memcpy(sl.off, o, sizeof(o));
        sl.use[0] = sl.use[1] = sl.odd;
        sl.use[2] = sl.use[3] = _mm256_setzero_ps();
        sl.n = 2;
    } else {
        int64_t o[4][2] = {{-w, -w - 1}, {w, -w + 1}, {w - 1, w - 1}, {w + 1, w + 1}};
        memcpy(sl.off, o, sizeof(o));
        sl.use[0] = sl.use[1] = all;
        sl.use[2] = sl.use[3] = sl.odd;
        sl.n = 4;
    }
    return sl;
}

/* Whether the 8 pixels of the range [p, end) from ``at`` lie in one row and all have the
 * neighbours of their class inside the frame (x - 1 >= 0, x + 8 < w; below, on an odd
 * row): plan8's and fill8's condition. */
static inline int slots8_fit(const LatticeJob *j, const Pos *at, int64_t p, int64_t end) {
    return at->x >= 1 && at->x + 9 <= j->w && p + 8 <= end && (!(at->y & 1) || at->y + 1 < j->h);
}

/* 8 floats from ``a`` at p + the slot's offsets: the even columns' where they differ. */
static inline __m256 slot_ps(const float *a, int64_t p, const int64_t *off, __m256 odd) {
    __m256 v = _mm256_loadu_ps(a + p + off[0]);
    return off[1] == off[0] ? v : _mm256_blendv_ps(v, _mm256_loadu_ps(a + p + off[1]), odd);
}

/* The same for a mask (lanes all set where nonzero) and for xyz triples. */
static inline __m256 slot_mask(const uint8_t *m, int64_t p, const int64_t *off, __m256 odd) {
    __m256 v = bytes8(m + p + off[0]);
    return off[1] == off[0] ? v : _mm256_blendv_ps(v, bytes8(m + p + off[1]), odd);
}

static inline void slot_xyz(const float *a, int64_t p, const int64_t *off, __m256 odd,
                            __m256 *v) {
    tr_load_xyz8(a + 3 * (p + off[0]), &v[0], &v[1], &v[2]);
    if (off[1] == off[0]) return;
    __m256 u[3];
    tr_load_xyz8(a + 3 * (p + off[1]), &u[0], &u[1], &u[2]);
    for (int c = 0; c < 3; c++) v[c] = _mm256_blendv_ps(v[c], u[c], odd);
}

/* plan_pixel for the 8 pixels p .. p + 7 of row y (frame = level: stride 1, no uniform
 * mask), all with both neighbours of their class inside the frame (x - 1 >= 0, x + 1 < w,
 * and on an odd row y + 1 < h): each neighbour slot's tests in lanes, in the scalar
 * loop's order, applied where the slot is one of the pixel's. The same values; the counts
 * of object and waiting pixels added to ``counts``. */
static void plan8(const LatticeJob *j, int64_t p, int64_t y, int64_t x, PlanConst *pc,
                  int64_t bi, int64_t *counts) {
    __m256 fm = bytes8(j->front_mask + p);
    int fbits = _mm256_movemask_ps(fm);
    if (!fbits) {
        memset(j->status + p, 0, 8);
        _mm256_storeu_ps(j->gap + p, _mm256_setzero_ps());
        return;
    }
    Slots8 sl = slots8(y, x, j->w);
    const __m256 all = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    const __m256 absm = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
    __m256 fn[3], bn[3], bm = bytes8(j->back_mask + p), bd = _mm256_loadu_ps(j->back_depth + p);
    tr_load_xyz8(j->front_normal + 3 * p, &fn[0], &fn[1], &fn[2]);
    tr_load_xyz8(j->back_normal + 3 * p, &bn[0], &bn[1], &bn[2]);
    __m256 inv_n = _mm256_set1_ps(pc->inv_n), amin = _mm256_set1_ps(j->alpha_min);
    __m256 inv_d = inv_tol8(_mm256_mul_ps(_mm256_set1_ps(j->depth_tol), _mm256_and_ps(bd, absm)));
    __m256 gap = j->per_pixel ? _mm256_mul_ps(amin, inv_tol8(_mm256_loadu_ps(j->alpha + p)))
                              : _mm256_set1_ps(alpha_gap(j, pc, bi, p));
    __m256 wait = sl.use[0];  /* a lane with no slot (a lattice pixel) waits on none */
    for (int s = 0; s < sl.n; s++) {
        const int64_t *off = sl.off[s];
        __m256 qfn[3], qbn[3];
        slot_xyz(j->front_normal, p, off, sl.odd, qfn);
        slot_xyz(j->back_normal, p, off, sl.odd, qbn);
        __m256 qbm = slot_mask(j->back_mask, p, off, sl.odd);
        __m256 ok = _mm256_and_ps(slot_mask(j->front_mask, p, off, sl.odd),
                                  _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                                      _mm256_castps_si256(qbm), _mm256_castps_si256(bm))));
        wait = _mm256_and_ps(wait, _mm256_or_ps(_mm256_andnot_ps(sl.use[s], all), ok));
        __m256 g = gap;
        if (j->per_pixel)
            g = tmax8(g, _mm256_mul_ps(amin, inv_tol8(slot_ps(j->alpha, p, off, sl.odd))));
        g = tmax8(g, _mm256_mul_ps(one_minus_dot_lanes(qfn, fn), inv_n));
        __m256 gb = tmax8(g, _mm256_mul_ps(one_minus_dot_lanes(qbn, bn), inv_n));
        __m256 dd = _mm256_sub_ps(slot_ps(j->back_depth, p, off, sl.odd), bd);
        gb = tmax8(gb, _mm256_mul_ps(_mm256_and_ps(dd, absm), inv_d));
        g = _mm256_blendv_ps(g, gb, bm);  /* the back tests where the pixel has a back */
        gap = _mm256_blendv_ps(gap, g, sl.use[s]);
    }
    wait = _mm256_and_ps(_mm256_and_ps(wait, fm),
                         _mm256_cmp_ps(gap, _mm256_set1_ps(1.0f), _CMP_LE_OQ));
    int wbits = _mm256_movemask_ps(wait);
    for (int l = 0; l < 8; l++)
        j->status[p + l] = (uint8_t)(((fbits >> l) & 1) + ((wbits >> l) & 1));
    _mm256_storeu_ps(j->gap + p, _mm256_and_ps(gap, wait));
    counts[0] += __builtin_popcount((unsigned)fbits);
    counts[1] += __builtin_popcount((unsigned)wbits);
}
#endif

static void plan_range(const void *job, int64_t begin, int64_t end) {
    const LatticeJob *j = (const LatticeJob *)job;
    int64_t lo[3][4], fo[3][4];
    neighbour_offsets(j, lo, fo);
    Pos at = pos_at(begin, j->h, j->w);
    int64_t view = at.bi, objects = 0, waiting = 0;
    PlanConst pc = {inv_tol(j->normal_tol), 0.0f, -1};
#ifdef TR_PLAN8
    int lanes = j->stride <= 1 && !j->uniform;
#endif
    for (int64_t p = begin; p < end; p++, pos_step(&at, j->h, j->w)) {
        if (at.bi != view) {
            add_counts(j, view, objects, waiting);
            view = at.bi;
            objects = waiting = 0;
        }
#ifdef TR_PLAN8
        if (lanes && slots8_fit(j, &at, p, end)) {
            int64_t c[2] = {0, 0};
            plan8(j, p, at.y, at.x, &pc, at.bi, c);
            objects += c[0];
            waiting += c[1];
            p += 7;  /* the loop's step: the row's pixel after them */
            at.x += 7;
            continue;
        }
#endif
        int64_t fp = frame_at(j, p, at.bi, at.y, at.x);  /* the layers are the frame's */
        if (!j->front_mask[fp]) {
            j->status[p] = 0;
            j->gap[p] = 0.0f;
            continue;
        }
        int c = neighbour_class(j, &at);
        if (c == 2) waiting += plan_pixel(j, p, fp, at.bi, lo[2], fo[2], 4, &pc);
        else if (c >= 0) waiting += plan_pixel(j, p, fp, at.bi, lo[c], fo[c], 2, &pc);
        else plan_pixel(j, p, fp, at.bi, lo[0], fo[0], 0, &pc);
        objects++;
    }
    add_counts(j, view, objects, waiting);
}

/* No pass lacks a rough pixel that the full pass has (the methods' switch of the rough
 * interfaces' energies, tiles.shade): a waiting pixel's lattice neighbours are rough and in
 * the first pass, and the second pass shades waiting pixels only, all rough. */
int torchrefract_lattice_plan(LatticeJob *job, int threads) {
    return tr_parallel_for(plan_range, job, job->b * job->h * job->w, 4096, threads);
}

/* A waiting pixel p whose mean was taken at measure t < 1: its mean alone (status 3) up
 * to blend_from, else blended with its shaded value by smoothstep's weight (status 5). */
static inline void mean_taken(const LatticeJob *j, int64_t p, float t) {
    if (t <= j->blend_from) {
        j->status[p] = 3;
        return;
    }
    float u = (t - j->blend_from) / (1.0f - j->blend_from);
    j->weight[p] = u * u * (3.0f - 2.0f * u);
    j->status[p] = 5;
}

/* One waiting pixel p (frame index fp) of the fill, its k lattice neighbours at the frame
 * offsets ``off`` (k a constant where inlined: the neighbours' indices stay in registers). */
static inline __attribute__((always_inline)) void fill_pixel(const LatticeJob *j, int64_t p,
                                                             int64_t fp, const int64_t *off,
                                                             int k) {
    int64_t nb[4];
    const float *v[4];
    for (int i = 0; i < k; i++) {
        nb[i] = fp + off[i];
        v[i] = j->radiance + 3 * nb[i];
    }
    float mean[3], rel = 0.0f;
    for (int c = 0; c < 3; c++) mean[c] = lattice_mean(j->radiance, 3, nb, k, c);
    float lum = ((mean[0] + mean[1]) + mean[2]) / 3.0f + 1e-3f, dmax = 0.0f;
    int finite = 1;
    for (int c = 0; c < 3; c++) {
        float lo = v[0][c], hi = v[0][c];
        for (int i = 1; i < k; i++) {
            lo = v[i][c] < lo ? v[i][c] : lo;
            hi = v[i][c] > hi ? v[i][c] : hi;
        }
        float d = hi - lo;  /* >= 0 where finite */
        finite &= isfinite(d);
        dmax = d > dmax ? d : dmax;
    }
    /* the largest of the channels' (hi - lo) / lum, by one division: a correctly rounded
     * division keeps the order of its numerators, so it is (max (hi - lo)) / lum, and
     * finite exactly where every channel's is (the largest overflows first) */
    float q = dmax / lum;
    finite &= isfinite(q);
    rel = q > 0.0f ? q : 0.0f;
    float t = tmax(j->gap[p], rel / j->rtol);
    if (finite && t < 1.0f) {  /* the mean, alone or to blend with the shaded value */
        for (int c = 0; c < 3; c++) j->radiance[3 * fp + c] = mean[c];
        for (int q = 0; q < j->npass; q++) {
            float *x = j->pass[q];
            int64_t ch = j->pass_ch[q];
            for (int64_t c = 0; c < ch; c++) x[fp * ch + c] = lattice_mean(x, ch, nb, k, c);
        }
        mean_taken(j, p, t);
    } else {
        j->status[p] = 4;
    }
}

#ifdef TR_PLAN8
/* fill8's last step: each waiting pixel's status (3, 5: its mean taken, 4: shaded),
 * weight and passes' means of several channels, one by one (``tbits``: the lanes whose
 * means were taken; t: their measures). */
static void fill_tail8(const LatticeJob *j, int64_t p, int64_t y, int64_t x,
                       int64_t off[3][4], int wbits, int tbits, __m256 t) {
    float tv[8];
    _mm256_storeu_ps(tv, t);
    for (int l = 0; l < 8; l++) {
        if (!(wbits >> l & 1)) continue;
        if (!(tbits >> l & 1)) {  /* (a lattice pixel set waiting: shaded, as fill_range) */
            j->status[p + l] = 4;
            continue;
        }
        int64_t fp = p + l, nb[4];
        int c = (y & 1) ? (int)((x + l) & 1) + 1 : 0, k = c == 2 ? 4 : 2;
        for (int i = 0; i < k; i++) nb[i] = fp + off[c][i];
        for (int qi = 0; qi < j->npass; qi++) {  /* (one-channel ones: fill8's lanes) */
            float *xq = j->pass[qi];
            int64_t ch = j->pass_ch[qi];
            if (ch == 1) continue;
            for (int64_t cc = 0; cc < ch; cc++) xq[fp * ch + cc] = lattice_mean(xq, ch, nb, k, cc);
        }
        mean_taken(j, p + l, tv[l]);
    }
}

/* lattice_mean of a one-channel array over the 8 pixels from p in lanes (the slots' k = 2
 * or 4 neighbours, the same operations). */
static inline __m256 slots_mean(const float *a, int64_t p, const Slots8 *sl) {
    __m256 sum = _mm256_add_ps(slot_ps(a, p, sl->off[0], sl->odd),
                               slot_ps(a, p, sl->off[1], sl->odd));
    __m256 m = _mm256_mul_ps(sum, _mm256_set1_ps(0.5f));
    if (sl->n < 4) return m;
    __m256 four = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(
        sum, slot_ps(a, p, sl->off[2], sl->odd)), slot_ps(a, p, sl->off[3], sl->odd)),
        _mm256_set1_ps(0.25f));
    return _mm256_blendv_ps(m, four, sl->use[2]);
}

/* fill_pixel for the waiting ones of the 8 pixels p .. p + 7 of row y (the level is the
 * frame: stride 1), all with their neighbours inside the frame (plan8's condition): the
 * means, spread and decision of each in lanes, by the scalar code's operations in its
 * order (a two-neighbour pixel's slots 2 and 3 not applied); the means written where they
 * are taken (masked stores), then fill_tail8. ``off``: neighbour_offsets' frame offsets. */
static void fill8(const LatticeJob *j, int64_t p, int64_t y, int64_t x, int64_t off[3][4]) {
    __m256i st = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)(j->status + p)));
    int wbits = _mm256_movemask_ps(_mm256_castsi256_ps(
        _mm256_cmpeq_epi32(st, _mm256_set1_epi32(2))));
    if (!wbits) return;
    Slots8 sl = slots8(y, x, j->w);
    __m256 four = sl.use[2];  /* the lanes with four neighbours: an odd row's odd columns */
    __m256 v[4][3];
    for (int s = 0; s < sl.n; s++) slot_xyz(j->radiance, p, sl.off[s], sl.odd, v[s]);
    const __m256 absm = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
    const __m256 inf = _mm256_set1_ps(INFINITY), zero = _mm256_setzero_ps();
    __m256 mean[3], finite = _mm256_castsi256_ps(_mm256_set1_epi32(-1)), dmax = zero;
    for (int c = 0; c < 3; c++) {  /* lattice_mean, k 2 or 4 */
        __m256 sum = _mm256_add_ps(v[0][c], v[1][c]);
        mean[c] = _mm256_mul_ps(sum, _mm256_set1_ps(0.5f));
        if (sl.n == 4)
            mean[c] = _mm256_blendv_ps(mean[c], _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(
                sum, v[2][c]), v[3][c]), _mm256_set1_ps(0.25f)), four);
    }
    __m256 lum = _mm256_add_ps(_mm256_div_ps(_mm256_add_ps(_mm256_add_ps(mean[0], mean[1]),
                                                           mean[2]), _mm256_set1_ps(3.0f)),
                               _mm256_set1_ps(1e-3f));
    for (int c = 0; c < 3; c++) {
        __m256 lo = v[0][c], hi = v[0][c];
        for (int s = 1; s < sl.n; s++) {
            __m256 lt = _mm256_cmp_ps(v[s][c], lo, _CMP_LT_OQ);
            __m256 gt = _mm256_cmp_ps(v[s][c], hi, _CMP_GT_OQ);
            lo = _mm256_blendv_ps(lo, v[s][c], s < 2 ? lt : _mm256_and_ps(four, lt));
            hi = _mm256_blendv_ps(hi, v[s][c], s < 2 ? gt : _mm256_and_ps(four, gt));
        }
        __m256 d = _mm256_sub_ps(hi, lo);
        finite = _mm256_and_ps(finite, _mm256_cmp_ps(_mm256_and_ps(d, absm), inf, _CMP_LT_OQ));
        dmax = _mm256_blendv_ps(dmax, d, _mm256_cmp_ps(d, dmax, _CMP_GT_OQ));
    }
    __m256 q = _mm256_div_ps(dmax, lum);  /* fill_pixel's one division */
    finite = _mm256_and_ps(finite, _mm256_cmp_ps(_mm256_and_ps(q, absm), inf, _CMP_LT_OQ));
    __m256 rel = _mm256_and_ps(q, _mm256_cmp_ps(q, zero, _CMP_GT_OQ));
    __m256 t = tmax8(_mm256_loadu_ps(j->gap + p),
                     _mm256_div_ps(rel, _mm256_set1_ps(j->rtol)));
    __m256 take = _mm256_and_ps(finite, _mm256_cmp_ps(t, _mm256_set1_ps(1.0f), _CMP_LT_OQ));
    /* no lattice pixel (an even row's even column) is filled: no plan lets one wait */
    int lattice = (y & 1) ? 0 : _mm256_movemask_ps(sl.odd) ^ 0xff;
    int tbits = _mm256_movemask_ps(take) & wbits & ~lattice;
    if (tbits) {
        __m256i tm = _mm256_cmpgt_epi32(
            _mm256_and_si256(_mm256_set1_epi32(tbits), _mm256_setr_epi32(1, 2, 4, 8, 16, 32,
                                                                         64, 128)),
            _mm256_setzero_si256());
        tr_store_xyz8_where(j->radiance + 3 * p, _mm256_castsi256_ps(tm), mean[0], mean[1],
                            mean[2]);
        for (int qi = 0; qi < j->npass; qi++)  /* one-channel passes: their means here */
            if (j->pass_ch[qi] == 1)
                _mm256_maskstore_ps(j->pass[qi] + p, tm, slots_mean(j->pass[qi], p, &sl));
    }
    fill_tail8(j, p, y, x, off, wbits, tbits, t);
}
#endif

static void fill_range(const void *job, int64_t begin, int64_t end) {
    const LatticeJob *j = (const LatticeJob *)job;
    int64_t lo[3][4], off[3][4];
    neighbour_offsets(j, lo, off);
    Pos at = pos_at(begin, j->h, j->w);
#ifdef TR_PLAN8
    int lanes = j->stride <= 1;
#endif
    for (int64_t p = begin; p < end; p++, pos_step(&at, j->h, j->w)) {
#ifdef TR_PLAN8
        if (lanes && slots8_fit(j, &at, p, end)) {
            fill8(j, p, at.y, at.x, off);
            p += 7;  /* the loop's step: the row's pixel after them */
            at.x += 7;
            continue;
        }
#endif
        if (j->status[p] != 2) continue;  /* (the plan lets a pixel wait on all its k) */
        int64_t fp = frame_at(j, p, at.bi, at.y, at.x);
        int c = neighbour_class(j, &at);
        if (c < 0) j->status[p] = 4;  /* (no plan lets such a pixel wait: shaded) */
        else if (c == 2) fill_pixel(j, p, fp, off[2], 4);
        else fill_pixel(j, p, fp, off[c], 2);
    }
}

int torchrefract_lattice_fill(LatticeJob *job, int threads) {
    return tr_parallel_for(fill_range, job, job->b * job->h * job->w, 4096, threads);
}

/* adaptive.plan's uniform pixels of a supersampled G-buffer (n x n sub-pixels a pixel):
 * those whose sub-pixels all agree with the first on both masks, both normals (within
 * normal_tol of 1 - cos) and the back depth (within depth_tol of it), all at least
 * smooth_alpha rough. The tensor code's float32 operations and order (optics.dot's sums,
 * tolerances rounded to float as torch compares a float32 tensor with a Python number).
 * Also the sub-pixels to shade (adaptive._shade_torch): covered (and in the region), but
 * for a uniform pixel's sub-pixels after its first. */
typedef struct {
    int64_t b, h, w, n;                         /* pixels (B, h, w); layers (B, nh, nw) */
    const uint8_t *front_mask, *back_mask;
    const float *front_normal, *back_normal, *back_depth;
    const float *alpha;                         /* (B, nh, nw), or (B,): per_pixel 0 */
    int per_pixel;
    float smooth_alpha, normal_tol, depth_tol;
    uint8_t *uniform;                           /* out (B, h, w) */
    const uint8_t *region;                      /* (B, nh, nw) or NULL: everywhere */
    uint8_t *shade;                             /* out (B, nh, nw) */
} UniformJob;

/* One pixel's test (uniform_range): u starts as its first sub-pixel's coverage and each
 * term can only clear it, so an empty first sub-pixel (most of a frame) and the first
 * failed term end the test (the same result as every term ANDed). */
static int uniform_pixel(const UniformJob *j, int64_t bi, int64_t s0, int64_t nw) {
    int64_t n = j->n;
    if (!j->front_mask[s0]) return 0;
    float tol = j->depth_tol * fabsf(j->back_depth[s0]);
    const float *fn0 = j->front_normal + 3 * s0, *bn0 = j->back_normal + 3 * s0;
    for (int64_t i = 0; i < n; i++)
        for (int64_t k = 0; k < n; k++) {
            int64_t s = s0 + i * nw + k;
            if (i || k) {
                if (j->front_mask[s] != j->front_mask[s0] || j->back_mask[s] != j->back_mask[s0])
                    return 0;
                if (!(1.0f - dot3(j->front_normal + 3 * s, fn0) <= j->normal_tol) ||
                    !(1.0f - dot3(j->back_normal + 3 * s, bn0) <= j->normal_tol) ||
                    !(fabsf(j->back_depth[s] - j->back_depth[s0]) <= tol))
                    return 0;
            }
            if (!((j->per_pixel ? j->alpha[s] : j->alpha[bi]) >= j->smooth_alpha)) return 0;
        }
    return 1;
}

static void uniform_range(const void *job, int64_t begin, int64_t end) {
    const UniformJob *j = (const UniformJob *)job;
    int64_t n = j->n, nw = j->w * n;
    Pos at = pos_at(begin, j->h, j->w);
    for (int64_t p = begin; p < end; p++, pos_step(&at, j->h, j->w)) {
        int64_t s0 = (at.bi * j->h * n + at.y * n) * nw + at.x * n;
        int u = uniform_pixel(j, at.bi, s0, nw);
        j->uniform[p] = (uint8_t)u;
        for (int64_t i = 0; i < n; i++)
            for (int64_t k = 0; k < n; k++) {
                int64_t s = s0 + i * nw + k;
                j->shade[s] = (uint8_t)(j->front_mask[s] && (!j->region || j->region[s]) &&
                                        !(u && (i || k)));
            }
    }
}

int torchrefract_uniform(const UniformJob *job, int threads) {
    return tr_parallel_for(uniform_range, job, job->b * job->h * job->w, 4096, threads);
}

int64_t torchrefract_uniform_job_size(void) { return (int64_t)sizeof(UniformJob); }

/* adaptive.refine's pixels shaded once to be shaded at every sub-pixel after all: a
 * uniform pixel whose 3x3 neighbourhood of uniform pixels' radiances (each at its first
 * sub-pixel: its center sample) spreads, max - min in a channel, by more than rtol times
 * its mean luminance + 1e-3 (the luminances (r + g) + b over 3, summed down each column,
 * the columns' sums left to right, over their count); a non-finite value among them
 * refines nothing. The tensor code's float32 operations in its order
 * (adaptive._refine_torch). */
typedef struct {
    int64_t b, h, w, n;         /* pixels (B, h, w); radiance (B, n h, n w, 3) */
    const uint8_t *uniform;     /* (B, h, w) */
    const float *radiance;
    float rtol;
    uint8_t *more;              /* out (B, h, w) */
} RefineJob;

/* A column of a pixel's 3x3 neighbourhood: its uniform pixels' channel maxima and minima,
 * their luminances summed top to bottom, their count, a non-finite value among them. */
typedef struct {
    float hi[3], lo[3], sum;
    int count, nan;
} Column;

static void column_at(const RefineJob *j, int64_t bi, int64_t y, int64_t x, Column *c) {
    int64_t n = j->n, nw = j->w * n;
    c->sum = 0.0f;
    c->count = c->nan = 0;
    if (x < 0 || x >= j->w) return;
    for (int64_t yy = y - 1; yy <= y + 1; yy++) {
        if (yy < 0 || yy >= j->h || !j->uniform[(bi * j->h + yy) * j->w + x]) continue;
        const float *v = j->radiance + 3 * ((bi * j->h * n + yy * n) * nw + x * n);
        for (int k = 0; k < 3; k++) {
            c->nan |= !isfinite(v[k]);
            c->hi[k] = c->count && c->hi[k] > v[k] ? c->hi[k] : v[k];
            c->lo[k] = c->count && c->lo[k] < v[k] ? c->lo[k] : v[k];
        }
        c->sum = c->sum + ((v[0] + v[1]) + v[2]) / 3.0f;
        c->count++;
    }
}

/* The test of the pixel whose neighbourhood's columns are c[0..2] (left to right): the
 * column sums added left to right. */
static int refine_columns(const RefineJob *j, const Column *c) {
    float hi[3] = {0.0f, 0.0f, 0.0f}, lo[3] = {0.0f, 0.0f, 0.0f};  /* set by the first column */
    float sum = (c[0].sum + c[1].sum) + c[2].sum;
    int count = 0, nan = 0;
    for (int i = 0; i < 3; i++) {
        if (!c[i].count) continue;
        for (int k = 0; k < 3; k++) {
            hi[k] = count && hi[k] > c[i].hi[k] ? hi[k] : c[i].hi[k];
            lo[k] = count && lo[k] < c[i].lo[k] ? lo[k] : c[i].lo[k];
        }
        count += c[i].count;
        nan |= c[i].nan;
    }
    float spread = tmax(tmax(hi[0] - lo[0], hi[1] - lo[1]), hi[2] - lo[2]);
    float mean = sum / (float)count + 1e-3f;
    return !nan && spread > j->rtol * mean;
}

/* The pixels [x0, x1) of row y of view bi, one at a time: along the row the columns slide,
 * one new column per pixel (a pixel not uniform, most of a frame's background, skips its
 * own and starts the window afresh after it). */
static void refine_segment(const RefineJob *j, int64_t bi, int64_t y, int64_t x0, int64_t x1) {
    int64_t p = (bi * j->h + y) * j->w + x0;
    Column c[3];
    int fresh = 1;
    for (int64_t x = x0; x < x1; x++, p++) {
        if (!j->uniform[p]) {
            j->more[p] = 0;
            fresh = 1;
            continue;
        }
        if (fresh) {
            for (int i = 0; i < 3; i++) column_at(j, bi, y, x - 1 + i, &c[i]);
            fresh = 0;
        } else {
            c[0] = c[1];
            c[1] = c[2];
            column_at(j, bi, y, x + 1, &c[2]);
        }
        j->more[p] = (uint8_t)refine_columns(j, c);
    }
}

#ifdef TR_HAVE_ENV8  /* AVX2 lanes (lighting.h) */
#define REFINE_TILE 64

/* A tile's columns (column_at's values) as lanes' arrays: slot i is column x0 - 1 + i;
 * counts as floats, a non-finite value as an all-ones mask. */
typedef struct {
    float hi[3][REFINE_TILE + 16], lo[3][REFINE_TILE + 16], sum[REFINE_TILE + 16];
    float count[REFINE_TILE + 16], nan[REFINE_TILE + 16];
} Columns;

/* column_at of the 8 columns from c0 (all inside the frame; n = 1) into slot i of cs, in
 * lanes: the same selects and sums, top to bottom. */
static void refine_cols8(const RefineJob *j, int64_t bi, int64_t y, int64_t c0, Columns *cs,
                         int i) {
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
    const __m256 inf = _mm256_set1_ps(INFINITY);
    const __m256 absm = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
    __m256 hi[3] = {zero, zero, zero}, lo[3] = {zero, zero, zero};
    __m256 sum = zero, count = zero, nan = zero;
    for (int64_t yy = y - 1; yy <= y + 1; yy++) {
        if (yy < 0 || yy >= j->h) continue;
        int64_t q = (bi * j->h + yy) * j->w + c0;
        __m256 u = bytes8(j->uniform + q);
        __m256 v[3];
        tr_load_xyz8(j->radiance + 3 * q, &v[0], &v[1], &v[2]);
        __m256 any = _mm256_cmp_ps(count, zero, _CMP_GT_OQ);  /* count before this row */
        for (int k = 0; k < 3; k++) {
            __m256 fin = _mm256_cmp_ps(_mm256_and_ps(v[k], absm), inf, _CMP_LT_OQ);
            nan = _mm256_or_ps(nan, _mm256_andnot_ps(fin, u));
            __m256 keep_hi = _mm256_and_ps(any, _mm256_cmp_ps(hi[k], v[k], _CMP_GT_OQ));
            __m256 keep_lo = _mm256_and_ps(any, _mm256_cmp_ps(lo[k], v[k], _CMP_LT_OQ));
            hi[k] = _mm256_blendv_ps(hi[k], _mm256_blendv_ps(v[k], hi[k], keep_hi), u);
            lo[k] = _mm256_blendv_ps(lo[k], _mm256_blendv_ps(v[k], lo[k], keep_lo), u);
        }
        __m256 lum = _mm256_div_ps(_mm256_add_ps(_mm256_add_ps(v[0], v[1]), v[2]),
                                   _mm256_set1_ps(3.0f));
        sum = _mm256_blendv_ps(sum, _mm256_add_ps(sum, lum), u);
        count = _mm256_add_ps(count, _mm256_and_ps(u, one));
    }
    for (int k = 0; k < 3; k++) {
        _mm256_storeu_ps(cs->hi[k] + i, hi[k]);
        _mm256_storeu_ps(cs->lo[k] + i, lo[k]);
    }
    _mm256_storeu_ps(cs->sum + i, sum);
    _mm256_storeu_ps(cs->count + i, count);
    _mm256_storeu_ps(cs->nan + i, nan);
}

/* refine_columns for the 8 pixels whose windows start at slot i, in lanes; their decisions
 * as a mask (the pixels' own uniformity not yet applied). */
static __m256 refine_windows8(const RefineJob *j, const Columns *cs, int i) {
    const __m256 zero = _mm256_setzero_ps();
    __m256 hi[3] = {zero, zero, zero}, lo[3] = {zero, zero, zero};
    __m256 count = zero, nan = zero;
    __m256 sum = _mm256_add_ps(_mm256_add_ps(_mm256_loadu_ps(cs->sum + i),
                                             _mm256_loadu_ps(cs->sum + i + 1)),
                               _mm256_loadu_ps(cs->sum + i + 2));
    for (int c = 0; c < 3; c++) {
        __m256 cc = _mm256_loadu_ps(cs->count + i + c);
        __m256 has = _mm256_cmp_ps(cc, zero, _CMP_GT_OQ);
        __m256 any = _mm256_cmp_ps(count, zero, _CMP_GT_OQ);
        for (int k = 0; k < 3; k++) {
            __m256 h = _mm256_loadu_ps(cs->hi[k] + i + c), l = _mm256_loadu_ps(cs->lo[k] + i + c);
            __m256 keep_hi = _mm256_and_ps(any, _mm256_cmp_ps(hi[k], h, _CMP_GT_OQ));
            __m256 keep_lo = _mm256_and_ps(any, _mm256_cmp_ps(lo[k], l, _CMP_LT_OQ));
            hi[k] = _mm256_blendv_ps(hi[k], _mm256_blendv_ps(h, hi[k], keep_hi), has);
            lo[k] = _mm256_blendv_ps(lo[k], _mm256_blendv_ps(l, lo[k], keep_lo), has);
        }
        count = _mm256_add_ps(count, cc);
        nan = _mm256_or_ps(nan, _mm256_and_ps(has, _mm256_loadu_ps(cs->nan + i + c)));
    }
    /* tmax's choice (b > a ? b : a; a NaN spread only where nan is set) */
    __m256 d0 = _mm256_sub_ps(hi[0], lo[0]), d1 = _mm256_sub_ps(hi[1], lo[1]);
    __m256 d2 = _mm256_sub_ps(hi[2], lo[2]);
    __m256 s01 = _mm256_blendv_ps(d0, d1, _mm256_cmp_ps(d1, d0, _CMP_GT_OQ));
    __m256 spread = _mm256_blendv_ps(s01, d2, _mm256_cmp_ps(d2, s01, _CMP_GT_OQ));
    __m256 mean = _mm256_add_ps(_mm256_div_ps(sum, count), _mm256_set1_ps(1e-3f));
    __m256 more = _mm256_cmp_ps(spread, _mm256_mul_ps(_mm256_set1_ps(j->rtol), mean),
                                _CMP_GT_OQ);
    return _mm256_andnot_ps(nan, more);
}

/* refine_segment for n = 1 in tiles of REFINE_TILE pixels: each tile's columns (and the
 * one past either end) in lanes where 8 of them lie inside the frame, else one by one
 * (column_at), then its pixels' windows in lanes. */
static void refine_segment8(const RefineJob *j, int64_t bi, int64_t y, int64_t x0,
                            int64_t x1) {
    Columns cs;
    for (int64_t xa = x0; xa < x1; xa += REFINE_TILE) {
        int64_t xb = xa + REFINE_TILE < x1 ? xa + REFINE_TILE : x1;
        int ncol = (int)(xb - xa) + 2;  /* columns xa - 1 .. xb */
        for (int i = 0; i < ncol;) {
            int64_t c0 = xa - 1 + i;
            if (c0 >= 0 && c0 + 8 <= j->w && i + 8 <= REFINE_TILE + 16) {
                refine_cols8(j, bi, y, c0, &cs, i);
                i += 8;
                continue;
            }
            Column c;
            column_at(j, bi, y, c0, &c);
            for (int k = 0; k < 3; k++) {
                cs.hi[k][i] = c.count ? c.hi[k] : 0.0f;
                cs.lo[k][i] = c.count ? c.lo[k] : 0.0f;
            }
            cs.sum[i] = c.sum;
            cs.count[i] = (float)c.count;
            memset(cs.nan + i, c.nan ? 0xff : 0, sizeof(float));
            i++;
        }
        for (int i = ncol; i < ncol + 8; i++) {  /* read by a last, partial group's lanes */
            for (int k = 0; k < 3; k++) cs.hi[k][i] = cs.lo[k][i] = 0.0f;
            cs.sum[i] = cs.count[i] = cs.nan[i] = 0.0f;
        }
        int64_t p = (bi * j->h + y) * j->w + xa;
        for (int64_t x = xa; x < xb; x += 8, p += 8) {
            int i = (int)(x - xa), m = xb - x < 8 ? (int)(xb - x) : 8;
            int own = 0;  /* the pixels' own uniformity (none read past the row) */
            for (int l = 0; l < m; l++) own |= (j->uniform[p + l] != 0) << l;
            int bits = own & _mm256_movemask_ps(refine_windows8(j, &cs, i));
            for (int l = 0; l < m; l++) j->more[p + l] = (uint8_t)(bits >> l & 1);
        }
    }
}
#endif

/* Row segment by row segment: in lanes where the radiance is the pixels' own (n = 1). */
static void refine_range(const void *job, int64_t begin, int64_t end) {
    const RefineJob *j = (const RefineJob *)job;
    Pos at = pos_at(begin, j->h, j->w);
    for (int64_t p = begin; p < end;) {
        int64_t x1 = at.x + (end - p) < j->w ? at.x + (end - p) : j->w;
#ifdef TR_HAVE_ENV8
        if (j->n == 1) refine_segment8(j, at.bi, at.y, at.x, x1);
        else refine_segment(j, at.bi, at.y, at.x, x1);
#else
        refine_segment(j, at.bi, at.y, at.x, x1);
#endif
        p += x1 - at.x;
        at.x = x1 - 1;
        pos_step(&at, j->h, j->w);
    }
}

int torchrefract_refine(const RefineJob *job, int threads) {
    return tr_parallel_for(refine_range, job, job->b * job->h * job->w, 4096, threads);
}

int64_t torchrefract_refine_job_size(void) { return (int64_t)sizeof(RefineJob); }

/* One level of a plan for the driver below: its pixels (B, h, w) at ``stride`` in the
 * frame, the plan's status (filled in place) and gap. */
typedef struct {
    int64_t stride, h, w;
    uint8_t *status;
    float *gap;
    float rtol;                     /* the fill's (adaptive.fill: LATTICE_RTOL over the
                                     * stride over blend_from) */
} ShadeLevel;

typedef int (*tr_kernel_fn)(void *job, int threads);

/* adaptive.fill and adaptive.merge for a fused method, after its first pass: per level,
 * the fill, then the method's kernel over the pixels left (status 4 and 5, in frame
 * order) shading over the image so far, and the blend of the status-5 ones with their
 * means (mean + weight (shaded - mean), as adaptive._blend). ``job`` is the method's job
 * (its ``Frame`` first), ``run`` its entry (torchrefract_specular, ...); the frame's own
 * pixels are the first pass's. */
typedef struct {
    tr_kernel_fn run;
    void *job;
    int64_t b, h, w;                /* the frame */
    int nlevels;
    const ShadeLevel *levels;       /* coarsest first */
    float blend_from;               /* BLEND_FROM */
    float *radiance;                /* (B*H*W, 3) */
    int npass;
    float *const *pass;             /* the method's passes, (B*H*W, pass_ch[k]) each */
    const int64_t *pass_ch;
} LatticeShadeJob;

/* A level's pixels left to shade (status 4 and 5), listed in frame order in parallel: the
 * level is cut into SCAN_CHUNKS fixed runs, counted, then each run writes its entries at
 * its offset, so the list is the serial scan's whatever the threads. */
#define SCAN_CHUNKS 64

typedef struct {
    const LatticeJob *lj;           /* its radiance and passes: the buffers a status-5 pixel
                                     * blends, buffer 0 the radiance (scan_buf) */
    int nbuf;
    int64_t chans, chunk;
    int64_t rest_at[SCAN_CHUNKS + 1], soft_at[SCAN_CHUNKS + 1];  /* counts, then offsets */
    int64_t *idx, *batch, *sidx;    /* the pass's pixels and views; the status-5 pixels */
    float *sw, *mean;               /* their blend weights and means (``chans`` each) */
} LevelScan;

static inline float *scan_buf(const LatticeJob *lj, int k) {
    return k == 0 ? lj->radiance : lj->pass[k - 1];
}

static inline int64_t scan_ch(const LatticeJob *lj, int k) {
    return k == 0 ? 3 : lj->pass_ch[k - 1];
}

static void count_range(const void *job, int64_t begin, int64_t end) {
    LevelScan *s = (LevelScan *)job;
    int64_t n = s->lj->b * s->lj->h * s->lj->w;
    for (int64_t c = begin; c < end; c++) {
        int64_t p1 = (c + 1) * s->chunk < n ? (c + 1) * s->chunk : n, r = 0, q = 0;
        for (int64_t p = c * s->chunk; p < p1; p++) {
            r += s->lj->status[p] >= 4;
            q += s->lj->status[p] == 5;
        }
        s->rest_at[c + 1] = r;
        s->soft_at[c + 1] = q;
    }
}

/* A run's entries: its pixels and views, a status-5 pixel's means (read before the pass
 * overwrites them) and weight; the passes of every listed pixel zeroed, as a fresh pass
 * has them (adaptive.merge takes the second pass's values at every pixel it shades; the
 * radiance is the image so far). */
static void collect_range(const void *job, int64_t begin, int64_t end) {
    const LevelScan *s = (const LevelScan *)job;
    const LatticeJob *lj = s->lj;
    int64_t n = lj->b * lj->h * lj->w;
    for (int64_t c = begin; c < end; c++) {
        int64_t p0 = c * s->chunk, p1 = p0 + s->chunk < n ? p0 + s->chunk : n;
        int64_t r = s->rest_at[c], q = s->soft_at[c];
        Pos at = pos_at(p0, lj->h, lj->w);
        for (int64_t p = p0; p < p1; p++, pos_step(&at, lj->h, lj->w)) {
            if (lj->status[p] < 4) continue;
            int64_t fp = frame_at(lj, p, at.bi, at.y, at.x);
            s->idx[r] = fp;
            s->batch[r++] = at.bi;
            if (lj->status[p] == 5) {
                float *m = s->mean + q * s->chans;
                for (int k = 0; k < s->nbuf; m += scan_ch(lj, k), k++)
                    for (int64_t ci = 0, ch = scan_ch(lj, k); ci < ch; ci++)
                        m[ci] = scan_buf(lj, k)[fp * ch + ci];
                s->sidx[q] = fp;
                s->sw[q++] = lj->weight[p];
            }
            for (int k = 1; k < s->nbuf; k++)
                for (int64_t ci = 0, ch = scan_ch(lj, k); ci < ch; ci++)
                    scan_buf(lj, k)[fp * ch + ci] = 0.0f;
        }
    }
}

/* The status-5 pixels blended with their means: mean + weight (shaded - mean). */
static void blend_range(const void *job, int64_t begin, int64_t end) {
    const LevelScan *s = (const LevelScan *)job;
    for (int64_t i = begin; i < end; i++) {
        float w = s->sw[i];
        const float *m = s->mean + i * s->chans;
        for (int k = 0; k < s->nbuf; m += scan_ch(s->lj, k), k++)
            for (int64_t c = 0, ch = scan_ch(s->lj, k); c < ch; c++) {
                float *x = scan_buf(s->lj, k) + s->sidx[i] * ch + c;
                *x = m[c] + w * (*x - m[c]);
            }
    }
}

/* One level's pass after its fill. Returns 0, or -1 (memory, or the kernel failed). */
static int shade_level(const LatticeShadeJob *J, const LatticeJob *lj, Frame *f, int threads) {
    LevelScan s;
    int64_t n = lj->b * lj->h * lj->w;
    s.lj = lj;
    s.nbuf = lj->npass + 1;
    s.chans = 0;
    for (int k = 0; k < s.nbuf; k++) s.chans += scan_ch(lj, k);
    s.chunk = (n + SCAN_CHUNKS - 1) / SCAN_CHUNKS;
    if (s.chunk < 1) s.chunk = 1;
    int64_t chunks = (n + s.chunk - 1) / s.chunk;
    s.rest_at[0] = s.soft_at[0] = 0;
    if (tr_parallel_for_grain(count_range, &s, chunks, 2, threads, 1) != 0) return -1;
    for (int64_t c = 0; c < chunks; c++) {
        s.rest_at[c + 1] += s.rest_at[c];
        s.soft_at[c + 1] += s.soft_at[c];
    }
    int64_t rest = s.rest_at[chunks], soft = s.soft_at[chunks];
    if (rest == 0) return 0;
    s.idx = (int64_t *)malloc(sizeof(int64_t) * (size_t)rest * 2);
    s.sidx = (int64_t *)malloc(sizeof(int64_t) * (size_t)(soft ? soft : 1));
    s.sw = (float *)malloc(sizeof(float) * (size_t)(soft ? soft : 1));
    s.mean = (float *)malloc(sizeof(float) * (size_t)(soft ? soft : 1) * (size_t)s.chans);
    int rc = -1;
    if (s.idx && s.sidx && s.sw && s.mean) {
        s.batch = s.idx + rest;
        rc = tr_parallel_for_grain(collect_range, &s, chunks, 2, threads, 1);
    }
    if (rc == 0) {
        int64_t n0 = f->n;
        const int64_t *idx0 = f->idx, *batch0 = f->batch;
        f->n = rest;
        f->idx = s.idx;
        f->batch = s.batch;
        rc = J->run(J->job, threads);
        f->n = n0;
        f->idx = idx0;
        f->batch = batch0;
    }
    if (rc == 0) rc = tr_parallel_for(blend_range, &s, soft, 4096, threads);
    free(s.idx); free(s.sidx); free(s.sw); free(s.mean);
    return rc;
}

/* Entry point (ctypes, shading/fused.py): the first pass (the frame's pixels), then every
 * level. Returns 0, or -1 (the caller then runs the levels by adaptive.fill and merge). */
int torchrefract_lattice_shade(LatticeShadeJob *J, int threads) {
    Frame *f = (Frame *)J->job;
    if (f->n > 0 && J->run(J->job, threads) != 0) return -1;
    for (int i = 0; i < J->nlevels; i++) {
        const ShadeLevel *L = J->levels + i;
        int64_t n = J->b * L->h * L->w;
        /* written by the fill, read by the pass, at status 5 only */
        float *weight = (float *)malloc((size_t)(n ? n : 1) * sizeof(float));
        if (!weight) return -1;
        LatticeJob lj = {.b = J->b, .h = L->h, .w = L->w, .rtol = L->rtol,
                         .radiance = J->radiance, .status = L->status, .gap = L->gap,
                         .weight = weight, .blend_from = J->blend_from, .npass = J->npass,
                         .pass = J->pass, .pass_ch = J->pass_ch, .stride = L->stride,
                         .fh = J->h, .fw = J->w};
        int rc = tr_parallel_for(fill_range, &lj, n, 4096, threads);
        if (rc == 0) rc = shade_level(J, &lj, f, threads);
        free(weight);
        if (rc != 0) return -1;
    }
    return 0;
}

int64_t torchrefract_lattice_shade_job_size(void) { return (int64_t)sizeof(LatticeShadeJob); }
int64_t torchrefract_lattice_plan_job_size(void) { return (int64_t)sizeof(LatticeJob); }
int64_t torchrefract_lattice_fill_job_size(void) { return (int64_t)sizeof(LatticeJob); }

/* subsamples.edges: the pixels of a one-sample G-buffer (B, h, w) whose n x n samples can
 * differ: the sub-pixels' flags (subpixels.h: their rasterized coverage not all alike, or
 * a fold among their triangles; the first's coverage) say they are not all covered as the
 * center is, in either layer, or fold; the front or back normal differs from a covered
 * neighbour's (3x3) by more than normal_tol in 1 - cos, or the back depth by more than
 * depth_tol relative; the front is smoother than smooth_alpha. The tensor code's float32
 * operations (subsamples._edges_torch: optics.dot's order). */
typedef struct {
    int64_t b, h, w;
    const uint8_t *front_mask, *back_mask;      /* (B, h, w) */
    const float *front_normal, *back_normal, *back_depth;
    const uint8_t *sub;                         /* (B, h, w) subpixels.h's flags */
    const float *alpha;                         /* (B, h, w), or (B,): per_pixel 0 */
    int per_pixel;
    float smooth_alpha, normal_tol, depth_tol;
    uint8_t *pairs;                             /* scratch (B, h, w): pairs_range's flags */
    uint8_t *edge;                              /* out (B, h, w) */
} EdgesJob;

/* The pairs of neighbouring pixels are tested once (the tests are symmetric but for the
 * depth tolerance, relative to each end's own depth): a first sweep writes per pixel p
 * PAIR_OWN (its own tests, or one of its forward pairs flags p) and, per forward
 * neighbour q (east, south, south-east, south-west), whether that pair flags q; a second
 * sweep gathers each pixel's flag from itself and its backward neighbours. */
enum { PAIR_OWN = 1, PAIR_E = 16, PAIR_S = 32, PAIR_SE = 64, PAIR_SW = 128 };

/* The flags of the pair (p, q) for p and for q (bits 1 and 2). */
static int pair_flags(const EdgesJob *j, int64_t p, int64_t q) {
    int out = 0;
    if (j->front_mask[p] && j->front_mask[q] &&
        1.0f - dot3(j->front_normal + 3 * q, j->front_normal + 3 * p) > j->normal_tol)
        out = 3;
    if (out != 3 && j->back_mask[p] && j->back_mask[q]) {
        if (1.0f - dot3(j->back_normal + 3 * q, j->back_normal + 3 * p) > j->normal_tol)
            return 3;
        float dp = j->back_depth[p], dq = j->back_depth[q], step = fabsf(dq - dp);
        out |= (step > j->depth_tol * fabsf(dp)) | (step > j->depth_tol * fabsf(dq)) << 1;
    }
    return out;
}

/* A pixel's own tests: its sub-pixels (either layer) and its roughness. */
static inline int own_flags(const EdgesJob *j, int64_t p, const Pos *at) {
    int s = j->sub[p], fm = j->front_mask[p], bm = j->back_mask[p];
    return (s & SUB_FRONT_DIFFERS) || ((s & SUB_FRONT_FIRST) != 0) != fm ||
           (s & SUB_BACK_DIFFERS) || ((s & SUB_BACK_FIRST) != 0) != bm ||
           (fm && (j->per_pixel ? j->alpha[p] : j->alpha[at->bi]) < j->smooth_alpha);
}

static const int64_t PAIR_DY[4] = {0, 1, 1, 1}, PAIR_DX[4] = {1, 0, 1, -1};

/* pairs_range's flags of one pixel. */
static int pixel_pairs(const EdgesJob *j, int64_t p, const Pos *at) {
    int bits = own_flags(j, p, at);
    if (j->front_mask[p] || j->back_mask[p])
        for (int k = 0; k < 4; k++) {
            int64_t yy = at->y + PAIR_DY[k], xx = at->x + PAIR_DX[k];
            if (yy >= j->h || xx < 0 || xx >= j->w) continue;
            int f = pair_flags(j, p, p + PAIR_DY[k] * j->w + PAIR_DX[k]);
            bits |= (f & 1) | (f >> 1) << (4 + k);
        }
    return bits;
}

#ifdef TR_HAVE_ENV8  /* AVX2 lanes (lighting.h) */
#define TR_EDGES8 1

/* one_minus_dot_lanes of 8 pixels' normals from p and q. */
static inline __m256 one_minus_dot8(const float *np, const float *nq) {
    __m256 p[3], q[3];
    tr_load_xyz8(np, &p[0], &p[1], &p[2]);
    tr_load_xyz8(nq, &q[0], &q[1], &q[2]);
    return one_minus_dot_lanes(q, p);
}

/* own_flags of the 8 pixels from p (one row, inside the frame) in lanes. */
static void own_flags8(const EdgesJob *j, int64_t p, Pos at, uint8_t *out) {
    __m256i s = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)(j->sub + p)));
    __m256i zero = _mm256_setzero_si256();
    __m256i differs = _mm256_cmpgt_epi32(
        _mm256_and_si256(s, _mm256_set1_epi32(SUB_FRONT_DIFFERS | SUB_BACK_DIFFERS)), zero);
    __m256i ff = _mm256_cmpgt_epi32(_mm256_and_si256(s, _mm256_set1_epi32(SUB_FRONT_FIRST)),
                                    zero);
    __m256i bf = _mm256_cmpgt_epi32(_mm256_and_si256(s, _mm256_set1_epi32(SUB_BACK_FIRST)),
                                    zero);
    __m256i fm = mask8(j->front_mask + p);
    __m256i flag = _mm256_or_si256(differs, _mm256_or_si256(
        _mm256_xor_si256(ff, fm), _mm256_xor_si256(bf, mask8(j->back_mask + p))));
    __m256 alpha = j->per_pixel ? _mm256_loadu_ps(j->alpha + p) : _mm256_set1_ps(j->alpha[at.bi]);
    __m256i smooth = _mm256_and_si256(fm, _mm256_castps_si256(
        _mm256_cmp_ps(alpha, _mm256_set1_ps(j->smooth_alpha), _CMP_LT_OQ)));
    int f = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_or_si256(flag, smooth)));
    for (int i = 0; i < 8; i++) out[i] = (uint8_t)(f >> i & 1);
}

/* pixel_pairs of the 8 pixels from p (one row, none on the frame's border nor its last
 * row: every pair inside), the pairs' tests in lanes with pair_flags' operations. */
static void pixel_pairs8(const EdgesJob *j, int64_t p, Pos at, uint8_t *out) {
    __m256i fm = mask8(j->front_mask + p), bm = mask8(j->back_mask + p);
    uint8_t own[8];
    own_flags8(j, p, at, own);
    if (_mm256_testz_si256(_mm256_or_si256(fm, bm), _mm256_or_si256(fm, bm))) {
        /* 8 empty pixels: no pair flags either end (each test needs p covered) */
        memcpy(out, own, 8);
        return;
    }
    __m256 tol = _mm256_set1_ps(j->normal_tol), dtol = _mm256_set1_ps(j->depth_tol);
    __m256 absm = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
    __m256 dp = _mm256_loadu_ps(j->back_depth + p);
    __m256i bits = _mm256_setzero_si256(), one = _mm256_set1_epi32(1);
    for (int k = 0; k < 4; k++) {
        int64_t q = p + PAIR_DY[k] * j->w + PAIR_DX[k];
        __m256i both_f = _mm256_and_si256(fm, mask8(j->front_mask + q));
        __m256i both_b = _mm256_and_si256(bm, mask8(j->back_mask + q));
        __m256i f = _mm256_and_si256(both_f, _mm256_castps_si256(_mm256_cmp_ps(
            one_minus_dot8(j->front_normal + 3 * p, j->front_normal + 3 * q), tol, _CMP_GT_OQ)));
        __m256i b = _mm256_castps_si256(_mm256_cmp_ps(
            one_minus_dot8(j->back_normal + 3 * p, j->back_normal + 3 * q), tol, _CMP_GT_OQ));
        __m256 dq = _mm256_loadu_ps(j->back_depth + q);
        __m256 step = _mm256_and_ps(_mm256_sub_ps(dq, dp), absm);
        __m256i d1 = _mm256_castps_si256(_mm256_cmp_ps(
            step, _mm256_mul_ps(dtol, _mm256_and_ps(dp, absm)), _CMP_GT_OQ));
        __m256i d2 = _mm256_castps_si256(_mm256_cmp_ps(
            step, _mm256_mul_ps(dtol, _mm256_and_ps(dq, absm)), _CMP_GT_OQ));
        __m256i both = _mm256_or_si256(f, _mm256_and_si256(both_b, b));  /* flags p and q */
        __m256i for_p = _mm256_or_si256(both, _mm256_and_si256(both_b, d1));
        __m256i for_q = _mm256_or_si256(both, _mm256_and_si256(both_b, d2));
        bits = _mm256_or_si256(bits, _mm256_and_si256(for_p, one));
        bits = _mm256_or_si256(bits, _mm256_and_si256(for_q, _mm256_set1_epi32(16 << k)));
    }
    int32_t b8[8];
    _mm256_storeu_si256((__m256i *)b8, bits);
    for (int i = 0; i < 8; i++) out[i] = (uint8_t)(b8[i] | own[i]);
}
#endif

static void pairs_range(const void *job, int64_t begin, int64_t end) {
    const EdgesJob *j = (const EdgesJob *)job;
    Pos at = pos_at(begin, j->h, j->w);
    for (int64_t p = begin; p < end;) {
#ifdef TR_EDGES8
        if (at.x >= 1 && at.x + 9 <= j->w && at.y + 1 < j->h && p + 8 <= end) {
            pixel_pairs8(j, p, at, j->pairs + p);
            for (int i = 0; i < 8; i++) pos_step(&at, j->h, j->w);
            p += 8;
            continue;
        }
#endif
        j->pairs[p] = (uint8_t)pixel_pairs(j, p, &at);
        pos_step(&at, j->h, j->w);
        p++;
    }
}

static void gather_range(const void *job, int64_t begin, int64_t end) {
    const EdgesJob *j = (const EdgesJob *)job;
    const uint8_t *s = j->pairs;
    int64_t w = j->w;
    Pos at = pos_at(begin, j->h, j->w);
    for (int64_t p = begin; p < end; p++, pos_step(&at, j->h, j->w)) {
        int e = s[p] & PAIR_OWN;
        if (at.x > 0) e |= s[p - 1] & PAIR_E;
        if (at.y > 0) {
            e |= s[p - w] & PAIR_S;
            if (at.x > 0) e |= s[p - w - 1] & PAIR_SE;
            if (at.x < w - 1) e |= s[p - w + 1] & PAIR_SW;
        }
        j->edge[p] = (uint8_t)(e != 0);
    }
}

int torchrefract_edges(const EdgesJob *job, int threads) {
    int64_t n = job->b * job->h * job->w;
    int rc = tr_parallel_for(pairs_range, job, n, 4096, threads);
    return rc != 0 ? rc : tr_parallel_for(gather_range, job, n, 16384, threads);
}

int64_t torchrefract_edges_job_size(void) { return (int64_t)sizeof(EdgesJob); }
