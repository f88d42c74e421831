/* Fused shading of ``specular`` (methods/specular.py, shading/paths.py) and
 * ``prefiltered`` (``blur``) without internal bounces, uniform roughness or a map: per
 * object pixel, in registers, the entry refraction, the march to the exit
 * (march_core.h, the march kernel's own search, candidates and walk), the exit
 * refraction, the interfaces' energies (smooth: Fresnel; rough: the SG table's, eq. 9 of
 * de Rousiers 2012, with the exit averaged over the entry lobe), the ``tir`` rule, the
 * absorption, the two environment lookups and the sphere lights.
 *
 * The tensor code (paths.trace_paths, render_specular) is the reference and the
 * differentiable path; this kernel follows it formula by formula in float32 (the table
 * lookups are trilinear as grid_sample's), and tests/test_fused.py holds the two together.
 * Rays are marched in blocks of 16 (BLOCK), so the search overlaps its plane reads as the
 * march kernel does; blocks are handed out dynamically, so a thread that loses its core
 * holds up no other.
 */

#include "bounces.h"

typedef struct {
    Frame f;
    int blur;                   /* 1: ``prefiltered``: the lookups blurred by the roughness
                                 * (prefiltered.blur_sharpness), from the SG pyramids */
    float *blur_sigma;          /* (B*H*W,) with ``blur``: the transmitted lobe's k^-1/2 */
    Bounces bo;                 /* internal bounces (bounces.h; limit 0: none) */
} SpecJob;

/* What one block of pixels hands on with internal bounces: the front reflection's light,
 * whether a light hides the pixel, and the paths. */
typedef struct {
    float front[BLOCK][3];
    uint8_t hidden[BLOCK];
    Paths paths;
} SpecBlock;

/* ``tir: conserve``'s (or internal bounces') spread at the exit (paths.spread_exit): the
 * cosine of the transmitted lobe's axis at the exit's normal, and the lobe's variance
 * (``in``: the table's axes of the entry at alpha1; z1: the entry cosine cos1's table
 * coordinate); the energies are then averaged over it (spread_interface_energies). */
static void spread_axis(const Frame *j, const SgAxes *in, int64_t b, float alpha1, float cos1,
                        float z1, float cos2, float *c_axis_out, float *var) {
    float eta = j->ior[b];
    int rough = alpha1 > j->table.alpha_min;
    float k1, sin_tilt;
    transmit_lobe_at(&j->table, in, j->dist[b], z1, &k1, &sin_tilt);
    /* cos(theta2 + tilt_axis - tilt_ray) by the angle-sum identities */
    float sc1 = 1.0f - cos1 * cos1;
    float sin_t = sqrtf(sc1 > 1e-12f ? sc1 : 1e-12f) / eta;
    float st2 = 1.0f - sin_t * sin_t;
    float cos_t = sqrtf(st2 > 1e-12f ? st2 : 1e-12f);
    float ca = cos_of_asin(sin_tilt), sa = sin_tilt;
    float cos_d = ca * cos_t + sa * sin_t, sin_d = sa * cos_t - ca * sin_t;
    float sc2 = 1.0f - cos2 * cos2;
    float sin2 = sqrtf(sc2 > 1e-12f ? sc2 : 1e-12f);
    float c_axis = cos2 * cos_d - sin2 * sin_d;
    if (c_axis < 0.0f) c_axis = 0.0f;
    *c_axis_out = rough ? c_axis : cos2;
    *var = rough ? 1.0f / k1 : 0.0f;
}

/* optics.exit_rule.leaving_weight: what leaves the last interface under the tir rule. */
static inline float leaving_weight(int mode, int tir, float e_t, float e_r, float esc) {
    if (mode == 0) {
        float w = e_t + e_r * esc;
        return w > 1.0f ? 1.0f : w;
    }
    if (mode == 2) return tir ? e_r : e_t;
    float kept = e_t + e_r;
    return tir ? (kept > 1.0f ? 1.0f : kept) : e_t;
}

/* The reflected lobe's spread for the next interface (render_specular's _interface): a
 * rough interface's internal reflection lobe (the table's moment sharpness) widens it. */
static float reflected_var_at(const SpecJob *sj, const SgAxes *out, int64_t b, float alpha,
                              float z, float var) {
    float k_r, ang, e;
    sg_lookup_at(&sj->f.table, out, sj->f.dist[b], 1, 0, z, &k_r, &ang, &e);
    return var + (alpha > 0.0f ? 1.0f / k_r : 0.0f);
}

/* reflected_var_at at the incident cosine cos (its table coordinate sg_theta(cos)). */
static inline float reflected_var(const SpecJob *sj, const SgAxes *out, int64_t b,
                                  float alpha, float cos, float var) {
    return reflected_var_at(sj, out, b, alpha, sg_theta(cos), var);
}

/* A marched ray's two interfaces (paths.trace_paths): the entry's cosine, Fresnel term
 * (block_fresnel) and mirror direction ``refl``; the exit's view-facing normal, cosine,
 * Fresnel term, refracted ray ``t_ref`` and the direction the transmitted light is looked
 * up along (``look``: the exit's refracted ray, with internal bounces (``bounce``) always,
 * else the ``tir: reflect`` mirror under TIR; the entry's refracted ray where no exit was
 * found). */
typedef struct {
    float cos1, f1, refl[3], n2[3], cos2, f2, t2[3], t_ref[3], look[3];
    int tir2;
} Exit;

static void exit_of(const Frame *j, const Rays *rays, int i, const float *d, const float *n1,
                    int64_t b, int bounce, Exit *e) {
    const float *t1 = rays->t + 3 * i;
    float eta = j->ior[b];
    int ok = rays->found[i];
    e->cos1 = -dot3(d, n1);
    face_forward(rays->normal + 3 * i, t1, e->n2);
    e->cos2 = -dot3(t1, e->n2);
    e->tir2 = refract(t1, e->n2, eta, e->t2) && ok;
    for (int c = 0; c < 3; c++) e->t_ref[c] = e->t2[c];
    if (j->tir_mode == 2 && e->tir2) reflect(t1, e->n2, e->t2);
    reflect(d, n1, e->refl);
    for (int c = 0; c < 3; c++) e->look[c] = ok ? (bounce ? e->t_ref[c] : e->t2[c]) : t1[c];
}

/* The Fresnel terms of a block's m exits' two interfaces (exit_of's cosines; the entry at
 * 1 / ior, the exit at ior), four at a time in lanes where built for it, the same bits. */
static void block_fresnel(const Frame *j, Exit *ex, int64_t r0, int m) {
    float c[2 * BLOCK], eta[2 * BLOCK], f[2 * BLOCK];
    for (int i = 0; i < m; i++) {
        float ior = j->ior[j->batch[r0 + i]];
        c[i] = ex[i].cos1;
        eta[i] = 1.0f / ior;
        c[m + i] = ex[i].cos2;
        eta[m + i] = ior;
    }
    fresnel_n(c, eta, 2 * m, f);
    for (int i = 0; i < m; i++) {
        ex[i].f1 = f[i];
        ex[i].f2 = f[m + i];
    }
}

/* The first exit with internal bounces (render_specular's _interface at k = 0): what the
 * exit lets out (its energies: the paths' e_t2, e_r2 where the batch is rough, Fresnel
 * elsewhere) along the refracted ray, and the mirror ray that goes on with the rest. ``out``:
 * the table's axes of the exit interface. */
static void first_exit(const SpecJob *sj, const SgAxes *out, Paths *ps, int i, int64_t b,
                       const Rays *rays, const float *t1, const Exit *ex, const EnvTap *tap,
                       const float *p2, float e_t1, float e_t2, float e_r2, float var1,
                       float path) {
    const Frame *j = &sj->f;
    const float *n2 = ex->n2;
    float cos2 = ex->cos2, f2 = ex->f2;
    int ok = rays->found[i];
    float alpha = roughness_on(j, b, rays->bary + 3 * i, ok ? rays->tri[i] : -1);
    float e_t = 1.0f - f2, e_r = f2, var = 0.0f, w1[3], w_next[3], r[3], l_out[3];
    if (j->rough) {
        e_t = e_t2;
        e_r = e_r2;
        var = reflected_var(sj, out, b, alpha, cos2, var1);
    }
    float w_out = ok ? e_t : (j->rough ? escape(j, b, alpha) : 1.0f);
    float refl = ok ? e_r : 0.0f;
    if (tap) incident_at(&j->lights, b, p2, ex->look, tap, l_out);  /* look: t_ref or t1 */
    else incident(&j->lights, b, p2, ex->look, l_out);
    for (int c = 0; c < 3; c++) {
        w1[c] = e_t1 * transmittance(j->absorption[3 * b + c], path);
        ps->acc[i][c] = w1[c] * w_out * l_out[c];
    }
    ps->bounces[i] = 0.0f;
    ps->residual[i] = 0.0f;
    if (!goes_on(&sj->bo, ps, i, ok, 0, w1, refl, w_next)) return;
    reflect(t1, n2, r);
    add_ray(ps, i, p2, r, w_next, var, 1.0f);
}

/* Ray r's view-facing normal at its next interface (n_view) and the incident cosine. */
static inline float inside_cosine(const Paths *ps, int r, float *n_view) {
    face_forward(ps->normal[r], ps->t[r], n_view);
    return -dot3(ps->t[r], n_view);
}

/* inside_specular's table coordinates and Fresnel terms for the wave's n rays
 * (tr_coords_fn), where the batch is rough: the spread's three cosines' coordinates, the
 * incident cosine's (the reflected lobe's), then the spread's three Fresnel terms
 * (Paths.coord[r][0..2], [3], [4..6]), for all rays at once in lanes (the same bits as
 * spread_interface_energies ray by ray). */
static void specular_coords(const void *job, Paths *ps, int64_t r0, int n, int last) {
    const Frame *j = &((const SpecJob *)job)->f;
    (void)last;
    if (!j->rough) return;
    float c[4 * RAYS], z[4 * RAYS], etas[3 * RAYS], f[3 * RAYS];
    for (int r = 0; r < n; r++) {
        float n_view[3], cos = inside_cosine(ps, r, n_view);
        spread_cosines(cos, ps->var[r], c + 3 * r);
        c[3 * n + r] = cos;
        for (int q = 0; q < 3; q++) etas[3 * r + q] = j->ior[j->batch[r0 + ps->pix[r]]];
    }
    sg_theta_n(c, 4 * n, z);
    fresnel_n(c, etas, 3 * n, f);
    for (int r = 0; r < n; r++) {
        float *o = ps->coord[r];
        for (int q = 0; q < 3; q++) {
            o[q] = z[3 * r + q];
            o[4 + q] = f[3 * r + q];
        }
        o[3] = z[3 * n + r];
    }
}

/* A later interface (render_specular's _interface, k >= 1): the smooth ray refracts out
 * with the interface's energies (Fresnel; rough: the table's, averaged over the lobe
 * carried), the ``tir`` rule at the budget's last interface; the mirror ray goes on. A ray
 * the march lost leaves along its own direction with the escape fraction. */
static float inside_specular(const void *job, const SgAxes *view_axes, Paths *ps, int r,
                             int64_t b, int last, float *dir, float *var_out) {
    const SpecJob *sj = (const SpecJob *)job;
    const Frame *j = &sj->f;
    float eta = j->ior[b], alpha = ps->alpha[r], *t = ps->t[r];
    SgAxes own;
    const SgAxes *out = view_axes + 1;
    if (j->rmap[b]) {
        sg_axes(&j->table, 1.0f / eta, alpha, &own);
        out = &own;
    }
    float n_view[3], t_out[3];
    float cos = inside_cosine(ps, r, n_view), f = fresnel(cos, eta);
    int tir = refract(t, n_view, eta, t_out);
    reflect(t, n_view, dir);
    float e_t = 1.0f - f, e_r = f, var = 0.0f;
    if (j->rough) {  /* the spread's and the cosine's coordinates: specular_coords */
        const float *z = ps->coord[r];
        float et[3], er[3];
        interface_energies3(&j->table, out, j->dist[b], z, z + 4, et, er);
        spread_sum(et, er, &e_t, &e_r);
        if (!last) var = reflected_var_at(sj, out, b, alpha, z[3], ps->var[r]);
    }
    float esc = j->rough && (!ps->found[r] || (last && j->tir_mode == 0))
                    ? escape(j, b, alpha) : 1.0f;
    float w_out = e_t, refl = e_r;
    if (last) {
        if (j->tir_mode == 2 && tir)
            for (int c = 0; c < 3; c++) t_out[c] = dir[c];
        w_out = leaving_weight(j->tir_mode, tir, e_t, e_r, esc);
        refl = j->tir_mode == 0 || tir ? 0.0f : e_r;
    }
    if (!ps->found[r]) {
        for (int c = 0; c < 3; c++) t_out[c] = t[c];
        w_out = esc;
        refl = 0.0f;
    }
    for (int c = 0; c < 3; c++) ps->look_d[r][c] = t_out[c];  /* (bounces.h: looked up) */
    ps->look_k[r] = INFINITY;
    ps->look_w[r] = w_out;
    *var_out = var;
    return refl;
}

/* A pixel of a block: its roughness at the entry and at the exit (a map's, at their UVs),
 * its table axes (the view's entry and exit, or its own where a map gives the roughness),
 * and its interfaces' energies (block_energies): the entry's, the exit's with the escape
 * fraction esc of the trapped light and the spread's variance var1. */
typedef struct {
    float alpha, alpha2;
    const SgAxes *ax;
    SgAxes own[2];
    float e_t1, e_r1, e_t2, e_r2, esc, var1;
    float k_r, k_t;             /* with ``blur``: the lookups' sharpness (blur_taps) */
} SpecPixel;

static void pixel_axes(const Frame *j, const SgAxes *view_ax, const Rays *rays, int i,
                       int64_t px, int64_t b, SpecPixel *sp) {
    float eta = j->ior[b];
    sp->alpha = roughness_at(j, b, j->front_uv + 2 * px);
    sp->alpha2 = sp->alpha;
    sp->ax = view_ax;
    if (j->rmap[b]) {
        if (rays->found[i]) {
            float uv2[2];
            interpolate(rays->bary + 3 * i, j->tri_uvs + 6 * rays->tri[i], 2, uv2);
            sp->alpha2 = roughness_at(j, b, uv2);
        }
        sg_axes(&j->table, eta, sp->alpha, sp->own);
        sg_axes(&j->table, 1.0f / eta, sp->alpha2, sp->own + 1);
        sp->ax = sp->own;
    }
}

/* The energies of a block's m pixels (paths.trace_paths): the entry's and the exit's,
 * smooth (Fresnel) or rough (the SG table's, eq. 9 of de Rousiers 2012); under ``tir:
 * conserve`` or with internal bounces (``spread``) the exit's averaged over the entry
 * lobe (spread_axis), with the escape fraction. The spreads' table coordinates, Fresnel
 * terms and reads are found for the whole block at once (in lanes: the same bits as
 * spread_interface_energies pixel by pixel). z1: the entries' table coordinates. */
static void block_energies(const Frame *j, SpecPixel *sp, const Exit *ex, const float *z1,
                           int64_t r0, int m, int spread) {
    float cs[3 * BLOCK], zs[3 * BLOCK], fs[3 * BLOCK], etas[3 * BLOCK];
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        SpecPixel *p = sp + i;
        float f1 = ex[i].f1, f2 = ex[i].f2;
        p->esc = 1.0f;
        p->var1 = 0.0f;
        if (!j->rough) {
            p->e_t1 = 1.0f - f1;
            p->e_r1 = f1;
            p->e_t2 = 1.0f - f2;
            p->e_r2 = f2;
            continue;
        }
        interface_energies_at(&j->table, p->ax, j->dist[b], z1[i], f1, &p->e_t1, &p->e_r1);
        if (!spread) {
            interface_energies(&j->table, p->ax + 1, j->dist[b], ex[i].cos2, f2, &p->e_t2,
                               &p->e_r2);
            continue;
        }
        float c_axis;
        spread_axis(j, p->ax, b, p->alpha, ex[i].cos1, z1[i], ex[i].cos2, &c_axis, &p->var1);
        spread_cosines(c_axis, p->var1, cs + 3 * i);
        for (int q = 0; q < 3; q++) etas[3 * i + q] = j->ior[b];
    }
    if (!j->rough || !spread) return;
    sg_theta_n(cs, 3 * m, zs);
    fresnel_n(cs, etas, 3 * m, fs);
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        float et[3], er[3];
        interface_energies3(&j->table, sp[i].ax + 1, j->dist[b], zs + 3 * i, fs + 3 * i, et,
                            er);
        spread_sum(et, er, &sp[i].e_t2, &sp[i].e_r2);
        sp[i].esc = escape(j, b, sp[i].alpha2);
    }
}

/* ``prefiltered``'s lookups for a block's m pixels (``blur``): each pixel's reflected and
 * transmitted sharpness (prefiltered.blur_sharpness, from the front roughness) and their
 * SG taps, eight at a time in lanes (block_taps: incident_sg's own taps). */
static void blur_taps(const Frame *j, SpecPixel *sp, const Exit *ex, int64_t r0, int m,
                      SgTap (*taps)[2]) {
    float dirs[2][3 * BLOCK], ks[2][BLOCK];
    for (int i = 0; i < m; i++) {
        float eta = j->ior[j->batch[r0 + i]], a2 = sp[i].alpha * sp[i].alpha;
        float q = 1.0f - 1.0f / eta, p = eta - 1.0f;
        float var_t = 0.5f * a2 * (q * q + p * p), var_r = 2.0f * a2;
        sp[i].k_t = ks[1][i] = var_t > 0.0f ? 1.0f / var_t : INFINITY;
        sp[i].k_r = ks[0][i] = var_r > 0.0f ? 1.0f / var_r : INFINITY;
        for (int c = 0; c < 3; c++) {
            dirs[0][3 * i + c] = ex[i].refl[c];
            dirs[1][3 * i + c] = ex[i].look[c];
        }
    }
    SgTap t[2][BLOCK];
    for (int k = 0; k < 2; k++) block_taps(j, r0, m, dirs[k], ks[k], t[k]);
    for (int i = 0; i < m; i++) {
        taps[i][0] = t[0][i];
        taps[i][1] = t[1][i];
    }
}

/* Step 3 for ray i of a marched block (paths.trace_paths, render_specular, and
 * render_prefiltered with ``blur``): with the pixel's energies (``sp``), the exit rule,
 * the absorption, the two lookups (``taps``: the reflected and the transmitted light's,
 * asked for by the block; with ``blur`` sg_taps, blur_taps'); the pixel and its passes
 * written. */
static void shade_pixel(const SpecJob *sj, const SpecPixel *sp, const Rays *rays, int i,
                        const float *d, const Exit *ex, const EnvTap *taps,
                        const SgTap *sg_taps, int tir1, int64_t px, int64_t b,
                        SpecBlock *sb) {
    const Frame *j = &sj->f;
    const float *p1 = rays->p + 3 * i, *t1 = rays->t + 3 * i;
    int ok = rays->found[i];
    const float *refl = ex->refl, *t2 = ex->look;  /* the transmitted light's direction */
    float p2[3], e_t1 = sp->e_t1, e_r1 = sp->e_r1, e_t2 = sp->e_t2, e_r2 = sp->e_r2;
    float esc = sp->esc, var1 = sp->var1;
    int bounce = sj->bo.limit > 0, tir2 = ex->tir2;
    float w2 = leaving_weight(j->tir_mode, tir2, e_t2, e_r2, esc), path;
    if (ok) {
        for (int c = 0; c < 3; c++) p2[c] = rays->pos[3 * i + c];
        path = rays->s[i];
    } else {  /* no exit: leave along the refracted ray (``look``), with weight 1 */
        for (int c = 0; c < 3; c++) p2[c] = p1[c];
        w2 = 1.0f;
        float th = j->back_dist[px] - j->front_dist[px];
        path = th > 0.0f ? th : 0.0f;
    }
    float l_refl[3], l_trans[3];
    if (sj->blur) {  /* prefiltered.blur_sharpness (blur_taps) */
        incident_sg_at(&j->lights, b, p1, refl, sp->k_r, sg_taps, l_refl);
        if (!bounce) incident_sg_at(&j->lights, b, p2, t2, sp->k_t, sg_taps + 1, l_trans);
        sj->blur_sigma[px] = 1.0f / sqrtf(sp->k_t);
    } else {
        incident_at(&j->lights, b, p1, refl, taps, l_refl);
        if (!bounce) incident_at(&j->lights, b, p2, t2, taps + 1, l_trans);
    }
    int64_t l;
    int hidden = j->lights.nl > 0 &&
                 hit_light(&j->lights, b, j->eye + 3 * b, d, &l) < j->front_dist[px];
    if (bounce) {  /* the pixel is written once its bounces are followed (shade_block) */
        sb->hidden[i] = (uint8_t)hidden;
        for (int c = 0; c < 3; c++) sb->front[i][c] = e_r1 * l_refl[c];
        first_exit(sj, sp->ax + 1, &sb->paths, i, b, rays, t1, ex, taps ? taps + 1 : NULL, p2,
                   e_t1, e_t2, e_r2, var1, path);
    } else if (!hidden) {
        for (int c = 0; c < 3; c++) {
            float att = transmittance(j->absorption[3 * b + c], path);
            j->radiance[3 * px + c] = e_r1 * l_refl[c] + e_t1 * w2 * att * l_trans[c];
        }
    }
    j->exit_found[px] = ok ? 1.0f : 0.0f;
    j->tir[px] = (tir1 || tir2) ? 1.0f : 0.0f;
}

/* The env taps of a block's reflected and transmitted directions, eight at a time
 * (env_taps8: the map coordinates in AVX2 lanes where built for it, the same bits). */
static void block_taps_of(const Frame *j, const Exit *ex, int64_t r0, int m,
                          EnvTap (*taps)[2]) {
    for (int i0 = 0; i0 < m; i0 += 8) {
        int n = m - i0 < 8 ? m - i0 : 8;
        float dirs[2][8][3];
        EnvTap t[2][8];
        for (int i = 0; i < n; i++)
            for (int c = 0; c < 3; c++) {
                dirs[0][i][c] = ex[i0 + i].refl[c];
                dirs[1][i][c] = ex[i0 + i].look[c];
            }
        for (int k = 0; k < 2; k++) env_taps8(&j->lights, n, j->batch + r0 + i0, dirs[k][0], t[k]);
        for (int i = 0; i < n; i++) {
            taps[i0 + i][0] = t[0][i];
            taps[i0 + i][1] = t[1][i];
        }
    }
}

/* One block of pixels: 1. the entry refraction (paths.trace_paths), 2. the march to the
 * exit over the block (march_core.h), 3. the rest per pixel. */
static void shade_block(const void *job, const SgAxes *axes, int64_t r0, int m) {
    const SpecJob *sj = (const SpecJob *)job;
    const Frame *j = &sj->f;
    Rays rays;
    float d[3 * BLOCK], n1[3 * BLOCK];
    int tir1[BLOCK];
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = j->batch[r0 + i];
        float *di = d + 3 * i, *ni = n1 + 3 * i, p1[3], t1[3], c0[3], ct[3];
        for (int c = 0; c < 3; c++) {
            di[c] = j->ray_dir[3 * px + c];
            p1[c] = j->front_pos[3 * px + c];
        }
        face_forward(j->front_normal + 3 * px, di, ni);
        tir1[i] = refract(di, ni, 1.0f / j->ior[b], t1);
        camera_coords(j, b, p1, 1, c0);
        camera_coords(j, b, t1, 0, ct);
        set_ray(j, &rays, i, b, p1, t1, c0, ct);
    }
    march_rays(j, &rays, m, j->march.steps, j->march.refine);
    Exit ex[BLOCK];
    EnvTap taps[BLOCK][2];  /* the block's lookups asked for at once, read after the energies */
    for (int i = 0; i < m; i++)
        exit_of(j, &rays, i, d + 3 * i, n1 + 3 * i, j->batch[r0 + i], sj->bo.limit > 0, ex + i);
    block_fresnel(j, ex, r0, m);
    if (!sj->blur) block_taps_of(j, ex, r0, m, taps);
    float cos1[BLOCK], z1[BLOCK];  /* the entries' table coordinates, in lanes */
    if (j->rough) {
        for (int i = 0; i < m; i++) cos1[i] = ex[i].cos1;
        sg_theta_n(cos1, m, z1);
    }
    SpecPixel sp[BLOCK];
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        pixel_axes(j, axes + 2 * b, &rays, i, j->idx[r0 + i], b, sp + i);
    }
    block_energies(j, sp, ex, z1, r0, m, j->tir_mode == 0 || sj->bo.limit > 0);
    SgTap sg_taps[BLOCK][2];
    if (sj->blur) blur_taps(j, sp, ex, r0, m, sg_taps);
    SpecBlock sb;
    sb.paths.n = 0;
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        shade_pixel(sj, sp + i, &rays, i, d + 3 * i, ex + i, sj->blur ? NULL : taps[i],
                    sj->blur ? sg_taps[i] : NULL, tir1[i], j->idx[r0 + i], b, &sb);
    }
    if (sj->bo.limit > 0)
        finish_block(j, &sj->bo, sj, inside_specular, specular_coords, 0, axes, 2, &sb.paths,
                     (const float (*)[3])sb.front, sb.hidden, r0, m);
}

/* Each view's entry (eta = ior) and exit (eta = 1 / ior) interfaces on the table (views
 * with a roughness map take theirs per pixel). */
static int spec_axes(const Frame *f, int64_t b, SgAxes *out) {
    sg_axes(&f->table, f->ior[b], f->alpha[b], out);
    sg_axes(&f->table, 1.0f / f->ior[b], f->alpha[b], out + 1);
    return 2;
}

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_specular(SpecJob *job, int threads) {
    return run_shading(job, &job->f, 2, spec_axes, shade_block, threads);
}

int64_t torchrefract_specular_job_size(void) { return (int64_t)sizeof(SpecJob); }
