/* The steps of the fused shading of ``rousiers`` (methods/rousiers/, de Rousiers et al. 2012) for its
 * default spread (``spread: rays``), either ``cone_rays``, every ``tir`` rule, uniform
 * roughness or a map, with or without internal bounces: per object pixel, in registers,
 *   1. the front lobes (lobes.front_lobes; the SG table, eqs. 8-9),
 *   2. the cone: the axis and its four bounding rays (eq. 12) marched to their exits
 *      (march_core.h; ``plane``: met on the axis exit's tangent plane), their screen
 *      footprint (cone.trace_cone),
 *   3. the exit lobe (exit.exit_interface, exit.exit_lobe) widened by the bounding rays
 *      refracted out at their own exits (cone.geometric_variance),
 *   4. the environment from the SG pyramid around the reflected and the exit lobe (sec.
 *      4.1) and the sphere lights' share of each lobe, the absorption, an index-matched
 *      object left invisible (shade.index_matched),
 *   5. with internal bounces (shading/bounces.follow, methods/rousiers/bounces.py): the
 *      light the first exit reflects back inside, one ray (or four, ``bounce_rays``) per
 *      pixel marched between the layers (march.march_inside) to the next interface, where
 *      the table splits it again (bounces.shade_inside), until the budget or the
 *      throughput is spent; per block, the rays still alive march together.
 * The tensor code (methods/rousiers/shade.py) is the reference and the differentiable
 * path; tests/test_fused.py holds the two together.
 *
 * Here as a header (csrc/rousiers.c holds the entry points) so that csrc/lean.c builds
 * ``lean`` and ``gsr`` on the same steps (front lobes, cone marches, exit lobe, bounces).
 */

#ifndef TORCHREFRACT_ROUSIERS_CORE_H
#define TORCHREFRACT_ROUSIERS_CORE_H

#include "bounces.h"

typedef struct {
    Frame f;
    int cone_steps, cone_refine;  /* the bounding rays' march (the axis': f.march) */
    float two_ln4;                /* 2 ln 4 as float32 (kernels.cone.ray_spread) */
    float *lobe_sigma, *footprint; /* out (B*H*W,) the passes of shade.PASSES */
    Bounces bo;                    /* internal bounces (bounces.h; limit 0: none) */
    float diffuse_var;             /* options.DIFFUSE_VAR */
    /* roughness maps (sec. 5.1; 0 levels: none in the batch): the L roughness levels of
     * each view (B, L; at least ALPHA_MIN; a uniform view's L times its roughness) and
     * their coverage over the back layer as box mips (cone.coverage_mips): per mip level
     * its (B, h, w, L) array and (h, w) */
    int levels, mips;
    const float *level_alpha;
    const float *const *cover;
    const int64_t *cover_hw;
    /* ``cone_rays: plane`` (1; 0: ``march``): the bounding rays met on the tangent plane at
     * the axis' exit, their normals the back layer's at their exits' pixels (the frame's
     * (B*H*W, 3) normals and mask, h x w a view) */
    int plane;
    const float *back_normal;
    const uint8_t *back_mask;
    int64_t h, w;
} RousJob;

enum { CONSERVE = 0, CLAMP = 1, REFLECT = 2, SPLIT = 3 };  /* exit_rule.TIR_RULES, + split */

/* The exit's rule: with internal bounces the table's own split (they follow the
 * reflected part), else the scene's ``tir`` rule. */
static inline int exit_mode(const RousJob *rj) {
    return rj->bo.limit > 0 ? SPLIT : rj->f.tir_mode;
}

/* ... the view's interfaces (frame.h's IN .. OUT0) followed by the leaving interface
 * (eta = 1 / ior) at each roughness level */
#define MAX_LEVELS 16
#define NAXES (AXES + MAX_LEVELS)


/* cone.bounding_angle: theta_b = 2 asin(x), x = sqrt(-expm1(-ln 4 / (k + 1)) / 2) (eq. 12),
 * wanted as its cosine and sine: 1 - 2 x^2 and 2 x sqrt(1 - x^2), in double from the float
 * x (no asin, sin, cos round trip). */
static inline void bounding_angle(float k, float *cb, float *sb) {
    float one_minus = -expm1f(-(float)log(4.0) / (k + 1.0f));
    double x = (double)sqrtf(0.5f * one_minus);
    *cb = (float)(1.0 - 2.0 * x * x);
    *sb = (float)(2.0 * x * sqrt((1.0 - x) * (1.0 + x)));
}

/* The exit lobe (exit.exit_lobe, ``spread: rays``): direction, sharpness, weight. */
/* The exit interface of a pixel (exit.ExitInterface): the front lobe arriving (axis p_t1,
 * sharpness k_t1, variance var1), the exact exit normal inward n_in, view2 = -p_t1, cos2,
 * the critical cosine, TIR, the bounding rays' variance var_geo (cone.geometric_variance),
 * the exit point p2, and whether the axis found its exit. */
typedef struct {
    const float *p_t1;
    float view2[3], n_in[3], p2[3];
    float k_t1, var1, cos2, cos_crit, var_geo;
    int tir, found;
    /* with bounces and a uniform roughness: the table's split at this exit, averaged over
     * the lobe (spread_table_energies at cos2, var1 on the leaving interface split_at,
     * kept for exit_lobe and first_reflection, which both ask for it); NULL: not kept */
    const SgAxes *split_at;
    float split_t, split_r;
} ExitGeo;

/* ``tir: clamp`` and ``conserve``'s incident cosine at the exit: clamped to just above
 * the critical one under TIR. */
static inline float clamped_cos(const ExitGeo *e) {
    return e->tir ? e->cos_crit + 1e-4f : e->cos2;
}

/* exit_lobe under ``tir: clamp`` or ``conserve``: the transmitted lobe at table coordinate
 * z_in (of clamped_cos) and its weight: clamp's, or conserve's energies averaged over the
 * entry lobe at the spread's table coordinates zs (of spread_cosines at cos2, var1) with
 * the escape fraction. */
static void clamped_lobe(const RousJob *rj, const SgAxes *ax, int64_t b, float alpha,
                         int mode, const ExitGeo *e, float z_in, const float *zs,
                         float *p_out, float *k_t2, float *weight) {
    const Frame *j = &rj->f;
    int64_t dist = j->dist[b];
    float t_t2, e_t2;
    sg_lobe_at(&j->table, ax + OUT, ax + OUT0, dist, 0, z_in, k_t2, &t_t2, &e_t2);
    lobe_axis(e->view2, e->n_in, t_t2, -1.0f, p_out);
    if (mode == CLAMP) {
        *weight = e->tir ? 1.0f : e_t2;
        return;
    }
    float esc = escape(j, b, alpha), et, er;
    table_energies_spread(&j->table, ax + OUT, ax + OUT0, dist, zs, &et, &er);
    float w = et + er * esc;
    *weight = w > 1.0f ? 1.0f : w;
}

/* exit_lobe's end: the unit axis, the sharpness widened by the geometric spread, the
 * weight. */
static inline void lobe_out(const ExitGeo *e, float k_t2, float weight, float *p_out,
                            float *k_out, float *w_out) {
    normalize3(p_out);
    float v = 1.0f / k_t2 + e->var_geo;
    *k_out = 1.0f / (v > 1e-12f ? v : 1e-12f);
    *w_out = weight;
}

static void exit_lobe(const RousJob *rj, const SgAxes *ax, int64_t b, float alpha, int mode,
                      const ExitGeo *e, float *p_out, float *k_out, float *w_out) {
    const Frame *j = &rj->f;
    int64_t dist = j->dist[b];
    const float *view2 = e->view2, *n_in = e->n_in;
    float cos2 = e->cos2, var1 = e->var1;
    int tir = e->tir;
    const SgAxes *out = ax + OUT, *out0 = ax + OUT0;
    float k_t2, t_t2, e_t2, weight;
    if (mode == SPLIT) {  /* bounces follow: the table's own split, averaged over the lobe */
        float er;
        sg_lobe(&j->table, out, out0, dist, 0, cos2, &k_t2, &t_t2, &e_t2);
        lobe_axis(view2, n_in, t_t2, -1.0f, p_out);
        if (e->split_at == out) weight = e->split_t;
        else spread_table_energies(&j->table, out, out0, dist, cos2, var1, &weight, &er);
    } else if (mode == REFLECT) {  /* the internal reflection lobe under TIR */
        float k_ti, t_ti, e_ti, z2 = sg_theta(cos2);
        sg_lobe_at(&j->table, out, out0, dist, 0, z2, &k_t2, &t_t2, &e_t2);
        sg_lobe_at(&j->table, out, out0, dist, 1, z2, &k_ti, &t_ti, &e_ti);
        if (tir) {
            lobe_axis(view2, n_in, t_ti, 1.0f, p_out);
            k_t2 = k_ti;
            weight = e_ti;
        } else {
            lobe_axis(view2, n_in, t_t2, -1.0f, p_out);
            weight = e_t2;
        }
    } else {  /* clamp, conserve */
        float cs[3], zs[3];
        if (mode == CONSERVE) {
            spread_cosines(cos2, var1, cs);
            sg_theta_n(cs, 3, zs);
        }
        clamped_lobe(rj, ax, b, alpha, mode, e, sg_theta(clamped_cos(e)), zs, p_out, &k_t2,
                     &weight);
    }
    lobe_out(e, k_t2, weight, p_out, k_out, w_out);
}

/* kernels.cone.ray_spread: the bounding rays refracted out at their exit normals, their
 * squared chords to the central ray's (refracted at exact_n); ``fallback`` where none
 * found its exit. */
static float ray_spread(const RousJob *rj, const float *p_t1, const float *exact_n,
                        const float (*dirs)[3], const float (*n4)[3], const uint8_t *ok4,
                        float ior, float fallback) {
    float n[3], t_c[3], sum = 0.0f;
    float m[3] = {-exact_n[0], -exact_n[1], -exact_n[2]};
    face_forward(m, p_t1, n);
    refract(p_t1, n, ior, t_c);
    int cnt = 0;
    float nk[4][3], t_k[4][3];
    for (int k = 0; k < 4; k++) {
        float mk[3] = {-n4[k][0], -n4[k][1], -n4[k][2]};
        face_forward(mk, dirs[k], nk[k]);
    }
    refract_x4(dirs, (const float (*)[3])nk, ior, t_k);
    for (int k = 0; k < 4; k++) {
        float dk[3];
        for (int c = 0; c < 3; c++) dk[c] = t_k[k][c] - t_c[c];
        float chord2 = dot3(dk, dk);
        sum = k == 0 ? (ok4[k] ? chord2 : 0.0f) : sum + (ok4[k] ? chord2 : 0.0f);
        cnt += ok4[k] != 0;
    }
    return cnt > 0 ? (sum / (float)cnt) / rj->two_ln4 : fallback;
}

/* What the steps of one block of pixels hand on: the axis' and the bounding rays' marches,
 * the front lobes, and the internal reflections. */
typedef struct {
    Rays axis, cone[4];
    float view[3 * BLOCK], dirs[BLOCK][4][3], k_t1[BLOCK];
    float e_t1[BLOCK], e_r[BLOCK], k_r[BLOCK], axis_r[3 * BLOCK];
    float front[BLOCK][3];  /* with bounces: e_r times the reflected lobe's light */
    uint8_t hidden[BLOCK];  /* a light in front of the pixel */
    float alpha[BLOCK];     /* the front roughness (the map at the front hit's UV) */
    const SgAxes *ax[BLOCK];         /* its table axes: the view's, or own */
    SgAxes own[BLOCK][AXES];
    Paths paths;
    /* rousiers' exits, prepared for the whole block before any pixel's lookups are read
     * (prepare_exit, block_taps: the reflections' taps before the marches, the exit
     * lobes' after), so that the lookups' texels come in while other work is done */
    ExitGeo ex[BLOCK];
    float c_xy[BLOCK][2], minor[BLOCK], major[BLOCK];
    float lobe_p[BLOCK][3], lobe_k[BLOCK], lobe_w[BLOCK];  /* the exit lobe (levels 0) */
    SgTap tap_r[BLOCK], tap_t[BLOCK];  /* the reflected and the exit lobe's lookups */
    int64_t plane_px[BLOCK][4];        /* ``cone_rays: plane``: the bounding exits' pixels */
} Block;

/* Step 1 for pixel i (lobes.front_lobes, cone.trace_cone): the front lobes (eqs. 8-9), the
 * axis p_t1 and the four bounding rays at theta_b around it (eq. 12), set to march. */
static void front_and_cone(const Frame *j, const SgAxes *ax, Block *k, int i, int64_t px,
                           int64_t b) {
    int64_t dist = j->dist[b];
    float d[3], p1[3], n1[3], *vi = k->view + 3 * i;
    for (int c = 0; c < 3; c++) {
        d[c] = j->ray_dir[3 * px + c];
        p1[c] = j->front_pos[3 * px + c];
        vi[c] = -d[c];
    }
    face_forward(j->front_normal + 3 * px, d, n1);
    float cos1 = clampf(dot3(vi, n1), 0.0f, 1.0f);
    float t_r, t_t1, p_t1[3], z1 = sg_theta(cos1);  /* both lobes' table coordinate */
    sg_lobe_at(&j->table, ax + IN, ax + IN0, dist, 1, z1, &k->k_r[i], &t_r, &k->e_r[i]);
    lobe_axis(vi, n1, t_r, 1.0f, k->axis_r + 3 * i);
    sg_lobe_at(&j->table, ax + IN, ax + IN0, dist, 0, z1, &k->k_t1[i], &t_t1, &k->e_t1[i]);
    lobe_axis(vi, n1, t_t1, -1.0f, p_t1);
    normalize3(p_t1);
    float c_p1[3], c_t1[3], u[3], v[3], c_u[3], c_v[3];
    camera_coords(j, b, p1, 1, c_p1);
    camera_coords(j, b, p_t1, 0, c_t1);
    set_ray(j, &k->axis, i, b, p1, p_t1, c_p1, c_t1);
    float cb, sb;
    bounding_angle(k->k_t1[i], &cb, &sb);
    tangent_frame(p_t1, u, v);
    camera_coords(j, b, u, 0, c_u);
    camera_coords(j, b, v, 0, c_v);
    for (int q = 0; q < 4; q++) {  /* (u, +), (u, -), (v, +), (v, -) */
        const float *a = q < 2 ? u : v, *ca = q < 2 ? c_u : c_v;
        float s = (q & 1) ? -1.0f : 1.0f, dq[3], cq[3];
        for (int c = 0; c < 3; c++) {
            dq[c] = cb * p_t1[c] + sb * s * a[c];
            cq[c] = cb * c_t1[c] + sb * s * ca[c];
            k->dirs[i][q][c] = dq[c];
        }
        set_ray(j, &k->cone[q], i, b, p1, dq, c_p1, cq);
    }
}

/* cone._on_tangent_plane (``cone_rays: plane``) for a block's m marched axes: the four
 * bounding rays from p1 met on the tangent plane at the axis' exit (its normal, or p_t1
 * where no exit was found), found where they run towards it and the axis found its exit;
 * the back layer's pixel of each exit (the axis exit's where one was not found), whose
 * normal bounding_normals reads, asked for now. */
static void on_tangent_plane(const RousJob *rj, Block *k, int m) {
    for (int i = 0; i < m; i++) {
        int found = k->axis.found[i];
        int64_t b = k->axis.batch[i];
        const float *p1 = k->axis.p + 3 * i, *pos = k->axis.pos + 3 * i;
        const float *pn = found ? k->axis.normal + 3 * i : k->axis.t + 3 * i;
        const float *pp = rj->f.proj + 16 * b;
        float rel[3] = {pos[0] - p1[0], pos[1] - p1[1], pos[2] - p1[2]};
        float num = dot3(rel, pn), xy_c[2], xy[2];
        project1(pos, pp, xy_c);
        for (int q = 0; q < 4; q++) {
            const float *dq = k->dirs[i][q];
            float den = dot3(dq, pn), s = num / (den > 1e-6f ? den : 1e-6f);
            float *qp = k->cone[q].pos + 3 * i;
            for (int c = 0; c < 3; c++) qp[c] = p1[c] + s * dq[c];
            int ok = den > 1e-6f && found;
            k->cone[q].found[i] = ok;
            if (ok) project1(qp, pp, xy);
            else { xy[0] = xy_c[0]; xy[1] = xy_c[1]; }
            /* floor, clamped to the frame (NaN: the first row / column) */
            float fx = clampf(floorf(xy[0]), 0.0f, (float)(rj->w - 1));
            float fy = clampf(floorf(xy[1]), 0.0f, (float)(rj->h - 1));
            int64_t flat = (b * rj->h + (fy == fy ? (int64_t)fy : 0)) * rj->w +
                           (fx == fx ? (int64_t)fx : 0);
            k->plane_px[i][q] = flat;
            __builtin_prefetch(rj->back_normal + 3 * flat);
            __builtin_prefetch(rj->back_mask + flat);
        }
    }
}

/* cone.bounding_normals for pixel i: the bounding rays' exit normals n4 and which were
 * found, ok4: their marches' (``cone_rays: march``), or for ``plane`` the back layer's at
 * the pixels on_tangent_plane found. */
static void bounding_normals(const RousJob *rj, const Block *k, int i, float n4[4][3],
                             uint8_t ok4[4]) {
    for (int q = 0; q < 4; q++) {
        int64_t flat = rj->plane ? k->plane_px[i][q] : 0;
        const float *n = rj->plane ? rj->back_normal + 3 * flat : k->cone[q].normal + 3 * i;
        ok4[q] = k->cone[q].found[i] && (!rj->plane || rj->back_mask[flat]);
        for (int c = 0; c < 3; c++) n4[q][c] = n[c];
    }
}

/* The footprint's larger extent in pixels (cone.trace_cone, kernels.cone.footprint): the
 * screen bounding box of the four exits (the axis' exit where one is not found); ``c``
 * the axis exit's pixel coordinates, ``minor`` the smaller extent (both at least 1). */
static float footprint_major(const Frame *j, const Block *k, int i, int64_t b, float *c,
                             float *minor) {
    const float *pp = j->proj + 16 * b;
    float xy[4][2], ext[2];
    project1(k->axis.pos + 3 * i, pp, c);
    for (int q = 0; q < 4; q++) {
        if (k->cone[q].found[i]) project1(k->cone[q].pos + 3 * i, pp, xy[q]);
        else { xy[q][0] = c[0]; xy[q][1] = c[1]; }
    }
    for (int a = 0; a < 2; a++) {
        float mx = xy[0][a], mn = xy[0][a];
        for (int q = 1; q < 4; q++) { mx = tmax(mx, xy[q][a]); mn = tmin(mn, xy[q][a]); }
        ext[a] = mx - mn;
        if (ext[a] < 1.0f) ext[a] = 1.0f;  /* clamp(min=1), NaN kept */
    }
    *minor = tmin(ext[0], ext[1]);
    return tmax(ext[0], ext[1]);
}

/* ndf.sample_box_mips of the coverage mips at pixel (x, y) and fractional level ``lv``
 * (trilinear: grid_sample's bilinear, zeros padding, align_corners=False, on the two mip
 * levels around it), normalized (cone.footprint_coverage): the L coverage ratios. */
static void coverage(const RousJob *rj, int64_t b, float x, float y, float lv, float *c) {
    int n = rj->mips, nl = rj->levels;
    lv = clampf(lv, 0.0f, (float)(n - 1));
    int l0 = (int)floorf(lv), l1 = l0 + 1 < n ? l0 + 1 : n - 1;
    float frac = lv - (float)l0, sum = 0.0f;
    for (int q = 0; q < nl; q++) c[q] = 0.0f;
    for (int lvl = l0; lvl <= l1; lvl++) {
        float w = (l0 == lvl ? 1.0f - frac : 0.0f) + (l1 == lvl ? frac : 0.0f);
        if (!(w > 0.0f)) continue;
        int64_t h = rj->cover_hw[2 * lvl], wd = rj->cover_hw[2 * lvl + 1];
        float scale = (float)(1 << lvl);
        float gx = (x / scale) / (float)wd * 2.0f - 1.0f, gy = (y / scale) / (float)h * 2.0f - 1.0f;
        float ix = ((gx + 1.0f) * (float)wd - 1.0f) / 2.0f;
        float iy = ((gy + 1.0f) * (float)h - 1.0f) / 2.0f;
        float fx0 = floorf(ix), fy0 = floorf(iy);
        int64_t x0 = (int64_t)fx0, y0 = (int64_t)fy0, xs[2] = {x0, x0 + 1}, ys[2] = {y0, y0 + 1};
        float tw[4] = {(fx0 + 1.0f - ix) * (fy0 + 1.0f - iy), (ix - fx0) * (fy0 + 1.0f - iy),
                       (fx0 + 1.0f - ix) * (iy - fy0), (ix - fx0) * (iy - fy0)};
        const float *img = rj->cover[lvl] + b * h * wd * nl;
        for (int q = 0; q < nl; q++) {
            float v = 0.0f;
            for (int t = 0; t < 4; t++) {  /* nw, ne, sw, se; zero outside */
                int64_t xx = xs[t & 1], yy = ys[t >> 1];
                float val = (xx >= 0 && xx < wd && yy >= 0 && yy < h)
                                ? img[(yy * wd + xx) * nl + q] : 0.0f;
                v = t == 0 ? val * tw[0] : v + val * tw[t];
            }
            c[q] = c[q] + w * v;
        }
    }
    for (int q = 0; q < nl; q++) sum = q == 0 ? c[0] : sum + c[q];
    for (int q = 0; q < nl; q++) c[q] = c[q] / (sum > 1e-12f ? sum : 1e-12f);
}

/* torch.lerp (its two branches). */
static inline float lerpf(float a, float b, float w) {
    return w < 0.5f ? a + w * (b - a) : b - (b - a) * (1.0f - w);
}

/* The first exit's internal reflection (rousiers.bounces.follow_bounces): the table's
 * reflected lobe (E_ri averaged over the arriving lobe, k_ri) along the mirror direction of
 * p_t1 about the exit normal; with ``bounce_rays: 4`` split into four rays around it
 * (bounces.split_lobe: tilted by +-sqrt(var) along two tangents, each with half the
 * variance and a quarter of the throughput); ``ax``: the table axes at the exit point's
 * roughness. ``acc`` starts with w1 l_trans, the light
 * the exit lets out. ``reflects``: the exit was found and the object is not index-matched
 * (elsewhere nothing is reflected). ``gsr`` (csrc/lean.c) blends the reflected energy
 * towards its lobes' ``sectors`` by ``apart`` (follow_bounces' ``reflected``; 0: none). */
static void first_reflection(const RousJob *rj, const SgAxes *ax, Paths *ps, int i, int64_t b,
                             int reflects, const float *p_t1, const float *n_in, float cos2,
                             float var1, const float *p2, const float *w1,
                             const float *l_trans, float apart, float sectors,
                             const SgAxes *split_at, float split_r) {
    const Frame *j = &rj->f;
    int64_t dist = j->dist[b];
    for (int c = 0; c < 3; c++) ps->acc[i][c] = w1[c] * l_trans[c];
    ps->bounces[i] = 0.0f;
    ps->residual[i] = 0.0f;
    float k_ri = 0.0f, t_ri, e_ri = 0.0f, e_ti, w_next[3];
    if (reflects) {
        float e_unused;
        sg_lobe(&j->table, ax + OUT, ax + OUT0, dist, 1, cos2, &k_ri, &t_ri, &e_unused);
        if (split_at == ax + OUT) e_ri = split_r;  /* the exit's, kept (ExitGeo) */
        else spread_table_energies(&j->table, ax + OUT, ax + OUT0, dist, cos2, var1, &e_ti, &e_ri);
        if (apart > 0.0f) e_ri = lerpf(e_ri, sectors, apart);
    }
    if (!goes_on(&rj->bo, ps, i, reflects, 0, w1, e_ri, w_next)) return;
    float d[3], var = var1 + 1.0f / (k_ri > 1e-12f ? k_ri : 1e-12f);
    reflect(p_t1, n_in, d);
    normalize3(d);
    if (rj->bo.rays == 1) {
        add_ray(ps, i, p2, d, w_next, var, 1.0f);
        return;
    }
    float u[3], v[3], s = sqrtf(var > 0.0f ? var : 0.0f), wq[3];
    tangent_frame(d, u, v);
    for (int c = 0; c < 3; c++) wq[c] = w_next[c] * 0.25f;
    for (int q = 0; q < 4; q++) {  /* offsets (1, 0), (-1, 0), (0, 1), (0, -1) */
        float o0 = q == 0 ? 1.0f : (q == 1 ? -1.0f : 0.0f);
        float o1 = q == 2 ? 1.0f : (q == 3 ? -1.0f : 0.0f), dq[3];
        for (int c = 0; c < 3; c++) dq[c] = d[c] + s * (o0 * u[c] + o1 * v[c]);
        normalize3(dq);
        add_ray(ps, i, p2, dq, wq, 0.5f * var, 0.25f);
    }
}

/* The lobe the light leaves by: exit.exit_lobe at roughness ``alpha``, axes ``ax`` (its
 * direction p, sharpness k and weight); where the exit is not found, the front lobe's. */
static inline void lost_exit(const ExitGeo *e, float *p, float *k, float *wt) {
    if (!e->found) {  /* leave with the front lobe */
        for (int c = 0; c < 3; c++) p[c] = e->p_t1[c];
        *k = e->k_t1;
        *wt = 1.0f;
    }
}

static void leaving_lobe(const RousJob *rj, const SgAxes *ax, int64_t b, float alpha,
                         int mode, const ExitGeo *e, float *p, float *k, float *wt) {
    exit_lobe(rj, ax, b, alpha, mode, e, p, k, wt);
    lost_exit(e, p, k, wt);
}

/* The light of one exit lobe (leaving_lobe): its sharpness k and weight, and the
 * environment and lights around it, seen from the exit point. */
static void exit_light(const RousJob *rj, const SgAxes *ax, int64_t b, float alpha, int mode,
                       const ExitGeo *e, float *k, float *wt, float *l) {
    const Frame *j = &rj->f;
    float p[3];
    leaving_lobe(rj, ax, b, alpha, mode, e, p, k, wt);
    incident_sg(&j->lights, &j->env, b, e->p2, p, *k, l);
}

/* Step 5's transmitted part (exit.transmitted_radiance): the light leaving through the
 * exit lobe, or with a roughness map one lobe per level by its coverage over the footprint
 * (sec. 5.1; nothing covered: the front roughness); returns the lobe's sharpness (the
 * coverage-weighted one with a map). */
static float transmitted(const RousJob *rj, const SgAxes *view_axes, const SgAxes *ax,
                         int64_t b, float alpha, int mode, const ExitGeo *e,
                         const float *c_xy, float minor, float *l_trans) {
    float kk, wt;
    if (rj->levels == 0) {
        exit_light(rj, ax, b, alpha, mode, e, &kk, &wt, l_trans);
        for (int c = 0; c < 3; c++) l_trans[c] = l_trans[c] * wt;
        return kk;
    }
    float cov[MAX_LEVELS], ksum = 0.0f, csum = 0.0f;
    coverage(rj, b, c_xy[0], c_xy[1], log2f(minor), cov);
    for (int q = 0; q < rj->levels; q++) csum = q == 0 ? cov[0] : csum + cov[q];
    int no_cov = csum < 0.5f;
    for (int c = 0; c < 3; c++) l_trans[c] = 0.0f;
    for (int q = 0; q < rj->levels; q++) {
        SgAxes lv[AXES];
        const SgAxes *la = ax;
        float a_q = alpha, w_q = 1.0f / (float)rj->levels, k_q, l_q[3];
        if (!no_cov) {
            a_q = rj->level_alpha[b * rj->levels + q];
            w_q = cov[q];
            lv[OUT] = view_axes[AXES + q];
            lv[OUT0] = view_axes[OUT0];
            la = lv;
        }
        exit_light(rj, la, b, a_q, mode, e, &k_q, &wt, l_q);
        float ww = w_q * wt;
        for (int c = 0; c < 3; c++) l_trans[c] = l_trans[c] + ww * l_q[c];
        ksum = ksum + w_q / (k_q > 1e-12f ? k_q : 1e-12f);
    }
    return 1.0f / (ksum > 1e-12f ? ksum : 1e-12f);
}

/* rousiers.shade.finish for pixel i, given the light of its front reflection ``l_refl``
 * and of its exit lobe(s) ``l_trans`` and its exit interface ``e``: an index-matched object
 * left invisible (shade.index_matched), a light in front hiding it (shade.composite), the
 * absorption along the axis' path inside; without bounces the pixel's radiance, with them
 * the first exit's reflection handed on (first_reflection; ``apart``, ``sectors``: gsr's
 * blend, 0 elsewhere). Shared by rousiers' and lean.c's pixels. */
static void finish_pixel(const RousJob *rj, const SgAxes *view_axes, Block *k, int i,
                         int64_t px, int64_t b, const ExitGeo *e, const float *l_refl,
                         float *l_trans, float apart, float sectors) {
    const Frame *j = &rj->f;
    float ior = j->ior[b];
    int found = k->axis.found[i], bounce = rj->bo.limit > 0;
    float er = k->e_r[i], et = k->e_t1[i];
    const float *p1 = k->axis.p + 3 * i, *v = k->view + 3 * i;
    float d[3] = {-v[0], -v[1], -v[2]};
    if (ior == 1.0f) {  /* index-matched: no interface (shade.index_matched) */
        incident_sg(&j->lights, &j->env, b, p1, d, INFINITY, l_trans);
        er = 0.0f;
        et = 1.0f;
    }
    float thick = j->back_dist[px] - j->front_dist[px];
    float path = found ? k->axis.s[i] : (thick > 0.0f ? thick : 0.0f);
    int64_t l;  /* a light between the eye and the object hides it (shade.composite) */
    int hidden = j->lights.nl > 0 &&
                 hit_light(&j->lights, b, j->eye + 3 * b, d, &l) < j->front_dist[px];
    float w1[3];
    for (int c = 0; c < 3; c++) {
        w1[c] = et * transmittance(j->absorption[3 * b + c], path);
        if (!bounce && !hidden) j->radiance[3 * px + c] = er * l_refl[c] + w1[c] * l_trans[c];
    }
    if (bounce) {  /* the pixel is written once its bounces are followed (cone_block) */
        k->hidden[i] = (uint8_t)hidden;
        for (int c = 0; c < 3; c++) k->front[i][c] = er * l_refl[c];
        /* the exit's internal reflection lobe uses the roughness at the exit point */
        float a_x = k->alpha[i];
        if (found) {
            a_x = roughness_on(j, b, k->axis.bary + 3 * i, k->axis.tri[i]);
            a_x = a_x > 1e-4f ? a_x : 1e-4f;
        }
        SgAxes own_x[AXES];
        first_reflection(rj, axes_at(j, view_axes, b, a_x, own_x), &k->paths, i, b,
                         found && ior != 1.0f, k->axis.t + 3 * i, e->n_in, e->cos2, e->var1,
                         e->p2, w1, l_trans, apart, sectors, e->split_at, e->split_r);
    }
}

/* Steps 3-4 for pixel i (exit.exit_interface, cone.trace_cone's footprint): the exit
 * interface at the exact exit normal, the footprint (without roughness levels
 * block_leaving_lobes then finds the block's exit lobes, and cone_block taps their
 * lookups). */
static void prepare_exit(const RousJob *rj, Block *k, int i, int64_t b) {
    const Frame *j = &rj->f;
    const SgAxes *ax = k->ax[i];
    float ior = j->ior[b];
    const float *p_t1 = k->axis.t + 3 * i;
    int found = k->axis.found[i];
    float exact_n[3], n4[4][3], k_t1 = k->k_t1[i];
    uint8_t ok4[4];
    for (int c = 0; c < 3; c++) exact_n[c] = found ? k->axis.normal[3 * i + c] : p_t1[c];
    bounding_normals(rj, k, i, n4, ok4);
    /* the exit interface: the exact exit normal, inward */
    ExitGeo *e = k->ex + i;
    *e = (ExitGeo){.p_t1 = p_t1, .k_t1 = k_t1, .found = found};
    float m_n[3] = {-exact_n[0], -exact_n[1], -exact_n[2]};
    face_forward(m_n, p_t1, e->n_in);
    for (int c = 0; c < 3; c++) e->view2[c] = -p_t1[c];
    e->cos2 = clampf(dot3(e->view2, e->n_in), 0.0f, 1.0f);
    float cc = 1.0f - 1.0f / (ior * ior);
    e->cos_crit = sqrtf(cc > 0.0f ? cc : 0.0f);
    e->tir = e->cos2 < e->cos_crit && found;
    float sin2 = 1.0f - e->cos2 * e->cos2;
    float co = 1.0f - ior * ior * (sin2 > 0.0f ? sin2 : 0.0f);
    float mg = ior * e->cos2 / sqrtf(co > 1e-4f ? co : 1e-4f), mag2 = mg * mg;
    e->var1 = 1.0f / (k_t1 > 1e-12f ? k_t1 : 1e-12f);
    e->var_geo = ray_spread(rj, p_t1, exact_n, (const float (*)[3])k->dirs[i],
                            (const float (*)[3])n4, ok4, ior, mag2 / k_t1);
    const float *p1 = k->axis.p + 3 * i;
    for (int c = 0; c < 3; c++) e->p2[c] = found ? k->axis.pos[3 * i + c] : p1[c];
    k->major[i] = footprint_major(j, k, i, b, k->c_xy[i], &k->minor[i]);
    if (rj->bo.limit > 0 && !j->rmap[b]) {  /* the split, asked for twice (ExitGeo) */
        e->split_at = ax + OUT;
        spread_table_energies(&j->table, ax + OUT, ax + OUT0, j->dist[b], e->cos2, e->var1,
                              &e->split_t, &e->split_r);
    }
}

/* Without roughness levels, the exit lobes of a block's m pixels after prepare_exit
 * (leaving_lobe, exit_light's lobe): under ``tir: clamp`` and ``conserve`` the table
 * coordinates of the clamped cosines and of the spreads found for the whole block at once,
 * in lanes (the same bits as pixel by pixel), so that the pixels' chains run side by side. */
static void block_leaving_lobes(const RousJob *rj, Block *k, int64_t r0, int m) {
    const Frame *j = &rj->f;
    int mode = exit_mode(rj);
    if (mode != CLAMP && mode != CONSERVE) {
        for (int i = 0; i < m; i++)
            leaving_lobe(rj, k->ax[i], j->batch[r0 + i], k->alpha[i], mode, k->ex + i,
                         k->lobe_p[i], &k->lobe_k[i], &k->lobe_w[i]);
        return;
    }
    float c_in[BLOCK], z_in[BLOCK], cs[3 * BLOCK], zs[3 * BLOCK];
    for (int i = 0; i < m; i++) {
        c_in[i] = clamped_cos(k->ex + i);
        if (mode == CONSERVE) spread_cosines(k->ex[i].cos2, k->ex[i].var1, cs + 3 * i);
    }
    sg_theta_n(c_in, m, z_in);
    if (mode == CONSERVE) sg_theta_n(cs, 3 * m, zs);
    for (int i = 0; i < m; i++) {
        const ExitGeo *e = k->ex + i;
        float k_t2, w;
        clamped_lobe(rj, k->ax[i], j->batch[r0 + i], k->alpha[i], mode, e, z_in[i], zs + 3 * i,
                     k->lobe_p[i], &k_t2, &w);
        lobe_out(e, k_t2, w, k->lobe_p[i], &k->lobe_k[i], &k->lobe_w[i]);
        lost_exit(e, k->lobe_p[i], &k->lobe_k[i], &k->lobe_w[i]);
    }
}

/* Step 5 for pixel i (prepare_exit first; exit.exit_lobe, shade.render_rousiers): the
 * front reflection's and the exit lobe's light, the absorption, the pixel (finish_pixel)
 * and its passes. */
static void shade_pixel(const RousJob *rj, const SgAxes *view_axes, Block *k, int i,
                        int64_t px, int64_t b) {
    const Frame *j = &rj->f;
    const ExitGeo *e = k->ex + i;
    int found = k->axis.found[i];
    float l_refl[3], l_trans[3], kk;
    const float *p1 = k->axis.p + 3 * i;
    incident_sg_at(&j->lights, b, p1, k->axis_r + 3 * i, k->k_r[i], k->tap_r + i, l_refl);
    if (rj->levels == 0) {  /* transmitted()'s one lobe, from its prepared tap */
        incident_sg_at(&j->lights, b, e->p2, k->lobe_p[i], k->lobe_k[i], k->tap_t + i,
                       l_trans);
        for (int c = 0; c < 3; c++) l_trans[c] = l_trans[c] * k->lobe_w[i];
        kk = k->lobe_k[i];
    } else {
        int mode = exit_mode(rj);
        kk = transmitted(rj, view_axes, k->ax[i], b, k->alpha[i], mode, e, k->c_xy[i],
                         k->minor[i], l_trans);
    }
    finish_pixel(rj, view_axes, k, i, px, b, e, l_refl, l_trans, 0.0f, 0.0f);
    j->exit_found[px] = found ? 1.0f : 0.0f;
    j->tir[px] = e->tir ? 1.0f : 0.0f;
    rj->lobe_sigma[px] = 1.0f / sqrtf(kk > 1e-12f ? kk : 1e-12f);
    rj->footprint[px] = found ? k->major[i] : 0.0f;
}

/* Ray r's arrival at an interface from inside: the view direction, the view-facing
 * normal, the incident cosine (returned), the critical one, TIR, and the cosine its
 * transmitted lobe is read at (held just above the critical one under TIR where the rule
 * lets the light out there). */
static float inside_cosines(const Frame *j, const Paths *ps, int r, int64_t b, int last,
                            float *view, float *n_view, float *cos_crit, int *tir,
                            float *cos_t) {
    int mode = j->tir_mode;
    float ior = j->ior[b];
    const float *t = ps->t[r];
    float cc = 1.0f - 1.0f / (ior * ior);
    *cos_crit = sqrtf(cc > 0.0f ? cc : 0.0f);
    for (int c = 0; c < 3; c++) view[c] = -t[c];
    face_forward(ps->normal[r], t, n_view);
    float cos = clampf(dot3(view, n_view), 0.0f, 1.0f);
    *tir = cos < *cos_crit;
    *cos_t = ((last && mode == CLAMP) || mode == CONSERVE) && *tir ? *cos_crit + 1e-4f : cos;
    return cos;
}

/* shade_inside's table coordinates for the wave's n rays (tr_coords_fn): of cos_t, of
 * cos, and of the spread's three cosines around cos (spread_cosines), for all rays at
 * once in lanes (sg_theta_n: the same bits as sg_theta ray by ray). */
static void inside_coords(const void *job, Paths *ps, int64_t r0, int n, int last) {
    const Frame *j = &((const RousJob *)job)->f;
    float c[5 * RAYS], z[5 * RAYS];
    for (int r = 0; r < n; r++) {
        float view[3], n_view[3], cos_crit, cos_t;
        int tir;
        float cos = inside_cosines(j, ps, r, j->batch[r0 + ps->pix[r]], last, view, n_view,
                                   &cos_crit, &tir, &cos_t);
        c[5 * r] = cos_t;
        c[5 * r + 1] = cos;
        spread_cosines(cos, ps->var[r], c + 5 * r + 2);
    }
    sg_theta_n(c, 5 * n, z);
    for (int r = 0; r < n; r++)
        for (int q = 0; q < 5; q++) ps->coord[r][q] = z[5 * r + q];
}

/* A rough interface met from inside at a later bounce (rousiers.bounces.shade_inside,
 * _split, _leaving): the table's transmitted lobe leaves (widened by the lobe carried,
 * magnified by the refraction, at most 2x), its reflected lobe goes on along the mirror
 * direction; the ``tir`` rule at the budget's last interface, ``conserve``'s diffuse part
 * (DIFFUSE_VAR) at every other. A ray the march lost leaves along its own direction with
 * the escape fraction. Adds the light leaving to ``acc``; returns the reflectance, the
 * direction and variance of the reflected lobe. */
static float shade_inside(const void *job, const SgAxes *view_axes, Paths *ps, int r,
                          int64_t b, int last, float *dir, float *var_out) {
    const RousJob *rj = (const RousJob *)job;
    const Frame *j = &rj->f;
    float alpha = ps->alpha[r] > 1e-4f ? ps->alpha[r] : 1e-4f;  /* microfacet.ALPHA_MIN */
    SgAxes own[AXES];
    const SgAxes *ax = axes_at(j, view_axes, b, alpha, own);
    const SgAxes *out = ax + OUT, *out0 = ax + OUT0;
    int64_t dist = j->dist[b];
    int mode = j->tir_mode, tir;
    float ior = j->ior[b], var = ps->var[r], *t = ps->t[r], cos_crit, cos_t;
    float n_view[3], view[3];
    inside_cosines(j, ps, r, b, last, view, n_view, &cos_crit, &tir, &cos_t);
    const float *z = ps->coord[r];  /* of cos_t, cos, the spread's (inside_coords) */
    float k_t, t_t, e_t, k_r = INFINITY, t_r = 0.0f, e_r = 0.0f;
    sg_lobe_at(&j->table, out, out0, dist, 0, z[0], &k_t, &t_t, &e_t);
    if (!(last && mode == CONSERVE))
        sg_lobe_at(&j->table, out, out0, dist, 1, z[1], &k_r, &t_r, &e_r);
    if (!last || mode == CONSERVE)  /* the split averaged over the lobe carried */
        table_energies_spread(&j->table, out, out0, dist, z + 2, &e_t, &e_r);
    float p_t[3], k_out, w_out = e_t, refl = e_r, inv_kr = 1.0f / (k_r > 1e-12f ? k_r : 1e-12f);
    lobe_axis(view, n_view, t_t, -1.0f, p_t);
    normalize3(p_t);
    float sin2 = 1.0f - cos_t * cos_t;
    float co = 1.0f - ior * ior * (sin2 > 0.0f ? sin2 : 0.0f);
    float mg = ior * cos_t / sqrtf(co > 1e-4f ? co : 1e-4f), mag2 = mg * mg;
    if (mag2 > 4.0f) mag2 = 4.0f;
    k_out = 1.0f / (1.0f / (k_t > 1e-12f ? k_t : 1e-12f) + mag2 * var);
    if (mode == CONSERVE) {
        float go_on = last ? 0.0f : expf(-(var + inv_kr) / rj->diffuse_var);
        w_out = e_t + (1.0f - go_on) * e_r * escape(j, b, alpha);
        if (w_out > 1.0f) w_out = 1.0f;
        refl = go_on * e_r;
    } else if (last && mode == CLAMP) {  /* TIR light leaves at the critical angle */
        float e_true = e_t, k_u, t_u;
        if (tir) sg_lobe_at(&j->table, out, out0, dist, 0, z[1], &k_u, &t_u, &e_true);
        w_out = tir ? (e_true + e_r > 1.0f ? 1.0f : e_true + e_r) : e_true;
        refl = tir ? 0.0f : e_r;
    } else if (last) {  /* reflect: under TIR the internal reflection lobe is read */
        if (tir) {
            lobe_axis(view, n_view, t_r, 1.0f, p_t);
            normalize3(p_t);
            k_out = 1.0f / (inv_kr + var);
        }
        w_out = tir ? e_r : e_t;
        refl = tir ? 0.0f : e_r;
    }
    if (!ps->found[r]) {  /* lost: along its own direction, the escape fraction */
        for (int c = 0; c < 3; c++) p_t[c] = t[c];
        k_out = 1.0f / (var > 1e-12f ? var : 1e-12f);
        w_out = escape(j, b, alpha);
        refl = 0.0f;
    }
    for (int c = 0; c < 3; c++) ps->look_d[r][c] = p_t[c];  /* (bounces.h: looked up) */
    ps->look_k[r] = k_out;
    ps->look_w[r] = w_out;
    reflect(t, n_view, dir);
    normalize3(dir);
    *var_out = var + inv_kr;
    return refl;
}

/* A method's steps 3-5 for pixel i of a block (``rousiers``: shade_pixel; ``lean`` and
 * ``gsr``: lean.c's lean_pixel), given the job it was handed. */
typedef void (*cone_pixel_fn)(const void *job, const SgAxes *view_axes, Block *k, int i,
                              int64_t px, int64_t b);

/* What cone_block prepares before a method's pixels: the front reflections' lookups
 * (tap_r), and rousiers' exits (prepare_exit) with their lookups (tap_t). */
enum { CONE_FRONT_TAPS = 1, CONE_EXITS = 2 };

/* One block of pixels of a method on the cone (``rousiers``, ``lean``, ``gsr``): step 1
 * per pixel, step 2 (the marches, march_core.h) per ray family over the block, then what
 * ``prepare`` asks for (CONE_FRONT_TAPS, CONE_EXITS), then ``pixel`` per pixel, then the
 * bounces. */
static void cone_block(const void *job, const RousJob *rj, const SgAxes *axes, int64_t r0,
                       int m, cone_pixel_fn pixel, int prepare) {
    const Frame *j = &rj->f;
    Block k;
    for (int i = 0; i < m; i++) {  /* the front roughness (pixels.object_pixels) */
        int64_t b = j->batch[r0 + i], px = j->idx[r0 + i];
        float a = roughness_at(j, b, j->front_uv + 2 * px);
        k.alpha[i] = a > 1e-4f ? a : 1e-4f;  /* microfacet.ALPHA_MIN */
        k.ax[i] = axes_at(j, axes + NAXES * b, b, k.alpha[i], k.own[i]);
        front_and_cone(j, k.ax[i], &k, i, px, b);
    }
    if (prepare & CONE_FRONT_TAPS)  /* the front reflections' lookups, asked for before
                                     * the marches */
        block_taps(j, r0, m, k.axis_r, k.k_r, k.tap_r);
    march_rays(j, &k.axis, m, j->march.steps, j->march.refine);
    if (rj->plane) on_tangent_plane(rj, &k, m);
    else
        for (int q = 0; q < 4; q++) march_rays(j, &k.cone[q], m, rj->cone_steps, rj->cone_refine);
    k.paths.n = 0;
    if (prepare & CONE_EXITS) {  /* every exit of the block first, then its lookups */
        for (int i = 0; i < m; i++) prepare_exit(rj, &k, i, j->batch[r0 + i]);
        if (rj->levels == 0) {
            block_leaving_lobes(rj, &k, r0, m);
            block_taps(j, r0, m, &k.lobe_p[0][0], k.lobe_k, k.tap_t);
        }
    }
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        pixel(job, axes + NAXES * b, &k, i, j->idx[r0 + i], b);
    }
    if (rj->bo.limit > 0)
        finish_block(j, &rj->bo, rj, shade_inside, inside_coords, 1, axes, NAXES, &k.paths,
                     (const float (*)[3])k.front, k.hidden, r0, m);
}

static void rous_pixel(const void *job, const SgAxes *view_axes, Block *k, int i, int64_t px,
                       int64_t b) {
    shade_pixel((const RousJob *)job, view_axes, k, i, px, b);
}

static void shade_block(const void *job, const SgAxes *axes, int64_t r0, int m) {
    cone_block(job, (const RousJob *)job, axes, r0, m, rous_pixel, CONE_FRONT_TAPS | CONE_EXITS);
}

/* Each view's interfaces on the table: entering (eta = ior) and leaving (1 / ior), at its
 * roughness (at least microfacet.ALPHA_MIN) and at the table's smallest (sg_lobe's fade). */
static int rous_axes(const Frame *f, int64_t b, SgAxes *out) {
    float ior = f->ior[b];
    view_axes(f, b, out);
    const RousJob *rj = (const RousJob *)f;  /* f is the job's first member */
    for (int q = 0; q < rj->levels; q++)
        sg_axes(&f->table, 1.0f / ior, rj->level_alpha[b * rj->levels + q], out + AXES + q);
    return AXES + rj->levels;
}

#endif
