/* What a ray sees when it leaves the object (lighting/envmap.py, lighting/lights.py), for
 * the fused shading kernels: the lat-long maps and the sphere lights of B views. */

#ifndef TORCHREFRACT_LIGHTING_H
#define TORCHREFRACT_LIGHTING_H

#include "optics.h"

typedef struct {
    const float *const *tex;    /* per view its map (H_b, W_b, 3) */
    const int64_t *tex_h, *tex_w;
    const float *rot_cos, *rot_sin;  /* (B,) the map's rotation about +Y: cos, sin of
                                      * -rotate_deg (envmap.rotate_y's, taken by torch) */
    const float *scale;         /* (B,) radiance scale */
    int64_t nl;                 /* lights per view (padding has radius 0) */
    const float *light_pos, *light_r, *light_le;  /* (B, L, 3), (B, L), (B, L, 3) */
    const double *gl_x, *gl_w;  /* Gauss-Legendre rule on [-1, 1] (lights._GL_X, _GL_W) */
    int64_t gl_n;
} Lights;

/* envmap.direction_to_uv of a direction (normalized, turned by -rotate_deg about +Y as
 * envmap.rotate_y turns it): (u, v) in [0, 1) x [0, 1]. */
static inline void map_uv(const Lights *L, int64_t b, const float *dir, float *u, float *v) {
    float len = norm3(dir);
    if (len < 1e-30f) len = 1e-30f;
    float d[3] = {dir[0] / len, dir[1] / len, dir[2] / len};
    float ca = L->rot_cos[b], sa = L->rot_sin[b];
    float x = ca * d[0] + sa * d[2], y = d[1], z = -sa * d[0] + ca * d[2];
    float uu = atan2f(x, -z) * (float)(0.5 / TR_PI);
    *u = uu - floorf(uu);
    *v = acosf(clampf(y, -1.0f, 1.0f)) * (float)(1.0 / TR_PI);
}

/* The four texels of one bilinear lookup in view b's map: rows y0, y1, (wrapped) columns
 * c0, c1, and the weights fx, fy. */
typedef struct {
    int64_t b, y0, y1, c0, c1;
    float fx, fy;
} EnvTap;

/* envmap.lookup's tap at the map coordinates (u, v). */
static inline EnvTap env_tap(const Lights *j, int64_t b, float u, float v) {
    int64_t h = j->tex_h[b], w = j->tex_w[b];
    /* the padded image's coordinates (one wrapped column each side), border-clamped */
    float gx = 2.0f * (u * (float)w - 0.5f + 1.0f) / (float)(w + 1) - 1.0f;
    float gy = 2.0f * (v * (float)(h - 1)) / (float)(h - 1) - 1.0f;
    /* grid_sample's unnormalization (aligned corners) and border clamp */
    float px = clampf((gx + 1.0f) * ((float)(w + 1) / 2.0f), 0.0f, (float)(w + 1));
    float py = clampf((gy + 1.0f) * ((float)(h - 1) / 2.0f), 0.0f, (float)(h - 1));
    int64_t x0 = (int64_t)floorf(px), y0 = (int64_t)floorf(py);
    int64_t x1 = x0 + 1 <= w + 1 ? x0 + 1 : x0, y1 = y0 + 1 <= h - 1 ? y0 + 1 : y0;
    /* (x - 1) mod w for x in [0, w + 1]: at most one wrap each way (no division) */
    int64_t c0 = x0 - 1, c1 = x1 - 1;
    c0 = c0 < 0 ? c0 + w : (c0 >= w ? c0 - w : c0);
    c1 = c1 < 0 ? c1 + w : (c1 >= w ? c1 - w : c1);
    EnvTap t = {b, y0, y1, c0, c1, px - (float)x0, py - (float)y0};
    return t;
}

/* envmap.lookup's tap along dir (normalized, turned as map_uv turns it). */
static inline EnvTap env_tap_dir(const Lights *j, int64_t b, const float *dir) {
    float u, v;
    map_uv(j, b, dir, &u, &v);
    return env_tap(j, b, u, v);
}

/* The bilinear read of a tap, scaled by the view's radiance scale. */
static void env_read(const Lights *j, const EnvTap *p, float *out) {
    int64_t w = j->tex_w[p->b];
    const float *t = j->tex[p->b];
    for (int c = 0; c < 3; c++) {
        float top = t[(p->y0 * w + p->c0) * 3 + c] * (1.0f - p->fx)
                    + t[(p->y0 * w + p->c1) * 3 + c] * p->fx;
        float bot = t[(p->y1 * w + p->c0) * 3 + c] * (1.0f - p->fx)
                    + t[(p->y1 * w + p->c1) * 3 + c] * p->fx;
        out[c] = (top * (1.0f - p->fy) + bot * p->fy) * j->scale[p->b];
    }
}

/* envmap.lookup: bilinear in the lat-long map, wrapped in u, clamped in v. */
static void env_lookup(const Lights *j, int64_t b, const float *dir, float *out) {
    EnvTap p = env_tap_dir(j, b, dir);
    env_read(j, &p, out);
}

/* The tap along dir, its texel rows asked into the cache: a pixel's lookups then overlap
 * their memory reads with the work done before them (the refracted directions scatter
 * over the map); env_read reads them later. */
static inline EnvTap env_prefetch(const Lights *j, int64_t b, const float *dir) {
    EnvTap p = env_tap_dir(j, b, dir);
    int64_t w = j->tex_w[b];
    __builtin_prefetch(j->tex[b] + (p.y0 * w + p.c0) * 3);
    __builtin_prefetch(j->tex[b] + (p.y1 * w + p.c0) * 3);
    return p;
}

/* One view's SG-pre-convolved pyramid (lighting/sg_pyramid.py, SGPyramid): the padded
 * map ``base`` (3, bh, bw) and the packed levels ``atlas`` (3, ah, aw), channels first;
 * ``meta``: v0, n, then kap_levels (n + 2: the map's, the n levels', the mean's), then
 * rects ((n + 2) x 4: y0, x0, h, w), then the n level sharpnesses, as floats. */
typedef struct {
    const float *const *base, *const *atlas, *const *meta;
    const int64_t *base_hw, *atlas_hw;  /* (B, 2) */
} SgEnv;

/* Bilinear read (grid_sample: border padding, aligned corners) of the level at rect
 * ``r`` of a (3, ih, iw) image at (u, v). */
static void sg_sample(const float *img, int64_t ih, int64_t iw, const float *r, float u,
                      float v, float *out) {
    float x = r[1] + 1.0f + u * r[3] - 0.5f, y = r[0] + v * (r[2] - 1.0f);
    float gx = 2.0f * x / (float)(iw - 1) - 1.0f, gy = 2.0f * y / (float)(ih - 1) - 1.0f;
    float px = clampf((gx + 1.0f) * ((float)(iw - 1) / 2.0f), 0.0f, (float)(iw - 1));
    float py = clampf((gy + 1.0f) * ((float)(ih - 1) / 2.0f), 0.0f, (float)(ih - 1));
    int64_t x0 = (int64_t)floorf(px), y0 = (int64_t)floorf(py);
    int64_t x1 = x0 + 1 < iw ? x0 + 1 : x0, y1 = y0 + 1 < ih ? y0 + 1 : y0;
    float fx = px - (float)x0, fy = py - (float)y0;
    for (int c = 0; c < 3; c++) {
        const float *p = img + c * ih * iw;
        float top = p[y0 * iw + x0] * (1.0f - fx) + p[y0 * iw + x1] * fx;
        float bot = p[y1 * iw + x0] * (1.0f - fx) + p[y1 * iw + x1] * fx;
        out[c] = top * (1.0f - fy) + bot * fy;
    }
}

/* sg_pyramid.sg_lookup_env: the map convolved with a normalized SG of sharpness k (inf: a
 * plain lookup) around dir: the two levels around k, blended linearly in the effective
 * sharpness k / (1 + v0 k) (_blend_weights). */
static void sg_env_lookup(const Lights *L, const SgEnv *e, int64_t b, const float *dir,
                          float k, float *out) {
    float u, v;
    map_uv(L, b, dir, &u, &v);
    const float *m = e->meta[b];
    float v0 = m[0];
    int64_t n = (int64_t)m[1];
    const float *kap_levels = m + 2, *rects = m + 2 + (n + 2), *ks = rects + 4 * (n + 2);
    int64_t i = 0;
    while (i < n && ks[i] > k) i++;  /* torch.searchsorted(-ks, -k) */
    float kap = isinf(k) ? 1.0f / v0 : k / (1.0f + v0 * k);
    float hi_k = kap_levels[i], lo_k = kap_levels[i + 1];
    float t = (hi_k - kap) / (hi_k - lo_k);
    float lo[3], hi[3];
    const int64_t *ahw = e->atlas_hw + 2 * b, *bhw = e->base_hw + 2 * b;
    sg_sample(e->atlas[b], ahw[0], ahw[1], rects + 4 * (i + 1), u, v, hi);
    if (i == 0) sg_sample(e->base[b], bhw[0], bhw[1], rects, u, v, lo);
    else sg_sample(e->atlas[b], ahw[0], ahw[1], rects + 4 * i, u, v, lo);
    for (int c = 0; c < 3; c++) out[c] = (lo[c] * (1.0f - t) + hi[c] * t) * L->scale[b];
}

/* lights.hit_lights: the nearest sphere light along a ray (inf where none). */
static float hit_light(const Lights *j, int64_t b, const float *o, const float *d,
                       int64_t *which) {
    float best = INFINITY;
    *which = -1;
    for (int64_t l = 0; l < j->nl; l++) {
        const float *p = j->light_pos + (b * j->nl + l) * 3;
        float r = j->light_r[b * j->nl + l];
        float oc[3] = {o[0] - p[0], o[1] - p[1], o[2] - p[2]};
        float bq = dot3(oc, d), c = dot3(oc, oc) - r * r;
        float disc = bq * bq - c;
        float sq = sqrtf(disc > 0.0f ? disc : 0.0f);
        float t0 = -bq - sq, t1 = -bq + sq;
        float t = t0 > 0.0f ? t0 : t1;
        if (disc >= 0.0f && t > 0.0f && r > 0.0f && t < best) {
            best = t;
            *which = l;
        }
    }
    return best;
}

/* lights.incident_radiance: the environment, or a light the ray hits (p: d's tap,
 * env_prefetch). */
static void incident_at(const Lights *j, int64_t b, const float *o, const float *d,
                        const EnvTap *p, float *out) {
    int64_t l;
    if (j->nl > 0 && isfinite(hit_light(j, b, o, d, &l))) {
        for (int c = 0; c < 3; c++) out[c] = j->light_le[(b * j->nl + l) * 3 + c];
        return;
    }
    env_read(j, p, out);
}

/* lights.incident_radiance along d. */
static void incident(const Lights *j, int64_t b, const float *o, const float *d, float *out) {
    EnvTap p = env_tap_dir(j, b, d);
    incident_at(j, b, o, d, &p, out);
}

/* torch.special.i0e: exp(-|x|) I0(x), by its power series up to 30 and its asymptotic
 * series beyond (both to double rounding there). */
static double i0e(double x) {
    x = fabs(x);
    if (x <= 30.0) {
        double q = 0.25 * x * x, term = 1.0, sum = 1.0;
        for (int k = 1; k < 200 && term > 1e-17 * sum; k++) {
            term *= q / ((double)k * (double)k);
            sum += term;
        }
        return sum * exp(-x);
    }
    double t = 1.0, sum = 1.0;
    for (int k = 1; k < 40 && fabs(t) > 1e-17; k++) {
        t *= (2.0 * k - 1.0) * (2.0 * k - 1.0) / (8.0 * k * x);
        sum += t;
    }
    return sum / sqrt(2.0 * TR_PI * x);
}

/* lights.sg_light_coverage: the fraction of a normalized SG lobe's mass (axis dir,
 * sharpness k, from origin o) on light l's disc, by the Rice integral on the chord map
 * (Gauss-Legendre), in float64 as the tensor code takes it. */
static double light_coverage(const Lights *L, int64_t b, int64_t l, const float *o,
                             const float *dir, float k) {
    const float *p = L->light_pos + (b * L->nl + l) * 3;
    double r = L->light_r[b * L->nl + l];
    if (!(r > 0.0)) return 0.0;
    double to[3] = {(double)p[0] - o[0], (double)p[1] - o[1], (double)p[2] - o[2]};
    double d = sqrt(to[0] * to[0] + to[1] * to[1] + to[2] * to[2]);
    if (d < 1e-30) d = 1e-30;
    if (d <= r) return 1.0;
    double rd = r / d, ct = 1.0 - rd * rd;
    double cos_t = sqrt(ct > 0.0 ? ct : 0.0);
    double cg = (to[0] / d) * dir[0] + (to[1] / d) * dir[1] + (to[2] / d) * dir[2];
    cg = cg < -1.0 ? -1.0 : (cg > 1.0 ? 1.0 : cg);
    double big_r = sqrt(fmax(2.0 * (1.0 - cos_t), 0.0)), c_g = sqrt(fmax(2.0 * (1.0 - cg), 0.0));
    double kk = k < 1e12f ? (double)k : 1e12;
    double s = 1.0 / sqrt(kk > 1e-12 ? kk : 1e-12), s2 = s * s;
    double a = fmax(c_g - 8.0 * s, 0.0), bb = fmin(big_r, c_g + 8.0 * s);
    double half = fmax((bb - a) * 0.5, 0.0), mass = 0.0;
    for (int64_t i = 0; i < L->gl_n; i++) {
        double x = (a + bb) * 0.5 + half * L->gl_x[i];
        double f = (x / s2) * exp(-((x - c_g) * (x - c_g)) / (2.0 * s2)) * i0e(x * c_g / s2);
        mass += f * L->gl_w[i];
    }
    mass = mass * half / (-expm1(-2.0 * kk));
    return mass < 0.0 ? 0.0 : (mass > 1.0 ? 1.0 : mass);
}

/* lights.incident_radiance_sg: the environment convolved with the lobe (sg_env_lookup);
 * with sphere lights, the share of the lobe on each light's disc sees the light (a plain
 * lookup, k = inf: the light the axis hits). */
static void incident_sg(const Lights *L, const SgEnv *e, int64_t b, const float *o,
                        const float *dir, float k, float *out) {
    sg_env_lookup(L, e, b, dir, k, out);
    if (L->nl == 0) return;
    int64_t hit;
    float t = hit_light(L, b, o, dir, &hit);
    if (isinf(k)) {
        if (isfinite(t))
            for (int c = 0; c < 3; c++) out[c] = L->light_le[(b * L->nl + hit) * 3 + c];
        return;
    }
    float cover[64], sum = 0.0f;
    int64_t nl = L->nl < 64 ? L->nl : 64;
    for (int64_t l = 0; l < nl; l++) {
        cover[l] = (float)light_coverage(L, b, l, o, dir, k);
        sum = l == 0 ? cover[l] : sum + cover[l];
    }
    float total = sum > 1.0f ? 1.0f : sum, scale = total / (sum > 1e-30f ? sum : 1e-30f);
    for (int c = 0; c < 3; c++) {
        float lights = 0.0f;
        for (int64_t l = 0; l < nl; l++) {
            float v = cover[l] * scale * L->light_le[(b * L->nl + l) * 3 + c];
            lights = l == 0 ? v : lights + v;
        }
        out[c] = (1.0f - total) * out[c] + lights;
    }
}

#endif
