/* Smooth-interface optics (optics/smooth.py), line by line in float32, for the fused
 * shading kernels. */

#ifndef TORCHREFRACT_OPTICS_H
#define TORCHREFRACT_OPTICS_H

#include "common.h"

TR_DEFINE_LANES(float, int, , fmaf, fabsf, sqrtf, 1e-30f, TR_SEL_SCALAR, TR_K_SCALAR)

/* common.h's intersect and interpolate (TR_DEFINE_VEC3) for float: the corners read in
 * place from the kernels' float32 tables (its copy into a local array, needed for its
 * double instance, was stored in vector moves and read back in scalars here: a stalled
 * store-to-load forward per corner). */
static inline float intersect(const float *o, const float *d, const float *tv, float *bary) {
    return hit(o, d, tv, bary);
}

static inline void interpolate(const float *bary, const float *corners, int c, float *out) {
    float w[3];
    weights(bary, w);
    blend(w, corners, c, out);
}

#define TR_PI 3.14159265358979323846

static inline float clampf(float x, float lo, float hi) {
    return x < lo ? lo : (x > hi ? hi : x);
}

/* Beer-Lambert transmittance exp(-a s) over a path of finite length s; exactly 1 without
 * absorption (expf(-0) is 1: most scenes absorb nothing, and expf is a library call). */
static inline float transmittance(float a, float s) {
    return a == 0.0f ? 1.0f : expf(-a * s);
}

static inline void face_forward(const float *n, const float *d, float *out) {
    float s = dot3(n, d) > 0.0f ? -1.0f : 1.0f;
    for (int i = 0; i < 3; i++) out[i] = s * n[i];
}

/* Fresnel's unpolarized reflectance at incident cosine cos_i for relative index eta (1
 * under TIR), written once for a lane type T as TR_DEFINE_REFRACT below: the scalar
 * ``fresnel`` and, where built for it, ``fresnel4f`` (four in SSE lanes: sgtable.h's
 * spread energies), the same bits lane by lane. */
#define TR_DEFINE_FRESNEL(T, S, SQRT, SEL, K)                                               \
    static inline TR_LANES_ATTR T fresnel##S(T cos_i, T eta) {                              \
        cos_i = SEL(cos_i < K(T, 0), K(T, 0), SEL(cos_i > K(T, 1), K(T, 1), cos_i));        \
        T sin2_t = eta * eta * (K(T, 1) - cos_i * cos_i);                                   \
        T ct = K(T, 1) - sin2_t;                                                            \
        T cos_t = SQRT(SEL(ct > K(T, 0), ct, K(T, 0)));                                     \
        T rs_den = eta * cos_i + cos_t, rp_den = cos_i + eta * cos_t;                       \
        rs_den = SEL(rs_den < K(T, 1e-12f), K(T, 1e-12f), rs_den);                          \
        rp_den = SEL(rp_den < K(T, 1e-12f), K(T, 1e-12f), rp_den);                          \
        T rs = (eta * cos_i - cos_t) / rs_den, rp = (cos_i - eta * cos_t) / rp_den;         \
        T f = K(T, 0.5f) * (rs * rs + rp * rp);                                             \
        f = SEL(f < K(T, 0), K(T, 0), SEL(f > K(T, 1), K(T, 1), f));                        \
        return SEL(sin2_t >= K(T, 1), K(T, 1), f);                                          \
    }

TR_DEFINE_FRESNEL(float, , sqrtf, TR_SEL_SCALAR, TR_K_SCALAR)

/* Snell (smooth.refract): the unit transmitted direction; returns TIR. Written once for
 * a lane type T as TR_DEFINE_LANES' bodies are (its dot3##S, norm3##S; M, SEL and K as
 * there): the scalar ``refract`` and, where built for it, four rays in SSE lanes
 * (refract_x4), the same bits lane by lane. */
#define TR_DEFINE_REFRACT(T, M, S, SQRT, SEL, K)                                           \
    static inline TR_LANES_ATTR M refract##S(const T *d, const T *n, T eta, T *t) {        \
        T c = -dot3##S(d, n);                                                               \
        T cos_i = SEL(c < K(T, 0), K(T, 0), SEL(c > K(T, 1), K(T, 1), c));                  \
        T sin2_t = eta * eta * (K(T, 1) - cos_i * cos_i);                                   \
        T ct = K(T, 1) - sin2_t;                                                            \
        T cos_t = SQRT(SEL(ct > K(T, 0), ct, K(T, 0)));                                     \
        T k = eta * cos_i - cos_t;                                                          \
        for (int i = 0; i < 3; i++) t[i] = eta * d[i] + k * n[i];                          \
        T len = norm3##S(t);                                                                \
        len = SEL(len < K(T, 1e-20f), K(T, 1e-20f), len);                                   \
        for (int i = 0; i < 3; i++) t[i] = t[i] / len;                                      \
        return sin2_t >= K(T, 1);                                                           \
    }

TR_DEFINE_REFRACT(float, int, , sqrtf, TR_SEL_SCALAR, TR_K_SCALAR)

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
typedef float v4f __attribute__((vector_size(16)));
typedef int v4i __attribute__((vector_size(16)));
static inline v4f fma4f(v4f a, v4f b, v4f c) {
    return (v4f)_mm_fmadd_ps((__m128)a, (__m128)b, (__m128)c);
}
static inline v4f sqrt4f(v4f a) { return (v4f)_mm_sqrt_ps((__m128)a); }
static inline v4f abs4f(v4f a) { return (v4f)((v4i)a & (v4i){~(1 << 31), ~(1 << 31),
                                                            ~(1 << 31), ~(1 << 31)}); }
#define SEL4F(m, a, b) ((v4f)_mm_blendv_ps((__m128)(b), (__m128)(a), (__m128)(m)))
#define K4F(T, x) ((T){(x), (x), (x), (x)})
TR_DEFINE_LANES(v4f, v4i, 4f, fma4f, abs4f, sqrt4f, 1e-30f, SEL4F, K4F)
TR_DEFINE_REFRACT(v4f, v4i, 4f, sqrt4f, SEL4F, K4F)
TR_DEFINE_FRESNEL(v4f, 4f, sqrt4f, SEL4F, K4F)
#endif

/* refract of four rays d[q] at normals n[q] (q < 4) into t[q]: in SSE lanes where built
 * for it (a pixel's bounding rays), else one by one; the same bits either way. */
static inline void refract_x4(const float (*d)[3], const float (*n)[3], float eta,
                              float (*t)[3]) {
#if defined(__AVX2__) && defined(__FMA__)
    v4f dv[3], nv[3], tv[3];
    for (int c = 0; c < 3; c++) {
        dv[c] = (v4f){d[0][c], d[1][c], d[2][c], d[3][c]};
        nv[c] = (v4f){n[0][c], n[1][c], n[2][c], n[3][c]};
    }
    refract4f(dv, nv, K4F(v4f, eta), tv);
    for (int q = 0; q < 4; q++)
        for (int c = 0; c < 3; c++) t[q][c] = tv[c][q];
#else
    for (int q = 0; q < 4; q++) refract(d[q], n[q], eta, t[q]);
#endif
}

static inline void reflect(const float *d, const float *n, float *r) {
    float k = 2.0f * dot3(d, n);
    for (int i = 0; i < 3; i++) r[i] = d[i] - k * n[i];
}

/* smooth.normalize (eps 1e-20). */
static inline void normalize3(float *v) {
    float len = norm3(v);
    if (len < 1e-20f) len = 1e-20f;
    for (int i = 0; i < 3; i++) v[i] = v[i] / len;
}

/* smooth.tangent_frame: u = p x h / |p x h| (h the x axis, the y axis near it), v = p x u. */
static inline void tangent_frame(const float *p, float *u, float *v) {
    float h[3] = {0.0f, 0.0f, 0.0f};
    h[fabsf(p[0]) < 0.9f ? 0 : 1] = 1.0f;
    cross3(p, h, u);
    normalize3(u);
    cross3(p, u, v);
}

/* asin(s) = s + s^3 Q(s^2) for s in [0, 1/2]: Q's minimax coefficients, highest power
 * first (relative error 2e-13), for tr_asin_poly and lighting.h's tr_acos_4d. */
static const double TR_ASIN_Q[9] = {
    0.028346745231833329, 0.0010675063150363118, 0.01686409027396012,
    0.016902683886393575, 0.022412417726695433, 0.030379945210024933,
    0.044642906474584963, 0.074999999534297119, 0.16666666666738632};

/* asin(s) for s in [0, 1/2], given z = s^2 (TR_ASIN_Q by Horner's rule in fma). */
static inline double tr_asin_poly(double s, double z) {
    double p = TR_ASIN_Q[0];
    for (int i = 1; i < 9; i++) p = fma(p, z, TR_ASIN_Q[i]);
    return fma(s * z, p, s);
}

/* asin of x in [-1, 1] in double: the polynomial up to |x| = 1/2, above it pi/2 - 2 asin(s)
 * with s = sqrt((1 - |x|) / 2). Rounded to float it is asinf's value (the correctly rounded
 * one but for a few in a million), without the C library's slow path. */
static inline double tr_asin_d(double x) {
    double a = fabs(x);
    if (!(a > 0.5)) return copysign(tr_asin_poly(a, a * a), x);
    double z = 0.5 * (1.0 - a);
    return copysign(TR_PI / 2 - 2.0 * tr_asin_poly(sqrt(z), z), x);
}

/* acos of y in [-1, 1] in double, as tr_acos_4d: pi/2 - asin(y) up to |y| = 1/2, above it
 * 2 asin(s), s = sqrt((1 - |y|) / 2), from pi where y < 0 (no cancellation near |y| = 1). */
static inline double tr_acos_d(double y) {
    double a = fabs(y);
    if (!(a > 0.5)) return TR_PI / 2 - copysign(tr_asin_poly(a, a * a), y);
    double z = 0.5 * (1.0 - a), r = 2.0 * tr_asin_poly(sqrt(z), z);
    return y < 0.0 ? TR_PI - r : r;
}

/* cos(asin(s)) for s in (-1, 1): sqrt((1 - s)(1 + s)) in double, rounded once (the table
 * gives its axis angles as sines: sgtable.h's sg_lookup). */
static inline float cos_of_asin(float s) {
    double d = (double)s;
    return (float)sqrt((1.0 - d) * (1.0 + d));
}

/* sgfit.lobe_axis: the lobe's unit axis -sin(t) u + sign cos(t) n from the table's signed
 * polar angle t, given as its sine ``st`` (sg_lookup: the angle is asin of the table's
 * value, so sin(t) is that value and cos(t) = cos_of_asin; u: the view's unit tangential
 * part; sign -1 transmit, +1 reflect). */
static inline void lobe_axis(const float *view, const float *n, float st, float sign,
                             float *out) {
    float dv = dot3(view, n);
    float vt[3] = {view[0] - dv * n[0], view[1] - dv * n[1], view[2] - dv * n[2]};
    float n2 = dot3(vt, vt), u[3];
    if (n2 > 1e-24f) {
        float r = sqrtf(n2);
        for (int i = 0; i < 3; i++) u[i] = vt[i] / r;
    } else {
        float alt[3] = {0.0f, 0.0f, 0.0f};
        alt[fabsf(n[0]) < 0.9f ? 0 : 1] = 1.0f;
        float da = dot3(alt, n);
        for (int i = 0; i < 3; i++) alt[i] = alt[i] - da * n[i];
        float r = norm3(alt);
        for (int i = 0; i < 3; i++) u[i] = alt[i] / r;
    }
    float ct = cos_of_asin(st);
    for (int i = 0; i < 3; i++) out[i] = -st * u[i] + sign * ct * n[i];
}

/* camera.project of one point in a view (proj: camera.projection_params): pixel x, y. */
static inline void project1(const float *pt, const float *pp, float *xy) {
    float rel[3] = {pt[0] - pp[0], pt[1] - pp[1], pt[2] - pp[2]};
    float z = dot3(rel, pp + 9);
    float zs = fabsf(z) > 1e-12f ? z : 1e-12f;
    float x = dot3(rel, pp + 3) / (zs * pp[12]);
    float y = dot3(rel, pp + 6) / (zs * pp[13]);
    xy[0] = ((x + 1.0f) * 0.5f) * pp[14];
    xy[1] = ((1.0f - y) * 0.5f) * pp[15];
}

/* torch's max / min of a then b, in order: NaN once any is */
static inline float tmax(float a, float b) { return a != a || b != b ? NAN : (b > a ? b : a); }
static inline float tmin(float a, float b) { return a != a || b != b ? NAN : (b < a ? b : a); }

#endif
