/* Fused shading of ``rousiers`` (methods/rousiers/, de Rousiers et al. 2012) without
 * internal bounces, for its default cone and spread (``cone_rays: march``, ``spread:
 * rays``), every ``tir`` rule, uniform roughness: per object pixel, in
 * registers,
 *   1. the front lobes (lobes.front_lobes; the SG table, eqs. 8-9),
 *   2. the cone: the axis and its four bounding rays (eq. 12) marched to their exits
 *      (march_core.h), their screen footprint (cone.trace_cone),
 *   3. the exit lobe (exit.exit_interface, exit.exit_lobe) widened by the bounding rays
 *      refracted out at their own exits (cone.geometric_variance),
 *   4. the environment from the SG pyramid around the reflected and the exit lobe (sec.
 *      4.1) and the sphere lights' share of each lobe, the absorption, an index-matched
 *      object left invisible (shade._index_matched).
 * The tensor code (methods/rousiers/shade.py) is the reference and the differentiable
 * path; tests/test_fused.py holds the two together.
 */

#include "frame.h"

typedef struct {
    Frame f;
    int cone_steps, cone_refine;  /* the bounding rays' march (the axis': f.march) */
    float two_ln4;                /* 2 ln 4 as float32 (kernels.cone.ray_spread) */
    float *lobe_sigma, *footprint; /* out (B*H*W,) the passes of shade.PASSES */
} RousJob;

/* Per view: the table's interfaces at (eta, alpha) and (eta, alpha_min), entering
 * (eta = ior) and leaving (eta = 1 / ior). */
enum { IN = 0, IN0 = 1, OUT = 2, OUT0 = 3, AXES = 4 };

/* cone.bounding_angle: theta_b = 2 asin(sqrt(-expm1(-ln 4 / (k + 1)) / 2)) (eq. 12). */
static inline float bounding_angle(float k) {
    float one_minus = -expm1f(-(float)log(4.0) / (k + 1.0f));
    return 2.0f * asinf(sqrtf(0.5f * one_minus));
}

/* The exit lobe (exit.exit_lobe, ``spread: rays``): direction, sharpness, weight. */
static void exit_lobe(const RousJob *rj, const SgAxes *ax, int64_t b, float alpha,
                      const float *view2, const float *n_in, float cos2, float cos_crit,
                      int tir, float var1, float var_geo, float *p_out, float *k_out,
                      float *w_out) {
    const Frame *j = &rj->f;
    int64_t dist = j->dist[b];
    const SgAxes *out = ax + OUT, *out0 = ax + OUT0;
    float k_t2, t_t2, e_t2, weight;
    if (j->tir_mode == 2) {  /* reflect: the internal reflection lobe under TIR */
        float k_ti, t_ti, e_ti;
        sg_lobe(&j->table, out, out0, dist, 0, cos2, &k_t2, &t_t2, &e_t2);
        sg_lobe(&j->table, out, out0, dist, 1, cos2, &k_ti, &t_ti, &e_ti);
        if (tir) {
            lobe_axis(view2, n_in, t_ti, 1.0f, p_out);
            k_t2 = k_ti;
            weight = e_ti;
        } else {
            lobe_axis(view2, n_in, t_t2, -1.0f, p_out);
            weight = e_t2;
        }
    } else {  /* clamp, conserve: the incident angle clamped to the critical one */
        float cos_in = tir ? cos_crit + 1e-4f : cos2;
        sg_lobe(&j->table, out, out0, dist, 0, cos_in, &k_t2, &t_t2, &e_t2);
        lobe_axis(view2, n_in, t_t2, -1.0f, p_out);
        if (j->tir_mode == 1) {
            weight = tir ? 1.0f : e_t2;
        } else {
            float esc = escape(j, b, alpha), et, er;
            spread_table_energies(&j->table, out, out0, dist, cos2, var1, &et, &er);
            weight = et + er * esc;
            if (weight > 1.0f) weight = 1.0f;
        }
    }
    normalize3(p_out);
    float v = 1.0f / k_t2 + var_geo;
    *k_out = 1.0f / (v > 1e-12f ? v : 1e-12f);
    *w_out = weight;
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
    for (int k = 0; k < 4; k++) {
        float mk[3] = {-n4[k][0], -n4[k][1], -n4[k][2]}, nk[3], t_k[3], dk[3];
        face_forward(mk, dirs[k], nk);
        refract(dirs[k], nk, ior, t_k);
        for (int c = 0; c < 3; c++) dk[c] = t_k[c] - t_c[c];
        float chord2 = dot3(dk, dk);
        sum = k == 0 ? (ok4[k] ? chord2 : 0.0f) : sum + (ok4[k] ? chord2 : 0.0f);
        cnt += ok4[k] != 0;
    }
    return cnt > 0 ? (sum / (float)cnt) / rj->two_ln4 : fallback;
}

/* What the steps of one block of pixels hand on: the axis' and the bounding rays' marches,
 * and the front lobes. */
typedef struct {
    Rays axis, cone[4];
    float view[3 * BLOCK], dirs[BLOCK][4][3], k_t1[BLOCK];
    float e_t1[BLOCK], e_r[BLOCK], k_r[BLOCK], axis_r[3 * BLOCK];
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
    float t_r, t_t1, p_t1[3];
    sg_lobe(&j->table, ax + IN, ax + IN0, dist, 1, cos1, &k->k_r[i], &t_r, &k->e_r[i]);
    lobe_axis(vi, n1, t_r, 1.0f, k->axis_r + 3 * i);
    sg_lobe(&j->table, ax + IN, ax + IN0, dist, 0, cos1, &k->k_t1[i], &t_t1, &k->e_t1[i]);
    lobe_axis(vi, n1, t_t1, -1.0f, p_t1);
    normalize3(p_t1);
    float c_p1[3], c_t1[3], u[3], v[3], c_u[3], c_v[3];
    camera_coords(j, b, p1, 1, c_p1);
    camera_coords(j, b, p_t1, 0, c_t1);
    set_ray(j, &k->axis, i, b, p1, p_t1, c_p1, c_t1);
    float th = bounding_angle(k->k_t1[i]), cb = cosf(th), sb = sinf(th);
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

/* The footprint's larger extent in pixels (cone.trace_cone, kernels.cone.footprint): the
 * screen bounding box of the four exits (the axis' exit where one is not found). */
static float footprint_major(const Frame *j, const Block *k, int i, int64_t b) {
    const float *pp = j->proj + 16 * b;
    float c[2], xy[4][2], ext[2];
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
    return tmax(ext[0], ext[1]);
}

/* Steps 3-5 for pixel i (exit.exit_interface, exit.exit_lobe, shade.render_rousiers): the
 * exit lobe widened by the bounding rays, the environment around it and around the
 * reflected lobe, the absorption; the pixel and its passes written. */
static void shade_pixel(const RousJob *rj, const SgAxes *ax, const Block *k, int i,
                        int64_t px, int64_t b) {
    const Frame *j = &rj->f;
    float ior = j->ior[b], alpha = j->alpha[b];
    alpha = alpha > 1e-4f ? alpha : 1e-4f;  /* microfacet.ALPHA_MIN (pixels.py) */
    const float *p_t1 = k->axis.t + 3 * i;
    int found = k->axis.found[i];
    float exact_n[3], n4[4][3], k_t1 = k->k_t1[i];
    uint8_t ok4[4];
    for (int c = 0; c < 3; c++) exact_n[c] = found ? k->axis.normal[3 * i + c] : p_t1[c];
    for (int q = 0; q < 4; q++) {
        ok4[q] = k->cone[q].found[i];
        for (int c = 0; c < 3; c++) n4[q][c] = k->cone[q].normal[3 * i + c];
    }
    /* the exit interface: the exact exit normal, inward */
    float m_n[3] = {-exact_n[0], -exact_n[1], -exact_n[2]}, n_in[3];
    face_forward(m_n, p_t1, n_in);
    float view2[3] = {-p_t1[0], -p_t1[1], -p_t1[2]};
    float cos2 = clampf(dot3(view2, n_in), 0.0f, 1.0f);
    float cc = 1.0f - 1.0f / (ior * ior);
    float cos_crit = sqrtf(cc > 0.0f ? cc : 0.0f);
    int tir = cos2 < cos_crit && found;
    float sin2 = 1.0f - cos2 * cos2;
    float co = 1.0f - ior * ior * (sin2 > 0.0f ? sin2 : 0.0f);
    float mg = ior * cos2 / sqrtf(co > 1e-4f ? co : 1e-4f), mag2 = mg * mg;
    float var1 = 1.0f / (k_t1 > 1e-12f ? k_t1 : 1e-12f);
    float var_geo = ray_spread(rj, p_t1, exact_n, (const float (*)[3])k->dirs[i],
                               (const float (*)[3])n4, ok4, ior, mag2 / k_t1);
    float p_out[3], kk, weight2;
    exit_lobe(rj, ax, b, alpha, view2, n_in, cos2, cos_crit, tir, var1, var_geo, p_out, &kk,
              &weight2);
    if (!found) {  /* leave with the front lobe */
        for (int c = 0; c < 3; c++) p_out[c] = p_t1[c];
        kk = k_t1;
        weight2 = 1.0f;
    }
    float thick = j->back_dist[px] - j->front_dist[px];
    float path = found ? k->axis.s[i] : (thick > 0.0f ? thick : 0.0f);
    float l_refl[3], l_trans[3], er = k->e_r[i], et = k->e_t1[i];
    const float *p1 = k->axis.p + 3 * i, *v = k->view + 3 * i;
    float d[3] = {-v[0], -v[1], -v[2]}, p2[3];
    for (int c = 0; c < 3; c++) p2[c] = found ? k->axis.pos[3 * i + c] : p1[c];
    incident_sg(&j->lights, &j->env, b, p1, k->axis_r + 3 * i, k->k_r[i], l_refl);
    if (ior == 1.0f) {  /* index-matched: no interface (shade._index_matched) */
        incident_sg(&j->lights, &j->env, b, p1, d, INFINITY, l_trans);
        er = 0.0f;
        et = 1.0f;
    } else {
        incident_sg(&j->lights, &j->env, b, p2, p_out, kk, l_trans);
        for (int c = 0; c < 3; c++) l_trans[c] = l_trans[c] * weight2;
    }
    int64_t l;  /* a light between the eye and the object hides it (shade._composite) */
    int hidden = j->lights.nl > 0 &&
                 hit_light(&j->lights, b, j->eye + 3 * b, d, &l) < j->front_dist[px];
    for (int c = 0; c < 3 && !hidden; c++) {
        float att = expf(-j->absorption[3 * b + c] * path);
        j->radiance[3 * px + c] = er * l_refl[c] + et * att * l_trans[c];
    }
    j->exit_found[px] = found ? 1.0f : 0.0f;
    j->tir[px] = tir ? 1.0f : 0.0f;
    rj->lobe_sigma[px] = 1.0f / sqrtf(kk > 1e-12f ? kk : 1e-12f);
    rj->footprint[px] = found ? footprint_major(j, k, i, b) : 0.0f;
}

/* One block of pixels: step 1 per pixel, step 2 (the marches, march_core.h) per ray
 * family over the block, steps 3-5 per pixel. */
static void shade_block(const void *job, const SgAxes *axes, int64_t r0, int m) {
    const RousJob *rj = (const RousJob *)job;
    const Frame *j = &rj->f;
    Block k;
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        front_and_cone(j, axes + AXES * b, &k, i, j->idx[r0 + i], b);
    }
    march_rays(j, &k.axis, m, j->march.steps, j->march.refine);
    for (int q = 0; q < 4; q++) march_rays(j, &k.cone[q], m, rj->cone_steps, rj->cone_refine);
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        shade_pixel(rj, axes + AXES * b, &k, i, j->idx[r0 + i], b);
    }
}

/* Each view's interfaces on the table: entering (eta = ior) and leaving (1 / ior), at its
 * roughness (at least microfacet.ALPHA_MIN) and at the table's smallest (sg_lobe's fade). */
static void rous_axes(const Frame *f, int64_t b, SgAxes *out) {
    float ior = f->ior[b], a = f->alpha[b] > 1e-4f ? f->alpha[b] : 1e-4f;
    float a0 = f->table.alpha_min;
    sg_axes(&f->table, ior, a, out + IN);
    sg_axes(&f->table, ior, a0, out + IN0);
    sg_axes(&f->table, 1.0f / ior, a, out + OUT);
    sg_axes(&f->table, 1.0f / ior, a0, out + OUT0);
}

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_rousiers(RousJob *job, int threads) {
    return run_shading(job, &job->f, AXES, rous_axes, shade_block, threads);
}

int64_t torchrefract_rousiers_job_size(void) { return (int64_t)sizeof(RousJob); }
