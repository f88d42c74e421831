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
} SgAxes;

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

/* The trilinear read of ``channels`` (T, E, A) volumes at (a, z). */
static void trilinear(const float *vol, int channels, const SgTable *t, const SgAxes *a,
                      float z, float *out) {
    int64_t z0, z1;
    float wz;
    axis_nodes(z, t->nt, &z0, &z1, &wz);
    int64_t se = t->na, st = t->na * t->ne, sc = st * t->nt;
    float wx = a->wx, wy = a->wy;
    for (int c = 0; c < channels; c++) {
        const float *v = vol + c * sc;
        const float *v00 = v + z0 * st + a->y0 * se, *v01 = v + z0 * st + a->y1 * se;
        const float *v10 = v + z1 * st + a->y0 * se, *v11 = v + z1 * st + a->y1 * se;
        float c00 = v00[a->x0] * (1.0f - wx) + v00[a->x1] * wx;
        float c01 = v01[a->x0] * (1.0f - wx) + v01[a->x1] * wx;
        float c10 = v10[a->x0] * (1.0f - wx) + v10[a->x1] * wx;
        float c11 = v11[a->x0] * (1.0f - wx) + v11[a->x1] * wx;
        float c0 = c00 * (1.0f - wy) + c01 * wy, c1 = c10 * (1.0f - wy) + c11 * wy;
        out[c] = c0 * (1.0f - wz) + c1 * wz;
    }
}

/* sgfit.interface_energies: (1 - F, F) plus the roughness's change of the table's
 * energies, at incident cosine c on the interface ``a`` (distribution d, Fresnel f). */
static void interface_energies(const SgTable *t, const SgAxes *a, int64_t d, float c,
                               float f, float *e_t, float *e_r) {
    float dd[2];
    int64_t per = t->nt * t->ne * t->na;
    trilinear(t->dvol + d * 2 * per, 2, t, a, sg_theta(c), dd);  /* transmit, reflect */
    float et = 1.0f - f + a->fade * dd[0], er = f + a->fade * dd[1];
    *e_t = et > 0.0f ? et : 0.0f;
    *e_r = er > 0.0f ? er : 0.0f;
}

/* sgfit.sg_lookup (eqs. 8-9) of lobe ``lobe`` (0 transmit, 1 reflect), with the moment
 * (or, ``l2``, the L2-optimal) sharpness: sharpness k, the sine of the axis's signed angle
 * (the angle is asin of the clamped table value: its sine is that value, and lobe_axis
 * takes the sine, so no asin and sin/cos round trip), energy. */
static void sg_lookup_at(const SgTable *t, const SgAxes *a, int64_t d, int lobe, int l2,
                         float z, float *k, float *angle, float *energy) {
    float o[3];
    int64_t per = 3 * t->nt * t->ne * t->na;
    trilinear((l2 ? t->vol_l2 : t->vol) + (d * 2 + lobe) * per, 3, t, a, z, o);
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

/* The transmitted lobe's sharpness and the sine of its axis angle (sg_lookup, moment
 * sharpness). */
static void transmit_lobe(const SgTable *t, const SgAxes *a, int64_t d, float c, float *k,
                          float *angle) {
    float e;
    sg_lookup(t, a, d, 0, 0, c, k, angle, &e);
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

/* sgfit.spread_interface_energies: interface_energies (exact Fresnel at each direction)
 * averaged over a lobe of variance var around the axis at cos_theta; n_ratio is Fresnel's
 * argument (incident over far side), ``a`` the table's interface (eta = 1 / n_ratio). */
static void spread_interface_energies(const SgTable *t, const SgAxes *a, int64_t d,
                                      float cos_theta, float var, float n_ratio, float *e_t,
                                      float *e_r) {
    float cs[3], ts = 0.0f, rs = 0.0f;
    spread_cosines(cos_theta, var, cs);
    for (int i = 0; i < 3; i++) {
        float et, er;
        interface_energies(t, a, d, cs[i], fresnel(cs[i], n_ratio), &et, &er);
        ts = i == 0 ? SPREAD_W[0] * et : ts + SPREAD_W[i] * et;
        rs = i == 0 ? SPREAD_W[0] * er : rs + SPREAD_W[i] * er;
    }
    *e_t = ts;
    *e_r = rs;
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

/* rousiers.lobes.spread_energies: the table's transmitted and reflected energies (faded as
 * sg_lobe's) averaged over a lobe of variance var around the axis at cos_theta. */
static void spread_table_energies(const SgTable *t, const SgAxes *a, const SgAxes *a0,
                                  int64_t d, float cos_theta, float var, float *e_t,
                                  float *e_r) {
    float cs[3], ts = 0.0f, rs = 0.0f;
    int64_t per = t->nt * t->ne * t->na;
    spread_cosines(cos_theta, var, cs);
    for (int i = 0; i < 3; i++) {
        float e[2], z = sg_theta(cs[i]);
        trilinear(t->evol + d * 2 * per, 2, t, a, z, e);
        e[0] = e[0] > 0.0f ? e[0] : 0.0f;
        e[1] = e[1] > 0.0f ? e[1] : 0.0f;
        if (a->fade < 1.0f) {
            float e0[2];
            trilinear(t->evol + d * 2 * per, 2, t, a0, z, e0);
            e0[0] = e0[0] > 0.0f ? e0[0] : 0.0f;
            e0[1] = e0[1] > 0.0f ? e0[1] : 0.0f;
            e[0] = e0[0] + a->fade * (e[0] - e0[0]);
            e[1] = e0[1] + a->fade * (e[1] - e0[1]);
        }
        ts = i == 0 ? SPREAD_W[0] * e[0] : ts + SPREAD_W[i] * e[0];
        rs = i == 0 ? SPREAD_W[0] * e[1] : rs + SPREAD_W[i] * e[1];
    }
    *e_t = ts;
    *e_r = rs;
}

#endif
