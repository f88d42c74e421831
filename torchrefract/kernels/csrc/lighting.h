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

/* atan(t) = t + t^3 P(t^2) for t in [0, tan(pi/8)]: P's minimax coefficients, highest
 * power first (relative error 1e-13), for tr_atan2_d and tr_atan2_4d. */
static const double TR_ATAN_P[8] = {
    0.032956795418701366, -0.060273074609466753, 0.076048000460782915,
    -0.090841018953464295, 0.11110819716745676, -0.142857081103604,
    0.19999999949854793, -0.33333333333266199};

/* atan2 of float values in double, one lane of tr_atan2_4d (below; the same steps): t =
 * min / max of |x|, |y| (or (t - 1) / (t + 1) above tan(pi/8), plus pi/4), atan(t) = t +
 * t^3 P(t^2) (relative error 1e-13), then pi/2 - r where |y| > |x|, pi - r where x's sign
 * bit is set, and y's sign. */
static inline double tr_atan2_d(double y, double x) {
    double ay = fabs(y), ax = fabs(x);
    double lo = ay < ax ? ay : ax, hi = ay > ax ? ay : ax;
    int big = lo > 0.41421356237309503 * hi;
    double num = big ? lo - hi : lo, den = big ? lo + hi : hi;
    if (den == 0.0) den = 1.0;  /* both zero: t = 0 (atan2f(+-0, +-0)) */
    double t = num / den, z = t * t;
    double p = TR_ATAN_P[0];
    for (int i = 1; i < 8; i++) p = fma(p, z, TR_ATAN_P[i]);
    double r = fma(t * z, p, t);
    if (big) r = r + TR_PI / 4;
    if (ay > ax) r = TR_PI / 2 - r;
    if (signbit(x)) r = TR_PI - r;
    return copysign(r, y);
}

/* envmap.direction_to_uv of a direction (normalized, turned by -rotate_deg about +Y as
 * envmap.rotate_y turns it): (u, v) in [0, 1) x [0, 1]. Its atan2 and acos in double,
 * rounded once (tr_atan2_d, tr_acos_d): the correctly rounded values but for a few in a
 * million, as map_uv8's (the background's), and without the C library's slower float
 * paths. */
static inline void map_uv(const Lights *L, int64_t b, const float *dir, float *u, float *v) {
    float len = norm3(dir);
    if (len < 1e-30f) len = 1e-30f;
    float d[3] = {dir[0] / len, dir[1] / len, dir[2] / len};
    float ca = L->rot_cos[b], sa = L->rot_sin[b];
    float x = ca * d[0] + sa * d[2], y = d[1], z = -sa * d[0] + ca * d[2];
    float uu = (float)tr_atan2_d(x, -z) * (float)(0.5 / TR_PI);
    *u = uu - floorf(uu);
    *v = (float)tr_acos_d(clampf(y, -1.0f, 1.0f)) * (float)(1.0 / TR_PI);
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

#if defined(__AVX2__) && defined(__FMA__)
/* env_lookup for 8 directions of one view in AVX2 lanes (background.c). Everything but
 * atan2f and acosf is map_uv's, env_tap's and env_read's float arithmetic op for op, so
 * it rounds as they do; those two are polynomials in double lanes, rounded once to float
 * (below). */
#include <immintrin.h>
#define TR_HAVE_ENV8 1

/* atan2 of float values, in double lanes: t = min / max of |x|, |y| (or (t - 1) / (t + 1)
 * above tan(pi/8), plus pi/4), atan(t) = t + t^3 P(t^2) by a minimax polynomial on
 * [0, tan^2(pi/8)] (relative error 1e-13), then pi/2 - r where |y| > |x|, pi - r where
 * x < 0 (its sign bit: atan2f's +-pi at x = -0), and y's sign. */
static inline __m256d tr_atan2_4d(__m256d y, __m256d x) {
    const __m256d sign = _mm256_set1_pd(-0.0);
    __m256d ay = _mm256_andnot_pd(sign, y), ax = _mm256_andnot_pd(sign, x);
    __m256d lo = _mm256_min_pd(ay, ax), hi = _mm256_max_pd(ay, ax);
    __m256d big = _mm256_cmp_pd(lo, _mm256_mul_pd(_mm256_set1_pd(0.41421356237309503), hi),
                                _CMP_GT_OQ);
    /* exact: where taken, lo and hi are floats within a factor 3 of each other */
    __m256d num = _mm256_blendv_pd(lo, _mm256_sub_pd(lo, hi), big);
    __m256d den = _mm256_blendv_pd(hi, _mm256_add_pd(lo, hi), big);
    /* both zero: t = 0 (atan2f(+-0, +-0)) */
    den = _mm256_blendv_pd(den, _mm256_set1_pd(1.0),
                           _mm256_cmp_pd(den, _mm256_setzero_pd(), _CMP_EQ_OQ));
    __m256d t = _mm256_div_pd(num, den), z = _mm256_mul_pd(t, t);
    __m256d p = _mm256_set1_pd(TR_ATAN_P[0]);
    for (int i = 1; i < 8; i++) p = _mm256_fmadd_pd(p, z, _mm256_set1_pd(TR_ATAN_P[i]));
    __m256d r = _mm256_fmadd_pd(_mm256_mul_pd(t, z), p, t);
    r = _mm256_add_pd(r, _mm256_and_pd(big, _mm256_set1_pd(TR_PI / 4)));
    r = _mm256_blendv_pd(r, _mm256_sub_pd(_mm256_set1_pd(TR_PI / 2), r),
                         _mm256_cmp_pd(ay, ax, _CMP_GT_OQ));
    r = _mm256_blendv_pd(r, _mm256_sub_pd(_mm256_set1_pd(TR_PI), r), x);
    return _mm256_or_pd(r, _mm256_and_pd(sign, y));
}

/* acos of float values in [-1, 1], in double lanes: asin(s) = s + s^3 Q(s^2) by a minimax
 * polynomial on s in [0, 1/2] (relative error 2e-13); acos(y) = pi/2 - asin(y) for
 * |y| <= 1/2, above it 2 asin(s) with s = sqrt((1 - |y|) / 2), taken from pi where
 * y < 0. */
static inline __m256d tr_acos_4d(__m256d y) {
    const __m256d sign = _mm256_set1_pd(-0.0), half = _mm256_set1_pd(0.5);
    __m256d a = _mm256_andnot_pd(sign, y);
    __m256d big = _mm256_cmp_pd(a, half, _CMP_GT_OQ);
    __m256d zb = _mm256_mul_pd(half, _mm256_sub_pd(_mm256_set1_pd(1.0), a));
    __m256d s = _mm256_blendv_pd(a, _mm256_sqrt_pd(zb), big);
    __m256d z = _mm256_blendv_pd(_mm256_mul_pd(a, a), zb, big);
    __m256d p = _mm256_set1_pd(TR_ASIN_Q[0]);
    for (int i = 1; i < 9; i++) p = _mm256_fmadd_pd(p, z, _mm256_set1_pd(TR_ASIN_Q[i]));
    __m256d r = _mm256_fmadd_pd(_mm256_mul_pd(s, z), p, s);
    __m256d small = _mm256_sub_pd(_mm256_set1_pd(TR_PI / 2),
                                  _mm256_or_pd(r, _mm256_and_pd(sign, y)));
    __m256d r2 = _mm256_add_pd(r, r);
    __m256d large = _mm256_blendv_pd(r2, _mm256_sub_pd(_mm256_set1_pd(TR_PI), r2), y);
    return _mm256_blendv_pd(small, large, big);
}

/* atan2f(y, x) and acosf(y) of 8 floats: the double results (above) rounded once to float,
 * the correctly rounded values but for a few in a million. The C library's (map_uv's, and
 * the tensor code's on strided tensors) may be an ulp off: u or v then moves a lookup by
 * 1e-4 texel, which across a hard edge of an HDR map is a visible relative difference. */
static inline __m256 tr_atan2f8(__m256 y, __m256 x) {
    __m256d lo = tr_atan2_4d(_mm256_cvtps_pd(_mm256_castps256_ps128(y)),
                             _mm256_cvtps_pd(_mm256_castps256_ps128(x)));
    __m256d hi = tr_atan2_4d(_mm256_cvtps_pd(_mm256_extractf128_ps(y, 1)),
                             _mm256_cvtps_pd(_mm256_extractf128_ps(x, 1)));
    return _mm256_set_m128(_mm256_cvtpd_ps(hi), _mm256_cvtpd_ps(lo));
}

static inline __m256 tr_acosf8(__m256 y) {
    __m256d lo = tr_acos_4d(_mm256_cvtps_pd(_mm256_castps256_ps128(y)));
    __m256d hi = tr_acos_4d(_mm256_cvtps_pd(_mm256_extractf128_ps(y, 1)));
    return _mm256_set_m128(_mm256_cvtpd_ps(hi), _mm256_cvtpd_ps(lo));
}

/* One view's constants for env_lookup8, broadcast. */
typedef struct {
    __m256 ca, sa, wf, wp1, hm1, wp1_half, hm1_half, scale;
    __m256i w, w3, wp1_i, hm1_i;
    const float *tex;
} EnvView8;

/* Whether view b's texel offsets fit the 32-bit gathers. */
static inline int env_view8_fits(const Lights *L, int64_t b) {
    return L->tex_h[b] * L->tex_w[b] * 3 <= INT32_MAX;
}

static inline EnvView8 env_view8(const Lights *L, int64_t b) {
    int64_t h = L->tex_h[b], w = L->tex_w[b];
    EnvView8 e;
    e.ca = _mm256_set1_ps(L->rot_cos[b]);
    e.sa = _mm256_set1_ps(L->rot_sin[b]);
    e.wf = _mm256_set1_ps((float)w);
    e.wp1 = _mm256_set1_ps((float)(w + 1));
    e.hm1 = _mm256_set1_ps((float)(h - 1));
    e.wp1_half = _mm256_set1_ps((float)(w + 1) / 2.0f);
    e.hm1_half = _mm256_set1_ps((float)(h - 1) / 2.0f);
    e.scale = _mm256_set1_ps(L->scale[b]);
    e.w = _mm256_set1_epi32((int)w);
    e.w3 = _mm256_set1_epi32((int)(3 * w));
    e.wp1_i = _mm256_set1_epi32((int)(w + 1));
    e.hm1_i = _mm256_set1_epi32((int)(h - 1));
    e.tex = L->tex[b];
    return e;
}

/* clampf(x, lo, hi) (a NaN gives lo, so that a lane's indices stay in the map) */
static inline __m256 tr_clamp8(__m256 x, __m256 lo, __m256 hi) {
    return _mm256_min_ps(_mm256_max_ps(x, lo), hi);
}

/* (x - 1) mod w for x in [0, w + 1] (env_tap's wrap). */
static inline __m256i tr_wrap8(__m256i x, __m256i w) {
    __m256i c = _mm256_sub_epi32(x, _mm256_set1_epi32(1));
    c = _mm256_add_epi32(c, _mm256_and_si256(_mm256_cmpgt_epi32(_mm256_setzero_si256(), c), w));
    __m256i over = _mm256_cmpgt_epi32(c, _mm256_sub_epi32(w, _mm256_set1_epi32(1)));
    return _mm256_sub_epi32(c, _mm256_and_si256(over, w));
}

/* map_uv of the directions (dx, dy, dz) in view e's frame. */
static inline void map_uv8(const EnvView8 *e, __m256 dx, __m256 dy, __m256 dz, __m256 *u,
                           __m256 *v) {
    const __m256 sign = _mm256_set1_ps(-0.0f);
    __m256 len = _mm256_mul_ps(dx, dx);
    len = _mm256_fmadd_ps(dy, dy, len);
    len = _mm256_sqrt_ps(_mm256_fmadd_ps(dz, dz, len));
    len = _mm256_max_ps(len, _mm256_set1_ps(1e-30f));
    dx = _mm256_div_ps(dx, len);
    dy = _mm256_div_ps(dy, len);
    dz = _mm256_div_ps(dz, len);
    __m256 x = _mm256_add_ps(_mm256_mul_ps(e->ca, dx), _mm256_mul_ps(e->sa, dz));
    __m256 z = _mm256_add_ps(_mm256_mul_ps(_mm256_xor_ps(e->sa, sign), dx),
                             _mm256_mul_ps(e->ca, dz));
    __m256 uu = _mm256_mul_ps(tr_atan2f8(x, _mm256_xor_ps(z, sign)),
                              _mm256_set1_ps((float)(0.5 / TR_PI)));
    *u = _mm256_sub_ps(uu, _mm256_floor_ps(uu));
    __m256 yc = tr_clamp8(dy, _mm256_set1_ps(-1.0f), _mm256_set1_ps(1.0f));
    *v = _mm256_mul_ps(tr_acosf8(yc), _mm256_set1_ps((float)(1.0 / TR_PI)));
}

/* env_lookup of the directions (dx, dy, dz): out[c] the 8 lanes' channel c. */
static inline void env_lookup8(const EnvView8 *e, __m256 dx, __m256 dy, __m256 dz,
                               __m256 *out) {
    __m256 u, v;
    map_uv8(e, dx, dy, dz, &u, &v);
    /* env_tap */
    const __m256 one = _mm256_set1_ps(1.0f), two = _mm256_set1_ps(2.0f);
    __m256 gx = _mm256_add_ps(_mm256_sub_ps(_mm256_mul_ps(u, e->wf), _mm256_set1_ps(0.5f)),
                              one);
    gx = _mm256_sub_ps(_mm256_div_ps(_mm256_mul_ps(two, gx), e->wp1), one);
    __m256 gy = _mm256_sub_ps(
        _mm256_div_ps(_mm256_mul_ps(two, _mm256_mul_ps(v, e->hm1)), e->hm1), one);
    __m256 px = tr_clamp8(_mm256_mul_ps(_mm256_add_ps(gx, one), e->wp1_half),
                          _mm256_setzero_ps(), e->wp1);
    __m256 py = tr_clamp8(_mm256_mul_ps(_mm256_add_ps(gy, one), e->hm1_half),
                          _mm256_setzero_ps(), e->hm1);
    __m256 x0f = _mm256_floor_ps(px), y0f = _mm256_floor_ps(py);
    __m256i x0 = _mm256_cvttps_epi32(x0f), y0 = _mm256_cvttps_epi32(y0f);
    __m256i one_i = _mm256_set1_epi32(1);
    __m256i x1 = _mm256_min_epi32(_mm256_add_epi32(x0, one_i), e->wp1_i);
    __m256i y1 = _mm256_min_epi32(_mm256_add_epi32(y0, one_i), e->hm1_i);
    __m256i c0 = tr_wrap8(x0, e->w), c1 = tr_wrap8(x1, e->w);
    c0 = _mm256_add_epi32(c0, _mm256_add_epi32(c0, c0));  /* 3 c */
    c1 = _mm256_add_epi32(c1, _mm256_add_epi32(c1, c1));
    __m256i r0 = _mm256_mullo_epi32(y0, e->w3), r1 = _mm256_mullo_epi32(y1, e->w3);
    __m256i i00 = _mm256_add_epi32(r0, c0), i01 = _mm256_add_epi32(r0, c1);
    __m256i i10 = _mm256_add_epi32(r1, c0), i11 = _mm256_add_epi32(r1, c1);
    __m256 fx = _mm256_sub_ps(px, x0f), fy = _mm256_sub_ps(py, y0f);
    __m256 gx_ = _mm256_sub_ps(one, fx), gy_ = _mm256_sub_ps(one, fy);
    /* env_read */
    for (int c = 0; c < 3; c++) {
        const float *t = e->tex + c;
        __m256 top = _mm256_add_ps(_mm256_mul_ps(_mm256_i32gather_ps(t, i00, 4), gx_),
                                   _mm256_mul_ps(_mm256_i32gather_ps(t, i01, 4), fx));
        __m256 bot = _mm256_add_ps(_mm256_mul_ps(_mm256_i32gather_ps(t, i10, 4), gx_),
                                   _mm256_mul_ps(_mm256_i32gather_ps(t, i11, 4), fx));
        out[c] = _mm256_mul_ps(_mm256_add_ps(_mm256_mul_ps(top, gy_), _mm256_mul_ps(bot, fy)),
                               e->scale);
    }
}

/* The lanes of 24 interleaved floats (8 xyz triples) as x, y, z vectors, and back:
 * three blends and a lane permutation each. */
static inline void tr_load_xyz8(const float *p, __m256 *x, __m256 *y, __m256 *z) {
    __m256 m0 = _mm256_loadu_ps(p), m1 = _mm256_loadu_ps(p + 8), m2 = _mm256_loadu_ps(p + 16);
    __m256 tx = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x92), m2, 0x24);
    __m256 ty = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x24), m2, 0x49);
    __m256 tz = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x49), m2, 0x92);
    *x = _mm256_permutevar8x32_ps(tx, _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5));
    *y = _mm256_permutevar8x32_ps(ty, _mm256_setr_epi32(1, 4, 7, 2, 5, 0, 3, 6));
    *z = _mm256_permutevar8x32_ps(tz, _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7));
}

/* x, y, z lanes as the three vectors of 8 interleaved triples (floats 0-7, 8-15, 16-23). */
static inline void tr_xyz8_parts(__m256 x, __m256 y, __m256 z, __m256 *out) {
    __m256 tx = _mm256_permutevar8x32_ps(x, _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5));
    __m256 ty = _mm256_permutevar8x32_ps(y, _mm256_setr_epi32(5, 0, 3, 6, 1, 4, 7, 2));
    __m256 tz = _mm256_permutevar8x32_ps(z, _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7));
    out[0] = _mm256_blend_ps(_mm256_blend_ps(tx, ty, 0x92), tz, 0x24);
    out[1] = _mm256_blend_ps(_mm256_blend_ps(tz, tx, 0x92), ty, 0x24);
    out[2] = _mm256_blend_ps(_mm256_blend_ps(ty, tz, 0x92), tx, 0x24);
}

static inline void tr_store_xyz8(float *p, __m256 x, __m256 y, __m256 z) {
    __m256 v[3];
    tr_xyz8_parts(x, y, z, v);
    for (int k = 0; k < 3; k++) _mm256_storeu_ps(p + 8 * k, v[k]);
}

/* tr_store_xyz8 of the lanes where ``m`` is set only (the other triples untouched). */
static inline void tr_store_xyz8_where(float *p, __m256 m, __m256 x, __m256 y, __m256 z) {
    __m256 v[3], mk[3];
    tr_xyz8_parts(x, y, z, v);
    tr_xyz8_parts(m, m, m, mk);
    for (int k = 0; k < 3; k++) _mm256_maskstore_ps(p + 8 * k, _mm256_castps_si256(mk[k]), v[k]);
}
#endif

/* The prefetch helpers below are inlined before GCC's interprocedural passes: called, a
 * function holding only __builtin_prefetch is found const (it writes no memory), and a
 * const call whose result is unused is deleted, prefetches and all (GCC 12, -O1 and up). */
#define TR_PREFETCH __attribute__((always_inline))

/* A tap's two texel rows asked into the cache: a kernel's lookups then overlap their
 * memory reads with the work done before env_read reads them (the refracted directions
 * scatter over the map). */
static inline TR_PREFETCH void env_tap_prefetch(const Lights *j, const EnvTap *p) {
    int64_t w = j->tex_w[p->b];
    const float *t = j->tex[p->b];
    /* a row's two texels (24 bytes) cross a cache line for 5 of the 16 offsets a 12-byte
     * texel takes, and c1 wraps to column 0: each texel's first and last float asked */
    __builtin_prefetch(t + (p->y0 * w + p->c0) * 3);
    __builtin_prefetch(t + (p->y0 * w + p->c1) * 3 + 2);
    __builtin_prefetch(t + (p->y1 * w + p->c0) * 3);
    __builtin_prefetch(t + (p->y1 * w + p->c1) * 3 + 2);
}

/* One view's SG-pre-convolved pyramid (lighting/sg_pyramid.py, SGPyramid): the padded
 * map ``base`` (3, bh, bw) and the packed levels ``atlas`` (3, ah, aw), channels first;
 * ``meta``: v0, n, then kap_levels (n + 2: the map's, the n levels', the mean's), then
 * rects ((n + 2) x 4: y0, x0, h, w), then the n level sharpnesses, as floats. */
typedef struct {
    const float *const *base, *const *atlas, *const *meta;
    const int64_t *base_hw, *atlas_hw;  /* (B, 2) */
} SgEnv;

/* One level's bilinear read (grid_sample: border padding, aligned corners) of the level
 * at rect ``r`` of a (3, ih, iw) image at (u, v): its texels and weights. */
typedef struct {
    const float *img;
    int64_t plane, iw, x0, x1, y0, y1;
    float fx, fy;
} SgLevelTap;

static inline SgLevelTap sg_level_tap(const float *img, int64_t ih, int64_t iw,
                                      const float *r, float u, float v) {
    float x = r[1] + 1.0f + u * r[3] - 0.5f, y = r[0] + v * (r[2] - 1.0f);
    float gx = 2.0f * x / (float)(iw - 1) - 1.0f, gy = 2.0f * y / (float)(ih - 1) - 1.0f;
    float px = clampf((gx + 1.0f) * ((float)(iw - 1) / 2.0f), 0.0f, (float)(iw - 1));
    float py = clampf((gy + 1.0f) * ((float)(ih - 1) / 2.0f), 0.0f, (float)(ih - 1));
    SgLevelTap q = {.img = img, .plane = ih * iw, .iw = iw};
    q.x0 = (int64_t)floorf(px);
    q.y0 = (int64_t)floorf(py);
    q.x1 = q.x0 + 1 < iw ? q.x0 + 1 : q.x0;
    q.y1 = q.y0 + 1 < ih ? q.y0 + 1 : q.y0;
    q.fx = px - (float)q.x0;
    q.fy = py - (float)q.y0;
    return q;
}

static inline void sg_level_read(const SgLevelTap *q, float *out) {
    for (int c = 0; c < 3; c++) {
        const float *p = q->img + c * q->plane;
        float top = p[q->y0 * q->iw + q->x0] * (1.0f - q->fx) + p[q->y0 * q->iw + q->x1] * q->fx;
        float bot = p[q->y1 * q->iw + q->x0] * (1.0f - q->fx) + p[q->y1 * q->iw + q->x1] * q->fx;
        out[c] = top * (1.0f - q->fy) + bot * q->fy;
    }
}

/* The level's texel rows asked into the cache (three channel planes, two rows). */
static inline TR_PREFETCH void sg_level_prefetch(const SgLevelTap *q) {
    for (int c = 0; c < 3; c++) {
        const float *p = q->img + c * q->plane;
        __builtin_prefetch(p + q->y0 * q->iw + q->x0);
        __builtin_prefetch(p + q->y1 * q->iw + q->x0);
    }
}

/* One SG lookup's two levels and their blend weight, computed apart from their reads so
 * that a kernel can ask for the texels early (sg_tap_prefetch) and read them after other
 * work (sg_env_read): the atlas is tens of MB and the lobes scatter over it. */
typedef struct {
    SgLevelTap hi, lo;
    float t;
} SgTap;

static inline TR_PREFETCH void sg_tap_prefetch(const SgTap *q) {
    sg_level_prefetch(&q->hi);
    sg_level_prefetch(&q->lo);
}

/* The two levels around sharpness k in view b's pyramid (torch.searchsorted(-ks, -k)):
 * the lower one's index, and the blend weight, linear in the effective sharpness
 * k / (1 + v0 k) (_blend_weights). */
static inline int64_t sg_levels_of(const SgEnv *e, int64_t b, float k, float *t) {
    const float *m = e->meta[b];
    float v0 = m[0];
    int64_t n = (int64_t)m[1];
    const float *kap_levels = m + 2, *ks = m + 2 + (n + 2) + 4 * (n + 2);
    int64_t i = 0;
    while (i < n && ks[i] > k) i++;
    float kap = isinf(k) ? 1.0f / v0 : k / (1.0f + v0 * k);
    float hi_k = kap_levels[i], lo_k = kap_levels[i + 1];
    *t = (hi_k - kap) / (hi_k - lo_k);
    return i;
}

/* The tap at map coordinates (u, v) between levels i and i + 1 (sg_levels_of). */
static inline SgTap sg_tap_uv(const SgEnv *e, int64_t b, int64_t i, float t, float u, float v) {
    const float *m = e->meta[b];
    int64_t n = (int64_t)m[1];
    const float *rects = m + 2 + (n + 2);
    const int64_t *ahw = e->atlas_hw + 2 * b, *bhw = e->base_hw + 2 * b;
    SgTap q;
    q.t = t;
    q.hi = sg_level_tap(e->atlas[b], ahw[0], ahw[1], rects + 4 * (i + 1), u, v);
    q.lo = i == 0 ? sg_level_tap(e->base[b], bhw[0], bhw[1], rects, u, v)
                  : sg_level_tap(e->atlas[b], ahw[0], ahw[1], rects + 4 * i, u, v);
    return q;
}

/* sg_pyramid.sg_lookup_env's tap: the map convolved with a normalized SG of sharpness k
 * (inf: a plain lookup) around dir, between the two levels around k. */
static inline SgTap sg_env_tap(const Lights *L, const SgEnv *e, int64_t b, const float *dir,
                               float k) {
    float u, v, t;
    map_uv(L, b, dir, &u, &v);
    int64_t i = sg_levels_of(e, b, k, &t);
    return sg_tap_uv(e, b, i, t, u, v);
}

/* The map coordinates of n <= 8 directions dirs[3 i ...], lookup i in view bs[i] (map_uv;
 * in AVX2 lanes where built for it: map_uv8 with each lane's rotation, the same bits). */
static inline void map_uv_n(const Lights *L, int n, const int64_t *bs, const float *dirs,
                            float *u, float *v) {
#ifdef TR_HAVE_ENV8
    float xs[3][8], ca[8], sa[8];
    for (int i = 0; i < 8; i++) {
        int q = i < n ? i : 0;
        for (int c = 0; c < 3; c++) xs[c][i] = dirs[3 * q + c];
        ca[i] = L->rot_cos[bs[q]];
        sa[i] = L->rot_sin[bs[q]];
    }
    EnvView8 ev;
    ev.ca = _mm256_loadu_ps(ca);
    ev.sa = _mm256_loadu_ps(sa);
    __m256 uu, vv;
    map_uv8(&ev, _mm256_loadu_ps(xs[0]), _mm256_loadu_ps(xs[1]), _mm256_loadu_ps(xs[2]), &uu,
            &vv);
    float ub[8], vb[8];
    _mm256_storeu_ps(ub, uu);
    _mm256_storeu_ps(vb, vv);
    for (int i = 0; i < n; i++) {
        u[i] = ub[i];
        v[i] = vb[i];
    }
#else
    for (int i = 0; i < n; i++) map_uv(L, bs[i], dirs + 3 * i, &u[i], &v[i]);
#endif
}

/* The taps of n <= 8 lookups (directions dirs[3 i ...], views bs[i]), their texels asked
 * for (env_tap_prefetch): their map coordinates by map_uv_n. */
static inline void env_taps8(const Lights *L, int n, const int64_t *bs, const float *dirs,
                             EnvTap *out) {
    float u[8], v[8];
    map_uv_n(L, n, bs, dirs, u, v);
    for (int i = 0; i < n; i++) {
        out[i] = env_tap(L, bs[i], u[i], v[i]);
        env_tap_prefetch(L, out + i);
    }
}

/* sg_env_tap of n <= 8 lookups, lookup i along dirs[3 i ...] at sharpness ks[i] in view
 * bs[i] (a block's pixels), their texels asked for: their map coordinates in AVX2 lanes
 * where built for it (map_uv8 with each lane's rotation, the same bits as map_uv). */
static inline void sg_env_tap8(const Lights *L, const SgEnv *e, int n, const int64_t *bs,
                               const float *dirs, const float *ks, SgTap *out) {
    float u[8], v[8];
    map_uv_n(L, n, bs, dirs, u, v);
    for (int i = 0; i < n; i++) {
        float t;
        int64_t lv = sg_levels_of(e, bs[i], ks[i], &t);
        out[i] = sg_tap_uv(e, bs[i], lv, t, u[i], v[i]);
        sg_tap_prefetch(out + i);
    }
}

/* sg_env_tap8 of n <= 8 directions of view b at one sharpness k (an anisotropic lobe's
 * taps), the levels found once. */
static inline void sg_env_taps(const Lights *L, const SgEnv *e, int64_t b,
                               const float (*dirs)[3], int n, float k, SgTap *out) {
    float u[8], v[8], t;
    int64_t bs[8];
    for (int i = 0; i < n; i++) bs[i] = b;
    map_uv_n(L, n, bs, &dirs[0][0], u, v);
    int64_t lv = sg_levels_of(e, b, k, &t);
    for (int i = 0; i < n; i++) {
        out[i] = sg_tap_uv(e, b, lv, t, u[i], v[i]);
        sg_tap_prefetch(out + i);
    }
}

static inline void sg_env_read(const Lights *L, int64_t b, const SgTap *q, float *out) {
    float lo[3], hi[3];
    sg_level_read(&q->hi, hi);
    sg_level_read(&q->lo, lo);
    for (int c = 0; c < 3; c++) out[c] = (lo[c] * (1.0f - q->t) + hi[c] * q->t) * L->scale[b];
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
 * env_taps8). */
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

/* torch.special.i0e, exp(-|x|) I0(x), as ATen computes it: Cephes' Chebyshev expansions
 * (S. L. Moshier's i0e) of exp(-x) I0(x) on [0, 8] in (x / 2 - 2) and of sqrt(x) exp(-x)
 * I0(x) beyond in (32 / x - 2), summed by Clenshaw's recurrence with its step x b1 - b2
 * fused, as the compiled CPU kernel does (the same bits as torch on this CPU). */
static const double TR_I0E_A[30] = {
    -4.41534164647933937950E-18, 3.33079451882223809783E-17, -2.43127984654795469359E-16,
    1.71539128555513303061E-15, -1.16853328779934516808E-14, 7.67618549860493561688E-14,
    -4.85644678311192946090E-13, 2.95505266312963983461E-12, -1.72682629144155570723E-11,
    9.67580903537323691224E-11, -5.18979560163526290666E-10, 2.65982372468238665035E-9,
    -1.30002500998624804212E-8, 6.04699502254191894932E-8, -2.67079385394061173391E-7,
    1.11738753912010371815E-6, -4.41673835845875056359E-6, 1.64484480707288970893E-5,
    -5.75419501008210370398E-5, 1.88502885095841655729E-4, -5.76375574538582365885E-4,
    1.63947561694133579842E-3, -4.32430999505057594430E-3, 1.05464603945949983183E-2,
    -2.37374148058994688156E-2, 4.93052842396707084878E-2, -9.49010970480476444210E-2,
    1.71620901522208775349E-1, -3.04682672343198398683E-1, 6.76795274409476084995E-1};
static const double TR_I0E_B[25] = {
    -7.23318048787475395456E-18, -4.83050448594418207126E-18, 4.46562142029675999901E-17,
    3.46122286769746109310E-17, -2.82762398051658348494E-16, -3.42548561967721913462E-16,
    1.77256013305652638360E-15, 3.81168066935262242075E-15, -9.55484669882830764870E-15,
    -4.15056934728722208663E-14, 1.54008621752140982691E-14, 3.85277838274214270114E-13,
    7.18012445138366623367E-13, -1.79417853150680611778E-12, -1.32158118404477131188E-11,
    -3.14991652796324136454E-11, 1.18891471078464383424E-11, 4.94060238822496958910E-10,
    3.39623202570838634515E-9, 2.26666899049817806459E-8, 2.04891858946906374183E-7,
    2.89137052083475648297E-6, 6.88975834691682398426E-5, 3.36911647825569408990E-3,
    8.04490411014108831608E-1};

/* Chebyshev series in lanes: 24 values at a time (the Gauss-Legendre rule's nodes), as six
 * vectors of four doubles held in registers through the recurrence. */
typedef double tr_v4d __attribute__((vector_size(32)));
#define TR_CHEB_N 24
#define TR_CHEB_V (TR_CHEB_N / 4)

/* out = y b0 - b1 lane by lane, rounded once (fma(y, b0, -b1), as ATen's kernel fuses it);
 * by pointer, so that no 32-byte vector is passed by value where AVX is not built. */
static inline void fms_v4d(const tr_v4d *y, const tr_v4d *b0, const tr_v4d *b1,
                           tr_v4d *out) {
#if defined(__AVX2__) && defined(__FMA__)
    *out = (tr_v4d)_mm256_fmsub_pd((__m256d)*y, (__m256d)*b0, (__m256d)*b1);
#else
    for (int l = 0; l < 4; l++) (*out)[l] = fma((*y)[l], (*b0)[l], -(*b1)[l]);
#endif
}

/* Cephes' chbevl (Clenshaw's recurrence, 0.5 (b0 - b2) after it) of the m coefficients c
 * at the TR_CHEB_N values y; the recurrences are independent, stepped side by side. */
static inline void chebyshev_v(const tr_v4d *y, const double *c, int m, tr_v4d *out) {
    tr_v4d b0[TR_CHEB_V], b1[TR_CHEB_V], b2[TR_CHEB_V];
    for (int v = 0; v < TR_CHEB_V; v++) {
        b0[v] = (tr_v4d){c[0], c[0], c[0], c[0]};
        b1[v] = b2[v] = (tr_v4d){0.0, 0.0, 0.0, 0.0};
    }
    for (int k = 1; k < m; k++)
        for (int v = 0; v < TR_CHEB_V; v++) {
            b2[v] = b1[v];
            b1[v] = b0[v];
            fms_v4d(y + v, b1 + v, b2 + v, b0 + v);
            b0[v] += c[k];
        }
    for (int v = 0; v < TR_CHEB_V; v++) out[v] = 0.5 * (b0[v] - b2[v]);
}

/* i0e of n values: out[i] = i0e(x[i]), TR_CHEB_N at a time, each expansion run where one of
 * the values is in its range (lanes past n computed on 1 and dropped). */
static void i0e_n(const double *x, int64_t n, double *out) {
    for (int64_t i0 = 0; i0 < n; i0 += TR_CHEB_N) {
        int m = n - i0 < TR_CHEB_N ? (int)(n - i0) : TR_CHEB_N, low = 0, high = 0;
        double v[TR_CHEB_N];
        tr_v4d ya[TR_CHEB_V], yb[TR_CHEB_V], ea[TR_CHEB_V], eb[TR_CHEB_V];
        for (int i = 0; i < TR_CHEB_N; i++) {
            v[i] = i < m ? fabs(x[i0 + i]) : 1.0;
            ya[i / 4][i % 4] = v[i] / 2.0 - 2.0;
            yb[i / 4][i % 4] = 32.0 / v[i] - 2.0;
            low |= i < m && v[i] <= 8.0;
            high |= i < m && !(v[i] <= 8.0);
        }
        if (low) chebyshev_v(ya, TR_I0E_A, 30, ea);
        if (high) chebyshev_v(yb, TR_I0E_B, 25, eb);
        for (int i = 0; i < m; i++)
            out[i0 + i] = v[i] <= 8.0 ? ea[i / 4][i % 4] : eb[i / 4][i % 4] / sqrt(v[i]);
    }
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
    if (half == 0.0) return 0.0;  /* the disc beyond 8 s of the lobe: the sum times 0 */
    for (int64_t i0 = 0; i0 < L->gl_n; i0 += TR_CHEB_N) {  /* the rule's 24 nodes at once */
        int m = L->gl_n - i0 < TR_CHEB_N ? (int)(L->gl_n - i0) : TR_CHEB_N;
        double x[TR_CHEB_N], z[TR_CHEB_N], bessel[TR_CHEB_N];
        for (int i = 0; i < m; i++) {
            x[i] = (a + bb) * 0.5 + half * L->gl_x[i0 + i];
            z[i] = x[i] * c_g / s2;
        }
        i0e_n(z, m, bessel);
        for (int i = 0; i < m; i++) {
            double f = (x[i] / s2) * exp(-((x[i] - c_g) * (x[i] - c_g)) / (2.0 * s2)) *
                       bessel[i];
            mass += f * L->gl_w[i0 + i];
        }
    }
    mass = mass * half / (-expm1(-2.0 * kk));
    return mass < 0.0 ? 0.0 : (mass > 1.0 ? 1.0 : mass);
}

/* lights.incident_radiance_sg: the environment convolved with the lobe (``tap``: the
 * sg_env_tap of dir and k); with sphere lights, the share of the lobe on each light's disc
 * sees the light (a plain lookup, k = inf: the light the axis hits). */
static void incident_sg_at(const Lights *L, int64_t b, const float *o, const float *dir,
                           float k, const SgTap *tap, float *out) {
    sg_env_read(L, b, tap, out);
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

/* incident_sg_at with the tap computed here. */
static void incident_sg(const Lights *L, const SgEnv *e, int64_t b, const float *o,
                        const float *dir, float k, float *out) {
    SgTap tap = sg_env_tap(L, e, b, dir, k);
    incident_sg_at(L, b, o, dir, k, &tap, out);
}

#endif
