/* The SG table's lookups (optics/sgfit.py) for the fused shading kernels: trilinear as
 * grid_sample's (border padding, aligned corners), in float32. */

#ifndef TORCHREFRACT_SGTABLE_H
#define TORCHREFRACT_SGTABLE_H

#include "optics.h"

/* (2 dist * 2 lobe, 3 ch, T, E, A) energy, log k, sin(axis angle); (2, 2, T, E, A) energy
 * change (SGTable.volume, SGTable.energy_change_volume); the axes' ranges. */
typedef struct {
    const float *vol, *dvol;
    const float *vol_l2;        /* as vol with the L2-optimal sharpness (GGX's lobes) */
    const float *evol;          /* (2, 2, T, E, A) energy (SGTable.energy_volume) */
    int64_t nt, ne, na;
    float eta_max, la0, la1, alpha_min, alpha_floor, log_k_min, log_k_max;
} SgTable;

/* One interface's place on the table's (alpha, eta) axes, the same for every pixel of a
 * view (uniform roughness): the two nodes and weight of each axis, as grid_sample finds
 * them (border padding, aligned corners), log alpha and the matched fade. */
typedef struct {
    int64_t x0, x1, y0, y1;
    float wx, wy, log_a, fade;
    /* The view's slices (sg_slices) for distribution slice_d: each looked-up volume's
     * channels' (alpha, eta) bilinear parts at the T theta nodes, (SG_SLICES, T); NULL
     * where the axes are a pixel's own (sg_axes): trilinear reads the volume. */
    const float *slice;
    int64_t slice_d;
} SgAxes;

/* The slots of a view's slices: per distribution, the energy change (2 channels), the
 * moment-sharpness lobes (transmit, reflect: 3 each), the L2-sharpness ones, the energy
 * (2): SgTable's dvol, vol, vol_l2, evol in the order the lookups read them. */
enum { SG_DV = 0, SG_V = 2, SG_VL2 = 8, SG_EV = 14, SG_SLICES = 16 };

/* The volume of a slot (lobe: the lobe volumes' 0 transmit, 1 reflect) for distribution d,
 * and its channels. */
static inline const float *sg_volume(const SgTable *t, int64_t d, int slot, int lobe,
                                     int *channels) {
    int64_t per = t->nt * t->ne * t->na;
    switch (slot) {
    case SG_DV: *channels = 2; return t->dvol + d * 2 * per;
    case SG_V: *channels = 3; return t->vol + (d * 2 + lobe) * 3 * per;
    case SG_VL2: *channels = 3; return t->vol_l2 + (d * 2 + lobe) * 3 * per;
    default: *channels = 2; return t->evol + d * 2 * per;
    }
}

static void axis_nodes(float g, int64_t size, int64_t *i0, int64_t *i1, float *w) {
    float f = clampf((g + 1.0f) * ((float)(size - 1) / 2.0f), 0.0f, (float)(size - 1));
    *i0 = (int64_t)floorf(f);
    *i1 = *i0 + 1 < size ? *i0 + 1 : *i0;
    *w = f - (float)*i0;
}

/* sgfit.matched_fade: the roughness's energy change faded out at eta = 1. */
static inline float matched_fade(float eta) {
    float x = fabsf(logf(eta)) / (float)log1p(0.1);
    x = clampf(x, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

/* sgfit._coordinates' x (log alpha) and y (log eta), for relative index eta (far side
 * over view side) and roughness alpha. */
static void sg_axes(const SgTable *t, float eta, float alpha, SgAxes *a) {
    float y = logf(clampf(eta, 1.0f / t->eta_max, t->eta_max)) / logf(t->eta_max);
    float la = logf(alpha > t->alpha_floor ? alpha : t->alpha_floor);
    float x = (clampf(la, t->la0, t->la1) - t->la0) * (2.0f / (t->la1 - t->la0)) - 1.0f;
    axis_nodes(x, t->na, &a->x0, &a->x1, &a->wx);
    axis_nodes(y, t->ne, &a->y0, &a->y1, &a->wy);
    a->log_a = la;
    a->fade = matched_fade(eta);
    a->slice = NULL;
    a->slice_d = -1;
}

/* sgfit._coordinates' z: theta_o = acos(c) (as _safe_acos01 takes it), normalized. */
static inline float sg_theta(float c) {
    c = clampf(c, 0.0f, 1.0f);
    const float eps2 = 1.1920929e-07f * 1.1920929e-07f;
    float s2 = 1.0f - c * c;
    if (s2 < eps2) s2 = eps2;
    float s = sqrtf(s2);
    float theta = c > 0.5f ? (float)tr_asin_d(s < 0.9f ? s : 0.9f)
                           : (float)tr_acos_d(c < 0.5f ? c : 0.5f);
    return clampf(theta, 0.0f, (float)(0.5 * TR_PI)) * (float)(4.0 / TR_PI) - 1.0f;
}

#if defined(__AVX2__) && defined(__FMA__)
/* sg_theta of four cosines in lanes, with the same float and double operations
 * (tr_asin_d's and tr_acos_d's branches as selects: one polynomial a lane, on the argument
 * its branch takes; their copysign is the identity on these non-negative arguments), so
 * the same bits. */
static inline v4f sg_theta4(v4f c) {
    const float eps2 = 1.1920929e-07f * 1.1920929e-07f;
    c = SEL4F(c < K4F(v4f, 0.0f), K4F(v4f, 0.0f), SEL4F(c > K4F(v4f, 1.0f), K4F(v4f, 1.0f), c));
    v4f s2 = K4F(v4f, 1.0f) - c * c;
    s2 = SEL4F(s2 < K4F(v4f, eps2), K4F(v4f, eps2), s2);
    v4f s = sqrt4f(s2);
    v4i big = c > K4F(v4f, 0.5f);  /* asin of min(s, 0.9), else acos of min(c, 0.5) */
    v4f arg = SEL4F(big, SEL4F(s < K4F(v4f, 0.9f), s, K4F(v4f, 0.9f)),
                    SEL4F(c < K4F(v4f, 0.5f), c, K4F(v4f, 0.5f)));
    __m256d a = _mm256_cvtps_pd((__m128)arg), half = _mm256_set1_pd(0.5);
    __m256d far = _mm256_cmp_pd(a, half, _CMP_GT_OQ);  /* (only asin's can be) */
    __m256d zb = _mm256_mul_pd(half, _mm256_sub_pd(_mm256_set1_pd(1.0), a));
    __m256d u = _mm256_blendv_pd(a, _mm256_sqrt_pd(zb), far);
    __m256d v = _mm256_blendv_pd(_mm256_mul_pd(a, a), zb, far);
    __m256d p = _mm256_set1_pd(TR_ASIN_Q[0]);
    for (int i = 1; i < 9; i++) p = _mm256_fmadd_pd(p, v, _mm256_set1_pd(TR_ASIN_Q[i]));
    __m256d r = _mm256_fmadd_pd(_mm256_mul_pd(u, v), p, u), pi2 = _mm256_set1_pd(TR_PI / 2);
    __m256d asin_r = _mm256_blendv_pd(r, _mm256_sub_pd(pi2, _mm256_mul_pd(_mm256_set1_pd(2.0),
                                                                          r)), far);
    __m256d bigd = _mm256_castsi256_pd(_mm256_cvtepi32_epi64((__m128i)big));
    v4f theta = (v4f)_mm256_cvtpd_ps(_mm256_blendv_pd(_mm256_sub_pd(pi2, r), asin_r, bigd));
    const v4f top = K4F(v4f, (float)(0.5 * TR_PI));
    theta = SEL4F(theta < K4F(v4f, 0.0f), K4F(v4f, 0.0f), SEL4F(theta > top, top, theta));
    return theta * K4F(v4f, (float)(4.0 / TR_PI)) - K4F(v4f, 1.0f);
}

/* Four values of x from i, the last of the m repeated past the end (a partial group of
 * four lanes; z may be x: each group is read before it is written). */
static inline v4f lanes_from(const float *x, int i, int m) {
    v4f v;
    for (int q = 0; q < 4; q++) v[q] = x[i + q < m ? i + q : m - 1];
    return v;
}
#endif

/* sg_theta of m cosines c into z (a spread's three, a block's), four at a time in lanes
 * where built for it, the same bits. */
static inline void sg_theta_n(const float *c, int m, float *z) {
#if defined(__AVX2__) && defined(__FMA__)
    for (int i = 0; i < m; i += 4) {
        v4f out = sg_theta4(lanes_from(c, i, m));
        for (int q = 0; q < 4 && i + q < m; q++) z[i + q] = out[q];
    }
#else
    for (int i = 0; i < m; i++) z[i] = sg_theta(c[i]);
#endif
}

/* The (alpha, eta) bilinear part of trilinear at one theta node: x, then y, on the
 * node's (E, A) plane ``p`` (row stride se). The one formula of trilinear and sg_slices. */
static inline float sg_bilinear(const float *p, int64_t se, const SgAxes *a) {
    const float *r0 = p + a->y0 * se, *r1 = p + a->y1 * se;
    float wx = a->wx, wy = a->wy;
    float c0 = r0[a->x0] * (1.0f - wx) + r0[a->x1] * wx;
    float c1 = r1[a->x0] * (1.0f - wx) + r1[a->x1] * wx;
    return c0 * (1.0f - wy) + c1 * wy;
}

/* The trilinear read of ``channels`` (T, E, A) volumes at (a, z); ``slice``: the same
 * channels' bilinear parts at each theta node (sg_slices), NULL: from the volume. */
static void trilinear(const float *vol, const float *slice, int channels, const SgTable *t,
                      const SgAxes *a, float z, float *out) {
    int64_t z0, z1;
    float wz;
    axis_nodes(z, t->nt, &z0, &z1, &wz);
    int64_t se = t->na, st = t->na * t->ne, sc = st * t->nt;
    for (int c = 0; c < channels; c++) {
        float c0, c1;
        if (slice) {
            c0 = slice[c * t->nt + z0];
            c1 = slice[c * t->nt + z1];
        } else {
            const float *v = vol + c * sc;
            c0 = sg_bilinear(v + z0 * st, se, a);
            c1 = sg_bilinear(v + z1 * st, se, a);
        }
        out[c] = c0 * (1.0f - wz) + c1 * wz;
    }
}

/* trilinear of a slot's volume (sg_volume) for distribution d: from the axes' slices
 * where they hold d's, else from the volume. */
static inline void sg_read(const SgTable *t, const SgAxes *a, int64_t d, int slot, int lobe,
                           float z, float *out) {
    int channels;
    const float *vol = sg_volume(t, d, slot, lobe, &channels);
    const float *slice = a->slice && a->slice_d == d
                             ? a->slice + (slot + lobe * channels) * t->nt : NULL;
    trilinear(vol, slice, channels, t, a, z, out);
}

/* A view's slices at its axes ``a`` for distribution d into ``buf`` (SG_SLICES * T
 * floats), then held by ``a``: every slot's channels' sg_bilinear at each theta node, the
 * values trilinear computes per lookup. Axes outside the table (a non-finite roughness or
 * index) keep none. */
static void sg_slices(const SgTable *t, int64_t d, SgAxes *a, float *buf) {
    if (!(a->x0 >= 0 && a->x1 < t->na && a->y0 >= 0 && a->y1 < t->ne && d >= 0 && d < 2))
        return;
    static const int slots[] = {SG_DV, SG_V, SG_V, SG_VL2, SG_VL2, SG_EV};
    static const int lobes[] = {0, 0, 1, 0, 1, 0};
    int64_t se = t->na, st = t->na * t->ne, sc = st * t->nt;
    for (int s = 0; s < 6; s++) {
        int channels;
        const float *vol = sg_volume(t, d, slots[s], lobes[s], &channels);
        float *o = buf + (slots[s] + lobes[s] * channels) * t->nt;
        for (int c = 0; c < channels; c++)
            for (int64_t z = 0; z < t->nt; z++)
                o[c * t->nt + z] = sg_bilinear(vol + c * sc + z * st, se, a);
    }
    a->slice = buf;
    a->slice_d = d;
}

/* sgfit.interface_energies: (1 - F, F) plus the roughness's change of the table's
 * energies, at incident cosine c on the interface ``a`` (distribution d, Fresnel f). */
static void interface_energies_at(const SgTable *t, const SgAxes *a, int64_t d, float z,
                                  float f, float *e_t, float *e_r) {
    float dd[2];
    sg_read(t, a, d, SG_DV, 0, z, dd);  /* transmit, reflect */
    float et = 1.0f - f + a->fade * dd[0], er = f + a->fade * dd[1];
    *e_t = et > 0.0f ? et : 0.0f;
    *e_r = er > 0.0f ? er : 0.0f;
}

/* interface_energies_at at three table coordinates z (Fresnel f): where the axes hold the
 * slices of distribution d, the three reads in lanes (axis_nodes and trilinear's slice
 * reads, op for op: the same bits), else one by one. */
static inline void interface_energies3(const SgTable *t, const SgAxes *a, int64_t d,
                                       const float *z, const float *f, float *e_t,
                                       float *e_r) {
#if defined(__AVX2__) && defined(__FMA__)
    if (a->slice && a->slice_d == d && t->nt < INT32_MAX / SG_SLICES) {
        const float top = (float)(t->nt - 1);
        v4f g = {z[0], z[1], z[2], z[2]};
        v4f x = (g + K4F(v4f, 1.0f)) * K4F(v4f, top / 2.0f);  /* axis_nodes */
        x = SEL4F(x < K4F(v4f, 0.0f), K4F(v4f, 0.0f), SEL4F(x > K4F(v4f, top), K4F(v4f, top), x));
        v4f fl = (v4f)_mm_floor_ps((__m128)x), w = x - fl;
        __m128i i0 = _mm_cvttps_epi32((__m128)fl);
        __m128i i1 = _mm_min_epi32(_mm_add_epi32(i0, _mm_set1_epi32(1)),
                                   _mm_set1_epi32((int)t->nt - 1));
        const float *dv = a->slice + SG_DV * t->nt;  /* (2 channels, T) */
        v4f dd[2];
        for (int c = 0; c < 2; c++) {
            v4f c0 = (v4f)_mm_i32gather_ps(dv + c * t->nt, i0, 4);
            v4f c1 = (v4f)_mm_i32gather_ps(dv + c * t->nt, i1, 4);
            dd[c] = c0 * (K4F(v4f, 1.0f) - w) + c1 * w;
        }
        v4f fv = {f[0], f[1], f[2], f[2]}, fade = K4F(v4f, a->fade);
        v4f et = K4F(v4f, 1.0f) - fv + fade * dd[0], er = fv + fade * dd[1];
        et = SEL4F(et > K4F(v4f, 0.0f), et, K4F(v4f, 0.0f));
        er = SEL4F(er > K4F(v4f, 0.0f), er, K4F(v4f, 0.0f));
        for (int i = 0; i < 3; i++) {
            e_t[i] = et[i];
            e_r[i] = er[i];
        }
        return;
    }
#endif
    for (int i = 0; i < 3; i++) interface_energies_at(t, a, d, z[i], f[i], e_t + i, e_r + i);
}

/* interface_energies_at at incident cosine c (its table coordinate sg_theta(c)). */
static inline void interface_energies(const SgTable *t, const SgAxes *a, int64_t d, float c,
                                      float f, float *e_t, float *e_r) {
    interface_energies_at(t, a, d, sg_theta(c), f, e_t, e_r);
}

/* sgfit.sg_lookup (eqs. 8-9) of lobe ``lobe`` (0 transmit, 1 reflect), with the moment
 * (or, ``l2``, the L2-optimal) sharpness: sharpness k, the sine of the axis's signed angle
 * (the angle is asin of the clamped table value: its sine is that value, and lobe_axis
 * takes the sine, so no asin and sin/cos round trip), energy. */
static void sg_lookup_at(const SgTable *t, const SgAxes *a, int64_t d, int lobe, int l2,
                         float z, float *k, float *angle, float *energy) {
    float o[3];
    sg_read(t, a, d, l2 ? SG_VL2 : SG_V, lobe, z, o);
    *angle = clampf(o[2], -1.0f + 1e-7f, 1.0f - 1e-7f);
    float extra = t->la0 - a->log_a;
    float log_k = o[1] + 2.0f * (extra > 0.0f ? extra : 0.0f);
    *k = expf(clampf(log_k, t->log_k_min, t->log_k_max));
    *energy = o[0] > 0.0f ? o[0] : 0.0f;
}

/* sg_lookup_at at incident cosine c (its table coordinate sg_theta(c); sg_lookup_at takes
 * it computed once where one cosine is looked up more than once). */
static inline void sg_lookup(const SgTable *t, const SgAxes *a, int64_t d, int lobe, int l2,
                             float c, float *k, float *angle, float *energy) {
    sg_lookup_at(t, a, d, lobe, l2, sg_theta(c), k, angle, energy);
}

/* The transmitted lobe's sharpness and the sine of its axis angle (sg_lookup_at, moment
 * sharpness) at table coordinate z. */
static void transmit_lobe_at(const SgTable *t, const SgAxes *a, int64_t d, float z, float *k,
                             float *angle) {
    float e;
    sg_lookup_at(t, a, d, 0, 0, z, k, angle, &e);
}

/* sgfit.spread_cosines: the three incident cosines (weights 1/4, 1/4, 1/2) standing for a
 * lobe of variance var around the axis at cos_theta. */
static void spread_cosines(float cos_theta, float var, float *cs) {
    float v = var > 1e-12f ? var : 1e-12f;
    float k = 1.0f / v;
    float mean_cos;
    if (k < 0.1f) mean_cos = k / 3.0f - k * k * k / 45.0f;
    else mean_cos = 1.0f / tanhf(k) - 1.0f / k;
    float s2 = clampf(2.0f * mean_cos / k, 1e-12f, 1.0f);
    int ray = var <= 0.0f;
    float sr = ray ? 0.0f : sqrtf(s2);
    float omc = 1.0f - s2;
    float cr = ray ? 1.0f : sqrtf(omc > 0.0f ? omc : 0.0f);
    float c = clampf(cos_theta, -1.0f, 1.0f);
    float sc = 1.0f - c * c;
    float s = sqrtf(sc > 1e-12f ? sc : 1e-12f);
    cs[0] = clampf(c * cr + s * sr, 0.0f, 1.0f);
    cs[1] = clampf(c * cr - s * sr, 0.0f, 1.0f);
    cs[2] = clampf(c * cr, 0.0f, 1.0f);
}

static const float SPREAD_W[3] = {0.25f, 0.25f, 0.5f};

/* The spread's weighted sums of the energies et, er at its three cosines. */
static inline void spread_sum(const float *et, const float *er, float *e_t, float *e_r) {
    float ts = 0.0f, rs = 0.0f;
    for (int i = 0; i < 3; i++) {
        ts = i == 0 ? SPREAD_W[0] * et[i] : ts + SPREAD_W[i] * et[i];
        rs = i == 0 ? SPREAD_W[0] * er[i] : rs + SPREAD_W[i] * er[i];
    }
    *e_t = ts;
    *e_r = rs;
}

/* fresnel of m cosines c at their own eta into f (a spread's three, a block's), four at a
 * time in lanes where built for it, the same bits. */
static inline void fresnel_n(const float *c, const float *eta, int m, float *f) {
#if defined(__AVX2__) && defined(__FMA__)
    for (int i = 0; i < m; i += 4) {
        v4f r = fresnel4f(lanes_from(c, i, m), lanes_from(eta, i, m));
        for (int q = 0; q < 4 && i + q < m; q++) f[i + q] = r[q];
    }
#else
    for (int i = 0; i < m; i++) f[i] = fresnel(c[i], eta[i]);
#endif
}

/* sgfit.spread_interface_energies: interface_energies (exact Fresnel at each direction)
 * averaged over a lobe of variance var around the axis at cos_theta; n_ratio is Fresnel's
 * argument (incident over far side), ``a`` the table's interface (eta = 1 / n_ratio). */
static void spread_interface_energies(const SgTable *t, const SgAxes *a, int64_t d,
                                      float cos_theta, float var, float n_ratio, float *e_t,
                                      float *e_r) {
    float cs[3], z[3], f[3], et[3], er[3], etas[3] = {n_ratio, n_ratio, n_ratio};
    spread_cosines(cos_theta, var, cs);
    sg_theta_n(cs, 3, z);
    fresnel_n(cs, etas, 3, f);
    interface_energies3(t, a, d, z, f, et, er);
    spread_sum(et, er, e_t, e_r);
}

/* rousiers.lobes.sg_lobe: sg_lookup with GGX's L2 sharpness, its energy faded towards the
 * smallest roughness's near IOR 1 (``a0``: the same interface at alpha_min). */
static void sg_lobe_at(const SgTable *t, const SgAxes *a, const SgAxes *a0, int64_t d,
                       int lobe, float z, float *k, float *angle, float *energy) {
    sg_lookup_at(t, a, d, lobe, d == 1, z, k, angle, energy);
    if (a->fade < 1.0f) {
        float k0, t0, e0;
        sg_lookup_at(t, a0, d, lobe, 0, z, &k0, &t0, &e0);
        *energy = e0 + a->fade * (*energy - e0);
    }
}

/* sg_lobe_at at incident cosine c. */
static inline void sg_lobe(const SgTable *t, const SgAxes *a, const SgAxes *a0, int64_t d,
                           int lobe, float c, float *k, float *angle, float *energy) {
    sg_lobe_at(t, a, a0, d, lobe, sg_theta(c), k, angle, energy);
}

/* The table's transmitted and reflected energies e (2) at table coordinate z, faded as
 * sg_lobe's (``a0``: the interface at alpha_min). */
static inline void table_energies_at(const SgTable *t, const SgAxes *a, const SgAxes *a0,
                                     int64_t d, float z, float *e) {
    sg_read(t, a, d, SG_EV, 0, z, e);
    e[0] = e[0] > 0.0f ? e[0] : 0.0f;
    e[1] = e[1] > 0.0f ? e[1] : 0.0f;
    if (a->fade < 1.0f) {
        float e0[2];
        sg_read(t, a0, d, SG_EV, 0, z, e0);
        e0[0] = e0[0] > 0.0f ? e0[0] : 0.0f;
        e0[1] = e0[1] > 0.0f ? e0[1] : 0.0f;
        e[0] = e0[0] + a->fade * (e[0] - e0[0]);
        e[1] = e0[1] + a->fade * (e[1] - e0[1]);
    }
}

/* table_energies_at at a spread's three table coordinates zs, summed with its weights. */
static inline void table_energies_spread(const SgTable *t, const SgAxes *a, const SgAxes *a0,
                                         int64_t d, const float *zs, float *e_t, float *e_r) {
    float et[3], er[3];
    for (int i = 0; i < 3; i++) {
        float e[2];
        table_energies_at(t, a, a0, d, zs[i], e);
        et[i] = e[0];
        er[i] = e[1];
    }
    spread_sum(et, er, e_t, e_r);
}

/* rousiers.lobes.spread_energies: the table's transmitted and reflected energies (faded as
 * sg_lobe's) averaged over a lobe of variance var around the axis at cos_theta. */
static void spread_table_energies(const SgTable *t, const SgAxes *a, const SgAxes *a0,
                                  int64_t d, float cos_theta, float var, float *e_t,
                                  float *e_r) {
    float cs[3], zs[3];
    spread_cosines(cos_theta, var, cs);
    sg_theta_n(cs, 3, zs);
    table_energies_spread(t, a, a0, d, zs, e_t, e_r);
}

#endif
