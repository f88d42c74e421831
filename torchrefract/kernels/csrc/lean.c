/* Fused shading of ``lean`` and ``gsr`` (methods/lean/, Dai and Wyman 2012) for their
 * default width (``spread: rays``), the SG pyramid (``env_lookup: sg``) and the marched cone
 * (``cone_rays: march``); every ``tir`` rule, roughness maps (``roughness_lobes`` 1 or 2),
 * any ``ewa_taps``, K = 1..8 subdivisions, sphere lights, absorption, internal bounces.
 * Per object pixel, in registers, after the LEAN moments' mip pyramid is built (in torch,
 * moments.lean_mips):
 *   1. the front lobes and the cone: ``rousiers``' steps 1-2 (rousiers_core.h's front_and_cone,
 *      the marches of march_core.h),
 *   2. the footprint (cone.trace_cone) and the moments over it: four taps along its major
 *      extent and the roughness moments at its center (moments.footprint_sums), their
 *      Gaussians (moments.gaussians: per subdivision and merged, the two-point roughness);
 *      ``lean`` without a roughness map reads no pyramid (moments.uniform_footprint),
 *   3. the exit lobes of the merged Gaussian at the exact exit normal (shade._lobes, exact),
 *      each at its own axis and widened by the bounding rays' covariance
 *      (shade._ray_covariances, lobes.ray_covariance), each read by EWA taps on the SG
 *      pyramid (lighting/ewa.py),
 *   4. ``gsr``: where the subdivisions' normals form separate groups (moments.separation),
 *      their own lobes, widened as the poster does (shade._paper_covariances,
 *      lobes.paper_covariance), blended in by the separation,
 *   5. the front reflection, an index-matched object left invisible, the absorption and
 *      ``rousiers``' internal bounces (bounces.h, rousiers_core.h's shade_inside; for ``gsr``
 *      the exit reflects inside what its lobes do not transmit, shade._reflected).
 * The tensor code (methods/lean/shade.py) is the reference and the differentiable path;
 * tests/test_fused_lean.py holds the two together.
 *
 * rousiers_core.h is included, not copied: its static steps (front lobes, cone, exit
 * lobe, first reflection, interfaces met from inside) are the same functions here.
 */

#include "rousiers_core.h"

#define LEAN_CH 9    /* moments.CHANNELS */
#define SLOPE_CH 6   /* moments.SLOPE_CHANNELS: the first LEAN_CH, without the roughness's */
#define MAX_K 8      /* GsrOptions.subdivisions' maximum */
#define MAX_LOBES (2 * MAX_K)
#define NZ_MIN 0.2f  /* moments.NZ_MIN */

typedef struct {
    RousJob r;                 /* the frame, the cone's marches, the passes, the bounces
                                * (r.levels 0: the roughness is in the moments) */
    int k;                     /* subdivisions K (1: lean) */
    int lobes;                 /* roughness lobes per subdivision (1, or 2 where the batch
                                * has a roughness map: shade._lobes' lobes_r) */
    int taps;                  /* ewa_taps */
    int mips;                  /* levels of the LEAN pyramid */
    int texel;                 /* its channels per texel: K * LEAN_CH, or for ``lean``
                                * (K = 1) 2 (w, w u) or 4 (w, w u, w u^2, w u^3), the
                                * channels its merged Gaussian reads (moments_range) */
    const float *const *lean;  /* per level its (B, h, w, texel) moments */
    const int64_t *lean_hw;    /* (mips, 2) */
} LeanJob;

/* ---- small 2x2 algebra (optics/cov2.py), symmetric matrices as (xx, xy, yy) ---- */

/* cov2.eig2: the larger and smaller eigenvalue and the unit eigenvector of the larger. */
static void eig2(float a, float b, float d, float *l1, float *l2, float *ev) {
    float half_tr = 0.5f * (a + d), diff = 0.5f * (a - d);
    float r = sqrtf((diff * diff + b * b) + 1e-30f);
    *l1 = half_tr + r;
    *l2 = half_tr - r;
    float vx, vy;
    if (diff >= 0.0f) { vx = *l1 - d; vy = b; }
    else { vx = b; vy = *l1 - a; }
    float ln = sqrtf(fmaf(vy, vy, vx * vx));
    if (ln > 1e-20f) {
        float l = ln > 1e-30f ? ln : 1e-30f;
        ev[0] = vx / l;
        ev[1] = vy / l;
    } else {
        ev[0] = 1.0f;
        ev[1] = 0.0f;
    }
}

/* cov2.psd2: negative eigenvalues raised to 0. */
static void psd2(const float *c, float *out) {
    float l1, l2, e[2];
    eig2(c[0], c[1], c[2], &l1, &l2, e);
    l1 = l1 > 0.0f ? l1 : (l1 != l1 ? l1 : 0.0f);
    l2 = l2 > 0.0f ? l2 : (l2 != l2 ? l2 : 0.0f);
    float f[2] = {-e[1], e[0]};
    out[0] = l1 * (e[0] * e[0]) + l2 * (f[0] * f[0]);
    out[1] = l1 * (e[0] * e[1]) + l2 * (f[0] * f[1]);
    out[2] = l1 * (e[1] * e[1]) + l2 * (f[1] * f[1]);
}

/* lobes.to_basis: a covariance in the basis (u, v) re-expressed in (e1, e2): R C R^T. */
static void to_basis(const float *c, const float *u, const float *v, const float *e1,
                     const float *e2, float *out) {
    float r[2][2] = {{dot3(e1, u), dot3(e1, v)}, {dot3(e2, u), dot3(e2, v)}};
    float cm[2][2] = {{c[0], c[1]}, {c[1], c[2]}}, rc[2][2];
    for (int a = 0; a < 2; a++)
        for (int q = 0; q < 2; q++) rc[a][q] = r[a][0] * cm[0][q] + r[a][1] * cm[1][q];
    out[0] = rc[0][0] * r[0][0] + rc[0][1] * r[0][1];
    out[1] = rc[0][0] * r[1][0] + rc[0][1] * r[1][1];
    out[2] = rc[1][0] * r[1][0] + rc[1][1] * r[1][1];
}

/* moments._tangents: u along the x axis projected onto the tangent plane of unit n. */
static void lean_tangents(const float *n, float *u, float *v) {
    u[0] = 1.0f - n[0] * n[0];
    u[1] = -(n[0] * n[1]);
    u[2] = -(n[0] * n[2]);
    normalize3(u);
    cross3(n, u, v);
}

/* basis^T c: camera coordinates to world (moments.gaussians' to_world). */
static inline void to_world(const float *basis, const float *c, float *w) {
    for (int i = 0; i < 3; i++)
        w[i] = (basis[i] * c[0] + basis[3 + i] * c[1]) + basis[6 + i] * c[2];
}

/* ---- the footprint and its moments ---- */

/* cone.trace_cone's footprint (kernels.cone.footprint): the axis exit's pixel, the extents
 * of the four exits' box (at least 1), the raw minor extent clamped to [0, 1] (``sub``). */
typedef struct {
    float c[2], major, minor, sub, level;
    int along_x;
} Foot;

static void footprint(const Frame *j, const Block *k, int i, int64_t b, Foot *fp) {
    const float *pp = j->proj + 16 * b;
    float xy[4][2], ext[2], raw[2];
    project1(k->axis.pos + 3 * i, pp, fp->c);
    for (int q = 0; q < 4; q++) {
        if (k->cone[q].found[i]) project1(k->cone[q].pos + 3 * i, pp, xy[q]);
        else { xy[q][0] = fp->c[0]; xy[q][1] = fp->c[1]; }
    }
    for (int a = 0; a < 2; a++) {
        float mx = xy[0][a], mn = xy[0][a];
        for (int q = 1; q < 4; q++) { mx = tmax(mx, xy[q][a]); mn = tmin(mn, xy[q][a]); }
        raw[a] = mx - mn;
        ext[a] = raw[a] < 1.0f ? 1.0f : raw[a];  /* clamp(min=1), NaN kept */
    }
    fp->minor = tmin(ext[0], ext[1]);
    fp->major = tmax(ext[0], ext[1]);
    fp->along_x = ext[0] >= ext[1];
    fp->sub = clampf(tmin(raw[0], raw[1]), 0.0f, 1.0f);
    fp->level = log2f(fp->minor);
}

/* A texel of zeros: grid_sample's padding (a corner outside reads 0). */
static const float ZERO_TEXEL[MAX_K * LEAN_CH];

/* ndf.sample_box_mips of the LEAN pyramid at pixel (x, y), fractional level lv: grid_sample's
 * bilinear (zeros padding, align_corners=False) on the two levels around it; the channels
 * in the ``nr`` ranges [rng[2r], rng[2r + 1]) (the others untouched). */
static void sample_lean(const LeanJob *lj, int64_t b, float x, float y, float lv,
                        const int *rng, int nr, float *out) {
    int n = lj->mips, nc = lj->texel;
    for (int r = 0; r < nr; r++)
        for (int q = rng[2 * r]; q < rng[2 * r + 1]; q++) out[q] = 0.0f;
    if (lv != lv) return;  /* no level matches (torch: floor(NaN) is no index) */
    lv = clampf(lv, 0.0f, (float)(n - 1));
    int l0 = (int)floorf(lv), l1 = l0 + 1 < n ? l0 + 1 : n - 1;
    float frac = lv - (float)l0;
    for (int lvl = l0; lvl <= l1; lvl++) {
        float w = (l0 == lvl ? 1.0f - frac : 0.0f) + (l1 == lvl ? frac : 0.0f);
        if (!(w > 0.0f)) continue;
        int64_t h = lj->lean_hw[2 * lvl], wd = lj->lean_hw[2 * lvl + 1];
        /* the texel coordinate: sample_box_mips' grid (x / 2^l / w * 2 - 1) unnormalized by
         * grid_sample ((g + 1) w - 1) / 2, i.e. x / 2^l - 1/2 (to a rounding of the
         * coordinate: the bilinear weights move by ~1e-7) */
        float inv = 1.0f / (float)(1 << lvl);
        float ix = x * inv - 0.5f, iy = y * inv - 0.5f;
        if (!(fabsf(ix) < 1e9f && fabsf(iy) < 1e9f)) continue;  /* far outside: all zeros */
        float fx0 = floorf(ix), fy0 = floorf(iy);
        int64_t x0 = (int64_t)fx0, y0 = (int64_t)fy0, xs[2] = {x0, x0 + 1}, ys[2] = {y0, y0 + 1};
        float tw[4] = {(fx0 + 1.0f - ix) * (fy0 + 1.0f - iy), (ix - fx0) * (fy0 + 1.0f - iy),
                       (fx0 + 1.0f - ix) * (iy - fy0), (ix - fx0) * (iy - fy0)};
        const float *img = lj->lean[lvl] + b * h * wd * nc, *src[4];
        for (int t = 0; t < 4; t++) {  /* nw, ne, sw, se */
            int64_t xx = xs[t & 1], yy = ys[t >> 1];
            src[t] = (xx >= 0 && xx < wd && yy >= 0 && yy < h) ? img + (yy * wd + xx) * nc
                                                               : ZERO_TEXEL;
        }
        const float *s0 = src[0], *s1 = src[1], *s2 = src[2], *s3 = src[3];
        float w0 = tw[0], w1 = tw[1], w2 = tw[2], w3 = tw[3];
        for (int r = 0; r < nr; r++)
            for (int q = rng[2 * r]; q < rng[2 * r + 1]; q++) {
                float v = ((s0[q] * w0 + s1[q] * w1) + s2[q] * w2) + s3[q] * w3;
                out[q] = out[q] + w * v;
            }
    }
}

static const float FOOTPRINT_TAPS[4] = {-0.375f, -0.125f, 0.125f, 0.375f};

/* The mean of the four taps along the footprint's major extent of texel channels [0, nc)
 * (the ``nr`` ranges ``rng`` read, the others 0) into mean. */
static void tap_means(const LeanJob *lj, int64_t b, const Foot *fp, const int *rng, int nr,
                      int nc, float *mean) {
    float tap[MAX_K * LEAN_CH];
    for (int q = 0; q < nc; q++) mean[q] = tap[q] = 0.0f;
    for (int t = 0; t < 4; t++) {
        float o = FOOTPRINT_TAPS[t] * fp->major;
        float x = fp->along_x ? fp->c[0] + o : fp->c[0] + 0.0f;
        float y = fp->along_x ? fp->c[1] + 0.0f : fp->c[1] + o;
        sample_lean(lj, b, x, y, fp->level, rng, nr, tap);
        for (int q = 0; q < nc; q++) mean[q] = mean[q] + tap[q];
    }
    for (int q = 0; q < nc; q++) mean[q] = mean[q] / 4.0f;
}

/* moments.footprint_sums of a pyramid without roughness channels (K * SLOPE_CH, one
 * roughness per view): the taps' means, then per subdivision w u, w u^2, w u^3 from the
 * view's roughness (u = alpha^2), into the LEAN_CH slots of acc. */
static void slope_sums(const LeanJob *lj, int64_t b, const Foot *fp, float *acc) {
    int nk = lj->k, nc = nk * SLOPE_CH, rng[2] = {0, nc};
    float mean[MAX_K * SLOPE_CH];
    tap_means(lj, b, fp, rng, 1, nc, mean);
    float alpha = lj->r.f.alpha[b], u = alpha * alpha, pw[3] = {u, u * u, (u * u) * u};
    for (int s = 0; s < nk; s++) {
        float *a = acc + s * LEAN_CH;
        for (int q = 0; q < SLOPE_CH; q++) a[q] = mean[s * SLOPE_CH + q];
        for (int q = 0; q < 3; q++) a[SLOPE_CH + q] = a[0] * pw[q];
    }
}

/* moments.footprint_sums: the moment sums (K, LEAN_CH) over the footprint. ``lean`` (K = 1)
 * reads only what its merged Gaussian uses: the coverage and the roughness moments (the
 * others are left 0). */
static void footprint_sums(const LeanJob *lj, int64_t b, const Foot *fp, float *acc) {
    int nk = lj->k, nc = nk * LEAN_CH, compact = lj->texel != nc;
    if (lj->texel == nk * SLOPE_CH) {  /* one roughness per view: its moments from it */
        slope_sums(lj, b, fp, acc);
        return;
    }
    int rng[4] = {0, nc, 0, 0}, nr = 1;  /* gsr: all channels */
    if (compact) {  /* lean's own pyramid: w, u's moments */
        rng[1] = lj->texel;
    } else if (nk == 1) {  /* lean on the full moments: w, and u (with its powers for two
                            * roughness lobes) */
        rng[1] = 1;
        rng[2] = 6;
        rng[3] = lj->lobes == 2 ? LEAN_CH : 7;
        nr = 2;
    }
    float center[MAX_K * LEAN_CH];
    for (int q = 0; q < nc; q++) center[q] = 0.0f;
    tap_means(lj, b, fp, rng, nr, nc, acc);
    sample_lean(lj, b, fp->c[0], fp->c[1], fp->level, rng, nr, center);
    if (compact)  /* channels (w, u, u^2, u^3) to their places among the LEAN_CH */
        for (int q = lj->texel - 1; q >= 1; q--) {
            acc[5 + q] = acc[q];
            center[5 + q] = center[q];
            acc[q] = center[q] = 0.0f;
        }
    for (int s = 0; s < nk; s++) {  /* the roughness moments at the center, at the taps' w */
        float *a = acc + s * LEAN_CH, *c = center + s * LEAN_CH;
        float scale = a[0] / (c[0] > 1e-12f ? c[0] : 1e-12f);
        for (int q = 6; q < LEAN_CH; q++) a[q] = c[0] > 1e-9f ? c[q] * scale : a[q];
    }
}

/* One Gaussian of normals (moments.Footprint, one subdivision of one pixel). */
typedef struct {
    float w, n[3], cov[3], u[3], v[3], var_mu, a2[2], aw[2];
} Gauss;

/* moments.two_point: nodes and weights of the two-point distribution with raw moments
 * m1, m2, m3 (in double, as the tensor code). */
static void two_point(float m1, float m2, float m3, float *nodes, float *weights) {
    double m1d = m1, m2d = m2, m3d = m3;
    double var = m2d - m1d * m1d;
    if (!(var >= 1e-30)) var = var != var ? var : 1e-30;
    double sd = sqrt(var);
    double mu3 = (m3d - 3.0 * m1d * m2d) + 2.0 * (m1d * m1d * m1d);
    double am = fabs(m1d) > 1e-12 ? fabs(m1d) : 1e-12;
    double sd3 = sd * sd * sd;
    double gamma = sd > 1e-6 * am ? mu3 / (sd3 > 1e-300 ? sd3 : 1e-300) : 0.0;
    double root = sqrt(gamma * gamma + 4.0);
    double a = 0.5 * (gamma - root), bb = 0.5 * (gamma + root);
    double q = -a / (bb - a);
    double n0 = m1d + sd * a, n1 = m1d + sd * bb;
    nodes[0] = (float)(n0 > 0.0 ? n0 : (n0 != n0 ? n0 : 0.0));
    nodes[1] = (float)(n1 > 0.0 ? n1 : (n1 != n1 ? n1 : 0.0));
    weights[0] = (float)(1.0 - q);
    weights[1] = (float)q;
}

/* moments.gaussians for one subdivision's sums ``acc`` (LEAN_CH) of a footprint whose sums
 * over all subdivisions cover ``total``; ``full``: also the normal, covariance and basis
 * (the roughness alone for the merged Gaussian of ``spread: rays``). */
static void gauss_of(const Frame *j, int64_t b, const float *acc, float total, int full,
                     int lobes, Gauss *g) {
    float cov_w = acc[0];
    float wk = cov_w / (total > 1e-12f ? total : 1e-12f);
    g->w = total > 1e-6f ? wk : 0.0f;
    float cw = cov_w > 1e-12f ? cov_w : 1e-12f, mean[8];
    for (int q = full ? 0 : 5; q < 8; q++) mean[q] = acc[1 + q] / cw;  /* (merged: u's) */
    int valid = cov_w > 1e-6f;
    g->var_mu = valid ? 0.5f * mean[5] : 0.0f;
    if (lobes == 2) two_point(mean[5], mean[6], mean[7], g->a2, g->aw);
    if (!full) {  /* (not read: the merged Gaussian's lobes sit at the exact normal) */
        for (int c = 0; c < 3; c++) g->n[c] = g->u[c] = g->v[c] = g->cov[c] = 0.0f;
        return;
    }
    float bx = mean[0], by = mean[1];
    float sxx = mean[2] - bx * bx, sxy = mean[3] - bx * by, syy = mean[4] - by * by;
    float n[3] = {bx, by, 1.0f}, u[3], v[3];
    normalize3(n);
    lean_tangents(n, u, v);
    /* slope_jacobian: columns (t_xy n_z - n_xy t_z) / n_z^2 for t = u, v */
    float nz = n[2] > NZ_MIN ? n[2] : (n[2] != n[2] ? n[2] : NZ_MIN), nz2 = nz * nz;
    float a00 = (u[0] * nz - n[0] * u[2]) / nz2, a10 = (u[1] * nz - n[1] * u[2]) / nz2;
    float a01 = (v[0] * nz - n[0] * v[2]) / nz2, a11 = (v[1] * nz - n[1] * v[2]) / nz2;
    float det = a00 * a11 - a01 * a10;
    float i00 = a11 / det, i01 = -a01 / det, i10 = -a10 / det, i11 = a00 / det;
    /* A^-1 Sigma A^-T, symmetrized, the microfacet variance taken out, PSD */
    float t00 = i00 * sxx + i01 * sxy, t01 = i00 * sxy + i01 * syy;
    float t10 = i10 * sxx + i11 * sxy, t11 = i10 * sxy + i11 * syy;
    float c00 = t00 * i00 + t01 * i01, c01 = t00 * i10 + t01 * i11;
    float c10 = t10 * i00 + t11 * i01, c11 = t10 * i10 + t11 * i11;
    float var_mu = 0.5f * mean[5];
    float cs[3] = {0.5f * (c00 + c00) - var_mu, 0.5f * (c01 + c10), 0.5f * (c11 + c11) - var_mu};
    const float *basis = j->basis + 9 * b;
    if (valid) {
        psd2(cs, g->cov);
        to_world(basis, n, g->n);
    } else {
        g->cov[0] = g->cov[1] = g->cov[2] = 0.0f;
        g->n[0] = g->n[1] = g->n[2] = 0.0f;
    }
    to_world(basis, u, g->u);
    to_world(basis, v, g->v);
}

/* moments.uniform_footprint: the merged Gaussian where the roughness is one value (no
 * map), its roughness alpha's own moments (``lean``, one roughness lobe). */
static void uniform_gauss(float alpha, Gauss *g) {
    g->w = 1.0f;
    g->var_mu = 0.5f * (alpha * alpha);
    for (int c = 0; c < 3; c++) g->n[c] = g->u[c] = g->v[c] = g->cov[c] = 0.0f;
}

/* moments.separation: how clearly the subdivisions' normals form separate groups, in
 * [0, 1] (smoothstep of the between / within trace ratio from 3 to 10). */
static float separation(const Gauss *g, int nk) {
    float nb[3] = {0.0f, 0.0f, 0.0f}, t1[3], t2[3], o[MAX_K][2], ob[2] = {0.0f, 0.0f};
    for (int s = 0; s < nk; s++)
        for (int c = 0; c < 3; c++) nb[c] = s == 0 ? g[0].w * g[0].n[c] : nb[c] + g[s].w * g[s].n[c];
    normalize3(nb);
    lean_tangents(nb, t1, t2);
    for (int s = 0; s < nk; s++) {
        o[s][0] = dot3(g[s].n, t1);
        o[s][1] = dot3(g[s].n, t2);
        for (int c = 0; c < 2; c++) ob[c] = s == 0 ? g[0].w * o[0][c] : ob[c] + g[s].w * o[s][c];
    }
    float between = 0.0f, within = 0.0f;
    for (int s = 0; s < nk; s++) {
        float d0 = o[s][0] - ob[0], d1 = o[s][1] - ob[1], cb[3];
        float bw = g[s].w * (d0 * d0 + d1 * d1);
        to_basis(g[s].cov, g[s].u, g[s].v, t1, t2, cb);
        float ww = g[s].w * (cb[0] + cb[2]);
        between = s == 0 ? bw : between + bw;
        within = s == 0 ? ww : within + ww;
    }
    float ratio = between / (within > 1e-10f ? within : 1e-10f);
    float x = clampf((ratio - 3.0f) / 7.0f, 0.0f, 1.0f);
    return x * x * (3.0f - 2.0f * x);
}

/* ---- the exit lobes ---- */

/* exit.exit_interface at normal n (outward) for the front lobe (p_t1, k_t1). */
static void exit_geo(float ior, const float *p_t1, float k_t1, int found, const float *n,
                     const float *p2, ExitGeo *e) {
    e->p_t1 = p_t1;
    e->k_t1 = k_t1;
    e->found = found;
    float m[3] = {-n[0], -n[1], -n[2]};
    face_forward(m, p_t1, e->n_in);
    for (int c = 0; c < 3; c++) {
        e->view2[c] = -p_t1[c];
        e->p2[c] = p2[c];
    }
    e->cos2 = clampf(dot3(e->view2, e->n_in), 0.0f, 1.0f);
    float cc = 1.0f - 1.0f / (ior * ior);
    e->cos_crit = sqrtf(cc > 0.0f ? cc : 0.0f);
    e->tir = e->cos2 < e->cos_crit && found;
    e->var1 = 1.0f / (k_t1 > 1e-12f ? k_t1 : 1e-12f);
    e->var_geo = 0.0f;  /* the table's lobe alone: widened by the covariances */
    e->split_at = NULL;  /* no split kept (rousiers_core.h's prepare_exit keeps one) */
}

/* exit.py's mag2, (d theta_out / d theta_in)^2 at the exit. */
static float exit_mag2(float ior, float cos2) {
    float sin2 = 1.0f - cos2 * cos2;
    float co = 1.0f - ior * ior * (sin2 > 0.0f ? sin2 : 0.0f);
    float mg = ior * cos2 / sqrtf(co > 1e-4f ? co : 1e-4f);
    return mg * mg;
}

/* One exit lobe (shade._Lobe): its interface, axis, sharpness, weight, share, roughness,
 * and what its interface reflects inside. */
typedef struct {
    ExitGeo e;
    float n[3], axis[3], k, energy, share, alpha, refl;
    int j;
} Lobe;

/* exit.exit_lobe (``spread: rays``, var_geo 0) at the interface of normal n, roughness
 * alpha, under ``mode``; ``refl``: also spread_energies' reflected part (for the bounces). */
static void make_lobe(const LeanJob *lj, const SgAxes *view_axes, int64_t b, int mode,
                      const float *p_t1, float k_t1, int found, const float *n,
                      const float *p2, float alpha, int refl, Lobe *lb) {
    const Frame *j = &lj->r.f;
    float ior = j->ior[b];
    exit_geo(ior, p_t1, k_t1, found, n, p2, &lb->e);
    for (int c = 0; c < 3; c++) lb->n[c] = n[c];
    SgAxes ax[AXES];
    sg_axes(&j->table, 1.0f / ior, alpha, ax + OUT);
    ax[OUT0] = view_axes[OUT0];
    lb->alpha = alpha;
    if (found) {
        exit_lobe(&lj->r, ax, b, alpha, mode, &lb->e, lb->axis, &lb->k, &lb->energy);
    } else {  /* leave with the front lobe */
        for (int c = 0; c < 3; c++) lb->axis[c] = p_t1[c];
        lb->k = k_t1;
        lb->energy = 1.0f;
    }
    lb->refl = 0.0f;
    if (refl) {
        float et;
        spread_table_energies(&j->table, ax + OUT, ax + OUT0, j->dist[b], lb->e.cos2,
                              lb->e.var1, &et, &lb->refl);
    }
}

/* What every lobe of a pixel shares: the front lobe, the exit point, the exact normal. */
typedef struct {
    const float *p_t1;
    float k_t1, p2[3], exact_n[3], alpha;
    int found;
    const Foot *fp;
} PixelExit;

/* shade._lobe_normals and shade._lobes over the nk Gaussians g: the lobes with a share
 * (those without add nothing), their count. ``exact``: at the exact exit normal (``spread:
 * rays``' mixture), else blended towards the Gaussians' normals as the footprint grows. */
static int lobe_set(const LeanJob *lj, const SgAxes *view_axes, int64_t b, int mode,
                    const PixelExit *px, const Gauss *g, int nk, int exact, int refl,
                    Lobe *out) {
    float wsum = 0.0f;
    for (int s = 0; s < nk; s++) wsum = s == 0 ? g[0].w : wsum + g[s].w;
    int have = px->found && wsum > 0.5f, nl = lj->lobes, count = 0;
    float w_ndf = exact ? 0.0f : clampf(log2f(px->fp->minor) / 2.0f, 0.0f, 1.0f);
    for (int s = 0; s < nk; s++) {
        float weight = have ? g[s].w : (s == 0 ? 1.0f : 0.0f);
        int use = have && g[s].w > 0.0f;
        float n[3];
        if (use) {  /* exact: 0 n_j + 1 n_exact, n_j finite */
            for (int c = 0; c < 3; c++)
                n[c] = exact ? px->exact_n[c]
                             : w_ndf * g[s].n[c] + (1.0f - w_ndf) * px->exact_n[c];
            normalize3(n);
        } else {
            for (int c = 0; c < 3; c++) n[c] = px->exact_n[c];
        }
        for (int r = 0; r < nl; r++) {
            float a2 = nl == 2 ? g[s].a2[r] : 2.0f * g[s].var_mu;
            float aw = nl == 2 ? g[s].aw[r] : 1.0f;
            float a = use ? sqrtf(a2 > 1e-8f ? a2 : (a2 != a2 ? a2 : 1e-8f)) : px->alpha;
            if (!use) aw = 1.0f / (float)nl;
            float share = weight * aw;
            if (share == 0.0f) continue;  /* adds 0 to every sum */
            Lobe *lb = out + count++;
            make_lobe(lj, view_axes, b, mode, px->p_t1, px->k_t1, px->found, n, px->p2, a,
                      refl, lb);
            lb->share = share;
            lb->j = s;
        }
    }
    return count;
}

/* lighting/ewa.ewa_radiance of one lobe: taps along the major axis of ``cov`` (in the basis
 * e1, e2) around ``axis``, each an SG lookup (lights included), averaged. */
static void ewa(const Frame *j, const LeanJob *lj, int64_t b, const float *origin,
                const float *axis, const float *cov, const float *e1, const float *e2,
                float *out) {
    float l1, l2, ev[2];
    int taps = lj->taps;
    eig2(cov[0], cov[1], cov[2], &l1, &l2, ev);
    l1 = l1 > 1e-12f ? l1 : (l1 != l1 ? l1 : 1e-12f);
    l2 = l2 > 1e-12f ? l2 : (l2 != l2 ? l2 : 1e-12f);
    if (taps == 1) {
        incident_sg(&j->lights, &j->env, b, origin, axis, 2.0f / (l1 + l2), out);
        return;
    }
    double cc = 3.0 * taps * taps / (taps * taps + 2.0);
    float lv = l1 * (float)(cc / (taps * taps));
    float v = tmax(l2, lv);
    float sp = 12.0f * (l1 - v) / (float)(taps * taps - 1.0);
    float spacing = sqrtf(sp > 1e-30f ? sp : (sp != sp ? sp : 1e-30f));
    float major[3], k = 1.0f / v, sum[3] = {0.0f, 0.0f, 0.0f};
    for (int c = 0; c < 3; c++) major[c] = ev[0] * e1[c] + ev[1] * e2[c];
    normalize3(major);
    float half = (float)(0.5 * (taps - 1)), cs[16], sn[16];
    for (int t = 0; t < taps; t++) {  /* z_t = -z_(T-1-t): cos even, sin odd */
        float z = ((float)t - half) * spacing;
        if (2 * t < taps - 1 || z == 0.0f) {
            cs[t] = cosf(z);
            sn[t] = sinf(z);
        } else {
            cs[t] = cs[taps - 1 - t];
            sn[t] = -sn[taps - 1 - t];
        }
    }
    /* every tap's texels asked for first, then read in order (incident_sg, split so the
     * reads overlap: the taps scatter over the pyramid) */
    float d[16][3];
    SgTap tap[16];
    for (int t = 0; t < taps; t++)
        for (int c = 0; c < 3; c++) d[t][c] = cs[t] * axis[c] + sn[t] * major[c];
    for (int t0 = 0; t0 < taps; t0 += 8)  /* eight at a time, in lanes */
        sg_env_taps(&j->lights, &j->env, b, (const float (*)[3])d[t0],
                    taps - t0 < 8 ? taps - t0 : 8, k, tap + t0);
    for (int t = 0; t < taps; t++) {
        float l[3];
        incident_sg_at(&j->lights, b, origin, d[t], k, &tap[t], l);
        for (int c = 0; c < 3; c++) sum[c] = t == 0 ? l[c] : sum[c] + l[c];
    }
    for (int c = 0; c < 3; c++) out[c] = sum[c] / (float)taps;
}

/* lobes.incidence_frame's e_perp for incident i at normal n_in. */
static void e_perp_of(const float *i, const float *n_in, float *e_perp, float *n_f) {
    float e[3];
    face_forward(n_in, i, n_f);
    cross3(i, n_f, e);
    float ln = norm3(e);
    if (ln > 1e-6f) {
        for (int c = 0; c < 3; c++) e_perp[c] = e[c] / (ln > 1e-12f ? ln : 1e-12f);
    } else {
        float v[3];
        tangent_frame(i, e_perp, v);
    }
}

/* shade._rays_mixture with shade._ray_covariances and shade._read (``spread: rays``): the
 * light of the merged Gaussian's lobes, each at its own axis and widened by the bounding
 * rays' covariance (l, N x 3), and the mixture's per-axis variance. */
static float rays_mixture(const LeanJob *lj, const SgAxes *view_axes, const Block *k, int i,
                          int64_t b, int mode, const PixelExit *px, const ExitGeo *xe,
                          const Gauss *merged, float *l) {
    const Frame *j = &lj->r.f;
    float ior = j->ior[b];
    Lobe lobes[2];
    int m = lobe_set(lj, view_axes, b, mode, px, merged, 1, 1, 0, lobes);
    /* lobes.incidence_frame's e_perp: the basis' second axis at every lobe */
    float e2[3], n_f[3];
    e_perp_of(px->p_t1, xe->n_in, e2, n_f);
    float variance = 0.0f;
    if (m > 1) {  /* the nodes' axes about their mean (the mixture's own spread) */
        float mean[3];
        for (int c = 0; c < 3; c++) {
            mean[c] = 0.0f;
            for (int q = 0; q < m; q++) mean[c] = mean[c] + lobes[q].share * lobes[q].axis[c];
        }
        float sum = 0.0f;
        for (int q = 0; q < m; q++) {
            float dq[3] = {lobes[q].axis[0] - mean[0], lobes[q].axis[1] - mean[1],
                           lobes[q].axis[2] - mean[2]};
            sum = sum + lobes[q].share * dot3(dq, dq);
        }
        variance = 0.5f * sum;
    }
    /* lobes.ray_covariance: the bounding rays refracted out at their own exit normals */
    float t_c[3], nc[3], e1r[3], rays[3] = {0.0f, 0.0f, 0.0f};
    float mn[3] = {-px->exact_n[0], -px->exact_n[1], -px->exact_n[2]};
    face_forward(mn, px->p_t1, nc);
    refract(px->p_t1, nc, ior, t_c);
    cross3(e2, t_c, e1r);
    normalize3(e1r);
    int cnt = 0;
    float n4[4][3];
    uint8_t ok4[4];
    bounding_normals(&lj->r, k, i, n4, ok4);
    float nk[4][3], t_k[4][3];  /* all four refracted at once (those not found unused) */
    for (int q = 0; q < 4; q++) {
        float mq[3] = {-n4[q][0], -n4[q][1], -n4[q][2]};
        face_forward(mq, k->dirs[i][q], nk[q]);
    }
    refract_x4(k->dirs[i], (const float (*)[3])nk, ior, t_k);
    for (int q = 0; q < 4; q++) {
        if (!ok4[q]) continue;
        float dk[3];
        for (int c = 0; c < 3; c++) dk[c] = t_k[q][c] - t_c[c];
        float x = dot3(dk, e1r), y = dot3(dk, e2);
        float add[3] = {x * x, x * y, y * y};
        for (int c = 0; c < 3; c++) rays[c] = rays[c] + add[c];
        cnt++;
    }
    if (cnt > 0) {
        float den = (float)cnt * (float)log(4.0);
        for (int c = 0; c < 3; c++) rays[c] = rays[c] / den;
    } else {
        float v = exit_mag2(ior, xe->cos2) / px->k_t1;
        rays[0] = v; rays[1] = 0.0f; rays[2] = v;
    }
    float wthn[3];
    psd2(rays, wthn);
    for (int q = 0; q < m; q++) {
        Lobe *lb = lobes + q;
        float axis[3], cov[3], lq[3], e1[3];
        for (int c = 0; c < 3; c++) axis[c] = lb->axis[c];
        if (px->found) normalize3(axis);
        cross3(e2, lb->axis, e1);  /* out_basis at the lobe's axis */
        normalize3(e1);
        float iso = 1.0f / (lb->k > 1e-12f ? lb->k : 1e-12f);
        cov[0] = (px->found ? wthn[0] : 0.0f) + iso;
        cov[1] = (px->found ? wthn[1] : 0.0f) + 0.0f;
        cov[2] = (px->found ? wthn[2] : 0.0f) + iso;
        variance = variance + (lb->share * 0.5f) * (cov[0] + cov[2]);
        ewa(j, lj, b, lb->e.p2, axis, cov, e1, e2, lq);
        float we = lb->share * lb->energy;
        for (int c = 0; c < 3; c++) l[c] = q == 0 ? we * lq[c] : l[c] + we * lq[c];
    }
    return variance;
}

/* ``gsr``'s own lobes (shade._lobes, not exact; shade._paper_covariances, shade._read): the
 * subdivisions' light, the mixture's per-axis variance, what their interfaces reflect
 * inside (shade._reflected). */
static float sector_lobes(const LeanJob *lj, const SgAxes *view_axes, int64_t b, int mode,
                          const PixelExit *px, const Gauss *g, int refl, float *l,
                          float *reflected) {
    const Frame *j = &lj->r.f;
    float ior = j->ior[b];
    Lobe lobes[MAX_LOBES];
    int m = lobe_set(lj, view_axes, b, mode, px, g, lj->k, 0, refl, lobes);
    float variance = 0.0f, sectors = 0.0f, sub2 = px->fp->sub * px->fp->sub;
    for (int c = 0; c < 3; c++) l[c] = 0.0f;
    for (int q = 0; q < m; q++) {
        Lobe *lb = lobes + q;
        const ExitGeo *e = &lb->e;
        const Gauss *gs = g + lb->j;
        /* lobes.paper_covariance */
        float cos_in = e->tir ? e->cos_crit + 1e-4f : e->cos2;
        float e_perp[3], n_f[3], e_par[3], cn[3], cs[3];
        e_perp_of(px->p_t1, e->n_in, e_perp, n_f);
        float sin2_t = ior * ior * (1.0f - cos_in * cos_in);
        float ct = 1.0f - sin2_t;
        float cos_t = sqrtf(ct > 1e-4f ? ct : 1e-4f);
        float mm = ior * cos_in / cos_t;
        mm = mm < 2.0f ? mm : (mm != mm ? mm : 2.0f);  /* lobes.M_MAX */
        float jn0 = 1.0f - mm, jn1 = ior * cos_in - sqrtf(ct > 0.0f ? ct : 0.0f);
        cross3(e_perp, n_f, e_par);
        for (int c = 0; c < 3; c++) cs[c] = sub2 * gs->cov[c];
        to_basis(cs, gs->u, gs->v, e_par, e_perp, cn);
        float cov[3] = {(jn0 * cn[0]) * jn0 + (mm * mm) * e->var1, (jn0 * cn[1]) * jn1 + 0.0f,
                        (jn1 * cn[2]) * jn1 + (ior * ior) * e->var1};
        float iso = 1.0f / (lb->k > 1e-12f ? lb->k : 1e-12f);
        for (int c = 0; c < 3; c++) cov[c] = (px->found ? cov[c] : 0.0f) + (c == 1 ? 0.0f : iso);
        float e1[3], lq[3];
        cross3(e_perp, lb->axis, e1);
        normalize3(e1);
        variance = variance + (lb->share * 0.5f) * (cov[0] + cov[2]);
        ewa(j, lj, b, e->p2, lb->axis, cov, e1, e_perp, lq);
        float we = lb->share * lb->energy;
        for (int c = 0; c < 3; c++) l[c] = l[c] + we * lq[c];
        sectors = sectors + lb->share * lb->refl;
    }
    *reflected = sectors;
    return variance;
}

/* Steps 2-5 for pixel i of a block (shade.render_lean, rousiers.shade.finish). */
static void lean_pixel(const LeanJob *lj, const SgAxes *view_axes, Block *k, int i,
                       int64_t px, int64_t b) {
    const RousJob *rj = &lj->r;
    const Frame *j = &rj->f;
    float ior = j->ior[b];
    int found = k->axis.found[i], nk = lj->k, bounce = rj->bo.limit > 0;
    int mode = exit_mode(rj);
    const float *p1 = k->axis.p + 3 * i;
    Foot fp;
    footprint(j, k, i, b, &fp);
    PixelExit pe = {.p_t1 = k->axis.t + 3 * i, .k_t1 = k->k_t1[i], .alpha = k->alpha[i],
                    .found = found, .fp = &fp};
    for (int c = 0; c < 3; c++) {
        pe.exact_n[c] = found ? k->axis.normal[3 * i + c] : pe.p_t1[c];
        pe.p2[c] = found ? k->axis.pos[3 * i + c] : p1[c];
    }
    ExitGeo xe;  /* the exact exit normal's interface (the mixture's center, the bounces) */
    exit_geo(ior, pe.p_t1, pe.k_t1, found, pe.exact_n, pe.p2, &xe);
    /* the moments over the footprint: per subdivision and merged (none where the
     * roughness is one value: moments.uniform_footprint) */
    float sums[MAX_K * LEAN_CH], msum[LEAN_CH];
    Gauss merged, g[MAX_K];
    if (lj->mips == 0) {
        uniform_gauss(k->alpha[i], &merged);
    } else {
        footprint_sums(lj, b, &fp, sums);
        for (int q = 0; q < LEAN_CH; q++) {
            float s = sums[q];
            for (int t = 1; t < nk; t++) s = s + sums[t * LEAN_CH + q];
            msum[q] = s;
        }
        gauss_of(j, b, msum, msum[0], 0, lj->lobes, &merged);
    }
    float l_trans[3];
    float variance = rays_mixture(lj, view_axes, k, i, b, mode, &pe, &xe, &merged, l_trans);
    float apart = 0.0f, sectors = 0.0f;
    if (nk > 1) {  /* gsr: the subdivisions' lobes where their normals part */
        float total = sums[0];
        for (int t = 1; t < nk; t++) total = total + sums[t * LEAN_CH];
        for (int t = 0; t < nk; t++) gauss_of(j, b, sums + t * LEAN_CH, total, 1, lj->lobes, g + t);
        apart = separation(g, nk);
        if (apart > 0.0f) {
            float l_k[3];
            float var_k = sector_lobes(lj, view_axes, b, mode, &pe, g, bounce, l_k, &sectors);
            for (int c = 0; c < 3; c++) l_trans[c] = lerpf(l_trans[c], l_k[c], apart);
            variance = lerpf(variance, var_k, apart);
        }
    }
    /* the front reflection (its lookup tapped by cone_block); rousiers.shade.finish */
    float l_refl[3];
    incident_sg_at(&j->lights, b, p1, k->axis_r + 3 * i, k->k_r[i], k->tap_r + i, l_refl);
    finish_pixel(rj, view_axes, k, i, px, b, &xe, l_refl, l_trans, apart, sectors);
    j->exit_found[px] = found ? 1.0f : 0.0f;
    j->tir[px] = xe.tir ? 1.0f : 0.0f;
    rj->lobe_sigma[px] = sqrtf(variance > 0.0f ? variance : (variance != variance ? variance : 0.0f));
    rj->footprint[px] = found ? fp.major : 0.0f;
}

static void lean_pixel_of(const void *job, const SgAxes *view_axes, Block *k, int i,
                          int64_t px, int64_t b) {
    lean_pixel((const LeanJob *)job, view_axes, k, i, px, b);
}

/* One block of pixels: rousiers_core.h's cone_block with lean_pixel. */
static void lean_block(const void *job, const SgAxes *axes, int64_t r0, int m) {
    cone_block(job, &((const LeanJob *)job)->r, axes, r0, m, lean_pixel_of, CONE_FRONT_TAPS);
}

/* ---- the LEAN moments of the back layer (moments.lean_mips' level 0) ---- */

typedef struct {
    Frame f;            /* read: nb, basis and the roughness (alpha, rmap, rmap_hw, rrange) */
    int64_t h, w;
    int k;              /* subdivisions */
    int compact;        /* 0: the K * LEAN_CH channels; 2 or 4 (K = 1): w, w u (, w u^2,
                         * w u^3), the channels ``lean``'s kernel reads (LeanJob.texel);
                         * SLOPE_CH: the K * SLOPE_CH channels without the roughness's
                         * (one roughness per view: footprint_sums gives them) */
    const float *normal, *uv;   /* the back layer's (B*H*W, 3), (B*H*W, 2) */
    const uint8_t *mask;        /* (B*H*W,) */
    float *out;                 /* (B*H*W, K * LEAN_CH) */
} MomentsJob;

/* moments.lean_mips per back pixel: the slopes s of its normal in the view's camera frame
 * (moments.slopes, n_z clamped), the second moments s s^T + A (alpha^2 / 2) A^T
 * (moments.slope_jacobian), the powers of alpha^2, weighted by coverage, in its
 * subdivision's channels (moments.sector); zeros elsewhere. */
static void moments_range(const void *arg, int64_t begin, int64_t end) {
    const MomentsJob *mj = (const MomentsJob *)arg;
    const Frame *f = &mj->f;
    int nk = mj->k, nc = !mj->compact ? nk * LEAN_CH
                        : mj->compact == SLOPE_CH ? nk * SLOPE_CH : mj->compact;
    int64_t hw = mj->h * mj->w;
    for (int64_t p = begin; p < end; p++) {
        float *o = mj->out + p * nc;
        for (int q = 0; q < nc; q++) o[q] = 0.0f;
        if (!mj->mask[p]) continue;  /* (coverage 0: the tensor code's channels times 0) */
        int64_t b = p / hw;
        if (mj->compact && mj->compact != SLOPE_CH) {
            float alpha = roughness_at(f, b, mj->uv + 2 * p), uu = alpha * alpha;
            float ch[4] = {1.0f, uu, uu * uu, (uu * uu) * uu};
            for (int q = 0; q < nc; q++) o[q] = ch[q];
            continue;
        }
        const float *basis = f->basis + 9 * b, *nw = mj->normal + 3 * p;
        float nc3[3] = {dot3(basis, nw), dot3(basis + 3, nw), dot3(basis + 6, nw)};
        float nz = nc3[2] > NZ_MIN ? nc3[2] : (nc3[2] != nc3[2] ? nc3[2] : NZ_MIN);
        float x = nc3[0], y = nc3[1], r = sqrtf(fmaf(y, y, x * x));
        float sc = 1.0f;
        if (r > 1e-12f) {
            float t = 1.0f - nz * nz;
            sc = sqrtf(t > 0.0f ? t : 0.0f) / (r > 1e-12f ? r : 1e-12f);
        }
        sc = sc < 1.0f ? sc : (sc != sc ? sc : 1.0f);
        float n[3] = {x * sc, y * sc, nz}, u[3], v[3];
        float s0 = n[0] / nz, s1 = n[1] / nz;
        lean_tangents(n, u, v);
        float nz2 = nz * nz;
        float a00 = (u[0] * nz - n[0] * u[2]) / nz2, a10 = (u[1] * nz - n[1] * u[2]) / nz2;
        float a01 = (v[0] * nz - n[0] * v[2]) / nz2, a11 = (v[1] * nz - n[1] * v[2]) / nz2;
        float alpha = roughness_at(f, b, mj->uv + 2 * p);
        float uu = alpha * alpha, var_mu = 0.5f * uu;
        float g00 = a00 * a00 + a01 * a01, g01 = a00 * a10 + a01 * a11;
        float g11 = a10 * a10 + a11 * a11;
        float ch[LEAN_CH] = {1.0f, s0, s1, s0 * s0 + var_mu * g00, s0 * s1 + var_mu * g01,
                             s1 * s1 + var_mu * g11, uu, uu * uu, (uu * uu) * uu};
        int sec = 0;
        if (nk > 1) {  /* sector: the slope's azimuth, sector 0 centered on the x axis */
            float two_pi = (float)(2.0 * TR_PI);
            float phi = atan2f(s1, s0) + (float)(TR_PI / nk);
            float rem = fmodf(phi, two_pi);
            if (rem != 0.0f && (rem < 0.0f) != (two_pi < 0.0f)) rem += two_pi;
            float fs = floorf(rem / (float)(2.0 * TR_PI / nk));
            sec = fs != fs ? 0 : (fs < 0.0f ? 0 : (fs > (float)(nk - 1) ? nk - 1 : (int)fs));
        }
        int per = mj->compact == SLOPE_CH ? SLOPE_CH : LEAN_CH;
        for (int q = 0; q < per; q++) o[sec * per + q] = ch[q];
    }
}

int torchrefract_lean_moments(MomentsJob *job, int threads) {
    if (job->k < 1 || job->k > MAX_K ||
        (job->compact && job->compact != SLOPE_CH &&
         (job->k != 1 || (job->compact != 2 && job->compact != 4))))
        return -1;
    return tr_parallel_for(moments_range, job, job->f.nb * job->h * job->w, 4096, threads);
}

int64_t torchrefract_lean_moments_job_size(void) { return (int64_t)sizeof(MomentsJob); }

/* Entry point (ctypes, shading/fused_lean.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_lean(LeanJob *job, int threads) {
    if (job->k < 1 || job->k > MAX_K || job->lobes < 1 || job->lobes > 2 || job->taps < 1 ||
        job->taps > 16 ||
        job->mips < 0 || job->r.levels != 0 ||
        (job->mips == 0 ? job->k != 1 || job->lobes != 1 || job->texel != 0
                        : job->texel != job->k * LEAN_CH &&
                              !(job->texel == job->k * SLOPE_CH && job->lobes == 1) &&
                              (job->k != 1 || job->texel != (job->lobes == 2 ? 4 : 2))))
        return -1;
    return run_shading(job, &job->r.f, NAXES, rous_axes, lean_block, threads);
}

int64_t torchrefract_lean_job_size(void) { return (int64_t)sizeof(LeanJob); }
